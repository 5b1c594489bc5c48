"""``endogsim demo``: the preview render runs from the CLI and writes a playable video and PNG frames; the
demo is a function of its seed (same seed, same materials; another seed, another scene)."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest
from typer.testing import CliRunner

from endogsim.cli.main import app
from endogsim.errors import DataError
from endogsim.pipeline.demo import DemoConfig, run_demo, synthesize_observed
from endogsim.synth.suite import DEMO_SCENE

# The demo on 6 frames of its scene (tiny_lift) with 12 reconstruction iterations and 1 identification iteration
# (its 90% intervals included). The grasper's path spans the clip: on 4 frames it lifts the patch 7 mm in 15 ms
# and the ground truth parts beside the bite (0.10% of the footprint on seed 0), which the generator refuses.
REDUCED = dict(frames=6, recon={"resolution_scale": 1.0, "iters": 12, "track_warmup_iters": 20},
               identify={"iters": 1})


def test_demo_writes_video_and_frames(tmp_path):
    res = CliRunner().invoke(app, ["demo", "--preview", "--out", str(tmp_path), "--preview-frames", "3"])
    assert res.exit_code == 0, res.output
    pngs = sorted((tmp_path / "frames").glob("*.png"))
    assert len(pngs) == 3
    img = iio.imread(pngs[1])
    assert img.shape == (256, 320, 3)
    # Tissue fills the view: reddish on average, and the tool adds grey pixels.
    mean = img.reshape(-1, 3).mean(0)
    assert mean[0] > 1.3 * mean[1] and mean[0] > 60
    video = iio.imread(tmp_path / "render.mp4")
    assert video.shape[0] == 3 and np.abs(video[1].astype(float) - img).mean() < 20  # lossy codec


def test_demo_rejects_bad_options(tmp_path):
    res = CliRunner().invoke(app, ["demo", "--preview", "--out", str(tmp_path), "--preview-frames", "1"])
    assert res.exit_code != 0 and "--preview-frames" in res.output


@pytest.fixture(scope="module")
def seed0_twice(tmp_path_factory):
    """Two reduced demos with seed 0, each in its own folder, from a process with 1 and with 2 torch threads
    (the demo runs on its own ``threads``, 1, and puts the process's setting back), the first with one
    simulation at a time, the second with two side by side."""
    import torch

    root = tmp_path_factory.mktemp("demo")
    before, runs = torch.get_num_threads(), []
    try:
        for k in range(2):
            torch.set_num_threads(k + 1)
            runs.append((root / f"run{k}", run_demo(root / f"run{k}", DemoConfig(**REDUCED, workers=k + 1))))
            assert torch.get_num_threads() == k + 1
    finally:
        torch.set_num_threads(before)
    return runs


def _identify_record(out) -> tuple:
    """What identification computed (no paths, no timings): materials, history and the interval evidence."""
    d = out / "run" / "identify"
    mats = json.loads((d / "materials_identified.json").read_text())["objects"]
    hist = [{k: v for k, v in h.items() if k != "seconds"} for h in json.loads((d / "history.json").read_text())]
    m = json.loads((d / "metrics.json").read_text())
    return mats, hist, m["identifiable"], m["intervals"], m["re_mean"], m["epe"]


def test_the_same_seed_gives_the_same_materials_whatever_the_processs_thread_count_and_the_workers(seed0_twice):
    (a, sa), (b, sb) = seed0_twice
    assert sa["seed"] == sb["seed"] == 0 and sa["threads"] == sb["threads"] == 1
    assert (sa["workers"], sb["workers"]) == (1, 2)
    assert sa["materials"] == sb["materials"] and sa["materials"][0]["E_identified"] > 0
    lo, hi = sa["materials"][0]["E_interval"]  # the summary carries each result's 90% interval and source
    assert lo <= sa["materials"][0]["E_identified"] <= hi and sa["materials"][0]["source"]
    assert sa["iterations"] == sb["iterations"] == {"reconstruct": 12, "identify": 1}
    assert sa["stopped_by_budget"] == sb["stopped_by_budget"] == {"reconstruct": False, "identify": False}
    assert _identify_record(a) == _identify_record(b)
    assert sa["recon_psnr_masked"] == sb["recon_psnr_masked"]
    assert (a / "scene_truth" / "images").is_dir() and (a / "render.mp4").is_file()


def test_the_demo_table_shows_each_result_with_its_interval():
    from endogsim.cli.common import with_interval

    assert with_interval(2472.85, [1715.1, 3084.9], ".4g") == "2473 [1715, 3085]"
    assert with_interval(0.47, None, ".3f") == "0.470" and with_interval(None, None, ".3f") == "-"


def test_another_seed_gives_another_scene(seed0_twice, tmp_path):
    (a, _), _ = seed0_twice
    other = synthesize_observed(tmp_path, DemoConfig(**REDUCED, seed=1))  # the demo's first step
    spec0 = json.loads((a / "scene_truth" / "scene.json").read_text())
    spec1 = json.loads((other / "scene.json").read_text())
    assert (spec0["seed"], spec1["seed"]) == (0, 1)
    assert spec0["objects"] == spec1["objects"] and spec0["frames"] == spec1["frames"] == REDUCED["frames"]
    im0 = sorted((a / "scene_truth" / "images").glob("*.png"))
    im1 = sorted((other / "images").glob("*.png"))
    assert len(im0) == len(im1) == REDUCED["frames"]
    diff = np.abs(iio.imread(im0[0]).astype(float) - iio.imread(im1[0]).astype(float)).mean()
    assert diff > 2.0, diff  # other textures (8-bit levels)


def test_a_folder_of_another_seed_is_refused(seed0_twice):
    (a, _), _ = seed0_twice
    with pytest.raises(DataError, match=f"seed 0, not '{DEMO_SCENE}' with seed 1"):
        run_demo(a, DemoConfig(**REDUCED, seed=1))
    res = CliRunner().invoke(app, ["demo", "--out", str(a), "--seed", "2"])  # --seed reaches the demo
    assert res.exit_code == 2 and "with seed 2" in res.output
