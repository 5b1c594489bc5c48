"""``endogsim bench convergence``: identification's discretisation against its 2x refinement."""

from __future__ import annotations

import json
import math

import pytest
from typer.testing import CliRunner

from endogsim.bench.convergence import TARGET_RMS_CHANGE, convergence_case, run_bench
from endogsim.cli.main import app
from endogsim.errors import DataError

CASE_KEYS = {"scene", "seed", "frames", "factor", "refine", "particles", "grid", "substeps", "particle_spacing_mm",
             "refined_particles", "refined_grid", "refined_substeps", "rms_motion_mm", "rms_motion_default_mm",
             "rms_change", "converged", "seconds", "refined_seconds"}


def _check_case(c: dict, frames: int) -> None:
    assert set(c) == CASE_KEYS
    assert c["scene"] == "tiny" and c["frames"] == frames and c["refine"] == ["grid", "particles", "substeps"]
    # the refinement: 2x the grid, 8x the particles (up to the outline's rounding), at least 2x the substeps
    assert c["refined_grid"] == 2 * c["grid"] and c["refined_substeps"] >= 2 * c["substeps"]
    assert 6 * c["particles"] < c["refined_particles"] < 10 * c["particles"]
    assert c["rms_motion_mm"] > 0 and c["rms_motion_default_mm"] > 0
    assert math.isfinite(c["rms_change"]) and 0 <= c["rms_change"] < 1
    assert c["converged"] == (c["rms_change"] <= TARGET_RMS_CHANGE)


def test_cli_writes_the_cases_and_settings(tmp_path):
    out = tmp_path / "conv.json"
    r = CliRunner().invoke(app, ["bench", "convergence", "--scenes", "tiny", "--frames", "3", "--seed", "1",
                                 "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert "rms change" in r.output and "tiny" in r.output
    res = json.loads(out.read_text())
    assert len(res["cases"]) == 1
    _check_case(res["cases"][0], 3)
    assert res["settings"]["scenes"] == ["tiny"] and res["settings"]["frames"] == 3
    assert res["settings"]["seed"] == 1 and res["cases"][0]["seed"] == 1
    assert res["settings"]["target_rms_change"] == TARGET_RMS_CHANGE


def test_a_refinement_sequence_gives_the_change_from_each_level_to_the_next(tmp_path):
    out = tmp_path / "seq.json"
    r = CliRunner().invoke(app, ["bench", "convergence", "--scenes", "tiny", "--frames", "3", "--levels", "1,2",
                                 "--json", str(out)])
    assert r.exit_code == 0, r.output
    q = json.loads(out.read_text())["sequences"][0]
    assert q["factors"] == [1, 2] and len(q["changes"]) == 1 and q["grid"][1] == 2 * q["grid"][0]
    # the same comparison as the default bench's, from the same simulations
    assert q["changes"][0] == pytest.approx(convergence_case("tiny", frames=3)["rms_change"], rel=1e-9)
    for bad in ("2,3", "1,1", "1", "1,x"):
        r = CliRunner().invoke(app, ["bench", "convergence", "--scenes", "tiny", "--levels", bad])
        assert r.exit_code == 2 and "levels" in r.output, (bad, r.output)


def test_a_part_of_the_discretisation_is_refined_alone(tmp_path):
    out = tmp_path / "substeps.json"
    r = CliRunner().invoke(app, ["bench", "convergence", "--scenes", "tiny", "--frames", "3", "--refine", "substeps",
                                 "--json", str(out)])
    assert r.exit_code == 0, r.output
    res = json.loads(out.read_text())
    c = res["cases"][0]
    assert res["settings"]["refine"] == c["refine"] == ["substeps"]
    # the same grid and particles, twice the substeps: is the motion converged in time?
    assert (c["refined_grid"], c["refined_particles"]) == (c["grid"], c["particles"])
    assert c["refined_substeps"] == 2 * c["substeps"]
    assert math.isfinite(c["rms_change"]) and c["rms_change"] > 0
    for bad in ("time", ""):
        r = CliRunner().invoke(app, ["bench", "convergence", "--scenes", "tiny", "--refine", bad])
        assert r.exit_code == 2 and "grid, particles, substeps" in r.output, (bad, r.output)
    with pytest.raises(DataError, match="every part"):
        run_bench(["tiny"], levels=[1, 2], refine=("grid",))


def test_unknown_scenes_are_refused_before_any_work():
    with pytest.raises(DataError, match="unknown suite scene.*nowhere"):
        run_bench(["tiny", "nowhere"])
    r = CliRunner().invoke(app, ["bench", "convergence", "--scenes", "nowhere"])
    assert r.exit_code == 2 and "nowhere" in r.output


@pytest.fixture(scope="module")
def tiny_default():
    return convergence_case("tiny")  # its default 10 frames (about 6 s on one core)


@pytest.mark.slow
def test_tiny_at_its_default_frames(tiny_default):
    _check_case(tiny_default, 10)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="issue 21: tiny's motion changes by ~25% under a 2x refinement (target 5%); "
                                       "remove this mark once the discretisation converges")
def test_tiny_meets_the_convergence_target(tiny_default):
    assert tiny_default["rms_change"] <= TARGET_RMS_CHANGE


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="issue 21: at identification's grid, tiny's motion grows with the substeps "
                                       "(0.42, 0.46, 0.50 mm at 9, 18, 36; without the probe nothing moves): "
                                       "docs/IDENTIFICATION.md section 3, stop 58")
def test_tiny_is_converged_in_time_at_its_grid():
    assert convergence_case("tiny", refine=("substeps",))["rms_change"] <= TARGET_RMS_CHANGE
