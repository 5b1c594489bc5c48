"""``endogsim simulate``: new interactions (tool trajectory, force, grasp) on the synthesized ``tiny`` scene."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from endogsim.errors import DataError, MaterialError, SimulationError
from endogsim.gaussians.model import covariance_to_scale_rot
from endogsim.pipeline.interaction import builtin_interactions, load_interaction
from endogsim.pipeline.simulate import resolve_scene, simulate_interaction

FRAMES = 4


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The ``tiny`` scene with 4 frames, synthesized once per test session (shared with other modules)."""
    from endogsim.synth import synthesize

    folder = tmp_path_factory.getbasetemp() / "shared_tiny_f4"
    if not (folder / "scene.json").is_file():
        synthesize("tiny", folder, seed=0, frames=FRAMES)
    return folder


def test_builtin_interactions_are_valid():
    names = builtin_interactions()
    assert {"poke", "press", "pull", "push_force"} <= set(names)
    for n in names:
        inter = load_interaction(n)
        assert inter.name == n and inter.frames >= 2
        assert inter.tool or inter.force or inter.grasp


@pytest.mark.parametrize("obj, needle", [
    ({"name": "x", "frames": 4}, "at least one of"),
    ({"tool": {"keyframes": [[0.5, 0, 0, 0]]}}, "tool.keyframes"),
    ({"tool": {"keyframes": [[0, 0, 0, 0], [0.5, 0, 0, 0], [0.4, 0, 0, 0]]}}, "increase"),
    ({"force": {"acceleration": [0, 0, 1], "t_start": 0.1, "t_end": 0.05}}, "window"),
    ({"force": {"acceleration": [0, 0, 1], "radius": -1}}, "force.radius"),
    ({"grasp": {"keyframes": [[0, 0, 0, 0]]}, "colour": 1}, "colour"),
    ({"tool": {"at": [3, 0], "keyframes": [[0, 0, 0, 0]]}}, "tool.at"),
])
def test_invalid_interactions_name_the_field(obj, needle):
    with pytest.raises(DataError, match="invalid interaction") as e:
        load_interaction(obj)
    assert needle in str(e.value)


def test_interaction_files_and_names(tmp_path):
    with pytest.raises(DataError, match="unknown interaction 'nope'.*poke"):
        load_interaction("nope")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(DataError, match="bad.json: not valid JSON"):
        load_interaction(bad)
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"name": "mine", "force": {"acceleration": [0, 0, 10]}}))
    assert load_interaction(good).name == "mine"
    with pytest.raises(DataError, match="not found"):
        load_interaction(tmp_path / "missing.json")


def test_covariance_round_trip():
    from endogsim.gaussians.model import covariance_from_scale_rot

    g = torch.Generator().manual_seed(0)
    scales = torch.rand(50, 3, generator=g, dtype=torch.float64) * 1e-3 + 1e-4
    quats = torch.randn(50, 4, generator=g, dtype=torch.float64)
    cov = covariance_from_scale_rot(scales, quats)
    log_s, q = covariance_to_scale_rot(cov)
    back = covariance_from_scale_rot(log_s.exp(), q)
    assert torch.allclose(back, cov, rtol=1e-6, atol=1e-14)


def test_resolve_scene_from_run_folder(tiny, tmp_path):
    assert resolve_scene(tiny) == (tiny, None)
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.json").write_text(json.dumps({"folder": str(tiny)}))
    (run / "materials_identified.json").write_text("{}")
    assert resolve_scene(run) == (tiny, run / "materials_identified.json")
    with pytest.raises(DataError, match="neither a scene folder"):
        resolve_scene(tmp_path)


def test_poke_writes_video_frames_ply_and_summary(tiny, tmp_path):
    from endogsim.gaussians.ply import read_ply

    inter = load_interaction("poke").model_copy(update={"frames": FRAMES})
    s = simulate_interaction(tiny, inter, "truth", tmp_path / "poke")
    out = tmp_path / "poke"
    assert (out / "simulation.mp4").stat().st_size > 0
    assert len(list((out / "frames").glob("*.png"))) == FRAMES
    plys = sorted((out / "ply").glob("*.ply"))
    assert len(plys) == FRAMES
    g0, g1 = read_ply(plys[0]), read_ply(plys[1])
    assert set(g0.object_ids.unique().tolist()) == {1, 2}  # tissue and the tool, with object ids
    tool = g0.object_ids == 2
    moved = (g1.means[tool] - g0.means[tool]).norm(dim=-1)
    assert moved.min() > 2e-3  # frame 1 (1/3 of the clip): the tool is most of its 4 mm in (eased keyframes)
    assert s["displacement"]["tissue"]["max_mm"] > 0.1  # and it pushed the tissue
    assert s["materials"]["tissue"]["source"] == "ground truth"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["resolved"]["tool_point"] and summary["files"]["video"] == "simulation.mp4"


def test_force_moves_the_region_and_hidden_tool_is_gone(tiny, tmp_path):
    inter = load_interaction("push_force").model_copy(update={"frames": FRAMES})
    s = simulate_interaction(tiny, inter, "truth", tmp_path / "force", write_ply_sequence=False)
    assert s["resolved"]["hidden_tools"] == [2] and s["resolved"]["force_particles"] > 10
    assert s["displacement"]["tissue"]["max_mm"] > 0.05
    assert not (tmp_path / "force" / "ply").exists()


def test_too_stiff_materials_raise_simulation_error(tiny, tmp_path):
    from endogsim.materials.field import MaterialField, MaterialRecord

    stiff = MaterialField([MaterialRecord(name="tissue", object_id=1, klass="liver", E=1e13, nu=0.45, density=1000.0)])
    with pytest.raises(SimulationError, match="interaction 'press'.*substeps"):
        simulate_interaction(tiny, "press", stiff, tmp_path / "stiff")
    empty = MaterialField([MaterialRecord(name="probe", object_id=2, klass="instrument", rigid=True, model="rigid",
                                          E=2e11, nu=0.3, density=7850.0)])
    with pytest.raises(MaterialError, match="no record for deformable object.*tissue"):
        simulate_interaction(tiny, "press", empty, tmp_path / "empty")


def test_a_grasp_that_tears_its_bite_out_is_reported(tiny, tmp_path):
    """A 500-Pa tissue grasped and drawn 12 mm up and 12 mm sideways in 4 frames: the tissue around the bite
    ends 1.93 cells from it (a 3-mm tug on the prior stays within 0.53), so the bite tore out by numerical
    fracture, and summary.json and the CLI say so."""
    from endogsim.cli.main import app
    from endogsim.materials.field import MaterialField, MaterialRecord

    MaterialField([MaterialRecord(name="tissue", object_id=1, klass="liver", E=500.0, nu=0.4, density=1060.0),
                   MaterialRecord(name="probe", object_id=2, klass="instrument", rigid=True, model="rigid", E=2e11,
                                  nu=0.3, density=7850.0)]).save(tmp_path / "soft.json")
    f = tmp_path / "yank.json"
    f.write_text(json.dumps({"name": "yank", "frames": FRAMES, "grasp": {
        "at": [0.0, 0.0], "radius": 0.003, "keyframes": [[0, 0, 0, 0], [1, 0.012, 0, -0.012]]}}))
    r = CliRunner().invoke(app, ["simulate", str(tiny), "--interaction", str(f), "--materials",
                                 str(tmp_path / "soft.json"), "--out", str(tmp_path / "yank"), "--no-ply"])
    assert r.exit_code == 0, r.output
    [bite] = json.loads((tmp_path / "yank" / "summary.json").read_text())["grasp_bites"]
    assert bite["torn"] and bite["ring_cells_max"] > bite["tolerance_cells"] == 1.5
    assert 0 < bite["torn_from"] <= bite["frame_of_max"]
    assert "bite tore out of the tissue" in " ".join(r.output.split())


def test_cli_grasp_from_file_and_clear_errors(tiny, tmp_path):
    from endogsim.cli.main import app

    f = tmp_path / "grasp.json"
    f.write_text(json.dumps({"name": "tug", "frames": 3, "grasp": {
        "at": [0.0, 0.0], "radius": 0.003, "keyframes": [[0, 0, 0, 0], [1, 0, 0, -0.003]]}}))
    runner = CliRunner()
    r = runner.invoke(app, ["simulate", str(tiny), "--interaction", str(f), "--materials", "prior",
                            "--out", str(tmp_path / "tug"), "--no-ply"])
    assert r.exit_code == 0, r.output
    s = json.loads((tmp_path / "tug" / "summary.json").read_text())
    assert s["interaction"]["name"] == "tug" and s["displacement"]["tissue"]["max_mm"] > 0.1
    # The grasp holds the tissue it closes on, which follows it the whole 3 mm (a Dirichlet condition).
    assert s["resolved"]["grasp_particles"] > 0 and s["displacement"]["tissue"]["max_mm"] == pytest.approx(3.0, abs=0.05)
    assert np.allclose(s["resolved"]["grasp_point"][:2], [0.0, 0.0], atol=0.004)
    # A 3-mm tug keeps the tissue around the bite within reach of it (the ring starts half a cell away).
    [bite] = s["grasp_bites"]
    assert bite["held_particles"] == s["resolved"]["grasp_particles"] and not bite["torn"] and bite["torn_from"] is None
    assert 0.45 < bite["ring_cells_max"] < bite["tolerance_cells"]
    f.write_text(json.dumps({"name": "bad", "grasp": {"keyframes": [[0.2, 0, 0, 0]]}}))
    r = runner.invoke(app, ["simulate", str(tiny), "--interaction", str(f), "--out", str(tmp_path / "bad")])
    assert r.exit_code == 2 and "grasp.keyframes" in r.output
