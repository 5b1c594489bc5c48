"""Material field records, prior table, optimisation view, per-particle expansion and the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from endogsim.errors import MaterialError
from endogsim.io.scene import ObjectLabel
from endogsim.materials import (
    CHOLECSEG8K_CLASSES,
    MaterialField,
    MaterialInitConfig,
    MaterialRecord,
    initialise_materials,
    load_prior_table,
    prior_record,
    resolve_class,
)

LABELS = {
    0: ObjectLabel(0, "liver", False, "liver"),
    1: ObjectLabel(1, "fat", False, "fat"),
    2: ObjectLabel(2, "grasper", True, "grasper"),
    4: ObjectLabel(4, "gallbladder", False, "gallbladder"),
}


def rec(**kw) -> MaterialRecord:
    base = dict(name="liver", object_id=0, klass="liver", E=5e3, nu=0.47, density=1060.0)
    base.update(kw)
    return MaterialRecord(**base)


# ---- records ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad,what", [({"E": 0.0}, "E = 0.0"), ({"E": -3.0}, "E = -3.0"), ({"E": math.inf}, "inf"),
                                      ({"E": math.nan}, "nan"), ({"nu": 0.5}, "nu = 0.5"), ({"nu": -1.0}, "nu = -1.0"),
                                      ({"density": 0.0}, "density = 0.0"), ({"density": -5.0}, "density")])
def test_impossible_materials_rejected(bad, what):
    with pytest.raises(MaterialError, match="object 3") as e:
        rec(object_id=3, **bad)
    assert what in str(e.value)


def test_json_round_trip_and_file_errors(tmp_path):
    f = initialise_materials(LABELS, MaterialInitConfig(backend="prior"))
    p = f.save(tmp_path / "m.json")
    g = MaterialField.load(p)
    assert [r.model_dump() for r in g.records] == [r.model_dump() for r in f.records]
    obj = json.loads(p.read_text())
    assert obj["units"]["E"] == "Pa" and obj["meta"]["prior_version"] == load_prior_table()["version"]
    obj["objects"][1]["nu"] = 0.7
    (tmp_path / "bad.json").write_text(json.dumps(obj))
    with pytest.raises(MaterialError, match="nu = 0.7"):
        MaterialField.load(tmp_path / "bad.json")
    with pytest.raises(MaterialError, match="not found"):
        MaterialField.load(tmp_path / "missing.json")
    with pytest.raises(MaterialError, match="duplicate"):
        MaterialField([rec(), rec()])


# ---- prior --------------------------------------------------------------------------------------------------------
def test_every_cholecseg8k_class_has_a_prior():
    classes = load_prior_table()["classes"]
    for colour_id, index, name in CHOLECSEG8K_CLASSES:
        for alias in (name, f"cholecseg8k:{colour_id}", f"cholecseg8k_index:{index}"):
            key = resolve_class(alias)
            assert key in classes, alias
    assert resolve_class("Gall_Bladder") == "gallbladder" and resolve_class("L-hook Electrocautery") == "l_hook"
    assert resolve_class("endonerf:0") == "unknown_tissue" and resolve_class("endonerf:1") == "instrument"
    for k in ("stomach", "small intestine", "large intestine", "kidney", "spleen", "artery", "titanium clip"):
        assert resolve_class(k) is not None, k


def test_prior_table_is_valid_and_cited():
    t = load_prior_table()
    assert t["version"]
    for key, e in t["classes"].items():
        for regime in ("in_vivo", "ex_vivo_tensile"):
            col = e[regime]
            assert 0 < col["E_min"] <= col["E"] <= col["E_max"], (key, regime)
            prior_record(0, key, key, regime=regime)  # physically valid record
        for s in e["sources"]:
            assert s in t["references"], (key, s)
        assert e["sources"] or "assumption" in e.get("notes", ""), key


def test_regime_switch_and_tools_rigid():
    vivo = prior_record(1, "gallbladder", "gallbladder", regime="in_vivo")
    tens = prior_record(1, "gallbladder", "gallbladder", regime="ex_vivo_tensile")
    assert vivo.E == 1e4 and tens.E == 1e6 and tens.E_min == 2.5e5 and tens.E_max == 9e6
    tool = prior_record(2, "grasper", "grasper", is_tool=True)
    assert tool.rigid and tool.model == "rigid" and tool.E == 2e11 and tool.density == 7900
    # Unknown names fall back to generic tissue / instrument.
    assert prior_record(5, "blob", "who-knows").klass == "who-knows"
    assert prior_record(5, "blob", "who-knows").E == 1e4 and prior_record(6, "x", "x", is_tool=True).rigid
    with pytest.raises(MaterialError, match="regime"):
        prior_record(1, "liver", "liver", regime="wet")


def test_manual_backend_one_value_for_deformables():
    f = initialise_materials(LABELS, MaterialInitConfig(backend="manual"))
    assert {(r.E, r.nu, r.density) for r in f.deformable} == {(1e4, 0.45, 1000.0)}
    assert f[2].rigid and f[2].E == 2e11 and all(r.source == "manual" for r in f.records)


# ---- optimisation view ---------------------------------------------------------------------------------------------
def test_simulator_materials_per_object():
    from endogsim.physics.constitutive import model_id

    f = initialise_materials(LABELS, MaterialInitConfig(backend="prior"))
    mats = f.simulator_materials()
    assert mats.E.shape == (5,) and torch.isnan(mats.E[3])  # id 3 has no record
    for r in f.records:
        assert float(mats.E[r.object_id]) == r.E and float(mats.nu[r.object_id]) == r.nu
        assert float(mats.density[r.object_id]) == r.density
        assert int(mats.model[r.object_id]) == (-1 if r.rigid else model_id(r.model))
    used = mats.used(torch.tensor([4, 0, 0, 1, 4]))
    assert used.E.tolist() == [f[i].E for i in (0, 1, 4)]
    with pytest.raises(MaterialError, match="rigid"):  # the tool (id 2) has no particles
        mats.used(torch.tensor([0, 2]))
    with pytest.raises(MaterialError, match="0..4"):
        mats.used(torch.tensor([7]))


def test_to_params_from_params_round_trip():
    f = initialise_materials(LABELS, MaterialInitConfig(backend="prior"))
    p = f.to_params()
    assert p.object_ids == [0, 1, 4] and p.log10_E.requires_grad and p.nu_raw.requires_grad
    assert torch.allclose(p.E(), torch.tensor([5e3, 2e3, 1e4], dtype=torch.float64))
    assert torch.allclose(p.nu(), torch.tensor([0.47, 0.48, 0.47], dtype=torch.float64))
    g = f.from_params(p)
    for r_old, r_new in zip(f.records, g.records):
        assert r_new.E == pytest.approx(r_old.E, rel=1e-9) and r_new.nu == pytest.approx(r_old.nu, abs=1e-9)
        assert r_new.source == ("identified" if not r_old.rigid else r_old.source)
    with torch.no_grad():
        p.log10_E[1] = 3.5
    assert f.from_params(p)[1].E == pytest.approx(10 ** 3.5)
    assert f.from_params(p)[2].E == 2e11  # the rigid tool is frozen


def test_simulator_materials_gradient_matches_finite_difference():
    f = initialise_materials(LABELS, MaterialInitConfig(backend="prior"))
    p = f.to_params()
    ids = torch.tensor([0, 0, 1, 2, 4, 4, 4])
    w = torch.linspace(0.5, 2.0, len(ids), dtype=torch.float64)

    def loss(params):
        mats = f.simulator_materials(params)
        return (w * (torch.log(mats.E[ids]) + 10 * mats.nu[ids])).sum()

    loss(p).backward()
    grads = torch.cat([p.log10_E.grad, p.nu_raw.grad])
    fd = []
    for name in ("log10_E", "nu_raw"):
        for i in range(3):
            vals = []
            for s in (1e-3, -1e-3):
                q = f.to_params()
                with torch.no_grad():
                    getattr(q, name)[i] += s
                vals.append(loss(q).item())
            fd.append((vals[0] - vals[1]) / 2e-3)
    assert torch.allclose(grads.float(), torch.tensor(fd), rtol=2e-2, atol=1e-3)
    assert grads[:3].abs().min() > 0  # every deformable object receives a gradient


def test_global_material_ties_objects():
    f = initialise_materials(LABELS, MaterialInitConfig(backend="prior"))
    p = f.to_params(global_material=True)
    assert p.log10_E.shape == (1,) and p.nu_raw.shape == (1,)
    assert p.log10_E.item() == pytest.approx(np.mean(np.log10([5e3, 2e3, 1e4])))
    with torch.no_grad():
        p.log10_E[0] = 4.0
    g = f.from_params(p)
    assert [g[i].E for i in (0, 1, 4)] == pytest.approx([1e4] * 3) and g[2].E == 2e11
    E = f.simulator_materials(p).E[torch.tensor([0, 1, 4, 2])]
    E.sum().backward()
    assert p.log10_E.grad.shape == (1,) and p.log10_E.grad.item() > 0


# ---- CLI ------------------------------------------------------------------------------------------------------------
def test_cli_init_and_show_from_labels_json(tmp_path):
    from endogsim.cli.main import app

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "labels.json").write_text(json.dumps({
        "0": {"name": "tissue", "is_tool": False, "klass": "unknown_tissue"},
        "1": {"name": "tool", "is_tool": True, "klass": "instrument"}}))
    out = tmp_path / "m.json"
    r = CliRunner().invoke(app, ["materials", "init", str(run_dir), "--backend", "prior", "--regime",
                                 "ex_vivo_tensile", "--out", str(out)])
    assert r.exit_code == 0, r.output
    f = MaterialField.load(out)
    assert f[0].E == 5e5 and f[1].rigid and "prior" in r.output
    r = CliRunner().invoke(app, ["materials", "show", str(out)], env={"COLUMNS": "200"})
    assert r.exit_code == 0 and "tissue" in r.output
    r = CliRunner().invoke(app, ["materials", "init", str(run_dir), "--backend", "manual", "--manual-nu", "0.6",
                                 "--out", str(out)])
    assert r.exit_code == 2 and "nu = 0.6" in r.output
    r = CliRunner().invoke(app, ["materials", "init", str(run_dir), "--backend", "mllm", "--out", str(out)])
    assert r.exit_code == 2 and "data folder" in r.output


def test_scene_label_keys_are_prior_classes():
    keys = ["liver", "gallbladder", "fat", "abdominal_wall", "gastrointestinal_tract", "connective_tissue", "blood",
            "cystic_duct", "hepatic_vein", "liver_ligament", "grasper", "l_hook", "instrument", "unknown_tissue"]
    assert all(resolve_class(k) == k for k in keys)


@pytest.mark.realdata
def test_cli_prior_on_shared_data(tmp_path):
    import os
    from pathlib import Path

    from endogsim.cli.main import app

    root = Path(os.environ.get("ENDOGSIM_SHARED_DATA", Path(__file__).parents[1] / ".." / "shared" / "data")).resolve()
    folder = root / "cholecseg8k_clip"
    if not folder.exists():
        pytest.skip(f"{folder} absent")
    out = tmp_path / "m.json"
    r = CliRunner().invoke(app, ["materials", "init", str(folder), "--backend", "prior", "--out", str(out)])
    assert r.exit_code == 0, r.output
    f = MaterialField.load(out)
    assert f.records and all(r.source == "prior" for r in f.records)
