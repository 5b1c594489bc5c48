"""Scene loaders, bad-input errors, video writing and ``endogsim info``."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from endogsim.errors import DataError, DataWarning
from endogsim.io import load_scene, write_frames_png, write_video
from endogsim.io.loaders import load_video

H, W, N = 24, 32, 4
FOCAL = 40.0


# ------------------------------------------------------------------------------------------- synthetic data
def _frames(n=N, h=H, w=W, seed=0):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, size=(n, h, w, 3), dtype=np.uint8)


def _poses_bounds(n=N, h=H, w=W, focal=FOCAL):
    m = np.zeros((n, 3, 5))
    m[:, :, :3] = np.eye(3)
    m[:, :, 4] = [h, w, focal]
    return np.concatenate([m.reshape(n, 15), np.tile([1.0, 100.0], (n, 1))], 1)


def make_endonerf(root: Path, *, n=N, ext=".png", depth_bits=None, masks=True, depth_npy=None) -> Path:
    (root / "images").mkdir(parents=True)
    frames = _frames(n)
    for i, f in enumerate(frames):
        cv2.imwrite(str(root / "images" / f"frame-{i:06d}.color{ext}"), f[..., ::-1])
    np.save(root / "poses_bounds.npy", _poses_bounds(n))
    if depth_bits:
        (root / "depth").mkdir()
        dtype = np.uint8 if depth_bits == 8 else np.uint16
        for i in range(n):
            d = np.full((H, W), 50 + i, dtype=dtype)
            d[0, 0] = 0  # invalid pixel
            cv2.imwrite(str(root / "depth" / f"frame-{i:06d}.depth.png"), d)
    if depth_npy is not None:
        (root / "depth").mkdir()
        for i in range(n):
            np.save(root / "depth" / f"frame-{i:06d}.npy", depth_npy(i))
    if masks:
        (root / "masks").mkdir()
        for i in range(n):
            m = np.zeros((H, W), np.uint8)
            m[:, : W // 4] = 255
            cv2.imwrite(str(root / "masks" / f"frame-{i:06d}.mask.png"), m)
    return root


def _names_file(exc: pytest.ExceptionInfo, path: Path) -> None:
    assert str(path) in str(exc.value), f"message does not name {path}: {exc.value}"


# ------------------------------------------------------------------------------------------- EndoNeRF
@pytest.mark.parametrize("bits", [8, 16])
def test_endonerf_synthetic_depth_masks_poses(tmp_path, bits):
    root = make_endonerf(tmp_path / "scene", depth_bits=bits)
    s = load_scene(root)
    assert s.frames.shape == (N, H, W, 3) and s.frames.dtype == np.float32
    ref = _frames(N).astype(np.float32) / 255
    np.testing.assert_allclose(s.frames, ref, atol=1e-6)
    np.testing.assert_allclose(s.K, [[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1]])
    np.testing.assert_allclose(s.times, np.arange(N) / 30.0)
    assert s.depth.shape == (N, H, W)
    assert s.depth[0, 0, 0] == 0  # invalid stays 0
    np.testing.assert_allclose(s.depth[2, 5, 5], 52 * 1e-3, rtol=1e-6)  # stored mm -> metres
    assert set(np.unique(s.object_masks)) == {0, 1}
    assert s.tool_mask[:, :, : W // 4].all() and not s.tool_mask[:, :, W // 4 :].any()
    assert s.labels[1].is_tool and s.labels[0].klass == "unknown_tissue"
    np.testing.assert_allclose(s.poses, np.tile(np.eye(4), (N, 1, 1)))


def test_endonerf_downscale_max_frames_jpg_depth_scale(tmp_path):
    root = make_endonerf(tmp_path / "scene", ext=".jpg", depth_bits=16)
    s = load_scene(root, downscale=2, max_frames=3, depth_scale=1.0, fps=10)
    assert s.frames.shape == (3, H // 2, W // 2, 3)
    assert s.object_masks.shape == s.depth.shape == (3, H // 2, W // 2)
    np.testing.assert_allclose(s.K[0], [FOCAL / 2, 0, W / 4])
    np.testing.assert_allclose(s.times, [0, 0.1, 0.2])
    assert s.depth.max() == pytest.approx(52.0)
    assert set(np.unique(s.object_masks)) <= {0, 1}


def test_endonerf_reads_depth_scale_and_frame_rate_from_scene_json(tmp_path):
    # An `endogsim synth` folder: 16-bit depth in 0.1 mm steps (10000 units per metre), 5 ms frames.
    import json

    root = make_endonerf(tmp_path / "scene", depth_bits=16)
    (root / "scene.json").write_text(json.dumps({"depth_scale": 10000.0, "scenario": {"frame_dt": 0.005}}))
    s = load_scene(root)
    np.testing.assert_allclose(s.depth[2, 5, 5], 52 / 10000.0, rtol=1e-6)
    np.testing.assert_allclose(s.times, np.arange(N) * 0.005)
    explicit = load_scene(root, depth_scale=1e-3, fps=30)  # explicit arguments win
    np.testing.assert_allclose(explicit.depth[2, 5, 5], 52e-3, rtol=1e-6)
    np.testing.assert_allclose(explicit.times, np.arange(N) / 30.0)
    (root / "scene.json").write_text(json.dumps({"depth_scale": -1}))
    with pytest.raises(DataError, match="depth_scale") as e:
        load_scene(root)
    _names_file(e, root / "scene.json")


def test_endonerf_without_masks_is_all_tissue(tmp_path):
    s = load_scene(make_endonerf(tmp_path / "s", masks=False))
    assert s.object_masks is None and list(s.labels) == [0] and s.tool_mask is None


def test_endonerf_float_tiff_depth_nan(tmp_path):
    root = make_endonerf(tmp_path / "s")
    (root / "depth").mkdir()
    for i in range(N):
        d = np.full((H, W), 50.0, np.float32)
        d[1, 1] = np.nan if i == 3 else 50.0
        assert cv2.imwrite(str(root / "depth" / f"d{i}.tiff"), d)
    with pytest.raises(DataError, match="NaN") as e:
        load_scene(root)
    _names_file(e, root / "depth" / "d3.tiff")


def test_endonerf_npy_depth(tmp_path):
    s = load_scene(make_endonerf(tmp_path / "s", depth_npy=lambda i: np.full((H, W), 0.05, np.float32)),
                   depth_scale=1.0)
    np.testing.assert_allclose(s.depth, 0.05)


# ------------------------------------------------------------------------------------------- real data
@pytest.mark.realdata
def test_real_endonerf_pulling(shared_data):
    root = shared_data / "endonerf_pulling"
    if not root.is_dir():
        pytest.skip("endonerf_pulling absent")
    s = load_scene(root, downscale=4, max_frames=5)
    assert s.frames.shape == (5, 128, 160, 3)
    assert s.depth is None and s.object_masks is None
    np.testing.assert_allclose(s.K[0, 0], 569.4682 / 4, rtol=1e-5)
    np.testing.assert_allclose(s.K[:2, 2], [80, 64])
    assert 0.05 < s.frames.mean() < 0.95


@pytest.mark.realdata
def test_real_cholecseg8k(shared_data):
    root = shared_data / "cholecseg8k_clip"
    if not root.is_dir():
        pytest.skip("cholecseg8k_clip absent")
    s = load_scene(root, downscale=2, max_frames=4)
    assert s.frames.shape == (4, 240, 427, 3)
    ids = set(np.unique(s.object_masks).tolist())
    assert {21, 22, 31, 50} <= ids and ids <= {-1, 11, 12, 13, 21, 22, 31, 32, 50}
    assert s.labels[31].is_tool and s.labels[32].klass == "l_hook" and not s.labels[21].is_tool
    np.testing.assert_allclose(s.times, np.arange(4) / 25.0)
    hfov = 2 * np.degrees(np.arctan(0.5 * s.width / s.K[0, 0]))
    assert 70 <= hfov <= 80


# ------------------------------------------------------------------------------------------- bad input
def test_missing_folder(tmp_path):
    with pytest.raises(DataError) as e:
        load_scene(tmp_path / "nope")
    _names_file(e, tmp_path / "nope")


def test_unknown_format(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "readme.txt").write_text("hi")
    with pytest.raises(DataError, match="unknown format") as e:
        load_scene(tmp_path / "x")
    _names_file(e, tmp_path / "x")


def test_empty_sequence(tmp_path):
    (tmp_path / "s" / "images").mkdir(parents=True)
    with pytest.raises(DataError, match="empty") as e:
        load_scene(tmp_path / "s")
    _names_file(e, tmp_path / "s" / "images")


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_truncated_frame(tmp_path, ext):
    root = make_endonerf(tmp_path / "s", ext=ext)
    bad = sorted((root / "images").iterdir())[2]
    bad.write_bytes(bad.read_bytes()[: len(bad.read_bytes()) // 2])
    with pytest.raises(DataError) as e:
        load_scene(root)
    _names_file(e, bad)


def test_garbage_frame(tmp_path):
    root = make_endonerf(tmp_path / "s")
    bad = sorted((root / "images").iterdir())[1]
    bad.write_bytes(b"not an image at all")
    with pytest.raises(DataError) as e:
        load_scene(root)
    _names_file(e, bad)


def test_frames_of_different_sizes(tmp_path):
    root = make_endonerf(tmp_path / "s")
    bad = sorted((root / "images").iterdir())[3]
    cv2.imwrite(str(bad), np.zeros((H + 2, W, 3), np.uint8))
    with pytest.raises(DataError, match="same size") as e:
        load_scene(root)
    _names_file(e, bad)


def test_mask_size_mismatch(tmp_path):
    root = make_endonerf(tmp_path / "s")
    bad = sorted((root / "masks").iterdir())[0]
    cv2.imwrite(str(bad), np.zeros((H, W + 4), np.uint8))
    with pytest.raises(DataError, match="mask") as e:
        load_scene(root)
    _names_file(e, bad)


def test_mask_count_mismatch(tmp_path):
    root = make_endonerf(tmp_path / "s")
    sorted((root / "masks").iterdir())[-1].unlink()
    with pytest.raises(DataError, match="masks") as e:
        load_scene(root)
    _names_file(e, root / "masks")


@pytest.mark.parametrize("value", [np.nan, -1.0])
def test_bad_depth_values(tmp_path, value):
    def depth(i):
        d = np.full((H, W), 0.05, np.float32)
        if i == 1:
            d[3, 3] = value
        return d

    root = make_endonerf(tmp_path / "s", depth_npy=depth)
    with pytest.raises(DataError, match="NaN|negative") as e:
        load_scene(root)
    _names_file(e, root / "depth" / "frame-000001.npy")


def test_poses_wrong_shape(tmp_path):
    root = make_endonerf(tmp_path / "s")
    np.save(root / "poses_bounds.npy", np.zeros((N, 15)))
    with pytest.raises(DataError, match=re.escape("(N, 17)")) as e:
        load_scene(root)
    _names_file(e, root / "poses_bounds.npy")


def test_poses_count_mismatch_and_corrupt(tmp_path):
    root = make_endonerf(tmp_path / "s")
    np.save(root / "poses_bounds.npy", _poses_bounds(N + 1))
    with pytest.raises(DataError, match="poses for"):
        load_scene(root)
    (root / "poses_bounds.npy").write_bytes(b"garbage")
    with pytest.raises(DataError) as e:
        load_scene(root)
    _names_file(e, root / "poses_bounds.npy")


def test_cholec_missing_mask(tmp_path):
    d = tmp_path / "clip"
    d.mkdir()
    for i in (1, 2):
        cv2.imwrite(str(d / f"frame_{i}_endo.png"), np.zeros((H, W, 3), np.uint8))
    cv2.imwrite(str(d / "frame_1_endo_watershed_mask.png"), np.full((H, W, 3), 21, np.uint8))
    with pytest.raises(DataError, match="watershed mask missing") as e:
        load_scene(d)
    _names_file(e, d / "frame_2_endo_watershed_mask.png")


def test_endonerf_poses_stored_as_text_are_named(tmp_path):
    root = make_endonerf(tmp_path / "clip")
    np.save(root / "poses_bounds.npy", _poses_bounds().astype(str))  # a TypeError traceback before
    with pytest.raises(DataError, match="poses are stored as <U32, not numbers") as e:
        load_scene(root)
    _names_file(e, root / "poses_bounds.npy")


def test_depth_maps_without_a_measurement_are_refused(tmp_path):
    root = make_endonerf(tmp_path / "clip", depth_npy=lambda i: np.zeros((H, W)))  # numpy warnings, then
    with pytest.raises(DataError, match="every depth pixel of the 4 maps is 0") as e:  # "no tissue pixel"
        load_scene(root)
    _names_file(e, root / "depth")


def test_cholec_times_follow_the_frame_numbers(tmp_path):
    d = tmp_path / "clip"
    d.mkdir()
    for i in (561, 562, 564):  # frame 563 left out
        cv2.imwrite(str(d / f"frame_{i}_endo.png"), np.zeros((H, W, 3), np.uint8))
        cv2.imwrite(str(d / f"frame_{i}_endo_watershed_mask.png"), np.full((H, W, 3), 21, np.uint8))
    with pytest.warns(DataWarning, match="frame numbers jump 562 -> 564"):
        sc = load_scene(d)
    np.testing.assert_allclose(sc.times, [0.0, 0.04, 0.12])


def test_endonerf_focal_length_no_endoscope_has_is_warned(tmp_path):
    root = make_endonerf(tmp_path / "clip")
    np.save(root / "poses_bounds.npy", _poses_bounds(focal=1e-6))  # a millionth of a pixel
    with pytest.warns(DataWarning, match="poses_bounds.npy: focal length 1e-06 px .* outside the 20-160 degrees"):
        load_scene(root)


def test_undecodable_video(tmp_path):
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"\x00" * 1000)
    with pytest.raises(DataError, match="decode|empty") as e:
        load_scene(bad)
    _names_file(e, bad)


# ------------------------------------------------------------------------------------------- video
def _smooth_frames(t=6, h=31, w=45):
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([np.stack([x / w, y / h, np.full_like(x, k / t, dtype=float)], -1) for k in range(t)]
                    ).astype(np.float32)


def test_video_round_trip_and_masks(tmp_path):
    frames = _smooth_frames()  # odd size: padded to even
    out = write_video(frames, tmp_path / "v.mp4", fps=12)
    assert out.is_file() and not list(tmp_path.glob("*.tmp*"))
    mdir = tmp_path / "m"
    write_frames_png(np.zeros((6, 32, 46, 3), np.uint8), mdir, "m_{:03d}.png")  # video padded to even
    s = load_video(out, mask_dir=mdir)
    assert s.frames.shape == (6, 32, 46, 3)
    assert np.abs(s.frames[:, :31, :45] - frames).mean() < 0.03
    np.testing.assert_allclose(s.times[1], 1 / 12, rtol=1e-3)
    assert s.object_masks is not None and (s.object_masks == 0).all()
    (mdir / "m_005.png").unlink()
    with pytest.raises(DataError, match="masks") as e:
        load_video(out, mask_dir=mdir)
    _names_file(e, mdir)


def test_write_frames_png(tmp_path):
    frames = _smooth_frames(t=2)
    paths = write_frames_png(frames, tmp_path / "png")
    assert [p.name for p in paths] == ["frame_0000.png", "frame_0001.png"]
    back = cv2.imread(str(paths[1]))[..., ::-1] / 255.0
    assert np.abs(back - frames[1]).max() <= 0.5 / 255 + 1e-6


# ------------------------------------------------------------------------------------------- CLI
def _app():
    from endogsim.cli.main import app

    return app


def test_cli_info_good_folder(tmp_path):
    root = make_endonerf(tmp_path / "s", depth_bits=16)
    r = CliRunner().invoke(_app(), ["info", str(root)])
    assert r.exit_code == 0, r.output
    for word in ("endonerf", "32x24", "depth", "tool", "tissue", "valid"):
        assert word in r.output


def test_cli_info_bad_folder(tmp_path):
    root = make_endonerf(tmp_path / "s")
    np.save(root / "poses_bounds.npy", np.zeros((3, 3)))
    r = CliRunner().invoke(_app(), ["info", str(root)])
    assert r.exit_code == 2
    assert "poses" in r.output and "Traceback" not in r.output
    assert r.exception is None or isinstance(r.exception, SystemExit)


def test_cli_run_and_validate_refuse_a_negative_support_friction_before_any_work(tmp_path):
    root = make_endonerf(tmp_path / "s")
    for cmd in ("run", "validate"):
        r = CliRunner().invoke(_app(), [cmd, str(root), "--out", str(tmp_path / cmd), "--support-friction", "-1"])
        assert r.exit_code == 2, r.output
        assert "support_friction" in r.output and "Traceback" not in r.output
        assert not (tmp_path / cmd / "recon").exists()


def test_cli_run_and_validate_take_the_force_scales_and_refuse_bad_ones_before_any_work(tmp_path, monkeypatch):
    """Gravity, damping and mass scaling set the scale of the E found (metrics.json ``force_scales``); a user who
    knows them (the camera's orientation from a robot's kinematics) gives them."""
    root = make_endonerf(tmp_path / "s")
    bad = [(["--gravity-direction", "0,0,0"], "gravity_direction"), (["--gravity-direction", "down"], "three numbers"),
           (["--gravity-direction", "0,1"], "gravity_direction"), (["--gravity", "-9.81"], "gravity"),
           (["--damping", "nan"], "damping"), (["--mass-scaling", "0.5"], "mass_scaling")]
    for cmd in ("run", "validate"):
        for given, word in bad:
            r = CliRunner().invoke(_app(), [cmd, str(root), "--out", str(tmp_path / cmd), *given])
            assert r.exit_code == 2, (given, r.output)
            assert word in r.output and "Traceback" not in r.output
            assert not (tmp_path / cmd / "recon").exists()
    import endogsim.pipeline.run as pipeline_run
    from endogsim.pipeline.scene_from_recon import RealScenario

    seen = []
    monkeypatch.setattr(pipeline_run, "run_pipeline", lambda data, out, cfg, **kw: seen.append(cfg.scenario) or {
        "stages": {}})
    given = ["--gravity-direction", "0,0,1", "--damping", "10", "--mass-scaling", "1", "--gravity", "9.81"]
    assert CliRunner().invoke(_app(), ["run", str(root), "--out", str(tmp_path / "g"), *given]).exit_code == 0
    assert CliRunner().invoke(_app(), ["run", str(root), "--out", str(tmp_path / "d")]).exit_code == 0
    assert seen[0] == RealScenario(gravity_direction=(0.0, 0.0, 1.0), damping=10.0, mass_scaling=1.0)
    assert seen[1] == RealScenario()  # the scenario's own defaults where nothing is given
    with pytest.raises(DataError, match="gravity_direction"):  # the Python API's check, for what the CLI parses
        RealScenario(gravity_direction=("down", 0, 0))


def test_cli_run_and_validate_take_the_optimiser_and_refuse_an_unknown_one_before_any_work(tmp_path, monkeypatch):
    root = make_endonerf(tmp_path / "s")
    for cmd in ("run", "validate"):
        r = CliRunner().invoke(_app(), [cmd, str(root), "--out", str(tmp_path / cmd), "--optimizer", "newton"])
        assert r.exit_code == 2, r.output
        assert "newton" in r.output and "rprop" in r.output and "Traceback" not in r.output
        assert not (tmp_path / cmd / "recon").exists()
    # a known one reaches the calibration's settings (the pipeline itself is not run here)
    import endogsim.pipeline.run as pipeline_run

    seen = {}

    def fake_pipeline(data, out, cfg, **kw):
        seen["optimizer"] = cfg.identify.optimizer
        return {"stages": {}}

    monkeypatch.setattr(pipeline_run, "run_pipeline", fake_pipeline)
    for given, used in ((["--optimizer", "rprop"], "rprop"), ([], pipeline_run.PIPELINE_OPTIMIZER)):
        r = CliRunner().invoke(_app(), ["run", str(root), "--out", str(tmp_path / "lm"), *given])
        assert r.exit_code == 0, r.output
        assert seen == {"optimizer": used}


def test_the_pipeline_calibrates_with_levenberg_marquardt_unless_told_otherwise():
    from endogsim.identify.config import IdentifyConfig
    from endogsim.pipeline.run import PipelineConfig
    from endogsim.pipeline.validate import ValidateConfig

    assert IdentifyConfig().optimizer == "rprop"  # the library's (and identify's, the suite's, the demo's)
    assert PipelineConfig().identify.optimizer == "lm"
    assert ValidateConfig().pipeline.identify.optimizer == "lm"
    assert PipelineConfig(identify={"iters": 1}).identify.optimizer == "lm"  # a dict fills in the pipeline's
    assert PipelineConfig(identify={"optimizer": "rprop"}).identify.optimizer == "rprop"
    assert PipelineConfig(identify=IdentifyConfig()).identify.optimizer == "rprop"  # a config is taken as it is


def test_the_optimizer_help_of_run_and_validate_names_the_pipelines_default():
    from endogsim.cli.demo import _PIPELINE_OPTIMIZER_HELP
    from endogsim.pipeline.run import PIPELINE_OPTIMIZER

    assert f"default {PIPELINE_OPTIMIZER} " in _PIPELINE_OPTIMIZER_HELP
