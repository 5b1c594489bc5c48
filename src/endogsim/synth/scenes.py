"""Build a benchmark scene in memory: Gaussians, MPM particles, boundary conditions, tools, ground truth.

:func:`build_procedural` turns a suite entry (``endogsim/data/benchmark_suite.json``) into a
:class:`BuiltScene`; :mod:`endogsim.synth.from_data` does the same from real frames. Simulation and file
writing live in :mod:`endogsim.synth.generate`.

Boundary conditions used by every scene (recorded in ``scene.json``):
  * ``back_face``: particles of the last extrusion layer (the hidden back of the tissue) are held in place,
    except inside an optional ``release`` disc (so a grasper can lift a flap);
  * ``border``: particles within ``border`` metres of an organ's outline are held (tissue continues
    outside the field of view);
  * the sim box walls (2 grid cells) are fixed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from endogsim.errors import DataError, SimulationError
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians
from endogsim.physics import MPMConfig, extrude_along_rays, p_wave_speed, plan_substeps
from endogsim.scene.motion import tool_capsule, tool_offsets, tool_speed
from endogsim.scene.schema import SceneObject, SimSettings, ToolCapsule
from endogsim.synth import procedural as proc
from endogsim.synth.suite import scene_spec

__all__ = ["BuiltScene", "build_procedural", "sim_settings", "tissue_from_surface"]


@dataclass
class BuiltScene:
    """A scene ready to simulate and render.

    Attributes:
        name: scene name. camera: the fixed endoscope. frames: number of rendered frames. frame_dt: s.
        gaussians: all Gaussians of frame 0 (tissue first, then tools), object ids set.
        tissue_gaussians: [G] bool, True for Gaussians advected by the simulation.
        tool_gaussians: {tool object id: [G] bool} Gaussians moving rigidly with each tool.
        particles: [P, 3] MPM particle positions (metres); particle_ids [P]; particle_vol [P] (m^3);
        anchored: [P] bool. objects: ground-truth records. tools: capsule tools with per-frame transforms.
        box_lo [3], box_size (metres): the sim box. gravity [3] m/s^2. damping 1/s.
        ground_truth / identification: discretisations (the ground truth is finer: more substeps and a finer
        grid, so the benchmark does not reward matching one discretisation). boundary_conditions, extrusion: descriptions for
        scene.json. depth_ref: typical distance (metres) for lighting. source: "procedural" or data folder.
    """

    name: str
    camera: Camera
    frames: int
    frame_dt: float
    gaussians: Gaussians
    tissue_gaussians: np.ndarray
    tool_gaussians: dict[int, np.ndarray]
    particles: np.ndarray
    particle_ids: np.ndarray
    particle_vol: np.ndarray
    anchored: np.ndarray
    objects: list[SceneObject]
    tools: list[ToolCapsule]
    box_lo: np.ndarray
    box_size: float
    gravity: np.ndarray
    damping: float
    ground_truth: SimSettings
    identification: SimSettings
    boundary_conditions: list[dict[str, Any]]
    extrusion: dict[str, Any]
    particle_spacing: float
    source: str = "procedural"
    extra: dict[str, Any] = field(default_factory=dict)


def sim_settings(objects: list[SceneObject], box_size: float, grid: int, frame_dt: float, substeps: int,
                 max_speed: float = 0.0, cfl_number: float = 0.5) -> SimSettings:
    """The discretisation the Warp simulator takes for ``grid`` cells over ``box_size`` metres with at least
    ``substeps`` per frame: :func:`endogsim.physics.plan_substeps` (CFL number ``cfl_number``, tool speed
    ``max_speed`` m/s) over the deformable objects, and the CFL number c_p dt / dx it reaches."""
    soft = [o for o in objects if not o.rigid]
    if not soft:
        raise DataError("a benchmark scene needs at least one deformable object")
    E, nu, rho = (np.array([getattr(o, k) for o in soft], float) for k in ("E", "nu", "density"))
    cfg = MPMConfig(grid_res=int(grid), frame_dt=frame_dt, substeps_per_frame=int(substeps), cfl_number=cfl_number)
    n, dt = plan_substeps(cfg, box_size, E, nu, rho, max_speed)
    cfl = float(np.max(p_wave_speed(E, nu, rho))) * dt / (box_size / grid)
    return SimSettings(grid=int(grid), dt=float(dt), substeps=int(n), cfl=cfl)


def _outline(obj: dict[str, Any]):
    """(mask_fn, edge_distance_fn, height_fn) of an organ in its local (u, v) coordinates (metres)."""
    w, h = obj["size"]
    dome = float(obj.get("dome", 0.0))
    excl = obj.get("exclude_ellipse")
    c = np.array(obj["center"], dtype=float)
    if obj["outline"] == "rect":
        def edge(u, v):
            return np.minimum(w / 2 - np.abs(u), h / 2 - np.abs(v))

        def height(u, v):
            return dome * np.clip(1 - (2 * u / w) ** 2, 0, 1) * np.clip(1 - (2 * v / h) ** 2, 0, 1)
    elif obj["outline"] == "ellipse":
        def edge(u, v):
            return (1 - np.sqrt((2 * u / w) ** 2 + (2 * v / h) ** 2)) * min(w, h) / 2

        def height(u, v):
            return dome * np.sqrt(np.clip(1 - (2 * u / w) ** 2 - (2 * v / h) ** 2, 0, 1))
    else:
        raise DataError(f"object {obj.get('name')!r}: unknown outline {obj['outline']!r} (use 'rect' or 'ellipse')")

    def mask(u, v):
        keep = edge(u, v) >= -1e-9
        if excl is not None:
            ec = np.array(excl["center"]) - c
            keep &= ((u - ec[0]) / excl["radii"][0]) ** 2 + ((v - ec[1]) / excl["radii"][1]) ** 2 > 1.0
        return keep

    return mask, edge, height


def tissue_from_surface(points: np.ndarray, edge_dist: np.ndarray, thickness: float, spacing: float,
                        anchors: dict[str, Any], object_id: int, camera: Camera) -> dict[str, np.ndarray]:
    """Particles of one tissue object from its visible surface samples ``points`` [S, 3] (metres), extruded
    away from ``camera`` along the viewing rays (:func:`endogsim.physics.extrude_along_rays`).

    ``edge_dist`` [S]: distance of each sample to the organ outline (metres) for the border anchor.
    Returns x [P, 3], ids [P], vol [P] (m^3), anchored [P] bool.
    """
    pts = torch.as_tensor(points, dtype=torch.float64)
    xt, src_t = extrude_along_rays(pts, camera.center().double(), thickness, spacing)
    x, src = xt.numpy(), src_t.numpy()
    layer = np.arange(len(x)) // len(points)
    n_layers = int(layer.max()) + 1
    anchored = np.zeros(len(x), bool)
    if anchors.get("back_face", True):
        back = layer == n_layers - 1
        rel = anchors.get("release")
        if rel is not None:
            d = np.linalg.norm(x[:, :2] - np.asarray(rel["center"])[None], axis=1)
            back &= d > rel["radius"]
        anchored |= back
    band = float(anchors.get("border", 0.0))
    if band > 0:
        anchored |= edge_dist[src] < band
    layer_dz = thickness / (n_layers - 1) if n_layers > 1 else spacing
    vol = np.full(len(x), spacing * spacing * layer_dz)
    return {"x": x, "ids": np.full(len(x), object_id, np.int64), "vol": vol, "anchored": anchored}


def ground_truth_and_identification(spec: dict[str, Any], objects: list[SceneObject], box_size: float,
                                     tools: list[ToolCapsule], name: str) -> tuple[SimSettings, SimSettings]:
    """The two discretisations of a scene from the suite's numerics keys.

    Identification: ``ident_grid`` cells, ``frame_dt / ident_dt`` substeps (the suite: 50^3 as the paper, but
    50 x 1e-4 s, not its 25 x 2e-4 s: explicit MPM is first order in dt, and next to sticky boundaries the
    motion changes enough per halving of dt to move the loss minimum; see the suite's description).
    Ground truth: ``gt_grid`` and ``gt_refine`` times the substeps (default: identification's), raised where the CFL
    number would pass ``gt_cfl``.
    """
    frame_dt = float(spec["frame_dt"])
    speed = tool_speed(tools, frame_dt)
    ident_sub = max(1, round(frame_dt / spec["ident_dt"]))
    ident = sim_settings(objects, box_size, spec["ident_grid"], frame_dt, ident_sub, speed)
    gt = sim_settings(objects, box_size, spec["gt_grid"], frame_dt, ident_sub * int(spec["gt_refine"]), speed,
                      cfl_number=float(spec["gt_cfl"]))
    if gt.grid < ident.grid or gt.substeps < ident.substeps:
        raise DataError(f"scene {name}: the ground truth must be at least as fine as identification "
                        f"(grid {gt.grid} vs {ident.grid}, substeps {gt.substeps} vs {ident.substeps})")
    if gt.cfl > 0.5:
        raise SimulationError(f"scene {name}: ground-truth CFL {gt.cfl:.2f} > 0.5")
    return gt, ident


def build_procedural(name: str, seed: int = 0, frames: int | None = None, scale: float = 1.0) -> BuiltScene:
    """Build suite scene ``name`` (see ``benchmark_suite.json``) for ``seed``; ``frames`` overrides the
    frame count, ``scale`` multiplies the image size (the geometry and simulation are unchanged)."""
    spec = scene_spec(name)
    if scale <= 0 or not math.isfinite(scale):
        raise DataError(f"--scale must be a positive number, got {scale}")
    T = int(frames if frames is not None else spec["frames"])
    if T < 2:
        raise DataError(f"--frames must be at least 2, got {T}")
    W, H = (max(16, round(s * scale)) for s in spec["image_size"])
    cam = proc.endoscope_camera(W, H, spec["fov_x_deg"])
    g_sp, p_sp = spec["gaussian_spacing"], spec["particle_spacing"]
    D = spec["distance"]

    objects, parts_g, parts_p = [], [], []
    bcs: list[dict[str, Any]] = [{"type": "box_walls", "cells": 2}]
    for k, o in enumerate(spec["objects"]):
        objects.append(SceneObject(id=o["id"], name=o["name"], klass=o["class"], rigid=o["rigid"],
                                   E=float(o["E"]), nu=float(o["nu"]), density=float(o["density"])))
        mask, edge, height = _outline(o)
        center = (o["center"][0], o["center"][1], D)
        tex_seed = seed * 1000 + 17 * o["id"] + k
        pts, col, uv = proc.tissue_surface(center, tuple(o["size"]), g_sp, tex_seed, height_fn=height,
                                           palette=o.get("palette", "mucosa"), mask_fn=mask)
        parts_g.append(proc.surface_gaussians(pts, col, g_sp, o["id"]))
        # Particles sample the same surface on a coarser lattice (same height field, no texture needed).
        ppts, _, puv = proc.tissue_surface(center, tuple(o["size"]), p_sp, tex_seed, height_fn=height,
                                           palette=o.get("palette", "mucosa"), mask_fn=mask)
        parts_p.append(tissue_from_surface(ppts, edge(puv[:, 0], puv[:, 1]), o["thickness"], p_sp,
                                           o.get("anchors", {}), o["id"], cam))
        bcs.append({"type": "anchors", "object": o["name"], **o.get("anchors", {})})

    t = spec["tool"]
    objects.append(SceneObject(id=t["id"], name=t["name"], klass=t["class"], rigid=True,
                               E=float(t["E"]), nu=float(t["nu"]), density=float(t["density"])))
    tip, end = np.array(t["tip"], float), np.array(t["end"], float)
    tool_g = proc.tool_gaussians(tip, end, t["radius"], 0.8 * g_sp, t["id"], seed=seed, jaw=t.get("jaw", False))
    tool = tool_capsule(t["id"], tip, end, t["radius"], tool_offsets(t["keyframes"], T))

    tissue = Gaussians.concat(parts_g)
    allg = Gaussians.concat([tissue, tool_g])
    allg = proc.bake_lighting(allg, cam, D)
    n_t = len(tissue)
    tissue_mask = np.zeros(len(allg), bool)
    tissue_mask[:n_t] = True
    box = spec["sim_box"]
    box_lo = np.asarray(box["center"], float) - box["size"] / 2
    gt, ident = ground_truth_and_identification(spec, objects, box["size"], [tool], name)
    cat = {k: np.concatenate([p[k] for p in parts_p]) for k in parts_p[0]}
    return BuiltScene(
        name=name, camera=cam, frames=T, frame_dt=spec["frame_dt"], gaussians=allg, tissue_gaussians=tissue_mask,
        tool_gaussians={t["id"]: ~tissue_mask}, particles=cat["x"], particle_ids=cat["ids"], particle_vol=cat["vol"],
        anchored=cat["anchored"], objects=objects, tools=[tool], box_lo=box_lo, box_size=box["size"],
        gravity=np.asarray(spec["gravity"], float), damping=spec["damping"], ground_truth=gt, identification=ident,
        boundary_conditions=bcs, extrusion={"along": "viewing_rays", "thickness": {o["name"]: o["thickness"] for o in spec["objects"]}},
        particle_spacing=p_sp, extra={"description": spec["description"], "depth_ref": D},
    )
