"""Build a benchmark scene in memory: Gaussians, MPM particles, boundary conditions, tools, ground truth.

:func:`build_procedural` turns a suite entry (``endogsim/data/benchmark_suite.json``) into a
:class:`BuiltScene`; :mod:`endogsim.synth.from_data` does the same from real frames. Simulation and file
writing live in :mod:`endogsim.synth.generate`.

Boundary conditions (recorded in ``scene.json``; particles and their conditions are built from that
description by :mod:`endogsim.scene.particles`, for the ground truth and for identification alike):
  * ``back_face``: the last layer of the slab (the hidden back of the tissue) is held ("fixed") or rests on
    a support that pushes but never pulls ("support": the suite's), with Coulomb friction (``support_friction``:
    the suite's default ``support_friction`` fills it in, as real video's scenario does), sticking while pressed
    (no coefficient) or frictionless ("slip_support"), except inside an optional ``release`` disc (so a grasper
    can lift a flap);
  * ``border``: particles within ``border`` metres of an organ's outline are held (tissue continues
    outside the field of view), except where the outline meets another organ (it goes on into that one);
  * the sim box walls (2 grid cells) are fixed.

The seed gives every organ its texture and surface relief. The instrument's path is designed on seed 0's
surface and moves with the relief beneath its tip, so the instrument presses or bites as deep for every seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from endogsim.errors import DataError
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians
from endogsim.scene.discretisation import at_materials, plan_discretisation, refine
from endogsim.scene.motion import tool_capsule, tool_offsets, tool_speed
from endogsim.scene.schema import SceneObject, SimSettings, ToolCapsule
from endogsim.synth import procedural as proc
from endogsim.synth.suite import scene_spec

__all__ = ["BuiltScene", "build_procedural", "scene_discretisations"]


@dataclass
class BuiltScene:
    """A scene ready to simulate and render.

    Attributes:
        name: scene name. camera: the fixed endoscope. frames: number of rendered frames. frame_dt: s.
        gaussians: all Gaussians in the rest (stress-free) configuration (tissue first, then tools), object
            ids set; the tissue Gaussians' centres sample the true surfaces the ground truth's particles fill.
        tissue_gaussians: [G] bool, True for Gaussians advected by the simulation.
        tool_gaussians: {tool object id: [G] bool} Gaussians moving rigidly with each tool.
        objects: ground-truth records. tools: capsule tools with per-frame transforms.
        box_lo [3], box_size (metres): the sim box. gravity [3] m/s^2. damping 1/s.
        settle_frames: frames of settling under gravity before frame 0 (the video starts at equilibrium).
        mass_scaling: identification's quasi-static mass scaling (:class:`endogsim.physics.Scenario`; the ground
            truth is never mass-scaled): the real regime's scenes are identified as the pipeline identifies real
            video (:class:`endogsim.pipeline.scene_from_recon.RealScenario`), the others with 1.
        forces: scene-level force descriptions (e.g. the paper protocol's impulse), as in scene.json.
        ground_truth / identification: discretisations (the ground truth is finer: 2x the grid, half the
            particle spacing, 2x the substeps, so the benchmark does not reward matching one discretisation).
        boundary_conditions, extrusion: descriptions for scene.json. source: "procedural" or data folder.
    """

    name: str
    camera: Camera
    frames: int
    frame_dt: float
    gaussians: Gaussians
    tissue_gaussians: np.ndarray
    tool_gaussians: dict[int, np.ndarray]
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
    settle_frames: int = 0
    settle_damping: float | None = None
    mass_scaling: float = 1.0
    forces: list[dict[str, Any]] = field(default_factory=list)
    source: str = "procedural"
    extra: dict[str, Any] = field(default_factory=dict)

    def identification_at_truth(self) -> SimSettings:
        """Identification's discretisation with the substeps the CFL rule takes for the true materials
        (:func:`~endogsim.scene.discretisation.at_materials`): what its grid and particles run the ground-truth
        problem at (``bench convergence``'s 1x; refined 2x, it is the ground truth's discretisation)."""
        return at_materials(self.identification, self.objects, self.box_size, self.frame_dt,
                            tool_speed(self.tools, self.frame_dt))


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


def _texture_seed(seed: int, obj: dict[str, Any], index: int) -> int:
    """The seed of the texture and relief of the ``index``-th organ ``obj`` of a scene built with ``seed``."""
    return seed * 1000 + 17 * obj["id"] + index


def _depth_beneath(spec: dict[str, Any], seed: int, xy: np.ndarray, radius: float) -> float | None:
    """Depth (metres from the lens) of the front-most organ surface beneath the disc of ``radius`` (metres)
    around the point ``xy`` [2] (metres), the median over samples of the disc, for the scene built with
    ``seed``; None when no organ lies beneath it."""
    g = np.linspace(-radius, radius, 7)
    du, dv = np.meshgrid(g, g)
    disc = du ** 2 + dv ** 2 <= radius ** 2
    points = np.asarray(xy, float)[None] + np.stack([du[disc], dv[disc]], 1)
    depths = []
    for k, o in enumerate(spec["objects"]):
        mask, _, height = _outline(o)
        uv = points - np.asarray(o["center"], float)[None]
        inside = mask(uv[:, 0], uv[:, 1])
        if inside.any():
            depths.append(float(np.median(proc.surface_depth(uv[inside], spec["distance"],
                                                             _texture_seed(seed, o, k), height))))
    return min(depths) if depths else None


def scene_discretisations(spec: dict[str, Any], objects: list[SceneObject], box_size: float,
                          tools: list[ToolCapsule], thickness: float) -> tuple[SimSettings, SimSettings]:
    """(ground truth, identification) discretisations of a scene from the suite's numerics keys:
    identification from the thinnest tissue (``cells_across_thickness``, :func:`plan_discretisation`), the
    ground truth ``ground_truth_refine`` times finer (:func:`refine`) than identification at the true materials.

    Identification's settings are planned without the materials, as a real video's are: their substeps are
    only the floor (``min_substeps``), and the simulator takes what the CFL rule asks for the materials it
    simulates at run time. Planned at the true materials, the floor would hand identification the truth's
    substep count wherever it tries a softer or more compressible material."""
    frame_dt = float(spec["frame_dt"])
    speed = tool_speed(tools, frame_dt)
    ident = plan_discretisation((), box_size, thickness, frame_dt, speed,
                                cells_across=int(spec["cells_across_thickness"]),
                                min_substeps=int(spec.get("min_substeps", 1)))
    gt = refine(at_materials(ident, objects, box_size, frame_dt, speed), objects, box_size, frame_dt, speed,
                factor=int(spec["ground_truth_refine"]))
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
    g_sp = spec["gaussian_spacing"]
    D = spec["distance"]

    objects, parts_g = [], []
    bcs: list[dict[str, Any]] = [{"type": "box_walls", "cells": 2}]
    for k, o in enumerate(spec["objects"]):
        objects.append(SceneObject(id=o["id"], name=o["name"], klass=o["class"], rigid=o["rigid"],
                                   E=float(o["E"]), nu=float(o["nu"]), density=float(o["density"]),
                                   model=o.get("model", spec["model"])))
        mask, edge, height = _outline(o)
        center = (o["center"][0], o["center"][1], D)
        pts, col, uv = proc.tissue_surface(center, tuple(o["size"]), g_sp, _texture_seed(seed, o, k), height_fn=height,
                                           palette=o.get("palette", "mucosa"), mask_fn=mask)
        parts_g.append(proc.surface_gaussians(pts, col, g_sp, o["id"]))
        anchors = dict(o.get("anchors", {}))
        if anchors.get("back_face") == "support" and spec.get("support_friction") is not None:
            anchors.setdefault("support_friction", float(spec["support_friction"]))
        bcs.append({"type": "anchors", "object": o["name"], **anchors})

    t = spec["tool"]
    objects.append(SceneObject(id=t["id"], name=t["name"], klass=t["class"], rigid=True,
                               E=float(t["E"]), nu=float(t["nu"]), density=float(t["density"])))
    tip, end = np.array(t["tip"], float), np.array(t["end"], float)
    # The path is designed on seed 0's surface; another seed's relief moves the tissue beneath the tip by up to
    # a few millimetres, which would turn a press into a touch or start the tool inside the tissue. The tool
    # moves with it along the view, so every seed is the same experiment on another texture and relief.
    here, design = (_depth_beneath(spec, s, tip[:2], t["radius"]) for s in (seed, 0))
    if here is not None and design is not None:
        tip[2] += here - design
        end[2] += here - design
    tool_g = proc.tool_gaussians(tip, end, t["radius"], 0.8 * g_sp, t["id"], seed=seed, jaw=t.get("jaw", False))
    # A grasper ("jaw") holds the tissue its jaws close on; a probe only pushes.
    tool = tool_capsule(t["id"], tip, end, t["radius"], tool_offsets(t["keyframes"], T),
                        contact="grasp" if t.get("jaw", False) else "sticky")

    tissue = Gaussians.concat(parts_g)
    allg = Gaussians.concat([tissue, tool_g])
    allg = proc.bake_lighting(allg, cam, D)
    n_t = len(tissue)
    tissue_mask = np.zeros(len(allg), bool)
    tissue_mask[:n_t] = True
    box = spec["sim_box"]
    box_lo = np.asarray(box["center"], float) - box["size"] / 2
    gt, ident = scene_discretisations(spec, objects, box["size"], [tool], min(o["thickness"] for o in spec["objects"]))
    return BuiltScene(
        name=name, camera=cam, frames=T, frame_dt=spec["frame_dt"], gaussians=allg, tissue_gaussians=tissue_mask,
        tool_gaussians={t["id"]: ~tissue_mask}, objects=objects, tools=[tool], box_lo=box_lo, box_size=box["size"],
        gravity=np.asarray(spec["gravity"], float), damping=spec["damping"], ground_truth=gt, identification=ident,
        boundary_conditions=bcs, extrusion={"along": "viewing_rays", "thickness": {o["name"]: o["thickness"] for o in spec["objects"]}},
        settle_frames=int(spec["settle_frames"]), settle_damping=spec.get("settle_damping"),
        mass_scaling=float(spec["mass_scaling"]), forces=list(spec.get("forces", [])),
        extra={"description": spec["description"], "depth_ref": D, "regime": spec.get("regime", "")},
    )
