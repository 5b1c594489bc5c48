"""Simulate a built scene and write its benchmark folder (EndoNeRF layout plus ground truth).

Folder written by :func:`synthesize` (T frames, H x W pixels, names as in EndoNeRF):
  images/frame-%06d.color.png       RGB, 8-bit
  depth/frame-%06d.depth.png        16-bit, depth_metres = value / scene.json["depth_scale"]; 0 = no surface
  masks/frame-%06d.mask.png         8-bit, 255 = tool (any rigid object), 0 = tissue / background
  object_masks/frame-%06d.png       16-bit object id per pixel (scene.json objects), 0 = background
  flow/frame-%06d.flow.npy          float32 [H, W, 2] ground-truth optical flow t -> t+1 (pixels), t < T-1
  flow/frame-%06d.valid.png         8-bit, 255 where the flow is defined (rendered alpha > 0.95)
  poses_bounds.npy                  (T, 17) LLFF: identity pose, [H, W, focal], near, far (metres)
  gaussians_t0.ply                  ground-truth Gaussians of frame 0 (the settled, observed state), object ids
  particles_ground_truth.npz        the ground truth's particles: x [P, 3] m, object_id [P], vol [P] m^3,
                                    pinned [P] (for inspection: identification never reads it)
  scene.json                        objects, scenario, camera, seed (see endogsim.scene.schema)

The ground truth is simulated by the Warp MLS-MPM of :mod:`endogsim.physics` at the scene's
``ground_truth`` discretisation, finer than identification's (2x the grid, half the particle spacing, 2x the
substeps; both in scene.json), from particles filling the objects' true surfaces (identification fills the
frame-0 Gaussians instead, as on a real video). The tissue first settles under gravity for
``settle_frames`` with the tools still: frame 0 is its equilibrium, as a video shows tissue at rest.
Gaussians follow the particles by :func:`endogsim.physics.bind_gaussians` /
:func:`endogsim.physics.drive_gaussians`, and tools move rigidly with their per-frame transforms.

The ground-truth flow is the Gaussian flow (:mod:`endogsim.gaussians.flow`) of the simulated Gaussians,
i.e. exactly the quantity identification compares against.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from endogsim.determinism import deterministic
from endogsim.errors import DataError, GroundTruthRefused, SimulationError
from endogsim.gaussians.flow import render_with_flow
from endogsim.gaussians.model import Gaussians, covariance_to_scale_rot
from endogsim.gaussians.ply import write_ply
from endogsim.gaussians.render import rasterize
from endogsim.io.atomic import atomic_folder, write_json_atomic
from endogsim.physics import (
    SETTLING_TOLERANCE,
    MPMConfig,
    ObjectMaterials,
    Scenario,
    SimBox,
    bind_gaussians,
    bite_records,
    drive_gaussians,
    simulate,
)
from endogsim.scene.coverage import PARTED_LIMIT, parted_share
from endogsim.scene.particles import (
    SceneParticles,
    build_particles,
    gaussian_surfaces,
    scenario_forces,
    tool_colliders,
)
from endogsim.scene.schema import IMAGES_PATTERN, CameraSpec, ScenarioSpec, SceneSpec
from endogsim.synth.scenes import BuiltScene, build_procedural
from endogsim.synth.suite import GENERATOR_REVISION, check_size

__all__ = ["synthesize", "ground_truth_problem", "simulate_built", "render_built", "write_scene_folder", "DEPTH_SCALE"]

DEPTH_SCALE = 10000.0  # 16-bit depth png units per metre (0.1 mm steps, up to 6.5 m)
VALID_ALPHA = 0.95


def _wall_cells(b: BuiltScene) -> int:
    return next((int(bc.get("cells", 2)) for bc in b.boundary_conditions if bc.get("type") == "box_walls"), 2)


def ground_truth_problem(b: BuiltScene) -> tuple[SceneParticles, ObjectMaterials, Scenario, MPMConfig]:
    """The ground-truth simulation of a built scene for :func:`endogsim.physics.simulate`.

    Returns the particles (the objects' true surfaces filled at the ground truth's spacing, with their
    boundary conditions, :mod:`endogsim.scene.particles`), the per-object ground-truth materials, the
    scenario (sim box, gravity, anchors, forces, capsule tools as point colliders, settling kept as frame 0)
    and the ``ground_truth`` numerics.
    """
    gt = b.ground_truth
    spec = _scene_spec(b, seed=0)
    deformable = [o.id for o in b.objects if not o.rigid]
    rest_tissue = b.gaussians.subset(torch.from_numpy(b.tissue_gaussians))
    filled = build_particles(gaussian_surfaces(rest_tissue, deformable, min_opacity=0.0), spec, b.camera, gt)
    M = max(o.id for o in b.objects) + 1
    E, nu, rho, model = [1.0] * M, [0.0] * M, [1.0] * M, ["fixed_corotated"] * M
    for o in b.objects:
        E[o.id], nu[o.id], rho[o.id] = o.E, o.nu, o.density
        if not o.rigid:
            model[o.id] = o.model
    materials = ObjectMaterials.of(E, nu, rho, model)
    colliders = tool_colliders(b.tools, filled.particles, ~filled.pinned, b.box_size / gt.grid)
    scenario = Scenario(SimBox(tuple(float(v) for v in b.box_lo), float(b.box_size)),
                        gravity=tuple(float(v) for v in b.gravity), anchors=filled.anchors(),
                        forces=scenario_forces(spec, filled.particles), colliders=colliders,
                        settle_frames=b.settle_frames, settle="keep", settle_damping=b.settle_damping)
    config = MPMConfig(grid_res=gt.grid, frame_dt=b.frame_dt, substeps_per_frame=gt.substeps, dt=None,
                       damping=b.damping, wall="sticky", wall_padding=max(2, _wall_cells(b)))
    return filled, materials, scenario, config


def simulate_built(b: BuiltScene) -> tuple[torch.Tensor, torch.Tensor, SceneParticles]:
    """Run the ground-truth simulation and drive the tissue Gaussians with it.

    Returns tissue means [T, Gt, 3] (metres) and covariances [T, Gt, 3, 3] (metres^2) = F Sigma_0 F^T per
    frame (frame 0: the equilibrium after settling), and the ground truth's particles.
    """
    filled, materials, scenario, config = ground_truth_problem(b)
    check_size(particles=len(filled.particles))
    res = simulate(filled.particles, materials, scenario, config, b.frames)
    if res.substeps != b.ground_truth.substeps:  # plan_substeps saw the same inputs when the scene was built
        raise SimulationError(f"scene {b.name}: the simulator took {res.substeps} substeps per frame, "
                              f"scene.json records {b.ground_truth.substeps}")
    cells = scenario.settling_cells(res.settling_left, config.grid_res)
    if cells > SETTLING_TOLERANCE:  # the rest of the settling would move in the video as if a tool did it
        raise GroundTruthRefused(
            f"scene {b.name}: the ground truth's settling ({b.settle_frames} frames at "
            f"{scenario.damping_of_frame(0, config.damping):g}/s) still "
            f"moves a particle by {1e3 * res.settling_left:.4f} mm in its last frame ({100 * cells:.2f}% of a "
            f"grid cell, tolerance {100 * SETTLING_TOLERANCE:g}%): frame 0 would not be the equilibrium a "
            f"video starts at; raise settle_frames")
    _check_bites(b, filled, scenario, res.positions, b.box_size / config.grid_res)
    tissue = b.gaussians.subset(torch.from_numpy(b.tissue_gaussians))
    binding = bind_gaussians(tissue.means, tissue.object_ids, filled.particles)
    means, covs = [], []
    for t in range(b.frames):
        m, c, _ = drive_gaussians(tissue, binding, res.positions[t], res.F[t], rotate_colors=False)
        means.append(m)
        covs.append(c)
    return torch.stack(means), torch.stack(covs), filled


def _check_bites(b: BuiltScene, filled: SceneParticles, scenario: Scenario, positions: torch.Tensor,
                 dx: float) -> None:
    """Refuse a ground truth whose grasper tears its bite out of the tissue: the torn plug's motion would be
    numerical fracture, how much of it set by the grid, not the material (``positions`` [T, P, 3] metres)."""
    spacing = _scene_spec(b, seed=0).scenario.spacing(b.ground_truth)
    for bite in bite_records(filled.particles.x, positions, scenario.colliders, spacing, dx):
        if bite["torn"]:
            raise GroundTruthRefused(
                f"scene {b.name}: a grasper's bite tears out of the tissue: from frame {bite['torn_from']} on, the "
                f"tissue around it lies more than the {bite['tolerance_cells']:g} grid cells a B-spline stencil "
                f"reaches from the bite (median; {bite['ring_cells_max']:.2f} cells at frame {bite['frame_of_max']}): "
                f"numerical fracture, by an amount the grid sets; give the grasper a gentler path")


def _check_parted(b: BuiltScene, ids: np.ndarray) -> None:
    """Refuse a ground truth whose tissue parts (``ids`` [T, H, W], its rendered object ids). Beside a grasper's bite
    drawn sideways a sheet parts by numerical fracture, by an amount the grid sets, which identification's
    continuum cannot follow. The bite check (:func:`_check_bites`) reads the median distance around the bite and
    misses a sheet that parts on one side of it."""
    share = parted_share(ids)
    if share.max() > PARTED_LIMIT:
        first = int(np.argmax(share > PARTED_LIMIT))
        raise GroundTruthRefused(
            f"scene {b.name}: the ground truth's tissue parts: from frame {first} on, the background shows through "
            f"more than {100 * PARTED_LIMIT:g}% of its frame-0 footprint ({100 * share.max():.2f}% at frame "
            f"{int(np.argmax(share))}): numerical fracture beside an instrument, by an amount the grid sets; give the "
            "instrument a gentler path, or the clip more frames (the path spans the clip)")


def _frame_state(b: BuiltScene, tx: torch.Tensor, tcov: torch.Tensor, cov0: torch.Tensor, t: int):
    """World means [N, 3] and covariances [N, 3, 3] of all Gaussians at frame t (float32)."""
    means = b.gaussians.means.detach().clone().float()
    cov = cov0.clone()
    tm = torch.from_numpy(b.tissue_gaussians)
    means[tm] = tx[t].float()
    cov[tm] = tcov[t].float()
    for tool in b.tools:
        sel = torch.from_numpy(b.tool_gaussians[tool.object_id])
        tf = torch.as_tensor(tool.matrices()[t], dtype=torch.float32)
        R = tf[:3, :3]
        means[sel] = means[sel] @ R.T + tf[:3, 3]
        cov[sel] = R @ cov[sel] @ R.T
    return means, cov


def render_built(b: BuiltScene, tx: torch.Tensor, tcov: torch.Tensor, progress: Callable[[int], None] | None = None) -> dict:
    """Render every frame of the simulated tissue (``tx``, ``tcov`` from :func:`simulate_built`):
    rgb [T,H,W,3], depth [T,H,W] m, alpha [T,H,W], ids [T,H,W] int (0 = background),
    flow [T-1,H,W,2] px (t -> t+1), valid [T-1,H,W] bool."""
    g = b.gaussians.detach()
    cov0 = g.covariances().float()
    opac = g.opacities.float()
    colors = g.colors_dc.clamp(0, 1).float()
    id_list = sorted({o.id for o in b.objects})
    onehot = (g.object_ids[:, None] == torch.tensor(id_list)[None]).float()
    out: dict[str, list] = {k: [] for k in ("rgb", "depth", "alpha", "ids", "flow", "valid")}
    states = [_frame_state(b, tx, tcov, cov0, t) for t in range(b.frames)]
    for t in range(b.frames):
        means, cov = states[t]
        with torch.no_grad():
            if t + 1 < b.frames:
                r = render_with_flow(means, opac, colors, b.camera, states[t + 1][0], covars=cov,
                                     covars_next=states[t + 1][1], features=onehot, backend="auto")
                out["flow"].append(r.flow.cpu().numpy().astype(np.float32))
                out["valid"].append(r.alpha.cpu().numpy() > VALID_ALPHA)
            else:
                r = rasterize(means, opac, colors, b.camera, covars=cov, features=onehot, backend="auto")
        alpha = r.alpha.cpu().numpy()
        best = r.features.cpu().numpy().argmax(-1)
        ids = np.where(alpha > 0.5, np.asarray(id_list)[best], 0)
        out["rgb"].append(r.rgb.clamp(0, 1).cpu().numpy())
        out["depth"].append(np.where(alpha > 0.5, r.depth.cpu().numpy(), 0.0))
        out["alpha"].append(alpha)
        out["ids"].append(ids)
        if progress is not None:
            progress(t)
    return {k: np.stack(v) if v else np.zeros((0,)) for k, v in out.items()}


def _scene_spec(b: BuiltScene, seed: int) -> SceneSpec:
    scenario = ScenarioSpec(
        box_lo=[float(v) for v in b.box_lo], box_size=float(b.box_size), gravity=[float(v) for v in b.gravity],
        frame_dt=float(b.frame_dt), damping=float(b.damping), boundary_conditions=b.boundary_conditions,
        tools=list(b.tools), extrusion=b.extrusion, ground_truth=b.ground_truth, identification=b.identification,
        settle_frames=int(b.settle_frames), settle_damping=b.settle_damping, forces=list(b.forces),
        mass_scaling=float(b.mass_scaling),
    )
    cam = CameraSpec(K=b.camera.K.double().tolist(), width=b.camera.width, height=b.camera.height,
                      viewmat=b.camera.viewmat.double().tolist())
    return SceneSpec(
        name=b.name, seed=seed, frames=b.frames, objects=b.objects, scenario=scenario, camera=cam,
        depth_scale=DEPTH_SCALE, source=b.source, generator=GENERATOR_REVISION,
        files={"images": IMAGES_PATTERN, "depth": "depth/frame-%06d.depth.png",
               "masks": "masks/frame-%06d.mask.png", "object_masks": "object_masks/frame-%06d.png",
               "flow": "flow/frame-%06d.flow.npy", "flow_valid": "flow/frame-%06d.valid.png",
               "gaussians_t0": "gaussians_t0.ply", "particles_ground_truth": "particles_ground_truth.npz"},
    )


def write_scene_folder(b: BuiltScene, r: dict, out_dir: Path, seed: int, frame0: Gaussians,
                       particles: SceneParticles) -> Path:
    """Write the rendered scene ``r`` (from :func:`render_built`) into ``out_dir`` atomically (a temporary
    sibling folder renamed into place; a previous scene folder there is replaced). ``frame0``: every Gaussian
    at frame 0 (the observed, settled state); ``particles``: the ground truth's (for inspection only)."""
    import cv2

    out_dir = Path(out_dir)
    if out_dir.exists() and not (out_dir / "scene.json").exists() and any(out_dir.iterdir()):
        raise DataError(f"{out_dir} exists and is not a synthesized scene folder; choose another --out")
    with atomic_folder(out_dir) as tmp:
        for sub in ("images", "depth", "masks", "object_masks", "flow"):
            (tmp / sub).mkdir()
        rigid = {o.id for o in b.objects if o.rigid}
        T = b.frames
        for t in range(T):
            rgb8 = (r["rgb"][t] * 255 + 0.5).astype(np.uint8)
            cv2.imwrite(str(tmp / "images" / f"frame-{t:06d}.color.png"), cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR))
            d16 = np.clip(np.round(r["depth"][t] * DEPTH_SCALE), 0, 65535).astype(np.uint16)
            cv2.imwrite(str(tmp / "depth" / f"frame-{t:06d}.depth.png"), d16)
            ids = r["ids"][t]
            cv2.imwrite(str(tmp / "masks" / f"frame-{t:06d}.mask.png"), np.where(np.isin(ids, list(rigid)), 255, 0).astype(np.uint8))
            cv2.imwrite(str(tmp / "object_masks" / f"frame-{t:06d}.png"), ids.astype(np.uint16))
            if t + 1 < T:
                np.save(tmp / "flow" / f"frame-{t:06d}.flow.npy", r["flow"][t].astype(np.float32))
                cv2.imwrite(str(tmp / "flow" / f"frame-{t:06d}.valid.png"), (r["valid"][t] * 255).astype(np.uint8))
        H, W = b.camera.height, b.camera.width
        focal = float(b.camera.K[0, 0])
        valid_d = r["depth"][r["depth"] > 0]
        near = float(valid_d.min() * 0.9) if valid_d.size else 0.01
        far = float(valid_d.max() * 1.1) if valid_d.size else 1.0
        pose = np.concatenate([np.eye(3, 4), np.array([[H], [W], [focal]])], 1).reshape(-1)
        np.save(tmp / "poses_bounds.npy", np.tile(np.concatenate([pose, [near, far]])[None], (T, 1)))
        write_ply(frame0, tmp / "gaussians_t0.ply")
        p = particles.particles
        np.savez(tmp / "particles_ground_truth.npz", x=p.x.double().numpy(), object_id=p.object_ids.numpy(),
                 vol=p.volume.double().numpy(), pinned=particles.pinned)
        d = _scene_spec(b, seed).to_json()
        d.update({k: v for k, v in b.extra.items() if k not in d})
        write_json_atomic(tmp / "scene.json", d)
    return out_dir


@deterministic()
def synthesize(scene_name: str, out_dir: str | os.PathLike, seed: int = 0, frames: int | None = None,
               scale: float | None = None, from_dir: str | os.PathLike | None = None,
               progress: Callable[[str, int, int], None] | None = None, **from_kwargs) -> Path:
    """Build, simulate, render and write one benchmark scene; returns the folder.

    Args:
        scene_name: a suite scene (``tiny``, ``press``, ...), or a free name when ``from_dir`` is given.
        out_dir: destination folder (replaced if it is a previous synth output).
        seed: textures, perturbations and noise all derive from it (same seed -> same files).
        frames: number of rendered frames (default: the suite's).
        scale: image-size factor (procedural, default 1) or downscale of the real frames (``from_dir``;
            default: 256 pixels wide).
        from_dir: build frame-0 Gaussians from a real scene folder (:mod:`endogsim.synth.from_data`).
        progress: optional callback (stage, done, total).
    """
    check_size(frames=frames)  # before anything is built: tool trajectories have one entry per frame
    torch.manual_seed(seed)
    if from_dir is not None:
        from endogsim.synth.from_data import build_from_data

        b = build_from_data(from_dir, name=scene_name, seed=seed, frames=frames, scale=scale, **from_kwargs)
    else:
        b = build_procedural(scene_name, seed=seed, frames=frames, scale=1.0 if scale is None else scale)
    check_size(b.frames, b.camera.width, b.camera.height)
    if progress is not None:
        progress("simulate", 0, 1)
    tx, tcov, particles = simulate_built(b)
    if progress is not None:
        progress("simulate", 1, 1)
    cb_r = (lambda t: progress("render", t + 1, b.frames)) if progress else None
    r = render_built(b, tx, tcov, progress=cb_r)
    _check_parted(b, r["ids"])
    means0, cov0 = _frame_state(b, tx, tcov, b.gaussians.covariances().float(), 0)
    log_scales, quats = covariance_to_scale_rot(cov0)
    frame0 = b.gaussians.with_(means=means0, log_scales=log_scales, quats=quats)
    return write_scene_folder(b, r, Path(out_dir), seed, frame0, particles)
