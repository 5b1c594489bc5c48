"""The per-run HTML report (well formed, offline, every linked file present) and FID."""

from __future__ import annotations

import json
import re
from html.parser import HTMLParser

import numpy as np
import pytest
import torch

from endogsim.errors import ModelError
from endogsim.evaluate.fid import FID_WEIGHTS_ENV, feature_statistics, fid, frechet_distance, load_inception

VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source", "track", "wbr"}


class _Checker(HTMLParser):
    """Checks that every non-void tag is closed in order and collects src / href values."""

    def __init__(self):
        super().__init__()
        self.stack: list[str] = []
        self.errors: list[str] = []
        self.links: list[str] = []
        self.tags: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        self.links += [v for k, v in attrs if k in ("src", "href") and v]
        if tag not in VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1] if self.stack else 'nothing'}")
        else:
            self.stack.pop()


@pytest.fixture(scope="module")
def run_with_simulation(tmp_path_factory):
    """A tiny identification run (1 iteration, with video) and one simulated interaction."""
    from endogsim.identify import IdentifyConfig, run_identify
    from endogsim.pipeline.interaction import load_interaction
    from endogsim.pipeline.simulate import simulate_interaction
    from endogsim.synth import synthesize

    scene = tmp_path_factory.getbasetemp() / "shared_tiny_f4"
    if not (scene / "scene.json").is_file():
        synthesize("tiny", scene, seed=0, frames=4)
    root = tmp_path_factory.mktemp("report")
    run = root / "run"
    run_identify(scene, run, init="prior", config=IdentifyConfig(iters=2, render_scale=0.5, patience=100), video=True)
    sim = root / "sims" / "press"
    simulate_interaction(run, load_interaction("press").model_copy(update={"frames": 3}), None, sim)
    return run, sim


def test_report_is_well_formed_and_links_exist(run_with_simulation, tmp_path, monkeypatch):
    monkeypatch.delenv(FID_WEIGHTS_ENV, raising=False)
    from endogsim.evaluate.report_html import write_report

    run, sim = run_with_simulation
    for out in (None, tmp_path / "elsewhere" / "r.html"):  # default place and a folder of its own
        path = write_report(run, simulations=[sim], out=out)
        text = path.read_text()
        p = _Checker()
        p.feed(text)
        p.close()
        assert not p.errors and not p.stack, (p.errors, p.stack)
        assert text.startswith("<!DOCTYPE html>")
        local = [u for u in p.links if not u.startswith("data:")]
        assert not [u for u in local if re.match(r"^[a-z]+://", u) or u.startswith("//")]  # no network
        assert any(u.endswith("comparison.mp4") for u in local) and any(u.endswith("simulation.mp4") for u in local)
        for u in local:
            assert (path.parent / u).is_file(), u
        assert p.tags.count("video") == 2
        assert p.tags.count("img") >= 3 * 2 + 2  # stills (observed / simulated / flow error) and the two plots
        assert "<script" not in text and "<link" not in text
    # The material table carries sources and the prior's range; metrics include FID with the reason it is n/a.
    assert "prior" in text and "E range" in text and "–" in text
    assert "FID: n/a (no Inception weights" in text
    assert "EPE (px)" in text and "PSNR (dB)" in text
    assert "<h2>Instruments</h2>" not in text  # a synthesized scene has no fitted colliders to show
    assert re.search(r"<h2>Settling</h2><p>8 frames under gravity before frame 0; in the last, a particle still "
                     r"moved \d\.\d{4} mm", text)  # what the settling left (metrics.json "settling")


def test_report_says_whether_a_grasps_bite_held(run_with_simulation, tmp_path):
    import json
    import shutil

    from endogsim.evaluate.report_html import write_report

    run, sim = run_with_simulation
    assert json.loads((sim / "summary.json").read_text())["grasp_bites"] == []  # `press` grasps nothing
    torn = tmp_path / "torn"
    shutil.copytree(sim, torn)
    s = json.loads((torn / "summary.json").read_text())
    s["grasp_bites"] = [{"held_particles": 240, "ring_cells_max": 1.93, "frame_of_max": 3, "torn": True,
                         "tolerance_cells": 1.5}]
    (torn / "summary.json").write_text(json.dumps(s))
    text = write_report(run, simulations=[sim, torn], out=tmp_path / "r.html").read_text()
    assert text.count("TORE OUT of the tissue") == 1 and "at most 1.93 grid cells (median) from it, frame 3" in text


def test_report_cli(run_with_simulation):
    from typer.testing import CliRunner

    from endogsim.cli.main import app

    run, sim = run_with_simulation
    r = CliRunner().invoke(app, ["report", str(run), "--simulation", str(sim), "--out", str(run / "cli.html")])
    assert r.exit_code == 0, r.output
    assert (run / "cli.html").stat().st_size > 1000
    r = CliRunner().invoke(app, ["report", str(sim)])
    assert r.exit_code == 2 and "no metrics.json" in r.output


# ------------------------------------------------------------------------------------------------------
# FID
# ------------------------------------------------------------------------------------------------------


def _brute_force_fid(a: np.ndarray, b: np.ndarray) -> float:
    """|mu_a - mu_b|^2 + tr(Sa) + tr(Sb) - 2 sum sqrt(eig(Sa Sb)) (Sa Sb has real eigenvalues >= 0)."""
    ma, mb = a.mean(0), b.mean(0)
    ca = (a - ma).T @ (a - ma) / (len(a) - 1)
    cb = (b - mb).T @ (b - mb) / (len(b) - 1)
    ev = np.linalg.eigvals(ca @ cb)
    return float(((ma - mb) ** 2).sum() + np.trace(ca) + np.trace(cb) - 2 * np.sqrt(np.clip(ev.real, 0, None)).sum())


def test_frechet_distance_matches_brute_force():
    rng = np.random.default_rng(0)
    for d, n in ((1, 200), (8, 100), (32, 400)):
        a = rng.normal(size=(n, d))
        b = rng.normal(size=(n, d)) @ rng.normal(size=(d, d)) * 0.5 + 0.3
        got = frechet_distance(*feature_statistics(a), *feature_statistics(b))
        assert got == pytest.approx(_brute_force_fid(a, b), rel=1e-6, abs=1e-9)
    # 1-D closed form: (m1 - m2)^2 + (s1 - s2)^2.
    assert frechet_distance(np.array([1.0]), np.array([[4.0]]), np.array([3.0]), np.array([[1.0]])) == pytest.approx(5.0)
    a = rng.normal(size=(50, 6))
    assert abs(frechet_distance(*feature_statistics(a), *feature_statistics(a))) < 1e-6


def test_fid_without_weights_says_how_to_give_them(tmp_path, monkeypatch):
    monkeypatch.delenv(FID_WEIGHTS_ENV, raising=False)
    with pytest.raises(ModelError, match="local Inception-v3 weights.*--fid-weights"):
        load_inception(None)
    with pytest.raises(ModelError, match="missing.pth: Inception weights file not found"):
        load_inception(tmp_path / "missing.pth")
    junk = tmp_path / "junk.pth"
    torch.save({"w": torch.zeros(2)}, junk)
    with pytest.raises(ModelError, match="not an Inception-v3 state dict"):
        load_inception(junk)
    with pytest.raises(ModelError, match="at least 2 feature vectors"):
        feature_statistics(np.zeros((1, 4)))


def _save_inception(tmp_path, classes: int):
    from endogsim.evaluate.fid import InceptionV3

    state = InceptionV3(fid=classes == 1008, num_classes=classes).state_dict()
    if classes == 1000:
        state["AuxLogits.fc.weight"] = torch.zeros(classes, 768)  # torchvision's training-only head is ignored
    weights = tmp_path / f"inception_{classes}.pth"
    torch.save(state, weights)
    return weights, state


def test_fid_weights_files_load(tmp_path):
    for classes in (1000, 1008):  # torchvision's layout and pytorch-fid's FID network
        weights, state = _save_inception(tmp_path, classes)
        net = load_inception(weights)
        assert net.Mixed_7c.pool == ("max" if classes == 1008 else "avg") and not net.training
    state["Mixed_7c.branch_pool.conv.weight"] = torch.zeros(3, 3, 1, 1)
    torch.save(state, weights)
    with pytest.raises(ModelError, match="do not fit Inception-v3"):
        load_inception(weights)


@pytest.mark.slow
def test_fid_with_a_local_weights_file(tmp_path):
    from endogsim.evaluate.fid import inception_features

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    a = rng.uniform(size=(2, 48, 64, 3)).astype(np.float32)
    b = np.clip(a + 0.3, 0, 1)
    weights, _ = _save_inception(tmp_path, 1000)
    f = inception_features(load_inception(weights), np.concatenate([a, b]))
    assert f.shape == (4, 2048) and np.isfinite(f).all()
    d = frechet_distance(*feature_statistics(f[:2]), *feature_statistics(f[2:]))
    assert d > 0  # (a randomly initialised network: tiny features, so compare relatively)
    assert abs(frechet_distance(*feature_statistics(f[:2]), *feature_statistics(f[:2]))) < 1e-6 * d
    assert fid(a, b, weights=weights) == pytest.approx(d, rel=1e-6)


def test_unreadable_instrument_records_do_not_fail_the_report(tmp_path):
    from endogsim.evaluate.report_html import write_report

    scene, run = tmp_path / "scene", tmp_path / "run"
    scene.mkdir()
    run.mkdir()
    (scene / "scene.json").write_text(json.dumps({"objects": [], "camera": {"K": [[100, 0, 50], [0, 100, 40], [0, 0, 1]]},
                                                  "colliders": [{"object_id": 1, "tip": [0, 0, 0.05]}]}))  # no end
    (run / "metrics.json").write_text(json.dumps({"scene": "s", "loss": "joint", "iterations": 0, "materials": {},
                                                  "folder": str(scene)}))
    html = write_report(run).read_text()
    assert "<h2>Instruments</h2>" in html and "could not be read" in html


def test_the_settling_says_whether_gravity_acted():
    from endogsim.evaluate.report_html import settling_text

    settle = {"frames": 8, "last_frame_motion_m": 1e-6, "cells": 0.001, "settled": True, "tolerance_cells": 0.02}
    assert settling_text({**settle, "gravity": True}).startswith("8 frames under gravity before frame 0")
    # impulse_paper settles with gravity off: the tissue relaxes against the instruments, it carries no weight
    assert settling_text({**settle, "gravity": False}).startswith("8 frames without gravity, the instruments at "
                                                                  "their frame-0 pose, before frame 0")
    assert "under gravity" in settling_text(settle)  # a record written before "gravity" was recorded


def test_a_discretisation_error_bar_wider_than_the_search_box_says_so():
    """press_real at seed 1: +-3.16 decades of E in a 4.3-decade box. The interval is clipped to the box; the
    text says the error bar spans more than it."""
    from endogsim.evaluate.report_html import discretisation_text

    disc = {"ratio": 1.44, "coarse_best": 76700.0, "shift": -0.46, "half_width": 3.16, "lower_bound": False}
    box = [50.0, 1e6]
    assert discretisation_text("E", disc, box) == ("+-3.16 decades, wider than the search box's 4.3 decades (the "
                                                   "optimum on a grid 1.44x coarser: 7.67e+04 Pa, -0.46 decades)")
    assert discretisation_text("E", {**disc, "half_width": 0.63}, box).startswith("+-0.63 decades (the optimum")
    assert discretisation_text("E", disc).startswith("+-3.16 decades (the optimum")  # no box given: nothing said
    nu = {"ratio": 1.44, "coarse_best": 0.3, "shift": -0.12, "half_width": 0.3, "lower_bound": True}
    assert discretisation_text("nu", nu, [0.0, 0.49]) == ("+-0.3, wider than the search box's 0.49 (the optimum on a "
                                                           "grid 1.44x coarser: 0.3, -0.12, or beyond)")
