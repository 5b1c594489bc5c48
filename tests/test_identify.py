"""Material identification through the differentiable simulator, on the synthesized ``tiny`` scene."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, replace

import numpy as np
import pytest
import torch

from endogsim.errors import DataError, MaterialError, SimulationError
from endogsim.identify import IdentifyConfig, identify
from endogsim.identify.loss import identification_loss, loss_residuals
from endogsim.identify.optimize import (
    NOT_IDENTIFIABLE,
    prepare_observations,
    project_into_search_box,
    stable_log10_E_max,
)
from endogsim.identify.report import write_outputs
from endogsim.materials.field import MaterialField, MaterialRecord
from endogsim.physics import capsule_collider_points
from endogsim.scene.discretisation import refine
from endogsim.scene.folder import load_sim_scene, rediscretised
from endogsim.scene.forward import render_sequence, simulate_materials

FRAMES = 10  # the whole ``tiny`` clip: its first frames alone barely depend on E (the probe drives them)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from endogsim.synth import synthesize

    return synthesize("tiny", tmp_path_factory.mktemp("ident") / "tiny", seed=0, frames=FRAMES)


@pytest.fixture(scope="module")
def problem(tiny):
    return load_sim_scene(tiny)


def field_from_truth(problem, E_factor=1.0, nu=None, E_override=None) -> MaterialField:
    recs = []
    for o in problem.spec.objects:
        E = o.E if o.rigid else (E_override if E_override is not None else o.E * E_factor)
        recs.append(MaterialRecord(name=o.name, object_id=o.id, klass=o.klass, rigid=o.rigid,
                                   model="rigid" if o.rigid else o.model, E=E,
                                   nu=o.nu if (o.rigid or nu is None) else nu, density=o.density, source="manual"))
    return MaterialField(recs)


def fast_config(**kw) -> IdentifyConfig:
    return IdentifyConfig(**{"iters": 3, "lr": 0.1, "patience": 100, "frame_stride": 2, "intervals": False,
                             "refined_correction": None, **kw})


@pytest.fixture(scope="module")
def run3(problem, tmp_path_factory):
    """Three uninterrupted iterations from E 2x too stiff."""
    d = tmp_path_factory.mktemp("run3")
    return identify(problem, field_from_truth(problem, 2.0), fast_config(), run_dir=d), d


def test_problem_matches_the_scene(problem):
    pb = problem
    assert pb.frames.shape == (FRAMES, pb.camera.height, pb.camera.width, 3)
    assert pb.deformable_ids == [1]
    assert pb.particles.object_ids.unique().tolist() == [1]  # the rigid tool is a collider, not particles
    assert len(pb.scenario.colliders) == 1
    # pinned particles (the border band), the support behind the back face, the border band's nodes
    assert [a.kind for a in pb.scenario.anchors] == ["fixed", "support", "sticky"]
    assert pb.gt_flow.shape == (FRAMES - 1, pb.camera.height, pb.camera.width, 2)


def test_a_coarsened_scene_is_the_same_scene_on_a_coarser_grid(problem):
    """The discretisation-error estimate's coarse scene: grid x 0.7 (rounded), the particle spacing scaled with
    the grid (two particles per cell and axis), the substeps too; the same frames, camera and Gaussians."""
    sc = problem.spec.scenario
    coarse = rediscretised(problem, 0.7)
    assert coarse.mpm.grid_res == round(0.7 * problem.mpm.grid_res) < problem.mpm.grid_res
    ratio = problem.mpm.grid_res / coarse.mpm.grid_res
    assert coarse.mpm.substeps_per_frame == max(1, math.ceil(problem.mpm.substeps_per_frame / ratio - 1e-9))
    n, n_coarse = problem.particles.x.shape[0], coarse.particles.x.shape[0]
    assert 0.7 / ratio ** 3 < n_coarse / n < 1.4 / ratio ** 3  # the same tissue volume, (1 / ratio)^3 the particles
    assert coarse.frames is not problem.frames and np.array_equal(coarse.frames, problem.frames)
    assert torch.equal(coarse.gaussians.means, problem.gaussians.means) and coarse.num_frames == problem.num_frames
    # refine's factor 2 (the ground truth's) is unchanged by allowing fractional factors
    fine = refine(sc.identification, problem.spec.objects, sc.box_size, sc.frame_dt, factor=2)
    assert fine.grid == 2 * sc.identification.grid and fine.substeps >= 2 * sc.identification.substeps
    assert fine.particle_spacing == pytest.approx(sc.spacing(sc.identification) / 2)


def test_a_refined_scene_is_the_same_scene_finer_and_its_coarse_estimate_follows_it(tiny, problem):
    """``refine``: identification at a finer discretisation than the scene's default (grid x F, spacing / F,
    substeps x F). The discretisation-error estimate coarsens the refined scene, not the default one."""
    fine = load_sim_scene(tiny, refine=1.5)
    base = problem.settings
    assert fine.settings.grid == fine.mpm.grid_res == round(1.5 * base.grid)
    ratio = fine.settings.grid / base.grid
    assert fine.settings.particle_spacing == pytest.approx(base.particle_spacing / ratio)
    assert fine.mpm.substeps_per_frame >= math.ceil(ratio * base.substeps - 1e-9)
    n, n_fine = len(problem.particles), len(fine.particles)
    assert 0.7 * ratio ** 3 < n_fine / n < 1.4 * ratio ** 3
    assert torch.equal(fine.gaussians.means, problem.gaussians.means)
    assert rediscretised(fine, 0.7).settings.grid == round(0.7 * fine.settings.grid)  # relative to the refined grid
    with pytest.raises(DataError, match="not both"):
        load_sim_scene(tiny, settings=base, refine=1.5)
    with pytest.raises(DataError, match="above the 256"):
        load_sim_scene(tiny, refine=10)
    for bad in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(MaterialError, match="refine"):
            IdentifyConfig(refine=bad)
    # The search box for E is the same at every refinement: the CFL rule's substeps grow with the grid.
    nu, rho = torch.tensor([0.49]), torch.tensor([1060.0])
    box = [float(stable_log10_E_max(pb, nu, rho, IdentifyConfig(E_max=1e9, refine=f)))
           for pb, f in ((problem, 1.0), (fine, 1.5))]
    assert box[1] == pytest.approx(box[0], abs=0.01) and box[0] < 9


def test_identification_at_a_refined_discretisation_says_so_and_refuses_a_scene_loaded_otherwise(tiny, problem,
                                                                                                  tmp_path):
    from endogsim.identify import run_identify

    cfg = fast_config(iters=0, refine=1.5)
    m = run_identify(tiny, tmp_path / "fine", init="prior", config=cfg, video=False)
    d = m["discretisation"]
    assert d["refine"] == 1.5 and d["grid"] == round(1.5 * problem.settings.grid) and d["particles"] > len(problem.particles)
    assert "1.5x the scene's identification discretisation" in (tmp_path / "fine" / "summary.txt").read_text()
    base = run_identify(tiny, tmp_path / "base", init="prior", config=fast_config(iters=0), video=False, problem=problem)
    assert base["discretisation"]["refine"] == 1.0 and base["discretisation"]["grid"] == problem.settings.grid
    # the synthesized scene's own force scales: tiny's gravity points into the scene, along the camera's z
    assert base["force_scales"] == {"gravity_m_s2": [0.0, 0.0, 9.81], "frame_dt_s": problem.mpm.frame_dt,
                                    "damping_per_s": problem.mpm.damping, "mass_scaling": 1.0, "applied_forces": 0,
                                    "impulses": 0, "kinematic_instruments": 1, "scales": ["weight", "inertia"]}
    with pytest.raises(DataError, match="refined 1.5x"):
        run_identify(tiny, tmp_path / "mixed", init="prior", config=cfg, video=False, problem=problem)


def test_materials_are_simulated_at_the_discretisation_they_were_identified_at(tiny, tmp_path):
    """An identified E belongs to the discretisation it was fitted at: the materials file records the factor,
    and ``simulate`` uses it unless told otherwise (the truth and a prior: 1)."""
    from endogsim.identify import run_identify
    from endogsim.pipeline.interaction import load_interaction
    from endogsim.pipeline.simulate import identified_refine, simulate_interaction

    run_identify(tiny, tmp_path / "fine", init="prior", config=fast_config(iters=0, refine=1.5), video=False)
    mats = tmp_path / "fine" / "materials_identified.json"
    assert identified_refine(mats) == 1.5 and identified_refine("truth") == identified_refine("prior") == 1.0
    poke = load_interaction("poke").model_copy(update={"frames": 2})
    fine = simulate_interaction(tmp_path / "fine", poke, None, tmp_path / "sim", write_ply_sequence=False)
    assert fine["discretisation"]["refine"] == 1.5
    coarse = simulate_interaction(tmp_path / "fine", poke, None, tmp_path / "sim1", write_ply_sequence=False, refine=1)
    assert coarse["discretisation"]["refine"] == 1.0 and coarse["particles"] < fine["particles"]
    # the substeps the materials simulated at (the CFL rule's count), not only the scene's floor
    for run in (fine, coarse):
        assert run["discretisation"]["substeps_at_materials"] == run["substeps"] >= run["discretisation"]["substeps"]


def test_materials_are_simulated_with_the_substeps_they_were_identified_with(tiny, problem, tmp_path):
    """Identification plans its time step once, at its starting materials; the materials file records that floor
    and ``simulate`` keeps it, so a field softer than its start (whose CFL count alone is smaller) moves as
    identification saw it move. Without the record (a hand-written file), or at another discretisation, the CFL
    rule alone decides."""
    from endogsim.identify import run_identify
    from endogsim.pipeline.interaction import load_interaction
    from endogsim.pipeline.simulate import identified_substeps, simulate_interaction

    stiff = field_from_truth(problem, 20.0)
    stiff.save(tmp_path / "stiff.json")
    m = run_identify(tiny, tmp_path / "run", init=str(tmp_path / "stiff.json"), config=fast_config(iters=0),
                     video=False, problem=problem)
    fitted = MaterialField.load(tmp_path / "run" / "materials_identified.json")
    floor = m["discretisation"]["substeps"]
    assert fitted.meta["substeps"] == floor > problem.mpm.substeps_per_frame  # planned at the stiff start
    soft = MaterialField([r.model_copy(update={"E": r.E / 20.0}) if not r.rigid else r for r in fitted.records],
                         meta=dict(fitted.meta))
    cfl = problem.simulator().timestep(soft.simulator_materials(), problem.particles.v).substeps
    assert cfl < floor and identified_substeps(soft, 1.0) == floor and identified_substeps(soft, 1.5) == 0
    poke = load_interaction("poke").model_copy(update={"frames": 2})
    kept = simulate_interaction(tiny, poke, soft, tmp_path / "kept", write_ply_sequence=False)
    assert kept["substeps"] == kept["discretisation"]["substeps"] == floor
    soft.meta.pop("substeps")
    alone = simulate_interaction(tiny, poke, soft, tmp_path / "alone", write_ply_sequence=False)
    assert alone["substeps"] == cfl
    bad = MaterialField(soft.records, meta={"refine": 1.0, "substeps": "many"})
    with pytest.raises(MaterialError, match="the materials: meta 'substeps' is 'many'"):
        identified_substeps(bad, 1.0)
    bad.save(tmp_path / "bad.json")  # a file is named in the error, and nothing is written
    with pytest.raises(MaterialError, match=r"bad\.json: meta 'substeps' is 'many'"):
        simulate_interaction(tiny, poke, tmp_path / "bad.json", tmp_path / "bad", write_ply_sequence=False)
    assert not (tmp_path / "bad").exists()


def test_the_refined_correction_lowers_the_refined_loss_and_its_materials_belong_to_the_refined_grid(problem, tmp_path,
                                                                                                      monkeypatch):
    """From one iteration's estimate (from E 3x too stiff; intervals off, so E and nu both move) the correction's
    steps lower the loss of the scene simulated 1.5x finer, as a simulation there confirms; the materials file says
    they belong to 1.5x, and the outputs say what moved. tiny's loss barely depends on E (0.0137-0.0153 from 750 to
    5000 Pa), so its gains lie within the frames' noise and the correction would take no step: here any gain
    counts (that rule: tests/test_refined_correction.py)."""
    import endogsim.identify.refined_correction as rc
    from endogsim.identify.optimize import evaluate_loss, planned_for, prepare_observations

    plain = identify(problem, field_from_truth(problem, 3.0), fast_config(iters=1))
    cfg = fast_config(iters=1, refined_correction=1.5)
    assert identify(problem, field_from_truth(problem, 3.0), cfg).correction.stopped == "not significant"
    monkeypatch.setattr(rc, "significant_z", lambda n: 0.0)
    res = identify(problem, field_from_truth(problem, 3.0), cfg, run_dir=tmp_path / "run")
    c = res.correction
    assert c.parameters == ["tissue E", "tissue nu"] and res.refined is not None
    assert c.before == pytest.approx([math.log10(plain.field[1].E), plain.field[1].nu], abs=1e-9)
    assert all(b < a for a, b in zip(c.refined_loss, c.refined_loss[1:])) and len(c.refined_loss) > 1
    assert res.field[1].E == pytest.approx(10 ** c.after[0]) and res.field[1].nu == pytest.approx(c.after[1])
    fine = planned_for(rediscretised(problem, 1.5), res.init_field, cfg)  # the refined level, planned as identify's
    assert (res.refined.settings.grid, res.refined.mpm.substeps_per_frame) == (fine.settings.grid,
                                                                             fine.mpm.substeps_per_frame)
    obs, cam = prepare_observations(problem, cfg, tmp_path / "run")
    at = {name: evaluate_loss(fine, res.init_field, fld.to_params(nu_bounds=cfg.nu_bounds), obs, cam, cfg,
                              grad=False)[0].parts["total"]
          for name, fld in (("plain", plain.field), ("corrected", res.field))}
    assert at["corrected"] == pytest.approx(c.refined_loss[-1], rel=1e-6) and at["corrected"] < at["plain"]
    m = write_outputs(tmp_path / "out", problem, res, cfg, init_name="test", video=False)
    assert MaterialField.load(tmp_path / "out" / "materials_identified.json").meta["refine"] == 1.5
    assert m["refined_correction"]["applied"] and m["refined_correction"]["discretisation"]["refine"] == 1.5
    assert "refined correction: tissue E" in (tmp_path / "out" / "summary.txt").read_text()


def test_capsule_collider_points_fill_the_capsule():
    tip, end, r, dx = np.array([0.0, 0.0, 0.0]), np.array([0.02, 0.0, 0.0]), 0.003, 0.002
    pts, rho = capsule_collider_points(tip, end, r, dx)
    d_axis = lambda p: np.linalg.norm(p - np.stack([np.clip(p[:, 0], 0, 0.02), 0 * p[:, 0], 0 * p[:, 0]], 1), axis=1)  # noqa: E731
    assert (d_axis(pts) + rho <= r + 1e-9).all()  # every contact sphere lies inside the capsule
    # Points of the capsule at least rho inside it are covered by some contact sphere.
    rng = np.random.default_rng(0)
    q = rng.uniform([-r, -r, -r], [0.02 + r, r, r], (2000, 3))
    q = q[d_axis(q) < r - rho]
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(pts).query(q)
    assert (dist <= rho + 1e-9).all()


def test_true_materials_reproduce_the_ground_truth_flow(problem):
    """The rebuilt scenario (anchors, capsule colliders, identification grid) explains the video at the truth."""
    from endogsim.identify.report import evaluate_field

    ev = evaluate_field(problem, field_from_truth(problem, 1.0))
    gt_mag = float(np.linalg.norm(problem.gt_flow, axis=-1)[problem.gt_flow_valid].mean())
    assert ev.epe < 0.1 and ev.epe < 0.5 * gt_mag, (ev.epe, gt_mag)
    assert ev.psnr > 35


def test_loss_is_least_near_the_true_material(problem):
    """The ground truth was simulated at twice identification's resolution, from its own particles: through
    the discretisation gap, noisy renders and the estimated (DIS) flow, the loss on a factor-2 grid of E is
    still least at the true E. (Not so for nu: at this discretisation nu = 0.47 scores slightly better than
    the true 0.4; the suite measures that bias.)"""
    from endogsim.identify.optimize import evaluate_loss, prepare_observations

    cfg = IdentifyConfig()
    obs, cam = prepare_observations(problem, cfg, None)
    loss = lambda fld: evaluate_loss(problem, fld, None, obs, cam, cfg, grad=False)[0].parts["total"]  # noqa: E731
    at_truth = loss(field_from_truth(problem))
    for factor in (0.25, 0.5, 2.0, 4.0):
        assert at_truth < loss(field_from_truth(problem, factor)), factor


def test_the_optimums_loss_from_its_iteration_is_the_one_the_intervals_compare_with(problem):
    """The intervals compare every trial with the optimum's per-frame loss, taken from the iteration that
    evaluated it (differentiable rollout, renders on the autograd path): it must be the untaped
    simulation's to the last bit, or the trials' noise would be measured against another simulation. The
    iteration's simulation, which scores the identified field when it has the same materials, must be the
    forward-only simulator's to the last bit too."""
    from endogsim.identify.optimize import evaluate_loss, prepare_observations

    cfg = fast_config()
    obs, cam = prepare_observations(problem, cfg, None)
    fld = field_from_truth(problem, 2.0)
    params = fld.to_params(global_material=cfg.global_material, nu_bounds=cfg.nu_bounds)
    taped, taped_sim = evaluate_loss(problem, fld, params, obs, cam, cfg, grad=True)
    taped.total.backward()
    plain, _ = evaluate_loss(problem, fld, params, obs, cam, cfg, grad=False)
    assert len(plain.per_frame) > 2 and taped.per_frame == plain.per_frame
    forward = problem.simulator().simulate(fld.simulator_materials())
    assert torch.equal(taped_sim.positions.detach(), forward.positions)
    assert torch.equal(taped_sim.F.detach(), forward.F)
    assert taped_sim.settling_left == forward.settling_left and taped_sim.substeps == forward.substeps
    assert all(torch.equal(a, b) for a, b in zip(taped_sim.colliders, forward.colliders))


def test_the_iterations_simulations_score_a_field_as_a_new_simulation_would(run3, problem):
    """The identified field (here the best iterate) is scored from the iteration's own simulation of the
    same materials: the same scores to the last digit as simulating it again. The initial field is found
    only where the optimiser's parameters give its materials to the last bit (nu's round trip through its
    raw value may change them; then it is simulated, unless the simulator's float32 inputs are the same), and a
    field no iteration simulated is simulated."""
    from endogsim.identify.report import evaluate_field

    res, _ = run3
    scene = res.scene  # planned at the initial materials, as the iterations simulated
    assert res.simulations.find(res.field.simulator_materials()) is not None
    for fld in (res.field, res.init_field):
        kept, fresh = evaluate_field(scene, fld, known=res.simulations), evaluate_field(scene, fld)
        assert (kept.epe, kept.psnr, kept.ssim, kept.settling_left) == (fresh.epe, fresh.psnr, fresh.ssim,
                                                                         fresh.settling_left)
        assert np.array_equal(kept.rgb, fresh.rgb) and kept.coverage.to_json() == fresh.coverage.to_json()
    other = field_from_truth(problem, 3.0)
    assert res.simulations.find(other.simulator_materials()) is None
    assert res.simulations.find(other.simulator_materials(), scene.simulator()) is None
    # nu one float64 step away (its round trip through the raw parameter can do that) gives the simulator the
    # same float32 inputs: found with the scene's simulator, scored as a new simulation scores it.
    nudged = MaterialField([r if r.rigid else r.model_copy(update={"nu": math.nextafter(r.nu, 1.0)})
                            for r in res.field.records])
    assert res.simulations.find(nudged.simulator_materials()) is None
    assert res.simulations.find(nudged.simulator_materials(), scene.simulator()) is not None
    kept, fresh = evaluate_field(scene, nudged, known=res.simulations), evaluate_field(scene, nudged)
    assert (kept.epe, kept.psnr, kept.ssim) == (fresh.epe, fresh.psnr, fresh.ssim)
    assert np.array_equal(kept.rgb, fresh.rgb)


def test_identification_plans_its_substeps_once_at_the_initial_materials(run3, problem):
    """Every trial simulates with the time step of the initial materials (2x the truth here) unless it needs a
    finer one: a softer trial keeps the initial count (its own CFL count is lower, and crossing it would make
    the loss jump by a substep's time-discretisation error), a stiffer one takes what the CFL rule asks."""
    from endogsim.identify.optimize import planned_for

    res, _ = run3
    v = problem.particles.v

    def count(scene, factor):
        return scene.simulator().timestep(field_from_truth(problem, factor).simulator_materials(), v).substeps

    planned = res.scene.mpm.substeps_per_frame
    assert planned == count(problem, 2.0) > problem.mpm.substeps_per_frame  # the scene's floor (1) is below it
    assert count(res.scene, 1.0) == planned > count(problem, 1.0)
    assert count(res.scene, 4.0) == count(problem, 4.0) > planned
    kept = [res.simulations.find(f.simulator_materials(), res.scene.simulator()) for f in (res.field, res.init_field)]
    assert [r.substeps for r in kept] == [planned, planned]
    # Planning twice is planning once; a caller plans as identify does.
    assert res.scene.planned_at(field_from_truth(problem, 2.0).simulator_materials()) is res.scene
    assert planned_for(problem, res.init_field, fast_config()).mpm.substeps_per_frame == planned


def test_loss_decreases_and_E_moves_towards_the_truth(run3):
    res, _ = run3
    losses = [h["loss"] for h in res.history]
    assert len(losses) == 3
    assert losses[-1] < losses[0]
    E = [h["E"]["1"] for h in res.history]
    assert E[0] > E[1] > E[2]  # 2x too stiff: every step softens
    assert res.history[0]["grad_log10_E"][0] > 0
    assert res.best_iteration == int(np.argmin(losses))


def test_gradient_matches_finite_differences(run3, problem):
    """The default gradient ("full") is the derivative of the very loss the loop minimises."""
    from endogsim.identify.optimize import evaluate_loss, prepare_observations

    res, _ = run3
    cfg = fast_config()
    obs, cam = prepare_observations(problem, cfg, None)
    h = 0.02  # decades
    L = [evaluate_loss(problem, field_from_truth(problem, 2.0 * 10 ** s), None, obs, cam, cfg,
                       grad=False)[0].parts["total"] for s in (h, -h)]
    fd = (L[0] - L[1]) / (2 * h)
    g = res.history[0]["grad_log10_E"][0]
    # float32 renders at half scale make the loss slightly rough at this step: 30% (3% at render_scale 1)
    assert fd > 0 and g == pytest.approx(fd, rel=0.3), (g, fd)


def test_rigid_objects_stay_frozen(run3, problem):
    res, _ = run3
    tool = next(o for o in problem.spec.objects if o.rigid)
    assert res.field[tool.id].E == tool.E and res.field[tool.id].nu == tool.nu and res.field[tool.id].rigid
    assert res.field[tool.id].source == "manual"
    assert all(set(h["E"]) == {"1"} for h in res.history)  # only the deformable object is a parameter
    assert res.field[1].source.startswith(("identified", "prior (not identifiable"))


def test_interrupted_run_resumes_to_the_same_result(run3, problem, tmp_path):
    res_a, _ = run3
    init = field_from_truth(problem, 2.0)
    first = identify(problem, init, fast_config(), run_dir=tmp_path, stop_after=1)
    assert first.iterations == 1 and first.stopped == "interrupted"
    assert (tmp_path / "checkpoint.pt").is_file()
    res_b = identify(problem, init, fast_config(), run_dir=tmp_path)
    assert res_b.iterations == 3
    np.testing.assert_allclose([h["loss"] for h in res_b.history], [h["loss"] for h in res_a.history], rtol=1e-6)
    # The same to float32 rounding of the gradients (the simulator and renderer compute in float32).
    assert res_b.field[1].E == pytest.approx(res_a.field[1].E, rel=1e-6)
    assert res_b.field[1].nu == pytest.approx(res_a.field[1].nu, rel=1e-6)
    # Other settings than the checkpoint's are refused, not silently mixed.
    with pytest.raises(DataError, match="other settings \\(option loss\\)"):  # named, so a user knows which
        identify(problem, init, fast_config(loss="render"), run_dir=tmp_path)


def test_a_resumed_run_takes_the_intervals_trials_from_its_checkpoint(problem, tmp_path, monkeypatch):
    """The intervals' trial simulations are kept in the checkpoint as each finishes: a run resumed after them
    (validate run again in its folder, an identify interrupted during its intervals) simulates only the
    optimum again (alone, first), and its intervals are the first run's to the last bit."""
    from endogsim.identify import optimize

    init, cfg = field_from_truth(problem, 2.0), fast_config(iters=1, intervals=True, coarse_factor=0.7)
    first = identify(problem, init, cfg, run_dir=tmp_path)
    trials = torch.load(tmp_path / "checkpoint.pt", weights_only=False)["trials"]
    assert sum(k[0] == "fine" for k in trials) >= 4 and any(k[0] == "coarse" for k in trials)
    simulated = []
    real = optimize.evaluate_loss
    monkeypatch.setattr(optimize, "evaluate_loss", lambda *a, **k: simulated.append(k["grad"]) or real(*a, **k))
    again = identify(problem, init, cfg, run_dir=tmp_path)
    assert simulated == [False]
    assert [asdict(i) for i in again.intervals] == [asdict(i) for i in first.intervals]


def test_a_time_budget_only_stops_the_run(run3, problem, tmp_path, capsys):
    """A budget spent after the first iteration stops the run there; that iteration is the unstopped run's
    first (the learning-rate schedule follows ``iters``, not the clock), and the metrics say it was stopped."""
    res_a, _ = run3
    res = identify(problem, field_from_truth(problem, 2.0), fast_config(time_budget=1e-9), run_dir=tmp_path)
    assert res.stopped == "time_budget" and res.iterations == 1
    assert res.history[0]["lr"] == res_a.history[0]["lr"]
    assert res.history[0]["loss"] == pytest.approx(res_a.history[0]["loss"], rel=1e-6)
    assert res.history[0]["E"]["1"] == pytest.approx(res_a.history[0]["E"]["1"], rel=1e-9)
    m = write_outputs(tmp_path, problem, res, fast_config(time_budget=1e-9), init_name="test", video=False)
    assert m["stopped_by_budget"] is True
    # and every reader is told: the metrics' notes, the summary, the HTML report and the CLI's closing lines
    # (an unfinished run's "not identifiable" must not read as the video's verdict)
    assert any("stopped by the time budget" in n for n in m["notes"])
    assert "stopped by the time budget" in (tmp_path / "summary.txt").read_text()
    from endogsim.evaluate.report_html import write_report

    assert "stopped by the time budget" in write_report(tmp_path).read_text()
    from endogsim.cli.common import print_budget_stops

    print_budget_stops({"calibration": 1})
    assert "calibration was stopped by its time budget (a safety stop) after 1 iterations" in capsys.readouterr().out


def test_unstable_request_is_refused_with_the_limit(problem):
    with pytest.raises(SimulationError, match="needs more than 400 substeps per frame"):
        identify(problem, field_from_truth(problem, E_override=1e8), fast_config(iters=1), strict=True)


def test_search_box_respects_the_stability_limit(problem):
    from endogsim.physics import max_stable_E

    fld = field_from_truth(problem, E_override=1e8)
    cfg = fast_config(E_max=1e9, max_substeps=60)  # the substep bound binds, not E_max
    params = fld.to_params(nu_bounds=cfg.nu_bounds)
    project_into_search_box(params, problem, fld, cfg)
    emax = max_stable_E(float(params.nu().detach()[0]), 1060.0, problem.mpm, problem.scenario.box.size, substeps=60)
    assert float(params.E()[0]) == pytest.approx(cfg.stability_margin * emax, rel=1e-6)
    cfg = fast_config(E_max=2e4)  # E_max binds
    params = fld.to_params(nu_bounds=cfg.nu_bounds)
    project_into_search_box(params, problem, fld, cfg)
    assert float(params.E()[0]) == pytest.approx(2e4, rel=1e-9)
    # Higher nu -> lower limit (near-incompressible materials need smaller steps).
    hi = stable_log10_E_max(problem, torch.tensor([0.3, 0.49]), torch.tensor([1000.0, 1000.0]), fast_config(E_max=1e9))
    assert hi[0] > hi[1]
    # Mass scaling k multiplies the densities the simulator sees, so the CFL-limited E goes up k-fold (real video's
    # k = 4: the box ended at 250 kPa on EndoNeRF pulling where the simulation was stable to 1 MPa).
    scaled = replace(problem, scenario=replace(problem.scenario, mass_scaling=4.0))
    hi4 = stable_log10_E_max(scaled, torch.tensor([0.3, 0.49]), torch.tensor([1000.0, 1000.0]), fast_config(E_max=1e9))
    assert torch.allclose(hi4 - hi, torch.full_like(hi, math.log10(4.0)), atol=1e-9)


def test_global_material_ties_parameters():
    recs = [MaterialRecord(name="liver", object_id=1, klass="liver", E=3000.0, nu=0.4, density=1060.0),
            MaterialRecord(name="gallbladder", object_id=2, klass="gallbladder", E=12000.0, nu=0.44, density=1030.0),
            MaterialRecord(name="probe", object_id=3, klass="instrument", model="rigid", rigid=True, E=2e11, nu=0.3,
                           density=7850.0)]
    fld = MaterialField(recs)
    p = fld.to_params(global_material=True, nu_bounds=(0.0, 0.49))
    assert p.log10_E.shape == (1,) and p.object_ids == [1, 2]
    assert float(p.E()[0]) == pytest.approx(6000.0)  # geometric mean
    mats = fld.simulator_materials(p)
    log10_E = torch.log10(mats.E)
    assert log10_E[1] == log10_E[2] and mats.nu[1] == mats.nu[2]
    assert float(log10_E[3]) == pytest.approx(math.log10(2e11))  # rigid: untouched
    # A gradient through either object reaches the single shared parameter.
    (log10_E[1] + 2 * log10_E[2]).backward()
    assert float(p.log10_E.grad[0]) == pytest.approx(3.0)
    out = fld.from_params(p)
    assert out[1].E == out[2].E and out[3].E == 2e11
    sep = fld.to_params(global_material=False, nu_bounds=(0.0, 0.49))
    assert sep.log10_E.shape == (2,)


def test_outputs_written(problem, run3, tmp_path):
    res, run_dir = run3
    m = write_outputs(run_dir, problem, res, fast_config(), init_name="test", video=True)
    for f in ("materials_identified.json", "metrics.json", "loss.png", "parameters.png", "comparison.mp4",
              "summary.txt", "history.json", "observed_flow.npz"):
        assert (run_dir / f).is_file(), f
    disk = json.loads((run_dir / "metrics.json").read_text())
    for k in ("re_mean", "re_E", "re_nu", "re_G", "re_K", "epe", "psnr", "ssim", "seconds", "iterations"):
        assert k in disk and math.isfinite(disk[k]), k
    assert disk["iterations"] == 3 and "tissue" in disk["re_objects"]
    stages = disk["stage_seconds"]  # wall time by stage: the stages this run had, each timed
    assert stages["iterations"] == disk["seconds"] and set(stages) >= {"iterations", "evaluation"}
    assert all(v >= 0 for v in stages.values())
    assert disk["stopped"] == "iters" and disk["stopped_by_budget"] is False
    assert disk["frame_stride"] == 2 and "5 of 10 frames compared (stride 2)" in (run_dir / "summary.txt").read_text()
    auto = write_outputs(tmp_path / "auto", problem, res, IdentifyConfig(intervals=False), init_name="test", video=False)
    assert auto["frame_stride"] == 1 and auto["config"]["frame_stride"] is None  # what ran, and what was asked
    ident = MaterialField.load(run_dir / "materials_identified.json")
    assert ident[1].E == pytest.approx(res.field[1].E)
    assert m["epe"] == disk["epe"]


def test_cli_identify_iters_zero(tiny, tmp_path):
    import typer
    from typer.testing import CliRunner

    from endogsim.cli.identify import register

    app = typer.Typer()
    register(app)

    @app.command("noop")
    def _noop() -> None:  # a second command keeps typer from collapsing the app into one command
        pass

    out = tmp_path / "run"
    r = CliRunner().invoke(app, ["identify", str(tiny), "--out", str(out), "--init", "prior", "--iters", "0", "--no-video"])
    assert r.exit_code == 0, r.output
    m = json.loads((out / "metrics.json").read_text())
    assert m["iterations"] == 0 and m["init"] == "prior"
    # no optimisation ran: the table gives the value's source (the prior), never "identified"
    assert m["materials"]["tissue"]["source"] == "prior" and "identified" not in r.output
    assert "E's scale: weight (gravity 9.81 m/s^2 along (0, 0, 1))" in " ".join(r.output.split())
    bad = CliRunner().invoke(app, ["identify", str(tmp_path / "missing"), "--out", str(out)])
    assert bad.exit_code == 2 and "scene.json" in bad.output


@pytest.fixture(scope="module")
def from_3x_off(problem, tmp_path_factory):
    """Identification from E 3x too stiff (nu known), 20 iterations at most: (result, true E)."""
    cfg = IdentifyConfig(iters=20, optimize_nu=False, patience=6, time_budget=None)
    res = identify(problem, field_from_truth(problem, 3.0), cfg, run_dir=tmp_path_factory.mktemp("from3x") / "run")
    return res, next(o.E for o in problem.spec.objects if not o.rigid)


@pytest.mark.slow
def test_from_3x_off_identification_moves_E_to_the_truth_within_the_discretisation_bias(from_3x_off):
    """The ground truth is simulated 2x finer than identification, whose motion is not converged (bench
    convergence: 0.243 on tiny), so the loss need not be least at the true E (at stop 27 it was least 1.2-1.3x
    above it; docs/IDENTIFICATION.md section 3). From 3x too stiff the estimate comes within that bias, the
    interval of the video's noise alone excludes the start, and the 90% interval with the discretisation's
    error (its grid convergence index) holds the true E."""
    res, E_true = from_3x_off
    iv = next(iv for iv in res.intervals if iv.parameter == "E")
    assert 0.8 < res.field[1].E / E_true < 1.5, (res.field[1].E, E_true)
    assert iv.statistical_interval[1] < 3.0 * E_true and res.field[1].source != NOT_IDENTIFIABLE
    assert iv.interval[0] <= E_true <= iv.interval[1], (iv.interval, iv.discretisation)


@pytest.mark.slow
def test_recovers_E_within_10_percent_from_3x_off(from_3x_off):
    """From E 3x too stiff (nu known), identification lands within 10% of the true E.

    Measured at stop 84: 2530 Pa for 2500 after 7 iterations (7500, 5957, 4519, 3244, 2179, 2659, 2407, 2530
    Pa), the refined correction (1.5x) keeping it. This was a strict xfail until then, for a loss least
    1.2-1.3x above the truth (3350 Pa at stop 27). The scene generator and the simulator have changed many
    times since, and the loss is now least within a few per cent of the truth on this clip (0.028226,
    0.028222, 0.028223 at 2407, 2530, 2659 Pa). The valley is flat: the noise's interval is [2084, 3307] Pa,
    so 10% is where Rprop stops in it, not what the video guarantees. A change upstream that moves the
    estimate out of 10% while the test above still passes is not by itself a regression of the method."""
    res, E_true = from_3x_off
    assert abs(res.field[1].E / E_true - 1) < 0.10, (res.field[1].E, E_true)


def test_the_automatic_frame_stride_compares_at_least_ten_frames():
    """Every second frame where that still leaves 10 to compare (the intervals' t-test), else every frame;
    an explicit stride is kept."""
    auto = IdentifyConfig()
    assert [auto.stride(n) for n in (3, 10, 16, 19, 20, 42, 63)] == [1, 1, 1, 2, 2, 2, 2]
    assert IdentifyConfig(frame_stride=3).stride(10) == 3 and IdentifyConfig(frame_stride=1).stride(63) == 1
    with pytest.raises(MaterialError, match="frame_stride = 0"):
        IdentifyConfig(frame_stride=0)


def test_a_gradient_that_cannot_move_the_loss_by_tol_over_a_unit_step_is_stationary():
    from endogsim.identify.optimize import stationary

    E, nu = torch.zeros(2, requires_grad=True), torch.zeros(2, requires_grad=True)
    (E * torch.tensor([1e-4, -5e-4]) + nu * torch.tensor([2e-4, 0.0])).sum().backward()
    assert stationary([E, nu], loss=1.0, tol=1e-3)  # the largest, 5e-4 per decade, is below 1e-3 of the loss
    assert not stationary([E, nu], loss=0.4, tol=1e-3)  # ... but not below 1e-3 of a smaller loss
    assert stationary([E], loss=-1.0, tol=1e-3)  # the loss's size counts, not its sign


def test_shared_scale_adam_is_adam_for_one_object_and_steps_weakly_observed_objects_less():
    from endogsim.identify.optimize import SharedScaleAdam

    a, b = torch.tensor([0.3], requires_grad=True), torch.tensor([0.3], requires_grad=True)
    ours, adam = SharedScaleAdam([a], lr=0.1), torch.optim.Adam([b], lr=0.1, betas=(0.9, 0.99))
    for k in range(5):
        for x, opt in ((a, ours), (b, adam)):
            opt.zero_grad()
            ((x - 2) ** 2 * torch.sin(x + k)).sum().backward()
            opt.step()
    assert torch.allclose(a, b, atol=1e-6)
    # Two objects, gradients 1 : 0.2: the first steps by lr, the second by a fifth of it (Adam: both by lr).
    x = torch.zeros(2, requires_grad=True)
    opt = SharedScaleAdam([x], lr=0.1)
    (x * torch.tensor([1.0, 0.2])).sum().backward()
    opt.step()
    assert torch.allclose(x.detach(), torch.tensor([-0.1, -0.02]), atol=1e-6)


def test_shared_scale_rprop_travels_far_settles_and_steps_weakly_observed_objects_less():
    from endogsim.identify.config import OPTIMIZER_KINDS
    from endogsim.identify.optimize import OPTIMIZERS, SharedScaleAdam, SharedScaleRprop

    # every optimiser the config takes is implemented: the gradient ones here, "lm" by identify's own loop
    assert sorted([*OPTIMIZERS.names(), "lm"]) == sorted(OPTIMIZER_KINDS)
    with pytest.raises(MaterialError, match="optimiser"):
        IdentifyConfig(optimizer="sgd")

    def run(make, steps=10):
        x = torch.tensor([0.0], requires_grad=True)
        opt, path = make([x]), []
        for k in range(steps):
            opt.zero_grad()
            ((x + 0.66) ** 2).sum().backward()  # a prior 0.66 decades off (the suite's stomach)
            opt.step()
            path.append(float(x.detach()))
        return path

    rprop = run(lambda p: SharedScaleRprop(p, lr=0.1))
    # Steps of 0.1, 0.12, 0.144, ... while the gradient keeps its sign; halved when it turns.
    assert [round(b - a, 6) for a, b in zip([0.0] + rprop, rprop)][:3] == [-0.1, -0.12, -0.144]
    assert abs(rprop[-1] + 0.66) < 0.05
    adam = run(lambda p: SharedScaleAdam(p, lr=0.1))
    assert abs(adam[-1] + 0.66) > 0.1  # Adam's steps of about lr leave it short after 10 iterations
    # Two objects, gradients 1 : 0.2: the first steps by the size, the second by a fifth of it.
    x = torch.zeros(2, requires_grad=True)
    opt = OPTIMIZERS.get("rprop")([{"params": [x]}], 0.1)
    (x * torch.tensor([1.0, 0.2])).sum().backward()
    opt.step()
    assert torch.allclose(x.detach(), torch.tensor([-0.1, -0.02]), atol=1e-6)
    # Its state round-trips through a checkpoint: a resumed run takes the same next step.
    again = OPTIMIZERS.get("rprop")([{"params": [y := x.detach().clone().requires_grad_()]}], 0.1)
    again.load_state_dict(opt.state_dict())
    for p, o in ((x, opt), (y, again)):
        o.zero_grad()
        (p * torch.tensor([1.0, 0.2])).sum().backward()
        o.step()
    assert torch.equal(x.detach(), y.detach()) and abs(float(x[0]) + 0.22) < 1e-6


# ---- Levenberg-Marquardt (optimizer "lm"; its numerics: tests/test_levenberg_marquardt.py) ----------------------

@pytest.mark.parametrize("loss", ["joint", "joint_track", "render", "flow"])
def test_the_residuals_square_to_the_loss(problem, loss):
    """sum r^2 is the identification loss of every preset (the track term where the scene has tracks), to the
    loss's float32 rounding."""
    cfg = IdentifyConfig(loss=loss)
    obs, cam = prepare_observations(problem, cfg, None)
    fld = field_from_truth(problem, 2.0)
    with torch.no_grad():
        sim = simulate_materials(problem, fld.simulator_materials(), cfg.grad_mode)
        rendered = render_sequence(problem, sim.positions, sim.F, cam, frames=range(0, problem.num_frames, 2))
    total = identification_loss(rendered, obs, cfg.term_weights()).parts["total"]
    r = loss_residuals(rendered, obs, cfg.term_weights())
    assert r.dtype == torch.float64 and total > 0
    assert float(r.square().sum()) == pytest.approx(total, rel=1e-6)  # the loss's terms sum in float32


def lm_config(**kw) -> IdentifyConfig:
    return IdentifyConfig(**{"optimizer": "lm", "iters": 6, "intervals": False, "time_budget": None,
                             "frame_stride": 2, "refined_correction": None, **kw})


@pytest.fixture(scope="module")
def lm_run(problem, tmp_path_factory):
    d = tmp_path_factory.mktemp("lm_run")
    return identify(problem, field_from_truth(problem, 2.0, nu=0.47), lm_config(), run_dir=d)


def test_lm_identification_lowers_the_loss_and_stops_by_its_tolerance(problem, lm_run):
    """From E 2x too stiff the loss falls at every iteration; the run ends by its tolerance (or its
    iterations) with E closer to the truth than where it started, and the history says how it stepped."""
    res = lm_run
    losses = [h["loss"] for h in res.history]
    assert all(b < a for a, b in zip(losses, losses[1:]))
    assert res.stopped in ("converged", "iters")
    true_E = next(o.E for o in problem.spec.objects if o.id == 1)
    E = res.field[1].E
    assert abs(math.log10(E / true_E)) < abs(math.log10(2.0)), E
    first = res.history[0]
    assert first["grad_log10_E"][0] > 0  # too stiff: the loss falls as E falls
    assert {"damping", "predicted_gain"} <= set(first)


def test_an_interrupted_lm_run_resumes_to_the_same_result(problem, lm_run, tmp_path):
    d = tmp_path / "resume"
    init = field_from_truth(problem, 2.0, nu=0.47)
    part = identify(problem, init, lm_config(), run_dir=d, stop_after=2)
    assert part.stopped == "interrupted" and part.iterations == 2
    done = identify(problem, init, lm_config(), run_dir=d)
    assert done.field[1].E == lm_run.field[1].E and done.field[1].nu == lm_run.field[1].nu
    assert [h["loss"] for h in done.history] == [h["loss"] for h in lm_run.history]


def test_lm_identification_does_not_depend_on_how_many_simulations_run_at_a_time(problem, lm_run, monkeypatch):
    from endogsim.scene.folder import SimScene

    monkeypatch.setattr(SimScene, "independent_simulations", lambda self: 1)
    one = identify(problem, field_from_truth(problem, 2.0, nu=0.47), lm_config())
    assert one.field[1].E == lm_run.field[1].E
    assert [h["loss"] for h in one.history] == [h["loss"] for h in lm_run.history]
