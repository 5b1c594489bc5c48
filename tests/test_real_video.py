"""The real-video path: instrument colliders, torn tissue caught, quasi-static mass scaling, moving cameras,
the track term, and ``endogsim validate`` on held-out frames."""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from endogsim.errors import DataError, SimulationError


def _shared_data() -> Path:
    env = os.environ.get("ENDOGSIM_SHARED_DATA")
    return Path(env) if env else (Path(__file__).parents[1] / ".." / "shared" / "data").resolve()


# ------------------------------------------------------------------------------------------------- colliders
def _sheet(z: float = 0.06, half: float = 0.02, step: float = 0.001) -> np.ndarray:
    u = np.arange(-half, half + 1e-12, step)
    xx, yy = np.meshgrid(u, u)
    return np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)], 1)


def test_a_collider_inside_the_tissue_is_moved_out_towards_the_camera():
    from endogsim.pipeline.scene_from_recon import _segment_distance, push_out_of_tissue

    tissue = _sheet()  # a sheet 6 cm from the camera; a capsule lying 1 mm into it
    tip, end, r = np.array([-0.01, 0.0, 0.061]), np.array([0.01, 0.0, 0.061]), 0.003
    assert (_segment_distance(tissue, tip, end) < r).sum() > 0
    tip2, end2, pushed, inside = push_out_of_tissue(tip, end, r, tissue, clearance=0.0005)
    assert inside == int((_segment_distance(tissue, tip, end) < r).sum())
    assert _segment_distance(tissue, tip2, end2).min() >= r + 0.0005 - 1e-9
    assert pushed == pytest.approx(0.0045, abs=1e-6)  # axis 1 mm behind the sheet + 3 mm radius + 0.5 mm clearance
    np.testing.assert_allclose(np.cross(tip2 - tip, (tip + end) / 2), 0.0, atol=1e-9)  # along the viewing ray
    same = push_out_of_tissue(tip2, end2, r, tissue, clearance=0.0005)
    assert same[2] == 0.0 and same[3] == 0  # already clear: untouched
    with pytest.raises(DataError, match="stays inside the tissue"):
        push_out_of_tissue(np.array([0, 0, 0.2]), np.array([0, 0, 0.01]), r, _sheet(half=0.2, step=0.004),
                           clearance=0.0, max_push=0.01)


def _grey_shaft(g: torch.Generator, n: int, x_lo: float, x_hi: float) -> torch.Tensor:
    """[n, 3] points on the near half of a shaft of radius 3 mm along x (x_lo..x_hi metres) at 4 cm depth."""
    s = torch.rand(n, generator=g) * (x_hi - x_lo) + x_lo
    a = torch.rand(n, generator=g) * torch.pi
    return torch.stack([s, -0.003 * torch.cos(a), 0.04 - 0.003 * torch.sin(a)], 1)


def test_the_collider_is_fitted_to_the_grey_core_not_to_a_leaking_mask():
    from endogsim.gaussians.model import Gaussians
    from endogsim.pipeline.scene_from_recon import instrument_colliders

    g = torch.Generator().manual_seed(0)
    # A grey shaft of radius 3 mm along x at 4 cm, seen from above, and a reddish leak of the mask beside it.
    n = 400
    shaft = _grey_shaft(g, n, -0.015, 0.015)
    leak = torch.stack([torch.rand(200, generator=g) * 0.03 - 0.015, 0.003 + torch.rand(200, generator=g) * 0.004,
                        torch.full((200,), 0.041)], 1)
    means = torch.cat([shaft, leak])
    colors = torch.cat([torch.full((n, 3), 0.6), torch.tensor([[0.8, 0.3, 0.3]]).expand(200, 3)])
    tool = Gaussians.from_points(means, colors, scales=0.0005, object_ids=7, opacity=0.9)
    fits = instrument_colliders(tool, [7], _sheet(z=0.05), dx=0.002)
    assert len(fits) == 1 and fits[0].object_id == 7 and fits[0].core == n
    assert 0.0027 < fits[0].radius < 0.0033  # the shaft's radius, not the 5 mm the leak would make it
    assert fits[0].pushed == 0.0 and fits[0].inside == 0


def test_the_working_end_is_the_one_inside_the_view_not_the_one_farther_in_depth():
    from endogsim.pipeline.scene_from_recon import working_end

    K = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])
    rect = np.ones((240, 320), bool)
    shaft_end = np.array([-0.1, 0.0, 0.06])  # projects left of the image: where the shaft comes in
    jaws = np.array([0.0, 0.005, 0.05])      # in the middle, and nearer the camera (as monocular depth has it)
    tip, end, how = working_end(shaft_end, jaws, K, rect)
    assert how == "image" and np.array_equal(tip, jaws) and np.array_equal(end, shaft_end)
    assert np.array_equal(working_end(jaws, shaft_end, K, rect)[0], jaws)  # whatever the fitted order
    # An endoscope's round field (CholecSeg8K): an end near the circle's edge is the shaft's, though it lies
    # well inside the image rectangle.
    yy, xx = np.mgrid[:240, :320]
    disc = (xx - 160) ** 2 + (yy - 120) ** 2 <= 110 ** 2
    near_rim = np.array([0.0225, -0.015, 0.05])  # (250, 60): 2 px inside the rim, 60 px below the top
    centre = np.array([0.002, 0.002, 0.06])
    assert disc[60, 250] and not disc[58, 252]
    tip, end, how = working_end(near_rim, centre, K, disc)
    assert how == "image" and np.array_equal(tip, centre) and np.array_equal(end, near_rim)
    # Both ends equally deep inside: the fitted order stands.
    a, b = np.array([-0.01, 0.0, 0.05]), np.array([0.01, 0.0, 0.05])
    assert working_end(a, b, K, rect)[2] == "depth" and np.array_equal(working_end(a, b, K, rect)[0], a)
    assert working_end(-a, -b, K, rect)[2] == "depth"  # both behind the camera: nothing to see


def test_the_collider_reaches_the_jaws_beyond_the_grey_shaft():
    from endogsim.gaussians.model import Gaussians
    from endogsim.pipeline.scene_from_recon import instrument_colliders

    g = torch.Generator().manual_seed(0)
    # A grey shaft of radius 3 mm along x at 4 cm from x = -60 mm (out of view on the left) to 0, and the
    # jaws, brownish in the light, from 0 to 8 mm: the grey core ends where the jaws begin.
    n = 400
    shaft = _grey_shaft(g, n, -0.06, 0.0)
    j = torch.rand(100, generator=g) * 0.008
    jaws = torch.stack([j, 0.002 * (torch.rand(100, generator=g) - 0.5), torch.full((100,), 0.0385)], 1)
    tool = Gaussians.from_points(torch.cat([shaft, jaws]), torch.cat([torch.full((n, 3), 0.6),
                                 torch.tensor([[0.6, 0.4, 0.3]]).expand(100, 3)]), scales=0.0005, object_ids=7,
                                 opacity=0.9)
    K = np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]])
    fit = instrument_colliders(tool, [7], _sheet(z=0.05), dx=0.002, K=K, field=np.ones((240, 320), bool))[0]
    assert fit.oriented == "image" and fit.core == n
    assert 0.0075 < fit.tip[0] < 0.0085 and fit.end[0] < -0.055  # the tip at the jaws' end, the end off view
    assert fit.to_json()["working_end_from"] == "image" and 0.008 < fit.jaws < 0.0105  # 8 mm and the core's end


# ------------------------------------------------------------------------------------------------- coverage
@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from endogsim.scene.folder import load_sim_scene
    from endogsim.synth import synthesize

    return load_sim_scene(synthesize("tiny", tmp_path_factory.mktemp("real") / "tiny", seed=0, frames=5))


def _truth(problem):
    from endogsim.physics import ObjectMaterials

    M = max(o.id for o in problem.spec.objects) + 1
    E, nu, rho, model = [1.0] * M, [0.0] * M, [1.0] * M, ["fixed_corotated"] * M
    for o in problem.spec.deformable:
        E[o.id], nu[o.id], rho[o.id], model[o.id] = o.E, o.nu, o.density, o.model
    return ObjectMaterials.of(E, nu, rho, model)


def test_torn_tissue_is_caught_by_its_coverage_naming_frame_and_object(tiny_scene):
    from endogsim.scene.coverage import check_coverage, tissue_coverage

    p = tiny_scene
    res = p.simulator().simulate(_truth(p))
    cam = p.camera.scaled(0.5)
    whole = tissue_coverage(p, res.positions, res.F, cam)
    check_coverage(whole, p)  # the ground truth's own materials: whole
    assert whole.worst()[2] < 0.002
    torn = res.positions.clone()
    right = res.positions[0, :, 0] > 0
    torn[3:, right, 0] += 0.02  # the right half pulled 2 cm away from frame 3 on
    cov = tissue_coverage(p, torn, res.F, cam)
    oid, frame, drop = cov.worst()
    assert oid == 1 and frame >= 3 and drop > 0.05
    with pytest.raises(SimulationError, match=r"object 'tissue' covers less of its footprint from frame 3 on"):
        check_coverage(cov, p)
    # The video's own masks cover the footprint throughout: the tear is all the simulation's.
    assert cov.observed is not None and max(cov.observed[1][0] - o for o in cov.observed[1]) < 1e-3


def test_a_coverage_drop_the_video_also_shows_is_not_a_tear():
    from endogsim.scene.coverage import Coverage, check_coverage, observed_objects

    # What the video covers: any of the scene's objects, whatever their ids (a real video's tissue is object
    # 0), not background or an unknown label; masks are resized without blending labels.
    labels = np.array([[0, 0, 31, 50], [0, 0, 31, 50]])
    assert observed_objects(labels, [0, 31], 4, 2).tolist() == [[True, True, True, False]] * 2
    assert observed_objects(labels, [0, 31], 2, 1).tolist() == [[True, True]]

    sim = {1: [0.99, 0.985, 0.97]}  # 2% drop at frame 2
    check_coverage(Coverage([0, 1, 2], sim, {1: 500}, observed={1: [1.0, 1.0, 0.985]}))  # the video shows 1.5%
    assert Coverage([0, 1, 2], sim, {1: 500}, observed={1: [1.0, 1.0, 0.985]}).worst()[2] == pytest.approx(0.005)
    with pytest.raises(SimulationError, match=r"by up to 2.0% more than the video shows, at frame 2"):
        check_coverage(Coverage([0, 1, 2], sim, {1: 500}, observed={1: [1.0, 1.0, 1.0]}))


# ------------------------------------------------------------------------------------------------- mass scaling
def test_mass_scaling_keeps_the_quasi_static_answer_with_fewer_substeps(tiny_scene):
    from endogsim.physics import Simulator

    p = tiny_scene
    base = replace(p.scenario, colliders=[], gravity=(0.0, 0.0, 9.81), settle_frames=0)
    mpm = replace(p.mpm, damping=200.0, substeps_per_frame=1)
    out = {}
    for k in (1.0, 4.0):  # sag under gravity, strongly damped: the equilibrium does not depend on the mass
        sim = Simulator(p.particles, replace(base, mass_scaling=k), mpm, 40)
        res = sim.simulate(_truth(p))
        out[k] = (res.positions[-1] - res.positions[0], res.substeps)
    sag1, n1 = out[1.0]
    sag4, n4 = out[4.0]
    assert n4 < 0.6 * n1  # the wave speed halves
    assert float(sag1[:, 2].max()) > 1e-4  # it sags (> 0.1 mm)
    rel = float((sag4 - sag1).norm(dim=-1).max() / sag1.norm(dim=-1).max())
    assert rel < 0.05, rel
    from endogsim.physics import ExternalForce, Scenario

    with pytest.raises(SimulationError, match="impulse"):
        Scenario(base.box, forces=[ExternalForce(acceleration=(0, 0, 1.0), impulse=True,
                                                 particle_mask=torch.ones(len(p.particles), dtype=torch.bool))],
                 mass_scaling=2.0)


def test_a_settling_that_stops_short_of_the_equilibrium_is_reported(tiny_scene):
    """Settling before frame 0 must reach the equilibrium, or the rest of it moves in the clip (a fit reads
    it as motion: on CholecSeg8K, 2 frames at 400/s left 0.08 mm RMS, and calibration stiffened the tissue to
    suppress it). Tissue sliding under gravity along its support, no instrument: 2 settle frames at 400/s
    (over-damped: slow) leave a drift the clip shows, and the record says so; 20 frames at 100/s settle."""
    from endogsim.identify.report import settling_record
    from endogsim.physics import ObjectMaterials, Simulator

    p = tiny_scene
    M = max(o.id for o in p.spec.objects) + 1
    prior = ObjectMaterials.of([1e4] * M, [0.47] * M, [1000.0] * M, ["fixed_corotated"] * M)
    mpm = replace(p.mpm, damping=100.0)
    drift, record = {}, {}
    for frames, damping in ((2, 400.0), (20, 100.0)):
        sc = replace(p.scenario, colliders=[], gravity=(0.0, 9.81, 0.0), mass_scaling=4.0, settle_frames=frames,
                     settle_damping=damping)
        res = Simulator(p.particles, sc, mpm, 3).simulate(prior)
        drift[frames] = float((res.positions[-1] - res.positions[0]).norm(dim=-1).max())
        record[frames] = settling_record(replace(p, scenario=sc, mpm=mpm), res.settling_left)
    assert not record[2]["settled"] and record[2]["frames"] == 2 and record[2]["cells"] > 0.01
    assert record[20]["settled"] and record[20]["cells"] < 0.005
    assert drift[2] > 1e-4 and drift[2] > 10 * drift[20], drift  # the unsettled one moves in the clip


# ------------------------------------------------------------------------------------------------- cameras, tracks
def test_a_moving_camera_renders_each_frame_in_its_own_view(tiny_scene):
    from endogsim.gaussians.camera import Camera
    from endogsim.scene.forward import in_view

    p = replace(tiny_scene)
    a = 0.1
    V = torch.eye(4).repeat(3, 1, 1)
    V[2, :3, :3] = torch.tensor([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]], dtype=torch.float32)
    V[2, :3, 3] = torch.tensor([0.003, -0.002, 0.001])
    p.viewmats = V
    pts = p.gaussians.means[:50].float()
    m, _ = in_view(p, pts, None, 2)
    plain = Camera(p.camera.K, p.camera.width, p.camera.height)
    torch.testing.assert_close(plain.project(m), Camera(p.camera.K, p.camera.width, p.camera.height, V[2]).project(pts))


def test_simulated_frames_are_exposed_and_cropped_as_the_endoscope_filmed_them(tiny_scene):
    """A moving endoscope's light and auto-exposure change every frame's colours, and its image ends at a
    circle: the simulated frames get the reconstruction's exposure of that frame and its field of view, at
    any render scale, differentiably (brute force: the bare render mapped by hand)."""
    from endogsim.scene.forward import render_sequence

    p = tiny_scene
    T = p.num_frames
    res = p.simulator().simulate(_truth(p))
    cam = p.camera.scaled(0.5)
    exposure = torch.zeros(T, 2, 3)
    exposure[:, 0] = torch.linspace(0, 0.2, T)[:, None] * torch.tensor([1.0, 0.5, -0.5])  # log gain
    exposure[:, 1] = torch.linspace(0, 0.03, T)[:, None]  # bias
    H, W = p.camera.height, p.camera.width
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    fov = (yy - H / 2) ** 2 + (xx - W / 2) ** 2 < (0.45 * H) ** 2
    filmed = replace(p, exposure=exposure, field_of_view=fov)
    bare = render_sequence(p, res.positions, res.F, cam, frames=[0, 3])
    pos = res.positions.clone().requires_grad_(True)
    seen = render_sequence(filmed, pos, res.F, cam, frames=[0, 3])
    small = torch.nn.functional.interpolate(fov[None, None].float(), size=(cam.height, cam.width))[0, 0]
    for k, t in enumerate((0, 3)):
        expect = (bare.rgb[k] * torch.exp(exposure[t, 0]) + exposure[t, 1]) * small[..., None]
        torch.testing.assert_close(seen.rgb[k], expect)
    assert float(seen.rgb[1].detach()[small == 0].abs().max()) == 0 and float(bare.rgb[1][small == 0].max()) > 0.1
    torch.testing.assert_close(seen.flow, bare.flow * small[..., None])  # the same motion, where it was filmed
    torch.testing.assert_close(seen.alpha, bare.alpha)
    seen.rgb[1].sum().backward()
    assert pos.grad is not None and float(pos.grad.abs().sum()) > 0


def test_the_flow_error_shown_is_zero_where_the_endoscope_films_nothing(tiny_scene):
    """The flow-error panel (comparison video, held-out stills) is |simulated - observed| inside the endoscope's
    circle and 0 beyond it, where an observed flow estimate bleeds into the black border and nothing is scored;
    a scene without a field of view shows the error everywhere."""
    from endogsim.identify.report import flow_error_map

    p = tiny_scene
    H, W = p.camera.height // 2, p.camera.width // 2  # the panel's scale need not be the field of view's
    yy, xx = torch.meshgrid(torch.arange(p.camera.height), torch.arange(p.camera.width), indexing="ij")
    fov = (yy - p.camera.height / 2) ** 2 + (xx - p.camera.width / 2) ** 2 < (0.45 * p.camera.height) ** 2
    rng = np.random.default_rng(0)
    flow = rng.normal(size=(3, H, W, 2)).astype(np.float32)
    seen = rng.normal(size=(3, H, W, 2)).astype(np.float32)
    everywhere = np.linalg.norm(flow - seen, axis=-1)
    np.testing.assert_allclose(flow_error_map(p, flow, seen), everywhere, rtol=1e-6)
    np.testing.assert_allclose(flow_error_map(p, flow, None), np.linalg.norm(flow, axis=-1), rtol=1e-6)
    small = fov[::2, ::2].numpy()
    cut = flow_error_map(replace(p, field_of_view=fov), flow, seen)
    np.testing.assert_allclose(cut[:, small], everywhere[:, small], rtol=1e-6)
    assert float(np.abs(cut[:, ~small]).max()) == 0.0 and float(everywhere[:, ~small].min()) > 0.0


def test_an_instrument_the_video_does_not_show_is_not_drawn(tiny_scene):
    from endogsim.scene.forward import render_sequence

    p = tiny_scene
    tid = p.spec.scenario.tools[0].object_id
    res = p.simulator().simulate(_truth(p))
    cam = p.camera.scaled(0.25)
    T = p.num_frames
    drawn = render_sequence(p, res.positions, res.F, cam, frames=[1, 2])
    seen = torch.ones(T, dtype=torch.bool)
    seen[2] = False  # out of view in frame 2: its pose is held there, but the video shows tissue
    gap = render_sequence(replace(p, tool_visible={tid: seen}), res.positions, res.F, cam, frames=[1, 2])
    never = render_sequence(replace(p, tool_visible={tid: torch.zeros(T, dtype=torch.bool)}), res.positions, res.F,
                            cam, frames=[1, 2])
    assert float((drawn.alpha[1] - never.alpha[1]).abs().max()) > 0.5  # the probe is in view and drawn
    torch.testing.assert_close(gap.rgb[0], drawn.rgb[0])  # frame 1: shown as before
    torch.testing.assert_close(gap.rgb[1], never.rgb[1])  # frame 2: the tissue alone
    torch.testing.assert_close(gap.alpha[1], never.alpha[1])


def test_the_track_term_compares_projected_trajectories():
    from endogsim.identify.loss import Observations, track_term
    from endogsim.scene.forward import Rendered

    T, N, H, W = 4, 30, 16, 20
    obs_tracks = torch.rand(T, N, 2) * torch.tensor([W, H])
    valid = torch.ones(T, N, dtype=torch.bool)
    valid[2, :10] = False  # behind a tool at frame 2
    obs = Observations(torch.zeros(T, H, W, 3), torch.zeros(T - 1, H, W, 2), torch.ones(T, H, W, dtype=torch.bool),
                       torch.ones(T - 1, H, W, dtype=torch.bool), obs_tracks, valid)
    sim = obs_tracks.clone().requires_grad_(True)
    r = Rendered(torch.zeros(T, H, W, 3), torch.zeros(T - 1, H, W, 2), torch.ones(T, H, W), list(range(T)), sim)
    frames, v = track_term(r, obs)
    assert frames == [1, 2, 3] and float(v.detach().abs().max()) == 0.0
    shifted = sim + torch.tensor([3.0, 4.0])
    frames, v = track_term(replace(r, tracks=shifted), obs)
    torch.testing.assert_close(v, torch.full((3,), 25.0))  # 5 px off everywhere (invalid tracks left out)
    v.sum().backward()
    assert sim.grad is not None and float(sim.grad[2, :10].abs().max()) == 0.0
    none = replace(r, tracks=None)
    assert track_term(none, obs)[0] == []


# ------------------------------------------------------------------------------------------------- validate
@pytest.fixture(scope="module")
def validated(tmp_path_factory):
    from endogsim.identify.config import IdentifyConfig
    from endogsim.pipeline.run import PipelineConfig
    from endogsim.pipeline.validate import ValidateConfig, run_validate
    from endogsim.recon.config import ReconConfig
    from endogsim.synth import synthesize

    root = tmp_path_factory.mktemp("validate")
    data = synthesize("tiny", root / "data", seed=0, frames=6)
    cfg = ValidateConfig(pipeline=PipelineConfig(recon=ReconConfig(iters=60, resolution_scale=1.0),
                                                 identify=IdentifyConfig(iters=1), interaction=None))
    return run_validate(data, root / "run", cfg, log=lambda *a: None), root / "run", cfg


def test_validate_returns_every_figure_and_its_prior_baseline_is_a_plain_simulation(validated):
    from endogsim.identify.loss import make_observations, observed_flow
    from endogsim.identify.run import initial_field
    from endogsim.pipeline.validate import heldout_scores
    from endogsim.scene.folder import load_sim_scene
    from endogsim.scene.forward import render_sequence

    res, run, cfg = validated
    assert set(res) >= {"clip", "train_frames", "test_frames", "prediction", "baselines", "materials", "identifiable",
                        "seconds"}
    assert res["train_frames"] == 4 and res["test_frames"] == 2
    # The real-video scenario moves the border along the tracks, so the kinematic baseline of that drive is there.
    assert set(res["baselines"]) == {"prior", "zero_motion", "border_interpolation", "reconstruction"}
    for v in [res["prediction"], *res["baselines"].values()]:
        assert set(v) == {"epe", "psnr_masked"} and all(np.isfinite(x) for x in v.values())
    assert set(res["comparison"]) == {"prior", "zero_motion", "border_interpolation"}
    for k in res["comparison"]:  # whether the prediction wins, tested against the frame-to-frame noise
        c = res["comparison"][k]
        assert c["epe"]["frames"] == 2 and c["mse"]["frames"] == 2 and res["beats"][k] in (True, False)
        assert res["beats"][k] == all(c[w]["z"] < -c[w]["significant_z"] and c[w]["relative"] <= -1e-3
                                      for w in ("epe", "mse"))
    assert json.loads((run / "validate" / "validate.json").read_text())["train_frames"] == 4
    # The tissue rests on the real-video scenario's Coulomb support (RealScenario.support_friction).
    anchors = [b for b in json.loads((run / "scene" / "scene.json").read_text())["scenario"]["boundary_conditions"]
               if b["type"] == "anchors"]
    assert anchors and all(b["back_face"] == "support" and b["support_friction"] == 1.0 for b in anchors)
    # What sets E's scale is the real-video scenario's assumptions (RealScenario), said wherever E is.
    scales = res["force_scales"]
    assert scales["gravity_m_s2"] == [0.0, 9.81, 0.0] and scales["mass_scaling"] == 4.0
    assert scales["damping_per_s"] == 100.0 and scales["scales"] == ["weight", "inertia"]
    assert scales["kinematic_instruments"] == 1
    assert "E's scale: weight (gravity 9.81 m/s^2 along (0, 1, 0)) and inertia (frames" in (
        run / "calibrate" / "summary.txt").read_text()
    html = (run / "report.html").read_text()
    assert "Held-out validation" in html and "Identifiability" in html and "Tissue coverage" in html
    assert "<h2>What sets E's scale</h2>" in html and "masses x4, damping 100/s" in html
    # how the instrument was fitted, and frame 0 with its capsule drawn
    assert "<h2>Instruments</h2>" in html and 'alt="instruments at frame 0"' in html and "working end from" in html
    # The prior baseline is a plain simulation of the scene with the initial materials, scored the same way.
    p = load_sim_scene(run / "scene")
    fld, _ = initial_field(p, "prior")
    sim = p.simulator().simulate(fld.simulator_materials())
    cam = p.camera.scaled(cfg.eval_scale)
    r = render_sequence(p, sim.positions, sim.F, cam, frames=[3, 4, 5])
    U = observed_flow(p.frames, cfg.pipeline.identify.flow)
    obs = make_observations(p.frames, U, p.object_masks, p.deformable_ids, (cam.width, cam.height))
    plain = heldout_scores(r.rgb[1:].numpy(), r.flow.numpy(), obs.frames[[4, 5]].numpy(), obs.flow[[3, 4]].numpy(),
                           obs.valid_rgb[[4, 5]].numpy(), obs.valid_flow[[3, 4]].numpy())
    assert plain == pytest.approx(res["baselines"]["prior"], rel=1e-6)


def test_validate_refuses_the_reconstruction_of_another_clip(validated, tmp_path):
    from endogsim.pipeline.validate import check_reconstruction_of
    from endogsim.synth import synthesize

    _, run, _ = validated
    check_reconstruction_of(run / "recon", run.parent / "data")  # its own clip: fine
    other = synthesize("tiny", tmp_path / "other", seed=1, frames=6)
    with pytest.raises(DataError, match="is not a reconstruction of .*other: .* gives other frames"):
        check_reconstruction_of(run / "recon", other)


def test_a_prediction_beats_a_baseline_only_beyond_the_frame_to_frame_noise():
    from endogsim.pipeline.validate import compare_to

    rng = np.random.default_rng(0)
    base = (0.4 + 0.1 * rng.random(20), 0.01 + 0.002 * rng.random(20))  # per-pair EPE, per-frame MSE
    same = compare_to(base, base)
    assert not same["beats"] and same["epe"]["z"] == 0.0 and same["epe"]["difference"] == 0.0
    # lower by 1e-7 px on average but noisy frame to frame: a tie (the old test called it a win)
    wobble = 1e-5 * (-1.0) ** np.arange(20)
    tie = compare_to((base[0] - 1e-7 + wobble, base[1] - 1e-9 + 1e-4 * wobble), base)
    assert tie["epe"]["difference"] == pytest.approx(-1e-7, abs=1e-12) and not tie["beats"]
    # 9e-8 px lower on every frame: significant frame after frame (renders that differ in the 7th digit
    # differ consistently), but no win: it is not 0.1% of the error (pulling's prediction vs zero motion)
    consistent = compare_to((base[0] - 9e-8, base[1] - 1e-8), base)
    assert consistent["epe"]["z"] < -consistent["epe"]["significant_z"] and not consistent["beats"]
    better = compare_to((base[0] * 0.9, base[1] * 0.9), base)  # 10% lower on every frame
    assert better["beats"] and better["epe"]["z"] < -better["epe"]["significant_z"]
    worse_psnr = compare_to((base[0] * 0.9, base[1] * 1.1), base)  # better flow, worse images: no win
    assert not worse_psnr["beats"]


def test_no_tissue_lies_inside_a_collider_at_frame_0(validated):
    from endogsim.pipeline.scene_from_recon import _segment_distance
    from endogsim.scene.folder import load_sim_scene

    _, run, _ = validated
    p = load_sim_scene(run / "scene")
    x = p.particles.x.double().numpy()
    tools = p.spec.scenario.tools
    assert len(tools) == 1  # one probe, one collider
    assert tools[0].visible == [True] * p.num_frames and p.tool_visible == {}  # seen in every frame
    for t in tools:
        assert _segment_distance(x, np.asarray(t.tip), np.asarray(t.end)).min() >= t.radius
    assert json.loads((run / "scene" / "scene.json").read_text())["colliders"][0]["object_id"] == tools[0].object_id


@pytest.mark.realdata
@pytest.mark.parametrize("clip, instruments", [("endonerf_pulling", 2), ("cholecseg8k_clip", 1)])
def test_real_clips_give_one_collider_per_instrument(tmp_path, clip, instruments):
    from endogsim.pipeline.scene_from_recon import _segment_distance, scene_from_reconstruction
    from endogsim.recon.config import ReconConfig
    from endogsim.recon.train import reconstruct
    from endogsim.scene.folder import load_sim_scene

    data = _shared_data() / clip
    if not data.is_dir():
        pytest.skip(f"no {data}")
    # A few iterations are enough: the objects and their Gaussians are made at initialisation.
    reconstruct(data, tmp_path / "recon", ReconConfig(iters=20, resolution_scale=0.25, max_frames=8))
    scene = scene_from_reconstruction(tmp_path / "recon", data, tmp_path / "scene")
    p = load_sim_scene(scene)
    tools = p.spec.scenario.tools
    assert len(tools) == instruments and len({t.object_id for t in tools}) == instruments
    assert all(t.visible is not None and len(t.visible) == p.num_frames for t in tools)
    x = p.particles.x.double().numpy()
    for t in tools:
        assert _segment_distance(x, np.asarray(t.tip), np.asarray(t.end)).min() >= t.radius
    # Held is the band along the view's outline, not where organs meet: until stop 32 CholecSeg8K's
    # gallbladder and gastrointestinal tract were held whole and half its particles were held (here 52%;
    # now 26%; pulling's one tissue 32%, at this quick reconstruction's resolution).
    held, ids = p.scenario.pinned(x), p.particles.object_ids.numpy()
    assert held.mean() < 0.4, held.mean()
    for oid in np.unique(ids):
        if (ids == oid).sum() >= 100:
            assert held[ids == oid].mean() < 0.75, (p.spec.object(int(oid)).name, held[ids == oid].mean())


def test_a_grasping_tool_holds_the_free_tissue_its_jaws_close_on():
    from endogsim.physics import GRASP_MARGIN, Particles
    from endogsim.scene.particles import tool_colliders
    from endogsim.scene.schema import ToolCapsule

    parts = Particles.box((0.0, 0.0, 0.0), (0.02, 0.02, 0.006), 0.001)
    x = parts.x.double().numpy()
    pinned = x[:, 0] > 0.0195  # the border band at +x
    eye = np.eye(4)[None].repeat(3, 0).tolist()
    tip = [0.0195, 0.01, 0.0075]  # the jaws at the pinned edge: only free particles may be held
    grasper = ToolCapsule(object_id=7, tip=tip, end=[0.0195, 0.01, 0.03], radius=0.002, transforms=eye, contact="grasp")
    probe = ToolCapsule(object_id=8, tip=tip, end=[0.0195, 0.01, 0.03], radius=0.002, transforms=eye)
    held, pushed = tool_colliders([grasper, probe], parts, ~pinned, dx=0.002)
    d = np.linalg.norm(x - np.asarray(tip), axis=1)
    expect = np.flatnonzero((d <= 0.002 + GRASP_MARGIN) & ~pinned)
    assert len(expect) > 5 and np.array_equal(held.holds.numpy(), expect)
    assert pushed.holds is None  # a probe only pushes
    with pytest.raises(ValueError, match="contact 'glue'"):
        ToolCapsule(object_id=7, tip=tip, end=tip, radius=0.002, transforms=eye, contact="glue")


def test_which_real_instruments_grasp_is_a_checked_choice():
    from endogsim.pipeline.scene_from_recon import RealScenario

    assert RealScenario().grasping == "graspers"
    with pytest.raises(DataError, match="grasping 'some'"):
        RealScenario(grasping="some")
    from endogsim.scene.schema import ObjectBoundary

    assert RealScenario().border_motion == "tracked" and ObjectBoundary.from_json({}).border_motion == "still"
    with pytest.raises(DataError, match="border_motion 'wiggle'"):
        RealScenario(border_motion="wiggle")
    with pytest.raises(DataError, match="border_motion 'wiggle'"):
        ObjectBoundary.from_json({"border_motion": "wiggle"})


def test_tissue_tracks_carry_points_by_the_nearest_tracks():
    from endogsim.scene.tracks import TissueTracks

    T = 4
    start = torch.tensor([[0.0, 0.0, 0.05], [0.01, 0.0, 0.05], [0.0, 0.01, 0.05]], dtype=torch.float64)
    shift = torch.tensor([0.0, 0.0, 0.001], dtype=torch.float64) * torch.arange(T)[:, None]
    tracks = TissueTracks(torch.arange(3), (start[None] + shift[:, None]).float())
    points = np.array([[0.004, 0.003, 0.052], [0.0, 0.0, 0.05]])
    path = tracks.carry(points)
    # Every track translates alike: any point is carried by the same translation; one on a track by its own.
    np.testing.assert_allclose(path - points[None], shift.numpy()[:, None].repeat(2, 1), atol=1e-7)
    tracks.positions[:, 1, 0] += 0.002 * torch.arange(T)  # the second track moves on its own
    path = tracks.carry(points[1:], use=np.array([False, True, True]))
    assert path[-1, 0, 0] > 0 and tracks.carry(points[1:])[-1, 0, 0] == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(DataError, match="no tissue track"):
        tracks.carry(points, use=np.zeros(3, bool))


def test_a_real_scene_moves_its_border_along_the_tracks_and_an_interaction_holds_it_still(validated, tmp_path):
    import shutil

    from endogsim.pipeline.simulate import Interaction, build_interaction
    from endogsim.pipeline.validate import border_interpolation
    from endogsim.scene.folder import load_sim_scene

    _, run, _ = validated
    p = load_sim_scene(run / "scene")
    (anchor,) = p.scenario.moving_anchors
    assert len(anchor.particles) > 0 and anchor.positions.shape == (p.num_frames, len(anchor.particles), 3)
    # The band's particles are not also pinned, and start where they are.
    assert not p.scenario.pinned(p.particles.x.double().numpy())[anchor.particles.numpy()].any()
    torch.testing.assert_close(anchor.positions[0], p.particles.x[anchor.particles].double(), atol=1e-6, rtol=0)
    spec = {"frames": p.num_frames + 3, "force": {"at": [0.0, 0.0], "acceleration": [0.0, 0.0, 1.0]}}
    inter, _ = build_interaction(p, Interaction.model_validate(spec))
    # The kinematic baseline of the same drive: the band on its paths, every other particle carried by it.
    moved = border_interpolation(p)
    torch.testing.assert_close(moved[:, anchor.particles], anchor.positions.float(), atol=1e-6, rtol=0)
    assert moved.shape == (p.num_frames, len(p.particles), 3) and border_interpolation(inter) is not None
    (still,) = inter.scenario.moving_anchors
    assert still.positions.shape[0] == p.num_frames + 3 and float((still.positions - anchor.positions[0]).abs().max()) == 0
    # An object without a track of its own is carried by the other objects' tracks, warned.
    from endogsim.errors import DataWarning
    from endogsim.scene.particles import particles_from_scene_gaussians

    filled = particles_from_scene_gaussians(p.gaussians, p.spec, p.camera, p.spec.scenario.identification)
    with pytest.warns(DataWarning, match="no tissue track of its own"):
        (other,) = filled.moving_anchors(p.tracks, np.full(len(p.tracks.index), -1), 0.002)
    torch.testing.assert_close(other.positions, anchor.positions)
    # A scene that asks for it without tracks is refused, naming the folder and the missing file.
    copy = tmp_path / "scene"
    shutil.copytree(run / "scene", copy)
    doc = json.loads((copy / "scene.json").read_text())
    doc["files"].pop("tracks")
    (copy / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(DataError, match="border_motion 'tracked' needs the reconstruction's tissue tracks"):
        load_sim_scene(copy)
