"""Simulate a built scene and write its benchmark folder (EndoNeRF layout plus ground truth).

Folder written by :func:`synthesize` (T frames, H x W pixels, names as in EndoNeRF):
  images/frame-%06d.color.png       RGB, 8-bit
  depth/frame-%06d.depth.png        16-bit, depth_metres = value / scene.json["depth_scale"]; 0 = no surface
  masks/frame-%06d.mask.png         8-bit, 255 = tool (any rigid object), 0 = tissue / background
  object_masks/frame-%06d.png       16-bit object id per pixel (scene.json objects), 0 = background
  flow/frame-%06d.flow.npy          float32 [H, W, 2] ground-truth optical flow t -> t+1 (pixels), t < T-1
  flow/frame-%06d.valid.png         8-bit, 255 where the flow is defined (rendered alpha > 0.95)
  poses_bounds.npy                  (T, 17) LLFF: identity pose, [H, W, focal], near, far (metres)
  gaussians_t0.ply                  ground-truth Gaussians of frame 0 with object ids
  particles_t0.npz                  MPM particles: x [P, 3] m, object_id [P], vol [P] m^3, anchored [P]
  scene.json                        objects, scenario, camera, seed (see endogsim.synth.spec)

The ground-truth flow is the Gaussian flow (:mod:`endogsim.gaussians.flow`) of the simulated Gaussians,
i.e. exactly the quantity identification compares against.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from endogsim.errors import DataError
from endogsim.gaussians.flow import render_with_flow
from endogsim.gaussians.ply import write_ply
from endogsim.gaussians.render import rasterize
from endogsim.synth.mpm import MPMProblem, run_mpm, skin_gaussians
from endogsim.synth.scenes import BuiltScene, build_procedural
from endogsim.synth.spec import CameraTruth, ScenarioTruth, SceneTruth, ToolTruth

__all__ = ["synthesize", "simulate_built", "render_built", "write_scene_folder", "DEPTH_SCALE"]

DEPTH_SCALE = 10000.0  # 16-bit depth png units per metre (0.1 mm steps, up to 6.5 m)
VALID_ALPHA = 0.95


def simulate_built(b: BuiltScene, progress: Callable[[int], None] | None = None):
    """Run the ground-truth MPM. Returns (tissue means [T, Gt, 3], tissue F [T, Gt, 3, 3]) as float64."""
    mu = {o.id: o.E / (2 * (1 + o.nu)) for o in b.objects}
    lam = {o.id: o.E * o.nu / ((1 + o.nu) * (1 - 2 * o.nu)) for o in b.objects}
    rho = {o.id: o.density for o in b.objects}
    ids = b.particle_ids
    problem = MPMProblem(
        x=b.particles, vol=b.particle_vol,
        mu=np.array([mu[i] for i in ids]), lam=np.array([lam[i] for i in ids]), density=np.array([rho[i] for i in ids]),
        anchored=b.anchored, box_lo=b.box_lo, box_size=b.box_size, grid=b.ground_truth.grid, dt=b.ground_truth.dt,
        substeps=b.ground_truth.substeps, frames=b.frames, gravity=b.gravity, tools=[c for _, c in b.tools],
        damping=b.damping,
    )
    res = run_mpm(problem, progress=progress)
    sel = torch.from_numpy(b.tissue_gaussians)
    return skin_gaussians(b.gaussians.means[sel].double().numpy(), b.gaussians.object_ids[sel].numpy(),
                          b.particles, b.particle_ids, res.x, res.F)


def _frame_state(b: BuiltScene, tx: np.ndarray, tF: np.ndarray, cov0: torch.Tensor, t: int):
    """World means [N, 3] and covariances [N, 3, 3] of all Gaussians at frame t (float32)."""
    means = b.gaussians.means.detach().clone().double()
    cov = cov0.clone()
    tm = torch.from_numpy(b.tissue_gaussians)
    means[tm] = torch.from_numpy(tx[t])
    F = torch.from_numpy(tF[t])
    cov[tm] = F @ cov0[tm] @ F.mT
    for tool_id, cap in b.tools:
        sel = torch.from_numpy(b.tool_gaussians[tool_id])
        means[sel] += torch.from_numpy(cap.offsets[t])
    return means.float(), cov.float()


def render_built(b: BuiltScene, tx: np.ndarray, tF: np.ndarray, progress: Callable[[int], None] | None = None) -> dict:
    """Render every frame: rgb [T,H,W,3], depth [T,H,W] m, alpha [T,H,W], ids [T,H,W] int (0 = background),
    flow [T-1,H,W,2] px (t -> t+1), valid [T-1,H,W] bool."""
    g = b.gaussians.detach()
    cov0 = g.covariances().double()
    opac = g.opacities.float()
    colors = g.colors_dc.clamp(0, 1).float()
    id_list = sorted({o.id for o in b.objects})
    onehot = (g.object_ids[:, None] == torch.tensor(id_list)[None]).float()
    out: dict[str, list] = {k: [] for k in ("rgb", "depth", "alpha", "ids", "flow", "valid")}
    states = [_frame_state(b, tx, tF, cov0, t) for t in range(b.frames)]
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


def _scene_truth(b: BuiltScene, seed: int, depth: np.ndarray) -> SceneTruth:
    tools = []
    for tool_id, cap in b.tools:
        mats = []
        for off in cap.offsets:
            m = np.eye(4)
            m[:3, 3] = off
            mats.append(m.tolist())
        tools.append(ToolTruth(object_id=tool_id, tip=list(map(float, cap.a)), end=list(map(float, cap.b)),
                               radius=float(cap.radius), transforms=mats))
    scenario = ScenarioTruth(
        box_lo=[float(v) for v in b.box_lo], box_size=float(b.box_size), gravity=[float(v) for v in b.gravity],
        frame_dt=float(b.frame_dt), damping=float(b.damping), boundary_conditions=b.boundary_conditions,
        tools=tools, particle_spacing=float(b.particle_spacing), extrusion=b.extrusion,
        ground_truth=b.ground_truth, identification=b.identification,
    )
    cam = CameraTruth(K=b.camera.K.double().tolist(), width=b.camera.width, height=b.camera.height,
                      viewmat=b.camera.viewmat.double().tolist())
    return SceneTruth(
        name=b.name, seed=seed, frames=b.frames, objects=b.objects, scenario=scenario, camera=cam,
        depth_scale=DEPTH_SCALE, source=b.source,
        files={"images": "images/frame-%06d.color.png", "depth": "depth/frame-%06d.depth.png",
               "masks": "masks/frame-%06d.mask.png", "object_masks": "object_masks/frame-%06d.png",
               "flow": "flow/frame-%06d.flow.npy", "flow_valid": "flow/frame-%06d.valid.png",
               "gaussians_t0": "gaussians_t0.ply", "particles_t0": "particles_t0.npz"},
    )


def write_scene_folder(b: BuiltScene, r: dict, out_dir: Path, seed: int) -> Path:
    """Write the rendered scene ``r`` (from :func:`render_built`) into ``out_dir`` atomically (a temporary
    sibling folder renamed into place)."""
    import cv2

    from endogsim.cli.common import write_json_atomic

    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out_dir.parent, prefix=f".{out_dir.name}.tmp"))
    try:
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
        write_ply(b.gaussians, tmp / "gaussians_t0.ply")
        np.savez(tmp / "particles_t0.npz", x=b.particles.astype(np.float64), object_id=b.particle_ids,
                 vol=b.particle_vol, anchored=b.anchored)
        truth = _scene_truth(b, seed, r["depth"])
        d = truth.to_json()
        d.update({k: v for k, v in b.extra.items() if k not in d})
        write_json_atomic(tmp / "scene.json", d)
        if out_dir.exists():
            if not (out_dir / "scene.json").exists() and any(out_dir.iterdir()):
                raise DataError(f"{out_dir} exists and is not a synthesized scene folder; choose another --out")
            shutil.rmtree(out_dir)
        os.replace(tmp, out_dir)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


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
    torch.manual_seed(seed)
    if from_dir is not None:
        from endogsim.synth.from_data import build_from_data

        b = build_from_data(from_dir, name=scene_name, seed=seed, frames=frames, scale=scale, **from_kwargs)
    else:
        b = build_procedural(scene_name, seed=seed, frames=frames, scale=1.0 if scale is None else scale)
    cb_sim = (lambda t: progress("simulate", t, b.frames - 1)) if progress else None
    tx, tF = simulate_built(b, progress=cb_sim)
    cb_r = (lambda t: progress("render", t + 1, b.frames)) if progress else None
    r = render_built(b, tx, tF, progress=cb_r)
    return write_scene_folder(b, r, Path(out_dir), seed)
