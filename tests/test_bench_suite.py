"""``endogsim bench suite``: per-scene runs, the paper's tables, in this process and on a local Ray cluster."""

from __future__ import annotations

import json
import math
import sys

import pytest

from endogsim.bench.suite import RUNS, run_suite, suite_tables
from endogsim.errors import EndoGSimError

SMALL = dict(iters=1, frames=3)  # tiny, 3 frames, one iteration: the whole machinery in well under a minute


def _fake(scene: str, re: float, epe: float, with_global: bool = False, fid=None) -> dict:
    runs = {f"{i}_{'on' if on else 'off'}": {"re_mean": re * (0.5 if on else 1), "epe": epe, "fid": fid,
                                             "materials": {"a": {"E": 1e3, "nu": 0.4}}} for i, on in RUNS}
    if with_global:
        runs["global_on"] = {"re_mean": 2 * re, "epe": 2 * epe, "fid": None, "materials": {"a": {"E": 2e3, "nu": 0.3}}}
    return {"scene": scene, "runs": runs}


def test_tables_average_over_scenes():
    t = suite_tables({"press": _fake("press", 0.2, 1.0), "two_tissues": _fake("two_tissues", 0.4, 3.0, True)})
    rows2 = t["table2"]["rows"]
    assert [r[0] for r in rows2] == ["press", "two_tissues", "average"]
    assert rows2[-1][1] == pytest.approx(0.15) and rows2[-1][2] == pytest.approx(2.0)
    rows3 = {(r[0], r[1]): r for r in t["table3"]["rows"]}
    assert rows3[("manual", "off")][2] == pytest.approx(0.3) and rows3[("prior", "on")][2] == pytest.approx(0.15)
    assert all(r[4] == "n/a" for r in t["table3"]["rows"])  # no FID without weights
    abl = t["ablation"]["rows"]
    assert [r[0] for r in abl] == ["object-wise material field", "one global material"] and abl[1][1] == pytest.approx(0.8)
    t = suite_tables({"press": _fake("press", 0.2, 1.0, fid=12.0)})
    assert t["table3"]["rows"][0][4] == pytest.approx(12.0) and "not run" in t["ablation"]["note"]


def test_clear_errors(tmp_path, monkeypatch):
    with pytest.raises(EndoGSimError, match="unknown suite scene.*nowhere"):
        run_suite(["nowhere"], tmp_path, tmp_path)
    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    with pytest.raises(EndoGSimError, match=r"pip install 'endogsim\[ray\]'"):
        run_suite(["tiny"], tmp_path / "s", tmp_path / "w", ray=True, **SMALL)


def _check(res: dict) -> None:
    runs = res["scenes"]["tiny"]["runs"]
    assert set(runs) == {"manual_off", "manual_on", "prior_off", "prior_on"}
    for r in runs.values():
        assert math.isfinite(r["re_mean"]) and math.isfinite(r["epe"]) and r["fid"] is None
    assert runs["prior_off"]["iterations"] == 0 and runs["prior_on"]["iterations"] >= 1
    t = res["tables"]
    assert t["table2"]["rows"][0][0] == "tiny" and t["table2"]["rows"][0][1] == pytest.approx(runs["prior_on"]["re_mean"])
    assert len(t["table3"]["rows"]) == 4
    json.dumps(res)  # --json writes exactly this


@pytest.fixture(scope="module")
def scenes_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("suite_scenes")


def test_suite_in_process_on_tiny(scenes_dir, tmp_path):
    res = run_suite(["tiny"], scenes_dir, tmp_path / "runs", **SMALL, log=lambda *a: None)
    _check(res)
    assert (scenes_dir / "tiny_f3" / "scene.json").is_file()  # cached for the next call
    assert (tmp_path / "runs" / "tiny" / "prior_on" / "metrics.json").is_file()


def test_suite_on_a_local_ray_cluster(scenes_dir, tmp_path):
    pytest.importorskip("ray")  # ~30 s with the scene cached by the test above (Ray start-up included)
    res = run_suite(["tiny"], scenes_dir, tmp_path / "runs", ray=True, **SMALL, log=lambda *a: None)
    _check(res)
    assert res["settings"]["ray"] is True


def test_cli_prints_the_tables(scenes_dir, tmp_path):
    from typer.testing import CliRunner

    from endogsim.cli.main import app

    out = tmp_path / "suite.json"
    r = CliRunner().invoke(app, ["bench", "suite", "--scenes", "tiny", "--iters", "0", "--frames", "3",
                                 "--scenes-dir", str(scenes_dir), "--work-dir", str(tmp_path / "w"), "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert "Table 2" in r.output and "Table 3" in r.output and "ablation" in r.output
    assert json.loads(out.read_text())["settings"]["scenes"] == ["tiny"]
