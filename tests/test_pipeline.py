"""End-to-end pipeline: scenario from a reconstruction, staged resumable `run`, the demo on a reduced setting."""

from __future__ import annotations

import json
import math
import shutil
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from endogsim.errors import DataError
from endogsim.pipeline.scene_from_recon import fit_tool_capsule


def test_capsule_fit_recovers_a_cylinder_seen_from_one_side():
    rng = np.random.default_rng(0)
    tip, end, r = np.array([0.01, 0.0, 0.06]), np.array([0.04, 0.02, 0.03]), 0.003
    axis = (end - tip) / np.linalg.norm(end - tip)
    e1 = np.cross(axis, [0, 0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    s = rng.uniform(0, np.linalg.norm(end - tip), 4000)
    ang = rng.uniform(0, 2 * math.pi, 4000)
    pts = tip + s[:, None] * axis + r * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
    centre = tip + s[:, None] * axis
    visible = ((pts - centre) * (-pts)).sum(1) > 0  # the half facing the camera at the origin
    t_fit, e_fit, r_fit = fit_tool_capsule(pts[visible])
    assert r_fit == pytest.approx(r, rel=0.1)
    assert np.linalg.norm(t_fit - tip) < 1.5e-3 and np.linalg.norm(e_fit - end) < 1.5e-3


def test_capsule_fit_refuses_too_few_points():
    with pytest.raises(DataError, match="at least 4"):
        fit_tool_capsule(np.zeros((2, 3)))


class _TagChecker(HTMLParser):
    VOID = {"meta", "img", "br", "hr", "source", "link", "input", "col", "wbr"}

    def __init__(self):
        super().__init__()
        self.stack, self.links = [], []

    def handle_starttag(self, tag, attrs):
        for k, v in attrs:
            if k in ("src", "href") and v and not v.startswith(("data:", "#")):
                self.links.append(v)
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if tag not in self.VOID:
            assert self.stack and self.stack[-1] == tag, f"unbalanced </{tag}>"
            self.stack.pop()


@pytest.fixture(scope="module")
def tiny_truth(tmp_path_factory):
    from endogsim.synth import synthesize

    return synthesize("tiny", tmp_path_factory.mktemp("pipe") / "truth", seed=0, frames=4)


def test_run_resumes_after_an_interrupted_stage_and_reports(tiny_truth, tmp_path):
    from endogsim.pipeline.run import PipelineConfig, run_pipeline

    cfg = PipelineConfig(recon={"iters": 12, "resolution_scale": 1.0, "eval_every": 0},
                         identify={"iters": 1, "time_budget": 120}, interaction="poke", tool_motion="truth")
    seen = []
    state = run_pipeline(tiny_truth, tmp_path, cfg, truth=tiny_truth, stop_after="scenario",
                         on_stage=lambda s, st: seen.append((s, st)))
    assert set(state["stages"]) == {"reconstruct", "scenario"}
    scene = json.loads((tmp_path / "scene" / "scene.json").read_text())
    truth = json.loads((Path(tiny_truth) / "scene.json").read_text())
    assert scene["objects"] == truth["objects"] and scene["scenario"]["box_size"] == truth["scenario"]["box_size"]
    assert scene["frames"] == 4 and (tmp_path / "scene" / "gaussians_t0.ply").is_file()

    seen.clear()
    state = run_pipeline(tiny_truth, tmp_path, cfg, truth=tiny_truth, on_stage=lambda s, st: seen.append((s, st)))
    assert ("reconstruct", "skip") in seen and ("scenario", "skip") in seen and ("identify", "done") in seen
    assert all(state["stages"][s]["done"] for s in ("identify", "simulate", "report"))
    assert math.isfinite(state["stages"]["identify"]["re_mean"])
    # the stage's seconds are its wall time, not metrics.json's seconds of its iterations
    ident = state["stages"]["identify"]
    assert ident["seconds"] >= ident["optimisation_seconds"] > 0
    # the simulate stage simulates the identified materials where they belong (1.5x after a refined correction)
    meta = json.loads((tmp_path / "identify" / "materials_identified.json").read_text())["meta"]
    assert state["stages"]["simulate"]["summary"]["discretisation"]["refine"] == meta["refine"]
    html = Path(state["stages"]["report"]["report"])
    checker = _TagChecker()
    checker.feed(html.read_text())
    assert not checker.stack
    for link in checker.links:
        assert (html.parent / link).exists(), link

    # The finished run moved elsewhere resumes with nothing to do and names its outputs where they are now.
    moved = tmp_path.parent / (tmp_path.name + "_moved")
    shutil.move(tmp_path, moved)
    seen.clear()
    state = run_pipeline(tiny_truth, moved, cfg, truth=tiny_truth, on_stage=lambda s, st: seen.append((s, st)))
    assert all(st == "skip" for _, st in seen) and len(seen) == 5
    assert Path(state["stages"]["report"]["report"]) == moved / "report.html"
    stored = json.loads((moved / "run.json").read_text())["stages"]
    assert stored["scenario"]["scene"] == stored["simulate"]["summary"]["scene_folder"] == str(moved / "scene")


def test_run_refuses_a_missing_dataset(tmp_path):
    from endogsim.pipeline.run import run_pipeline

    with pytest.raises(DataError, match="no such dataset"):
        run_pipeline(tmp_path / "nope", tmp_path / "run")


@pytest.mark.slow
def test_demo_end_to_end(tmp_path):
    from endogsim.pipeline.demo import DemoConfig, run_demo

    s = run_demo(tmp_path, DemoConfig(recon={"resolution_scale": 1.0, "iters": 200}, identify={"iters": 4}))
    assert (tmp_path / "render.mp4").is_file() and Path(s["report"]).is_file()
    assert s["materials"] and all(r["E_identified"] > 0 for r in s["materials"])
