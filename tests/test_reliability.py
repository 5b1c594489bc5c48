"""Issue 22: nothing silently wrong, one run per folder, every error names its cause.

One test (or a few) per case of the issue, on small inputs: the ``tiny`` scene with 4 frames, hand-made
data folders, a fake MLLM endpoint.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from endogsim.errors import DataError, DataWarning, MaterialError
from endogsim.io.atomic import finite_json, write_json_atomic
from endogsim.io.runfolder import run_folder

FRAMES = 4


def strict_json(path: Path):
    """``path`` parsed as standard JSON (NaN, Infinity refused)."""
    def refuse(name):
        raise ValueError(f"{path}: {name} is not JSON")

    return json.loads(Path(path).read_text(), parse_constant=refuse)


def cli(*args: str):
    from endogsim.cli.main import app

    return CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "200"})


def one_line_error(result, needle: str) -> str:
    """The CLI failed with exit code 2 and one ``error:`` line holding ``needle``; returns that line."""
    lines = [ln for ln in result.output.splitlines() if ln.startswith("error:")]
    assert result.exit_code == 2 and len(lines) == 1 and needle in lines[0], result.output
    assert "Traceback" not in result.output
    return lines[0]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The ``tiny`` scene with 4 frames (shared with the other test modules that use it)."""
    from endogsim.synth import synthesize

    folder = tmp_path_factory.getbasetemp() / "shared_tiny_f4"
    if not (folder / "scene.json").is_file():
        synthesize("tiny", folder, seed=0, frames=FRAMES)
    return folder


def scene_copy(src: Path, dst: Path, edit=None) -> Path:
    """A copy of the scene folder ``src`` whose scene.json dict went through ``edit``."""
    import shutil

    shutil.copytree(src, dst)
    if edit is not None:
        d = json.loads((dst / "scene.json").read_text())
        edit(d)
        (dst / "scene.json").write_text(json.dumps(d))
    return dst


def test_version_is_printed_by_both_entry_points():
    """``endogsim --version`` printed "Missing command." (exit 2) before its option was eager; ``python -m
    endogsim`` is the same command line."""
    import subprocess
    import sys

    from endogsim import __version__

    result = cli("--version")
    assert result.exit_code == 0 and result.output.strip() == __version__, result.output
    run = subprocess.run([sys.executable, "-m", "endogsim", "--version"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == __version__, run.stderr


def test_the_command_lists_read_as_sentences():
    """Every command's description in ``endogsim --help`` (and its groups') is its docstring with the source's line
    breaks joined: Typer printed them as they were, breaking each description mid-sentence."""
    for group in ((), ("bench",), ("materials",)):
        out = cli(*group, "--help").output
        assert "Commands" in out, out
        panel = out[out.index("╭─ Commands"):].splitlines()
        width = len(panel[0]) - 2
        rows = [ln.strip("│").rstrip() for ln in panel[1:] if ln.startswith("│")]
        for row, following in zip(rows, rows[1:]):
            if following.startswith("   "):  # no command name: a continuation line
                # ``row`` goes on in ``following``: it was wrapped at the panel's edge, not at a source line.
                assert len(row) > width - 25, out
    from endogsim.cli.main import app

    assert all("\n" not in c.help for c in app.registered_commands if c.help)


# ------------------------------------------------------------------------------------------------------ JSON, folders
def test_json_files_never_hold_nan_or_infinity(tmp_path):
    p = write_json_atomic(tmp_path / "m.json", {"epe": math.nan, "psnr": 30.0, "grad": [1.0, -math.inf],
                                                "stages": {"identify": {"epe": math.inf}}})
    d = strict_json(p)
    assert d["epe"] is None and d["grad"] == [1.0, None] and d["stages"]["identify"]["epe"] is None
    assert d["non_finite"] == {"epe": "nan", "grad[1]": "-inf"} and d["stages"]["identify"]["non_finite"] == {"epe": "inf"}
    # read back and written again (run.json is), the note stays while the value is null
    assert finite_json(d)["non_finite"] == d["non_finite"]
    assert "non_finite" not in finite_json({**d, "epe": 1.0, "grad": [1.0, 2.0]})


HOLD_LOCK = textwrap.dedent("""
    import sys, time
    from endogsim.io.runfolder import run_folder
    with run_folder(sys.argv[1], "identify"):
        print("locked", flush=True)
        time.sleep(60)
""")


def hold_lock(folder: Path) -> subprocess.Popen:
    """A process that holds the lock of ``folder`` (as `identify` would) until killed."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "src")}
    p = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(folder)], stdout=subprocess.PIPE, text=True, env=env)
    assert p.stdout.readline().strip() == "locked"
    return p


def test_a_second_command_on_a_run_folder_is_refused_with_the_holders_pid(tiny, tmp_path):
    out = tmp_path / "run"
    holder = hold_lock(out)
    try:
        with pytest.raises(DataError, match=f"in use by PID {holder.pid} \\(endogsim identify"):
            with run_folder(out, "identify"):
                pass
        one_line_error(cli("identify", tiny, "--out", out, "--iters", 0, "--no-video"), f"in use by PID {holder.pid}")
        one_line_error(cli("simulate", tiny, "-i", "poke", "--out", out), f"in use by PID {holder.pid}")
    finally:
        holder.kill()  # SIGKILL: the OS releases the lock; no stale lock blocks the next command
        holder.wait()
    with run_folder(out, "identify"):
        with run_folder(out, "identify"):  # re-entrant within one process
            pass
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # the lock file is gone


def test_run_folder_removes_the_folders_it_created_when_the_command_fails(tmp_path):
    with pytest.raises(RuntimeError):
        with run_folder(tmp_path / "a" / "b" / "out", "synth"):
            raise RuntimeError("failed")
    assert list(tmp_path.iterdir()) == []
    keep = tmp_path / "keep"
    with pytest.raises(RuntimeError):
        with run_folder(keep, "reconstruct"):
            (keep / "checkpoint.pt").write_bytes(b"state")  # what a failed run wrote stays (to resume)
            raise RuntimeError("failed")
    assert (keep / "checkpoint.pt").is_file()


def test_run_folder_refuses_a_file_and_an_unwritable_folder(tmp_path, monkeypatch):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(DataError, match="is a file"):
        with run_folder(f, "identify"):
            pass
    import tempfile

    def read_only(*a, **k):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "TemporaryFile", read_only)
    with pytest.raises(DataError, match="ro: cannot write here \\(Permission denied\\)"):
        with run_folder(tmp_path / "ro", "identify"):
            pass
    assert not (tmp_path / "ro").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_output_folder_is_one_line(tiny, tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        one_line_error(cli("simulate", tiny, "-i", "poke", "--out", ro / "sim"), "Permission denied")
        one_line_error(cli("materials", "init", tiny, "--out", ro / "m.json"), "Permission denied")
    finally:
        ro.chmod(0o700)


def test_an_output_file_that_is_a_folder_is_one_line(tiny, tmp_path):
    with pytest.raises(IsADirectoryError, match="a folder, not a file to write"):
        write_json_atomic(tmp_path, {})
    one_line_error(cli("materials", "init", tiny, "--out", tmp_path), f"{tmp_path}: a folder, not a file to write")


def test_cli_turns_os_errors_naming_a_file_into_one_line(tmp_path):
    import typer

    from endogsim.cli.common import user_errors

    @user_errors
    def fails():
        raise PermissionError(13, "Permission denied", str(tmp_path / "x.json"))

    with pytest.raises(typer.Exit) as e:
        fails()
    assert e.value.exit_code == 2


# ------------------------------------------------------------------------------------------------------ reconstruct
RECON = {"iters": 2, "resolution_scale": 0.25, "eval_every": 0, "checkpoint_every": 1000}


@pytest.fixture(scope="module")
def other(tmp_path_factory):
    """Another 4-frame scene (seed 1): dataset B."""
    from endogsim.synth import synthesize

    return synthesize("tiny", tmp_path_factory.mktemp("other") / "B", seed=1, frames=FRAMES)


def test_reconstruct_refuses_the_run_folder_of_another_dataset(tiny, other, tmp_path):
    from endogsim.recon.config import ReconConfig
    from endogsim.recon.train import reconstruct

    cfg = ReconConfig(**RECON)
    reconstruct(tiny, tmp_path / "run", cfg)
    made = strict_json(tmp_path / "run" / "provenance.json")
    assert made["data"] == str(Path(tiny).resolve()) and made["frames"] == FRAMES and made["resolution"] == [40, 32]
    assert len(made["frames_sha256"]) == 64 and made["config"]["iters"] == 2
    with pytest.raises(DataError, match="was made from .*gives other frames.*--fresh"):
        reconstruct(other, tmp_path / "run", cfg)
    with pytest.raises(DataError, match="other frames"):  # other frames of the same data: another resolution
        reconstruct(tiny, tmp_path / "run", ReconConfig(**{**RECON, "resolution_scale": 0.5}))
    one_line_error(cli("reconstruct", other, "--out", tmp_path / "run", "--iters", 2, "--resolution-scale", 0.25),
                   "gives other frames")
    reconstruct(other, tmp_path / "run", cfg, resume=False)  # --fresh
    assert strict_json(tmp_path / "run" / "provenance.json")["data"] == str(Path(other).resolve())


@pytest.mark.parametrize("damage", ["truncate", "empty"])
def test_corrupt_reconstruction_checkpoint_is_one_line_offering_fresh(tiny, tmp_path, damage):
    from endogsim.recon.config import ReconConfig
    from endogsim.recon.train import reconstruct

    reconstruct(tiny, tmp_path / "run", ReconConfig(**RECON))
    ckpt = tmp_path / "run" / "checkpoint.pt"
    ckpt.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2] if damage == "truncate" else b"")
    with pytest.raises(DataError, match="checkpoint.pt: corrupt checkpoint .*--fresh"):
        reconstruct(tiny, tmp_path / "run", ReconConfig(**RECON))
    r = cli("reconstruct", tiny, "--out", tmp_path / "run", "--iters", 2, "--resolution-scale", 0.25)
    one_line_error(r, "corrupt checkpoint")


def cholec_clip(folder: Path, size: tuple[int, int], n: int = 6) -> Path:
    """A CholecSeg8K-style clip of ``n`` random frames of ``size`` = (W, H) px (liver and a grasper)."""
    import cv2

    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        cv2.imwrite(str(folder / f"frame_{i}_endo.png"), rng.integers(0, 255, (size[1], size[0], 3), np.uint8))
        ids = np.full((size[1], size[0], 3), 21, np.uint8)
        ids[: size[1] // 3] = 31
        cv2.imwrite(str(folder / f"frame_{i}_endo_watershed_mask.png"), ids)
    return folder


def test_frames_too_small_for_reconstruction_are_refused(tmp_path):
    from endogsim.recon.config import ReconConfig
    from endogsim.recon.train import reconstruct

    clip = cholec_clip(tmp_path / "clip", (24, 14))
    with pytest.raises(DataError, match="the frames are 24x14 px at resolution scale 1; .*at least 32 px"):
        reconstruct(clip, tmp_path / "run", ReconConfig(iters=2, resolution_scale=1.0))
    assert not (tmp_path / "run").exists()
    one_line_error(cli("reconstruct", clip, "--out", tmp_path / "run", "--resolution-scale", 0.5), "at least 32 px")


# ------------------------------------------------------------------------------------------------------ scene.json
@pytest.mark.parametrize("key, value, needle", [
    ("E", math.nan, "E = nan Pa must be finite"), ("E", -5.0, "E = -5.0 Pa must be finite and > 0"),
    ("nu", 0.5, "nu = 0.5 must lie in \\(-1, 0.5\\)"), ("E", "soft", "E = 'soft'; it must be a number"),
    ("density", None, "gives E, nu but not all of E, nu and density"),
])
def test_impossible_ground_truth_is_refused_on_load(tiny, tmp_path, key, value, needle):
    from endogsim.scene.schema import load_scene_spec

    def edit(d):
        d["objects"][0][key] = value

    bad = scene_copy(tiny, tmp_path / "bad", edit)
    with pytest.raises((DataError, MaterialError), match=needle):
        load_scene_spec(bad)
    one_line_error(cli("identify", bad, "--out", tmp_path / "run", "--iters", 0, "--no-video"), "scene.json")
    assert not (tmp_path / "run").exists()  # nothing written, no empty folder left


@pytest.mark.parametrize("edit, needle", [
    (lambda d: d.update(frames=1000), "frames = 1000, but its images end at frame 3 \\(images/frame-000004"),
    (lambda d: d["files"].update(images="../B/images/frame-%06d.color.png"), "points outside the scene folder"),
    (lambda d: d["files"].update(gaussians_t0="/etc/passwd"), "files.gaussians_t0 = '/etc/passwd' points outside"),
])
def test_scene_json_frames_and_files_are_checked(tiny, tmp_path, edit, needle):
    from endogsim.scene.schema import load_scene_spec

    bad = scene_copy(tiny, tmp_path / "bad", edit)
    with pytest.raises(DataError, match=needle):
        load_scene_spec(bad)


# ------------------------------------------------------------------------------------------------------ identify
def test_identify_never_writes_nan_and_refuses_corrupt_state(tiny, tmp_path):
    from endogsim.identify import IdentifyConfig, run_identify

    def no_flow(d):  # a scene without ground-truth flow (a real video): EPE against the observed flow
        d["files"].pop("flow")
        d["files"].pop("flow_valid")

    scene = scene_copy(tiny, tmp_path / "scene", no_flow)
    run = tmp_path / "run"
    cfg = IdentifyConfig(iters=1, frame_stride=2)
    m = run_identify(scene, run, config=cfg, video=False)
    assert math.isfinite(m["epe"]) and m["epe_reference"] == "observed flow"
    written = strict_json(run / "metrics.json")  # parses with NaN/inf refused
    assert written["epe"] == pytest.approx(m["epe"])

    flow = run / "observed_flow.npz"
    flow.write_bytes(flow.read_bytes()[:100])
    with pytest.raises(DataError, match="observed_flow.npz: corrupt observed-flow cache .*--fresh"):
        run_identify(scene, run, config=cfg, video=False)
    ckpt = run / "checkpoint.pt"
    ckpt.write_bytes(b"")
    one_line_error(cli("identify", scene, "--out", run, "--iters", 1, "--frame-stride", 2, "--no-video"),
                   "checkpoint.pt: corrupt checkpoint")
    r = cli("identify", scene, "--out", run, "--iters", 1, "--frame-stride", 2, "--no-video", "--fresh")
    assert r.exit_code == 0, r.output


def test_an_evaluation_never_reads_a_flow_cache_made_from_other_frames(tmp_path):
    """The report scores EPE against the observed flow through identification's keyed cache: a cache left by
    another video (the same file name, another key) is estimated again, not served."""
    from types import SimpleNamespace

    from endogsim.identify import IdentifyConfig
    from endogsim.identify.loss import observed_flow
    from endogsim.identify.report import reference_observed_flow
    from endogsim.io.atomic import save_npz_atomic

    rng = np.random.default_rng(0)
    frames = np.clip(rng.random((3, 40, 48, 3), dtype=np.float32), 0, 1)
    cfg = IdentifyConfig()
    save_npz_atomic(tmp_path / "observed_flow.npz", compressed=True, flow=np.full((2, 40, 48, 2), 7.0, np.float32),
                    key=np.array("another video"))
    got = reference_observed_flow(SimpleNamespace(gt_flow=None, frames=frames), cfg, tmp_path)
    np.testing.assert_array_equal(got, observed_flow(frames, cfg.flow))
    assert not np.any(got == 7.0)
    again = reference_observed_flow(SimpleNamespace(gt_flow=None, frames=frames), cfg, tmp_path)  # now cached
    np.testing.assert_array_equal(again, got)
    with_truth = SimpleNamespace(gt_flow=np.zeros((2, 40, 48, 2), np.float32), frames=frames)
    assert reference_observed_flow(with_truth, cfg, tmp_path) is None  # the ground truth is the reference


def test_identify_and_simulate_refuse_materials_for_objects_the_scene_lacks(tiny, tmp_path):
    from endogsim.identify import run_identify
    from endogsim.pipeline.simulate import simulate_interaction

    d = json.loads(cli_materials(tiny, tmp_path / "m.json").read_text())
    d["objects"].append({**d["objects"][0], "object_id": 7, "name": "spleen"})
    (tmp_path / "m.json").write_text(json.dumps(d))
    with pytest.raises(MaterialError, match="'spleen' \\(id 7\\), which scene 'tiny' .* does not have"):
        run_identify(tiny, tmp_path / "run", init=str(tmp_path / "m.json"))
    with pytest.raises(MaterialError, match="'spleen' \\(id 7\\)"):
        simulate_interaction(tiny, "poke", tmp_path / "m.json", tmp_path / "sim")
    assert not (tmp_path / "run").exists() and not (tmp_path / "sim").exists()
    one_line_error(cli("simulate", tiny, "-i", "poke", "-m", tmp_path / "m.json", "--out", tmp_path / "sim"), "spleen")
    assert not (tmp_path / "sim").exists()


def cli_materials(data: Path, out: Path, *extra) -> Path:
    """``endogsim materials init DATA --out OUT`` (prior backend unless ``extra`` says otherwise)."""
    r = cli("materials", "init", data, "--out", out, *extra)
    assert r.exit_code == 0, r.output
    return out


# ------------------------------------------------------------------------------------------------------ simulate
def test_an_interaction_that_moves_the_tool_out_of_the_box_is_refused(tiny, tmp_path):
    from endogsim.pipeline.simulate import simulate_interaction

    far = {"name": "far", "frames": 6, "tool": {"at": [0.0, 0.0], "keyframes": [[0, 0, 0, 0], [1.0, 0, 0, 0.1]]}}
    with pytest.raises(DataError, match="moves tool 'probe' \\(id 2\\) out of the simulation box .* at frame 3 its "
                                        "tip is at z = .* not grown"):
        simulate_interaction(tiny, far, "truth", tmp_path / "sim")
    back = {**far, "tool": {"keyframes": [[0, 0, 0, 0], [1.0, 0, 0, -0.1]]}}
    with pytest.raises(DataError, match="out of the simulation box"):
        simulate_interaction(tiny, back, "truth", tmp_path / "sim")
    assert not (tmp_path / "sim").exists()


def test_simulate_frames_are_validated_like_the_files(tiny, tmp_path):
    one_line_error(cli("simulate", tiny, "-i", "poke", "--frames", 0, "--out", tmp_path / "sim"),
                   "--frames 0: invalid interaction (frames: Input should be greater than or equal to 2)")
    one_line_error(cli("simulate", tiny, "-i", "poke", "--frames", 100000, "--out", tmp_path / "sim"), "less than or equal to 400")
    assert not (tmp_path / "sim").exists()


def test_a_force_without_an_end_round_trips_through_its_json(tmp_path):
    from endogsim.pipeline.interaction import load_interaction

    inter = load_interaction({"name": "hold", "force": {"at": [0, 0], "acceleration": [0, 0, 10]}})
    p = write_json_atomic(tmp_path / "interaction.json", inter.model_dump(mode="json"))
    assert strict_json(p)["force"]["t_end"] is None and load_interaction(p) == inter


# ------------------------------------------------------------------------------------------------------ synth
@pytest.mark.parametrize("args, needle", [
    (["--frames", 1_000_000_000], "--frames 1000000000: a synthesized scene has 2 to 400 frames"),
    (["--scale", 1000], "images of 160000x128000 px: the limit is 2048 px a side"),
    (["--scale", 12, "--frames", 400], "400 frames of 1920x1536 px are 1180 M pixel-frames; the limit is 50 M"),
])
def test_synth_sizes_are_bounded_up_front(tmp_path, args, needle):
    one_line_error(cli("synth", "tiny", "--out", tmp_path / "big", *args), needle)
    assert not (tmp_path / "big").exists()


def test_particle_count_is_bounded():
    from endogsim.synth.suite import MAX_PARTICLES, check_size

    check_size(24, 160, 128, 5000)
    with pytest.raises(DataError, match=f"the limit is {MAX_PARTICLES}"):
        check_size(particles=MAX_PARTICLES + 1)


# ------------------------------------------------------------------------------------------------------ materials
def test_materials_init_reads_scene_folders_and_run_folders(tiny, tmp_path):
    from endogsim.materials import MaterialField

    f = MaterialField.load(cli_materials(tiny, tmp_path / "scene.json.materials"))
    assert {r.object_id: (r.name, r.klass, r.rigid) for r in f.records} == {
        1: ("tissue", "liver", False), 2: ("probe", "instrument", True)}
    recon = tmp_path / "recon"  # a reconstruction run folder: objects.json and provenance.json
    recon.mkdir()
    (recon / "objects.json").write_text(json.dumps({"1": {"name": "tissue", "is_tool": False, "class": "liver"}}))
    (recon / "provenance.json").write_text(json.dumps({"data": str(tiny)}))
    assert MaterialField.load(cli_materials(recon, tmp_path / "r.json"))[1].klass == "liver"
    one_line_error(cli("materials", "init", recon, "--backend", "mllm", "--out", tmp_path / "x.json"),
                   f"the mllm/replay backends need a data folder (this run was made from {tiny})")
    run = tmp_path / "run"  # an `endogsim run` folder: its scene
    (run / "scene").mkdir(parents=True)
    (run / "scene" / "scene.json").write_text((Path(tiny) / "scene.json").read_text())
    assert MaterialField.load(cli_materials(run, tmp_path / "s.json"))[2].rigid


class SilentOrHtmlServer:
    """A local endpoint that answers every request with an HTML page (status 200), or after ``delay`` s."""

    def __init__(self, delay: float = 0.0) -> None:
        import threading
        from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

        outer = self
        self.requests = 0

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def do_POST(self):
                outer.requests += 1
                self.rfile.read(int(self.headers["Content-Length"]))
                time.sleep(delay)
                page = b"<html><body>Welcome to nginx!</body></html>"
                try:
                    self.send_response(200)
                    self.send_header("Content-Type", "text/html")
                    self.send_header("Content-Length", str(len(page)))
                    self.end_headers()
                    self.wfile.write(page)
                except (BrokenPipeError, ConnectionResetError):
                    pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/v1"
        threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True).start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def two_objects():
    """A 32x32, two-frame scene with a liver (id 1) and a gallbladder (id 2)."""
    from endogsim.io.scene import ObjectLabel, Scene

    frames = np.random.default_rng(0).uniform(0.2, 0.8, (2, 32, 32, 3)).astype(np.float32)
    masks = np.full((2, 32, 32), -1, np.int32)
    masks[:, :16], masks[:, 16:] = 1, 2
    labels = {1: ObjectLabel(1, "liver", False, "liver"), 2: ObjectLabel(2, "gallbladder", False, "gallbladder")}
    return Scene(frames=frames, times=np.array([0.0, 0.04]), K=np.eye(3), object_masks=masks, labels=labels)


def mllm_field(tmp_path, url: str, **cfg):
    from endogsim.materials import MaterialInitConfig, MLLMConfig, MLLMFallbackWarning, initialise_materials

    scene = two_objects()
    mcfg = MLLMConfig(model="m", base_url=url, cache_dir=tmp_path / "cache", **cfg)
    with pytest.warns(MLLMFallbackWarning):
        return initialise_materials(scene.labels, MaterialInitConfig(backend="mllm", mllm=mcfg), scene)


def test_mllm_unreachable_fails_fast_and_records_the_real_source(tmp_path):
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    f = mllm_field(tmp_path, f"http://127.0.0.1:{port}/v1", max_retries=0)
    assert f[1].source.startswith("prior (mllm fallback: APIConnectionError")
    assert f[2].source.startswith("prior (mllm fallback: endpoint unreachable (APIConnectionError")
    assert f.meta["backend"] == "mllm" and f.meta["sources"] == {"mllm": 0, "prior": 2}
    assert "2 of 2 objects took the prior" in f.meta["note"]


def test_silent_mllm_is_bounded_in_total_time(tmp_path):
    server = SilentOrHtmlServer(delay=5.0)
    try:
        t0 = time.monotonic()
        f = mllm_field(tmp_path, server.url, timeout_s=60.0, total_timeout_s=1.0, max_retries=2)
        assert time.monotonic() - t0 < 4.0  # 1 s of budget (the default 60 s x 3 tries x 2 objects: 6 min)
    finally:
        server.close()
    assert "Timeout" in f[1].source and "unreachable" in f[2].source


def test_mllm_answering_html_falls_back_with_a_reason(tmp_path):
    server = SilentOrHtmlServer()
    try:
        f = mllm_field(tmp_path, server.url, max_retries=0)
    finally:
        server.close()
    assert "did not answer in the chat-completions format" in f[1].source and f[1].E == 5e3


# ------------------------------------------------------------------------------------------------------ loaders
def endonerf_copy(tiny: Path, dst: Path) -> Path:
    """The tiny scene as a plain EndoNeRF folder (images, 16-bit depth, masks, poses_bounds.npy)."""
    import shutil

    for sub in ("images", "depth", "masks"):
        shutil.copytree(tiny / sub, dst / sub)
    shutil.copy(tiny / "poses_bounds.npy", dst / "poses_bounds.npy")
    return dst


def test_a_text_file_named_poses_bounds_is_named_as_such(tiny, tmp_path):
    from endogsim.io import load_scene

    d = endonerf_copy(tiny, tmp_path / "d")
    (d / "poses_bounds.npy").write_text("focal 569\n")
    with pytest.raises(DataError, match="poses_bounds.npy: not a NumPy .npy file \\(no NUMPY header"):
        load_scene(d)


def test_assumed_intrinsics_and_saturated_depth_are_warned_and_recorded(tiny, tmp_path):
    import cv2

    from endogsim.io import load_scene
    from endogsim.recon.config import ReconConfig
    from endogsim.recon.train import reconstruct

    d = endonerf_copy(tiny, tmp_path / "d")
    (d / "poses_bounds.npy").unlink()
    depth = sorted((d / "depth").glob("*.png"))
    for p in depth:
        im = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        im[:8] = 65535  # the top rows saturated
        cv2.imwrite(str(p), im)
    with pytest.warns(DataWarning) as caught:
        s = load_scene(d)
    assert any("no poses_bounds.npy: intrinsics assumed (a 75-degree" in str(w.message) for w in caught)
    assert any("6.2% of the depth pixels in depth/ are saturated at 65535" in str(w.message) for w in caught)
    assert (s.depth[:, :8] == 0).all() and len(s.notes) == 2
    with pytest.warns(DataWarning):
        reconstruct(d, tmp_path / "run", ReconConfig(**RECON))
    assert strict_json(tmp_path / "run" / "metrics.json")["data_notes"] == s.notes


def test_a_truncated_video_is_warned_and_recorded(tmp_path):
    import imageio_ffmpeg

    from endogsim.io import load_scene

    frames = (np.random.default_rng(0).uniform(0, 1, (60, 64, 80, 3)) * 255).astype(np.uint8)
    w = imageio_ffmpeg.write_frames(str(tmp_path / "full.mp4"), (80, 64), fps=30,
                                    output_params=["-movflags", "+faststart"], macro_block_size=16)  # index first
    w.send(None)
    for f in frames:
        w.send(f)
    w.close()
    data = (tmp_path / "full.mp4").read_bytes()
    (tmp_path / "cut.mp4").write_bytes(data[: len(data) // 2])
    with pytest.warns(DataWarning, match="but the container says 2 s at 30 fps \\(about 60 frames\\): the file is "
                                         "probably truncated"):
        s = load_scene(tmp_path / "cut.mp4")
    assert s.num_frames < 50 and "truncated" in s.notes[0]
    assert not load_scene(tmp_path / "full.mp4").notes


# ------------------------------------------------------------------------------------------------------ run
def test_run_stages_are_done_only_while_their_inputs_and_outputs_match(tiny, other, tmp_path):
    from endogsim.pipeline.run import PipelineConfig, run_pipeline

    cfg = PipelineConfig(recon={**RECON, "resolution_scale": 1.0}, tool_motion="truth")
    out = tmp_path / "run"

    def run(data, **kw) -> list:
        seen = []
        run_pipeline(data, out, cfg, truth=data, stop_after="scenario", on_stage=lambda s, st: seen.append((s, st)),
                     **kw)
        return [st for _, st in seen if st != "start"]

    assert run(tiny) == ["done", "done"]
    assert run(tiny) == ["skip", "skip"]
    (out / "scene" / "scene.json").write_text("{")  # a truncated stage file: that stage runs again
    assert run(tiny) == ["skip", "done"]
    metrics = out / "recon" / "metrics.json"
    metrics.write_bytes(metrics.read_bytes()[:50])
    assert run(tiny)[0] == "done"  # resumed from its checkpoint and exported again
    state = strict_json(out / "run.json")
    assert set(state["stages"]["reconstruct"]) >= {"done", "inputs", "outputs"}
    with pytest.raises(DataError, match="was made from .*--fresh"):  # another dataset into this run folder
        run(other)
    assert run(other, fresh=True) == ["done", "done"]


@pytest.mark.parametrize("text", ['{"data": "x"}', "[]", '{"stages": []}', '{"stages": {"reconstruct": 1}}'])
def test_a_run_state_that_is_json_but_not_a_run_state_is_one_line(tmp_path, text):
    from endogsim.pipeline.run import _load_state

    (tmp_path / "run.json").write_text(text)
    with pytest.raises(DataError, match=r"run\.json: not a run state .*--fresh"):
        _load_state(tmp_path / "run.json")


# ------------------------------------------------------------------------------------------------------ kill and resume
@pytest.mark.slow
def test_a_sigkilled_identify_resumes_to_the_same_result_and_leaves_no_lock(tiny, tmp_path):
    import signal

    from endogsim.identify import IdentifyConfig, run_identify

    args = ["identify", str(tiny), "--iters", "4", "--frame-stride", "2", "--no-video", "--time-budget", "600"]
    ref = run_identify(tiny, tmp_path / "ref", config=IdentifyConfig(iters=4, frame_stride=2, time_budget=600),
                       video=False)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "src"), "OMP_NUM_THREADS": "1"}
    p = subprocess.Popen([sys.executable, "-c", "from endogsim.cli.main import app; app()", *args, "--out", str(tmp_path / "cut")],
                         env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ckpt = tmp_path / "cut" / "checkpoint.pt"
    while not ckpt.is_file() and p.poll() is None:
        time.sleep(0.05)
    p.send_signal(signal.SIGKILL)
    assert p.wait() == -signal.SIGKILL and not (tmp_path / "cut" / "metrics.json").exists()
    r = cli(*args, "--out", tmp_path / "cut")  # the killed holder's lock went with it
    assert r.exit_code == 0, r.output
    assert not (tmp_path / ".cut.lock").exists()
    got = strict_json(tmp_path / "cut" / "metrics.json")
    assert got["materials"] == strict_json(tmp_path / "ref" / "metrics.json")["materials"] == ref["materials"]


# ------------------------------------------------------------------------------------------------------ stop 29 audit
def test_the_working_folder_is_never_replaced_or_written_into(tiny, tmp_path, monkeypatch):
    from endogsim.io.atomic import atomic_folder

    work = tmp_path / "work"
    work.mkdir()
    (work / "mine.txt").write_text("the user's own file")
    monkeypatch.chdir(work)
    for target in (".", "", "..", str(work)):
        with pytest.raises(OSError, match="the working folder"):
            with atomic_folder(target):
                pass
    for args in (["synth", "tiny", "--out", "", "--frames", 3], ["identify", tiny, "--out", ".", "--iters", 0]):
        r = cli(*args)
        assert r.exit_code == 2 and "name a folder to write" in r.output, r.output
    assert sorted(p.name for p in work.iterdir()) == ["mine.txt"]


def test_simulate_finds_the_identified_materials_of_either_run_layout(tiny, tmp_path):
    import shutil

    from endogsim.pipeline.simulate import resolve_scene

    run = tmp_path / "run"  # `endogsim run`: RUN/scene/ and RUN/identify/materials_identified.json
    shutil.copytree(tiny, run / "scene")
    (run / "identify").mkdir()
    (run / "identify" / "materials_identified.json").write_text("{}")
    assert resolve_scene(run) == (run / "scene", run / "identify" / "materials_identified.json")
    ident = tmp_path / "ident"  # `endogsim identify`: metrics.json names the scene folder, maybe relatively
    ident.mkdir()
    (ident / "materials_identified.json").write_text("{}")
    (ident / "metrics.json").write_text(json.dumps({"folder": "/gone/scene", "folder_from_run": "../run/scene"}))
    assert resolve_scene(ident) == (ident / "../run/scene", ident / "materials_identified.json")  # both moved
    (ident / "metrics.json").write_text("{}")  # a reconstruction's metrics name no scene
    with pytest.raises(DataError, match="names no scene folder"):
        resolve_scene(ident)
    one_line_error(cli("simulate", tiny, "-i", "poke", "--out", tiny), "--out is the scene")
    (ident / "metrics.json").write_text('{"folder": "run/sce')
    with pytest.raises(DataError, match="metrics.json: not a JSON object"):
        resolve_scene(ident)


@pytest.mark.parametrize("option, needle", [
    ({"iters": "100"}, "iters = '100' must be an integer"),
    ({"deformation": {"resolution": [0, 0, 0]}}, "deformation.resolution \\[0, 0, 0\\] must be 3 integers >= 2"),
    ({"deformation": {"multires": [0]}}, "deformation.multires \\[0\\] must be integers >= 1"),
    ({"deformation": {"resolution": 5}}, "deformation.resolution = 5 must be a list of integers"),
    ({"flow": "dis"}, "flow = 'dis' must be a table"),
    ({"checkpoint_every": 0}, "checkpoint_every 0 must be >= 1"),
    ({"lr_means": -1.0}, "lr_means -1.0 must be > 0"),
    ({"sh_degree": -1}, "sh_degree -1 must be 0, 1, 2 or 3"),
])
def test_reconstruction_config_files_are_checked_before_anything_runs(tmp_path, option, needle):
    from endogsim.recon.config import ReconConfig

    # resolution [0, 0, 0] and multires [0] crashed the HexPlane kernel with a segfault
    with pytest.raises(DataError, match=f"cfg.json: {needle}"):
        ReconConfig.from_dict(option, source="cfg.json")


@pytest.mark.parametrize("edit, needle", [
    (lambda d: next(b for b in d["scenario"]["boundary_conditions"] if b["type"] == "anchors").update(object="livr"),
     "names object 'livr', which the scene"),
    (lambda d: d["scenario"]["boundary_conditions"].append({"type": "magic"}), "type is one of anchors, box_walls, static"),
    (lambda d: d["scenario"]["tools"][0].update(radius=-0.003), "tool 2 radius \\(m\\) = -0.003 must be a number > 0"),
    (lambda d: d["scenario"]["tools"][0].update(tip=[0.0, 0.0]), "tool 2 tip \\(m\\) = .* must be 3 finite"),
    (lambda d: d["scenario"]["identification"].update(grid=38.5), "identification.grid = 38.5 must be an integer"),
    (lambda d: d["scenario"].update(box_size="big"), "box_size \\(m\\) = 'big' must be a number"),
    (lambda d: d["camera"].update(K=[[1, 0], [0, 1]]), "camera.K \\(pixels\\) = .* must be 3 x 3"),
    (lambda d: d["objects"][1].update(id=d["objects"][0]["id"]), "object ids .* must be distinct integers"),
])
def test_scene_geometry_is_checked_on_load(tiny, tmp_path, edit, needle):
    from endogsim.scene.schema import load_scene_spec

    bad = scene_copy(tiny, tmp_path / "bad", edit)
    with pytest.raises(DataError, match=needle):
        load_scene_spec(bad)
    one_line_error(cli("simulate", bad, "-i", "poke", "--out", tmp_path / "sim", "--frames", 2), "scene.json")


def test_a_single_frame_and_impossible_options_are_refused_before_any_work(tiny, tmp_path):
    one = tmp_path / "one"  # a clip of one frame: no motion, nothing to hold out
    (one / "images").mkdir(parents=True)
    import shutil

    shutil.copy(tiny / "images" / "frame-000000.color.png", one / "images" / "frame-000000.color.png")
    one_line_error(cli("reconstruct", one, "--out", tmp_path / "r", "--iters", 5), "1 frame; a 4D reconstruction")
    one_line_error(cli("identify", tiny, "--out", tmp_path / "i", "--iters", 1, "--device", "tpu"),
                   "device 'tpu' is not cpu, cuda or cuda:N")
    one_line_error(cli("identify", tiny, "--out", tmp_path / "i2", "--iters", 1, "--render-scale", 0.01),
                   "comparing motion needs at least 8 px a side")


def test_run_options_are_checked_before_the_reconstruction(tiny, tmp_path):
    for args, needle in ((["--interaction", "bogus"], "unknown interaction 'bogus'"),
                         (["--materials-backend", "bogus"], "--materials-backend 'bogus' is neither"),
                         (["--truth", tmp_path / "nope"], "nope: no scene.json"),
                         (["--device", "tpu"], "device 'tpu' is not cpu, cuda or cuda:N"),
                         (["--time-budget", "-1"], "time_budget = -1.0 s must be > 0")):
        one_line_error(cli("run", tiny, "--out", tmp_path / "run", *args), needle)
        assert not (tmp_path / "run").exists()  # refused before any stage ran
    one_line_error(cli("validate", tiny, "--out", tmp_path / "v", "--device", "tpu"), "device 'tpu'")
    assert not (tmp_path / "v").exists()
    from endogsim.cli.demo import _identify_config  # --time-budget: the pipeline's 480 s, a number, or 0: none

    assert [_identify_config(None, None, time_budget=b).time_budget for b in (None, 60, 0)] == [480, 60, None]
    # --refined-correction: identification's 1.5, a factor, or 0: none
    assert [_identify_config(None, None, refined_correction=f).refined_correction
            for f in (None, 1.3, 0)] == [1.5, 1.3, None]
    one_line_error(cli("run", tiny, "--out", tmp_path / "run", "--refined-correction", "0.5"),
                   "refined_correction = 0.5 must lie in (1, 4]")
    one_line_error(cli("validate", tiny, "--out", tmp_path / "v", "--json", tmp_path), "--json names a folder")


def test_a_moved_run_folder_resumes_its_identification(tiny, tmp_path):
    import shutil

    from endogsim.identify import IdentifyConfig, run_identify

    shutil.copytree(tiny, tmp_path / "a" / "scene")
    run_identify(tmp_path / "a" / "scene", tmp_path / "a" / "identify", config=IdentifyConfig(iters=1, frame_stride=2, intervals=False),
                 video=False)
    first = json.loads((tmp_path / "a" / "identify" / "history.json").read_text())
    shutil.move(tmp_path / "a", tmp_path / "b")  # the whole run folder, scene and all, somewhere else
    m = run_identify(tmp_path / "b" / "scene", tmp_path / "b" / "identify",
                     config=IdentifyConfig(iters=2, frame_stride=2, intervals=False), video=False)
    again = json.loads((tmp_path / "b" / "identify" / "history.json").read_text())
    assert m["iterations"] == 2 and again[0]["loss"] == first[0]["loss"]  # resumed, not started over


def test_a_report_of_metrics_that_are_not_an_identify_runs_is_refused(tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "metrics.json").write_text("{}")  # it wrote a report of "None"s
    one_line_error(cli("report", tmp_path / "run"), "metrics.json lacks scene, loss, iterations, materials")


def test_a_new_interaction_draws_the_instruments_the_video_hid(tiny, tmp_path):
    from endogsim.pipeline.interaction import load_interaction
    from endogsim.pipeline.simulate import build_interaction
    from endogsim.scene.folder import load_sim_scene

    def hide(d):  # the probe out of view in frame 1 of the 4 filmed
        d["scenario"]["tools"][0]["visible"] = [True, False, True, True]

    scene = scene_copy(tiny, tmp_path / "scene", hide)
    base = load_sim_scene(scene)
    assert set(base.tool_visible) == {2}
    problem, _ = build_interaction(base, load_interaction("poke"))
    assert problem.tool_visible == {}  # the video's visibility is not the new experiment's
    r = cli("simulate", scene, "-i", "poke", "--out", tmp_path / "sim", "--frames", 6, "--no-ply")
    assert r.exit_code == 0, r.output  # longer than the clip: it indexed the clip's visibility past its end


def _moving_endoscope(d, frames=FRAMES):
    """scene.json edit: a camera that moves sideways 1 mm a frame and brightens 5% a frame (a moving
    endoscope's reconstruction), with a field of view."""
    views = np.eye(4)[None].repeat(frames, 0)
    views[:, 0, 3] = -0.001 * np.arange(frames)
    d["camera"]["viewmats"] = views.tolist()
    d["camera"]["exposure"] = {"log_gain": [[0.05 * t] * 3 for t in range(frames)], "bias": [[0.0] * 3] * frames}
    d["files"]["field_of_view"] = "field_of_view.png"


def test_a_scene_folder_carries_the_endoscopes_exposure_and_field_of_view(tiny, tmp_path):
    import cv2
    import torch

    from endogsim.scene.folder import load_sim_scene

    scene = scene_copy(tiny, tmp_path / "scene", _moving_endoscope)
    d = json.loads((scene / "scene.json").read_text())
    circle = np.zeros((d["camera"]["height"], d["camera"]["width"]), np.uint8)
    cv2.circle(circle, (circle.shape[1] // 2, circle.shape[0] // 2), circle.shape[0] // 2, 255, -1)
    cv2.imwrite(str(scene / "field_of_view.png"), circle)
    p = load_sim_scene(scene)
    assert p.exposure.shape == (FRAMES, 2, 3) and float(p.exposure[2, 0, 1]) == pytest.approx(0.10)
    assert torch.equal(p.field_of_view, torch.from_numpy(circle > 0))

    cv2.imwrite(str(scene / "field_of_view.png"), circle[:-2])
    with pytest.raises(DataError, match="field_of_view.png: the field of view is .* the camera"):
        load_sim_scene(scene)
    bad = scene_copy(tiny, tmp_path / "bad", lambda d: (_moving_endoscope(d, FRAMES - 1)))
    with pytest.raises(DataError, match="camera.exposure.log_gain = .* must be 4 x 3 finite"):
        load_sim_scene(bad)


def test_a_new_interaction_on_a_moving_endoscope_is_filmed_from_frame_0s_camera(tiny, tmp_path):
    """The clip's camera path and exposure are the video's, like its instruments' visibility: a new experiment,
    longer than the clip or not, is seen by frame 0's camera (the world frame), as frame 0 exposed it."""
    from endogsim.pipeline.interaction import load_interaction
    from endogsim.pipeline.simulate import build_interaction
    from endogsim.scene.folder import load_sim_scene

    scene = scene_copy(tiny, tmp_path / "scene", lambda d: (_moving_endoscope(d), d["files"].pop("field_of_view")))
    base = load_sim_scene(scene)
    assert base.viewmats is not None and base.exposure is not None
    problem, _ = build_interaction(base, load_interaction("poke"))
    assert problem.viewmats is None and problem.exposure is None
    r = cli("simulate", scene, "-i", "poke", "--out", tmp_path / "sim", "--frames", 6, "--no-ply")
    assert r.exit_code == 0, r.output  # it indexed the clip's 4 camera poses past their end
