"""From a 4D reconstruction to a simulation-ready scene folder (the "Scenario" stage of DESIGN.md section 2).

:func:`scene_from_reconstruction` writes a folder in the layout of ``endogsim synth`` (so ``endogsim identify``,
``endogsim simulate`` and ``endogsim validate`` read it unchanged):

  images/frame-%06d.color.png   the observed frames at the reconstruction's resolution
  object_masks/frame-%06d.png   object id per pixel (when the data has masks; one id per instrument)
  gaussians_t0.ply              the reconstructed Gaussians of frame 0, with object ids
  tracks.npz                    the reconstruction's trajectories of sampled tissue Gaussians
                                (:mod:`endogsim.scene.tracks`, identification's track term)
  field_of_view.png             the endoscope's image circle (255 inside), when the video has a border
  scene.json                    objects, camera (per-frame viewmats and exposure when the endoscope moves), the
                                scenario: sim box, boundary conditions, one capsule collider per instrument
                                moved by its reconstructed rigid motion, settling, discretisation

Two ways to get the scenario:
  * ``truth`` given (the benchmark protocol, DESIGN.md section 8): the ground-truth scene's boundary settings
    (sim box, anchors, thickness, gravity, tool capsule shape, discretisation) are reused; the Gaussians come
    from the reconstruction, the tool motion from the reconstruction or (the paper's "same boundary
    settings") from the ground truth.
  * no ``truth`` (real video): everything comes from the reconstruction and :class:`RealScenario`, whose
    docstring says where each choice comes from.

Colliders on real video (:func:`instrument_colliders`): each instrument is its own object (the
reconstruction splits tool masks into tracked instances), and its capsule is fitted to its grey metal core
(low-saturation Gaussians: a fallback tool mask leaks onto reddish tissue, and those Gaussians would widen
the capsule into the tissue), its tip is the end deeper inside the field of view (instruments enter the view
from its edge; depth got it backwards on every real instrument tried) and reaches to the jaws beyond the
grey core. A monocular reconstruction places instruments a few millimetres off in
depth, so a fitted capsule can start inside the tissue; it is then moved towards the camera along its
viewing ray until no tissue particle lies inside it, with a warning giving the count and the distance.
"""

from __future__ import annotations

import json
import math
import shutil
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from endogsim.errors import DataError, DataWarning
from endogsim.gaussians.model import Gaussians
from endogsim.io.atomic import atomic_folder, write_json_atomic

__all__ = ["RealScenario", "ToolFit", "scene_from_reconstruction", "fit_tool_capsule", "instrument_colliders",
           "push_out_of_tissue", "grey_core", "working_end", "extend_to_jaws"]


@dataclass(frozen=True)
class RealScenario:
    """The scenario of a real video: what a video cannot measure, chosen once for all clips.

    Attributes:
        thickness: tissue behind the visible surface (metres). A video sees only the front surface; 8 mm is
            the order of the abdominal organs' walls and of the layer a tool indents (tissue_mechanics.md),
            and the tissue behind rests on a support (``back_face``), so thicker tissue adds little.
        border: width (metres) of the band held along each tissue object's outline in view: the tissue goes on
            beyond the image.
        border_motion: how the band is held: "tracked" (the default) moves it along the reconstruction's
            tracks of the tissue there, "still" holds it at rest. What moves real tissue is mostly out of view
            (the grasper's pull carried through the membrane, breathing, the tissue beyond the image): on
            EndoNeRF pulling a band held still left the simulated tissue motionless in the held-out frames,
            0.371 px EPE like a frozen frame; tracked, the tissue inside the band follows and the held-out EPE
            falls by about a tenth where the band is not (docs/REAL_VIDEO.md section 9).
        back_face: "support": the anatomy behind pushes, never pulls, so a grasper can lift the tissue off.
        support_friction: the support's Coulomb coefficient (``scene.json`` ``support_friction``): pressed on
            it, the tissue slides once its tangential speed beats 1x the normal speed it loses. A support that
            sticks while pressed decided the calibration by switching nodes on and off at a float's last
            bit; with 1, EndoNeRF pulling's prediction beats the prior and zero motion on both measures and
            its calibration stops by its tolerance (docs/REAL_VIDEO.md section 13).
        box_margin: free space around the tissue in the sim box, as a fraction of its extent per side.
        cells_across: grid cells across ``thickness`` (:mod:`endogsim.scene.discretisation`).
        gravity: magnitude (m/s^2) and ``gravity_direction`` (frame 0's camera coordinates; +y is image
            down). The camera's orientation is unknown; the default is the laparoscope's usual upright view
            (CholecSeg8K's liver above the gallbladder, the fluid at the bottom). Frame 0 is the observed
            equilibrium: the settling under gravity is subtracted from every rollout, so gravity shapes the
            response (pre-stress) and not the observed rest shape.
        damping: grid velocity damping (1/s). On EndoNeRF pulling the tissue follows the grasper 5-6 frames
            (170-200 ms) late without overshoot: strongly over-damped; 100/s relaxes velocity in 10 ms, so the
            motion is quasi-static between frames, as observed.
        settle_frames, settle_damping: settling before frame 0 (frames, 1/s). Settling must reach the
            equilibrium, or the rest of it happens in the clip's first frames, where calibration fits it as
            motion (stiffer tissue settles less). A strong damping slows it: over-damped, the slowest mode
            relaxes in c / omega^2. Measured at the prior (`/work/notes/stop32/settle2.py`), motion left for
            the clip after settling: CholecSeg8K 0.081 mm RMS after 2 frames at 400/s, 0.024 after 4; at
            100/s 0.0048 after 2, 0.0004 after 4 (30/s, under-damped: 0.0014); EndoNeRF pulling 0.017 mm
            (2 at 400/s), 0.0014 (4 at 100/s).
        mass_scaling: quasi-static mass scaling k (:class:`endogsim.physics.Scenario`): substeps / sqrt(k).
            On EndoNeRF pulling (42 frames, prior materials) k = 4 changes the particle motion by 7% RMS
            (k = 16: 25%) and halves the substeps; the discretisation itself is further from converged.
        grey_saturation: an instrument's Gaussians with saturation (max - min) / max of their colour below
            this are its metal core (the collider is fitted to those).
        clearance: a collider pushed out of the tissue ends this far (in grid cells) from the nearest particle.
        grasping: which instruments hold the tissue their jaws close on (``ToolCapsule.contact`` "grasp"; the
            others only push): "graspers", those whose class names a grasper (CholecSeg8K class 31); "all",
            for data without instrument classes (the fallback segmentation) where every instrument grasps,
            as in EndoNeRF pulling; "none".
        instrument_radius: (lo, hi) metres: a fitted shaft radius is clipped to the standard instrument sizes,
            5 mm laparoscopic (2.5 mm) to 8.5 mm robotic (4.25 mm) shafts. Depth from a monocular
            reconstruction scales every size (EndoNeRF pulling's 8 mm da Vinci instruments measure 11-14 mm
            at the fallback depth; CholecSeg8K's 5 mm grasper measures 1.9 mm on its few grey Gaussians).
    """

    thickness: float = 0.008
    border: float = 0.004
    border_motion: Literal["tracked", "still"] = "tracked"
    back_face: str = "support"
    support_friction: float = 1.0
    box_margin: float = 0.1
    cells_across: int = 3
    gravity: float = 9.81
    gravity_direction: tuple[float, float, float] = (0.0, 1.0, 0.0)
    damping: float = 100.0
    settle_frames: int = 4
    settle_damping: float = 100.0
    mass_scaling: float = 4.0
    grey_saturation: float = 0.3
    clearance: float = 0.25
    grasping: Literal["graspers", "all", "none"] = "graspers"
    instrument_radius: tuple[float, float] = (0.0025, 0.00425)

    def __post_init__(self) -> None:
        if self.grasping not in ("graspers", "all", "none"):
            raise DataError(f"scenario.grasping {self.grasping!r} must be graspers|all|none")
        if self.border_motion not in ("tracked", "still"):
            raise DataError(f"scenario.border_motion {self.border_motion!r} must be tracked|still")
        for name, unit, least in (("support_friction", "", 0), ("gravity", " m/s^2", 0), ("damping", " 1/s", 0),
                                  ("mass_scaling", "", 1)):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= least):
                raise DataError(f"scenario.{name} {value}{unit} must be a finite number >= {least}")
        try:
            direction = np.asarray(self.gravity_direction, float)
            pointing = (direction.shape == (3,) and np.isfinite(direction).all()
                        and (self.gravity == 0 or direction.any()))
        except (TypeError, ValueError):
            pointing = False
        if not pointing:
            raise DataError(f"scenario.gravity_direction {self.gravity_direction} must be three finite numbers, "
                            "not all zero (frame 0's camera coordinates: +y is image down, +z along the view)")


@dataclass
class ToolFit:
    """One instrument's collider and how it was fitted.

    Attributes:
        object_id: the instrument's object id.
        tip, end: [3] capsule axis ends (metres, frame 0); radius: metres.
        gaussians: the instrument's Gaussians; core: those fitted (its grey core, or all when too few are grey).
        pushed: distance (metres) the capsule was moved towards the camera out of the tissue.
        inside: tissue particles inside the capsule as fitted (before the push).
        oriented: how its working end (``tip``) was found: "image" (:func:`working_end`) or "depth".
        jaws: how far (metres) the working end was extended beyond the grey core (:func:`extend_to_jaws`).
    """

    object_id: int
    tip: np.ndarray
    end: np.ndarray
    radius: float
    gaussians: int
    core: int
    pushed: float = 0.0
    inside: int = 0
    oriented: str = "depth"
    jaws: float = 0.0

    def to_json(self) -> dict:
        return {"object_id": self.object_id, "tip": self.tip.tolist(), "end": self.end.tolist(), "radius": self.radius,
                "gaussians": self.gaussians, "core_gaussians": self.core, "pushed_m": self.pushed,
                "tissue_particles_inside_before_push": self.inside, "working_end_from": self.oriented,
                "jaws_extension_m": self.jaws}


def fit_tool_capsule(points: np.ndarray, camera_center: np.ndarray | None = None,
                     radius_bounds: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """A capsule (tip [3], end [3], radius m) around a tool's Gaussians seen from one side.

    The axis is the principal direction of the points; the radius is half the tool's width across the
    axis and the viewing ray (clipped to ``radius_bounds``, metres, when given); the axis sits that far
    behind the visible surface (the points lie on the near half of the shaft). ``tip`` is the end farther
    from the camera (the working end, in a laparoscope's geometry; on a monocular reconstruction that is
    unreliable, and :func:`working_end` orients the capsule from the image).
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 4:
        raise DataError(f"a tool needs at least 4 Gaussians to fit a collider, got {len(pts)}")
    cam = np.zeros(3) if camera_center is None else np.asarray(camera_center, float)
    c = pts.mean(0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    axis = vt[0]
    ray = (c - cam) / max(np.linalg.norm(c - cam), 1e-12)
    across = np.cross(axis, ray)
    if np.linalg.norm(across) < 1e-6:  # a tool pointing straight at the camera: any perpendicular
        across = vt[1]
    across /= np.linalg.norm(across)
    w = (pts - c) @ across
    radius = max(0.5 * float(np.percentile(w, 97) - np.percentile(w, 3)), 1e-4)
    if radius_bounds is not None:
        radius = float(np.clip(radius, *radius_bounds))
    c_axis = c + ray * (2.0 / math.pi) * radius  # centroid of a half cylinder's surface is 2r/pi off the axis
    s = (pts - c) @ axis
    a, b = c_axis + axis * np.percentile(s, 1), c_axis + axis * np.percentile(s, 99)
    tip, end = (a, b) if np.linalg.norm(a - cam) >= np.linalg.norm(b - cam) else (b, a)
    return tip, end, radius


def working_end(tip: np.ndarray, end: np.ndarray, K: np.ndarray, field: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """Orient a capsule fitted to an instrument: (tip, end, how), ``tip`` its working end (the jaws).

    Instruments enter the view from its edge (through a trocar outside it), so the end whose image lies
    deeper inside the field of view is the working end. Depth cannot tell: a monocular reconstruction put
    the shaft end farther from the camera than the jaws on all three instruments of the shared clips
    (EndoNeRF pulling's grasper and probe, CholecSeg8K's grasper), so the bite of every grasp sat on the
    shaft. When both ends are equally deep inside (within 2 px; an instrument wholly in view), the
    fitted order is kept ("depth").

    Args:
        tip, end: [3] capsule axis ends at frame 0 (metres, camera frame).
        K: [3, 3] intrinsics; field: [H, W] bool, pixels inside the endoscope's field of view.
    Returns:
        (tip, end, "image" | "depth").
    """
    import cv2

    H, W = field.shape
    # Signed distance (px) to the field's edge, the image's own border counted as one: positive inside,
    # negative outside (the black around an endoscope's circle).
    pad = np.pad(field, 1)
    signed = (cv2.distanceTransform(pad.astype(np.uint8), cv2.DIST_L2, 5)
              - cv2.distanceTransform((~pad).astype(np.uint8), cv2.DIST_L2, 5))[1:-1, 1:-1]

    def depth_in_view(p: np.ndarray) -> float:
        if p[2] <= 0:
            return -math.inf  # behind the camera
        u, v = (K @ p)[:2] / (K @ p)[2]
        off = float(np.hypot(max(-u, 0.0, u - (W - 1)), max(-v, 0.0, v - (H - 1))))  # beyond the image
        return float(signed[int(np.clip(v, 0, H - 1)), int(np.clip(u, 0, W - 1))]) - off

    d_tip, d_end = depth_in_view(np.asarray(tip, float)), depth_in_view(np.asarray(end, float))
    if not abs(d_tip - d_end) >= 2.0:  # as deep inside, or both behind the camera (NaN)
        return tip, end, "depth"
    return (tip, end, "image") if d_tip > d_end else (end, tip, "image")


#: The farthest a capsule is extended beyond its grey core to reach the jaws (metres): a grasper's jaws
#: are 10-20 mm long; more is a floater or the mask leaking along the axis.
MAX_JAWS = 0.015


def extend_to_jaws(tip: np.ndarray, end: np.ndarray, radius: float, points: np.ndarray) -> np.ndarray:
    """The working end moved along the axis to the farthest of the instrument's Gaussians: a capsule fitted
    to the grey core of the shaft stops where the jaws begin (CholecSeg8K's grasper: 8 mm short), and the
    jaws are what grasps. Never shortened, never by more than ``MAX_JAWS``.

    Args:
        tip, end: [3] the capsule's working end and other end (metres).
        radius: the capsule's radius (metres); Gaussians within 2 radii of the axis count.
        points: [N, 3] the instrument's opaque Gaussians (metres); the 99th percentile along the axis is
            its reach (a few floaters do not count).
    Returns:
        the new tip [3] (metres).
    """
    tip, end = np.asarray(tip, float), np.asarray(end, float)
    length = float(np.linalg.norm(tip - end))
    axis = (tip - end) / max(length, 1e-12)
    s = (np.asarray(points, float) - end) @ axis
    near = _segment_distance(points, end, end + axis * max(s.max(), 0.0)) <= 2 * radius
    reach = float(np.percentile(s[near], 99)) if near.any() else 0.0
    return end + axis * min(max(reach, length), length + MAX_JAWS)


#: Gaussians at least this opaque count as an instrument's surface (its grey core, its jaws).
GREY_MIN_OPACITY = 0.3


def grey_core(g: Gaussians, max_saturation: float, min_opacity: float = GREY_MIN_OPACITY,
              min_count: int = 20) -> torch.Tensor:
    """[N] bool: the opaque, low-saturation (metal) Gaussians of ``g``; all opaque ones when fewer than
    ``min_count`` are grey (an instrument painted or lit in colour)."""
    rgb = g.colors_dc.detach().clamp(0, 1)
    hi, lo = rgb.max(-1).values, rgb.min(-1).values
    opaque = g.opacities.detach() >= min_opacity
    grey = opaque & ((hi - lo) / hi.clamp_min(1e-3) < max_saturation)
    return grey if int(grey.sum()) >= min_count else opaque


def _segment_distance(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance [N] of points x [N, 3] to the segment a-b."""
    ab = b - a
    s = np.clip((x - a) @ ab / max(float(ab @ ab), 1e-18), 0.0, 1.0)
    return np.linalg.norm(x - (a + s[:, None] * ab), axis=1)


def push_out_of_tissue(tip: np.ndarray, end: np.ndarray, radius: float, tissue: np.ndarray, clearance: float,
                       camera_center: np.ndarray | None = None, max_push: float = 0.05) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Move a capsule towards the camera, along the viewing ray of its centre, until no tissue point lies
    within ``radius + clearance`` of its axis.

    Args:
        tip, end: [3] axis ends (metres); radius: metres; tissue: [P, 3] tissue particle positions (metres).
        clearance: extra distance kept from the nearest tissue point (metres).
        max_push: the farthest move (metres); a capsule that needs more is refused.
    Returns:
        (tip, end, pushed distance in metres, tissue points inside the capsule before the push).
    """
    tip, end = np.asarray(tip, float), np.asarray(end, float)
    cam = np.zeros(3) if camera_center is None else np.asarray(camera_center, float)
    c = (tip + end) / 2
    toward = (cam - c) / max(np.linalg.norm(cam - c), 1e-12)
    inside = int((_segment_distance(tissue, tip, end) < radius).sum())

    def clear(s: float) -> bool:
        return bool(_segment_distance(tissue, tip + s * toward, end + s * toward).min() >= radius + clearance)

    if clear(0.0):
        return tip, end, 0.0, inside
    if not clear(max_push):
        raise DataError(f"a tool collider stays inside the tissue even {max_push * 1e3:.0f} mm closer to the camera")
    lo, hi = 0.0, max_push
    for _ in range(40):  # bisection to well below a micrometre
        mid = (lo + hi) / 2
        lo, hi = (lo, mid) if clear(mid) else (mid, hi)
    return tip + hi * toward, end + hi * toward, hi, inside


def instrument_colliders(g0: Gaussians, tool_ids: list[int], tissue_particles: np.ndarray, dx: float,
                         scenario: RealScenario = RealScenario(), K: np.ndarray | None = None,
                         field: np.ndarray | None = None) -> list[ToolFit]:
    """One capsule per instrument, fitted to its grey core at frame 0, its working end found in the image
    (:func:`working_end`) and reaching to the jaws (:func:`extend_to_jaws`), pushed out of the tissue.

    Args:
        g0: every Gaussian at frame 0 (world metres; the camera at the origin).
        tool_ids: the instruments' object ids (one per instrument).
        tissue_particles: [P, 3] the tissue's particles at frame 0 (metres).
        dx: the simulation grid's cell (metres).
        K: [3, 3] intrinsics and field: [H, W] bool, the endoscope's field of view (all True without a
            border), to find each instrument's working end; without them, the end farther from the camera.
    Returns:
        a :class:`ToolFit` per instrument with at least 4 Gaussians; warns (:class:`DataWarning`) for every
        instrument whose capsule held tissue particles, with the count and the distance it was moved (one
        only closer than the clearance is moved without a warning; scene.json records every move).
    """
    fits = []
    for oid in tool_ids:
        sel = g0.object_ids == oid
        if int(sel.sum()) < 4:
            warnings.warn(f"instrument {oid}: {int(sel.sum())} Gaussians, too few for a collider; it does not "
                          "touch the simulated tissue", DataWarning, stacklevel=2)
            continue
        tool = g0.subset(sel)
        core = grey_core(tool, scenario.grey_saturation)
        pts = tool.means[core].detach().double().numpy()
        tip, end, radius = fit_tool_capsule(pts)
        measured = radius
        if not scenario.instrument_radius[0] <= measured <= scenario.instrument_radius[1]:
            tip, end, radius = fit_tool_capsule(pts, radius_bounds=scenario.instrument_radius)
            warnings.warn(f"instrument {oid}: its Gaussians measure a radius of {measured * 1e3:.1f} mm; the collider "
                          f"takes {radius * 1e3:.1f} mm, the nearest standard instrument size (the depth of a "
                          "monocular reconstruction scales every size)", DataWarning, stacklevel=2)
        oriented, jaws = "depth", 0.0
        if K is not None and field is not None:
            tip, end, oriented = working_end(tip, end, K, field)
            opaque = tool.opacities.detach() >= GREY_MIN_OPACITY
            core_tip, tip = tip, extend_to_jaws(tip, end, radius, tool.means[opaque].detach().double().numpy())
            jaws = float(np.linalg.norm(tip - core_tip))
        tip, end, pushed, inside = push_out_of_tissue(tip, end, radius, tissue_particles, scenario.clearance * dx)
        if inside:
            warnings.warn(f"instrument {oid}: its fitted collider (radius {radius * 1e3:.1f} mm) held {inside} tissue "
                          f"particles at frame 0; moved {pushed * 1e3:.2f} mm towards the camera out of the tissue",
                          DataWarning, stacklevel=2)
        fits.append(ToolFit(oid, tip, end, radius, int(sel.sum()), int(core.sum()), pushed, inside, oriented, jaws))
    return fits


def _relative_transforms(M: np.ndarray) -> np.ndarray:
    """[T, 4, 4] canonical -> frame t transforms to frame 0 -> frame t transforms (frame 0 = identity)."""
    return M @ np.linalg.inv(M[0])[None]


def _real_scenario(objects: list[dict], tissue_pts: np.ndarray, frame_dt: float, sc: RealScenario) -> dict:
    """The ``scenario`` of scene.json for a real video (tools added by the caller)."""
    from endogsim.scene.discretisation import plan_discretisation
    from endogsim.scene.schema import SceneObject

    rays = tissue_pts / np.linalg.norm(tissue_pts, axis=1, keepdims=True)
    extent_pts = np.concatenate([tissue_pts, tissue_pts + sc.thickness * rays])
    lo, hi = extent_pts.min(0), extent_pts.max(0)
    size = float((hi - lo).max() * (1 + 2 * sc.box_margin))
    box_lo = ((lo + hi) / 2 - size / 2).tolist()
    soft = [SceneObject(id=o["id"], name=o["name"], klass=o["class"], rigid=o["rigid"]) for o in objects]
    ident = plan_discretisation(soft, size, sc.thickness, frame_dt, cells_across=sc.cells_across)
    g = np.asarray(sc.gravity_direction, float)
    g = sc.gravity * g / max(np.linalg.norm(g), 1e-12)
    return {
        "box_lo": box_lo, "box_size": size, "gravity": g.tolist(), "frame_dt": frame_dt, "damping": sc.damping,
        "boundary_conditions": [{"type": "box_walls", "cells": 2}] + [
            {"type": "anchors", "object": o["name"], "back_face": sc.back_face, "border": sc.border,
             "border_motion": sc.border_motion,
             **({"support_friction": sc.support_friction} if sc.back_face == "support" else {})}
            for o in objects if not o["rigid"]],
        "tools": [],
        "extrusion": {"along": "viewing_rays", "thickness": {o["name"]: sc.thickness for o in objects if not o["rigid"]}},
        "ground_truth": asdict(ident), "identification": asdict(ident),
        "settle_frames": sc.settle_frames, "settle_damping": sc.settle_damping, "mass_scaling": sc.mass_scaling,
    }


def scene_from_reconstruction(
    recon_run: str | Path,
    data: str | Path,
    out: str | Path,
    *,
    truth: str | Path | None = None,
    tool_motion: str = "reconstructed",
    scenario: RealScenario = RealScenario(),
    name: str | None = None,
) -> Path:
    """Write a simulation-ready scene folder from a reconstruction run.

    Args:
        recon_run: an ``endogsim reconstruct`` run folder.
        data: the dataset it was reconstructed from (observed frames and masks are read from it).
        out: the scene folder to write (replaced if it is one already).
        truth: a ground-truth scene folder (``endogsim synth``) whose boundary settings, materials and
            flow to reuse (benchmark protocol); None for a real video.
        tool_motion: "reconstructed" (the tools' tracked rigid motion) or "truth" (the ground-truth scene's
            tool transforms; needs ``truth``).
        scenario: the scenario of a real video (unused with ``truth``).
        name: scene name (default: the data folder's name).
    Returns:
        ``out``. ``scene.json`` records the collider fits (``colliders``).
    """
    import cv2

    from endogsim.gaussians.ply import write_ply
    from endogsim.io import load_scene
    from endogsim.io.images import resize_frames
    from endogsim.physics import max_stable_E  # noqa: F401 - imported to fail early without Warp
    from endogsim.recon.model import load_reconstruction
    from endogsim.scene.particles import particles_from_scene_gaussians
    from endogsim.scene.schema import IMAGES_PATTERN, load_scene_spec, scene_spec_from_json
    from endogsim.scene.tracks import TissueTracks, sample_tracks, write_tissue_tracks

    recon_run, data, out = Path(recon_run), Path(data), Path(out)
    if tool_motion not in ("reconstructed", "truth"):
        raise DataError(f"tool_motion must be 'reconstructed' or 'truth', got {tool_motion!r}")
    if tool_motion == "truth" and truth is None:
        raise DataError("tool_motion='truth' needs a ground-truth scene folder (truth=...)")
    rec = load_reconstruction(recon_run)
    cam = rec.camera
    g0: Gaussians = rec.gaussians_at(0, include_tools=True)
    T = rec.num_frames
    tool_tf = {oid: _relative_transforms(M.double().numpy()) for oid, M in rec.tool_transforms().items()}
    tool_ids = sorted(i for i, lab in rec.labels.items() if lab.is_tool)
    tissue_ids = sorted({int(i) for i in g0.object_ids.unique().tolist()} - set(tool_ids))
    if not tissue_ids:
        raise DataError(f"{recon_run}: the reconstruction holds no tissue Gaussians to simulate")

    scene = load_scene(data)
    if scene.frames.shape[0] < T:
        raise DataError(f"{data}: {scene.frames.shape[0]} frames, but the reconstruction {recon_run} has {T}")
    frames = resize_frames(scene.frames[:T], (cam.width, cam.height))
    masks = _instance_masks(recon_run, T, (cam.width, cam.height))
    if masks is None and scene.object_masks is not None:
        masks = resize_frames(scene.object_masks[:T].astype(np.int32), (cam.width, cam.height), nearest=True)

    gt = load_scene_spec(truth) if truth is not None else None
    if gt is not None and (gt.camera.width, gt.camera.height) != (cam.width, cam.height):
        raise DataError(f"{truth}: ground truth is {gt.camera.width}x{gt.camera.height} but the reconstruction is "
                        f"{cam.width}x{cam.height}; reconstruct with --resolution-scale 1 for the benchmark")
    if gt is not None and gt.frames < T:
        raise DataError(f"{truth}: ground truth has {gt.frames} frames, the reconstruction {T}")

    times = rec.times.double().numpy()
    if gt is not None:
        objects = [dict(asdict(o)) for o in gt.objects]
        for o in objects:
            o["class"] = o.pop("klass")
        sc_doc = json.loads(json.dumps(asdict(gt.scenario)))
        frame_dt = gt.scenario.frame_dt
    else:
        objects = [{"id": i, "name": rec.labels[i].name if i in rec.labels else f"object_{i}",
                    "class": rec.labels[i].klass if i in rec.labels else "unknown_tissue",
                    "rigid": i in tool_ids, "E": None, "nu": None, "density": None}
                   for i in tissue_ids + [i for i in tool_ids if int((g0.object_ids == i).sum()) >= 4]]
        frame_dt = float(np.median(np.diff(times))) if T > 1 else 1 / 30
        tissue_pts = g0.means[torch.isin(g0.object_ids, torch.tensor(tissue_ids))].detach().double().numpy()
        sc_doc = _real_scenario(objects, tissue_pts, frame_dt, scenario)

    cam_doc = {"K": cam.K.double().tolist(), "width": cam.width, "height": cam.height, "viewmat": np.eye(4).tolist(),
               "viewmats": None if rec.viewmats is None else rec.viewmats[:T].double().tolist(),
               # each frame's colours as its camera exposed them: simulated renders compare like with like
               "exposure": None if rec.exposure is None else
               {"log_gain": rec.exposure.log_gain[0, :T].detach().double().tolist(),
                "bias": rec.exposure.bias[0, :T].detach().double().tolist()}}
    doc = {
        "name": name or (gt.name if gt is not None else data.name), "seed": gt.seed if gt is not None else 0,
        "frames": T, "objects": objects, "scenario": sc_doc, "camera": cam_doc,
        "depth_scale": gt.depth_scale if gt is not None else 10000.0,
        "files": {"images": IMAGES_PATTERN, "gaussians_t0": "gaussians_t0.ply", "tracks": "tracks.npz"},
        "source": "reconstruction+truth" if gt is not None else "reconstruction",
        "reconstruction": str(recon_run), "data": str(data), "tool_motion": tool_motion,
    }

    # Tools: one capsule per instrument, moved by its reconstructed (or the ground truth's) rigid motion.
    spec = scene_spec_from_json(doc, out / "scene.json")
    ident = spec.scenario.identification
    # The tissue particles identification will simulate (load_sim_scene builds the same from gaussians_t0.ply).
    tissue_particles = particles_from_scene_gaussians(g0, spec, rec.camera, ident).particles.x.double().numpy()
    if gt is None:
        field = (np.ones((cam.height, cam.width), bool) if rec.field_of_view is None
                 else rec.field_of_view.cpu().numpy().astype(bool))
        fits = instrument_colliders(g0, tool_ids, tissue_particles, spec.scenario.box_size / ident.grid, scenario,
                                    K=cam.K.double().cpu().numpy(), field=field)
        shapes = {f.object_id: (f.tip, f.end, f.radius) for f in fits}
    else:  # benchmark protocol: the ground truth's collider shapes
        fits = []
        shapes = {t.object_id: (np.asarray(t.tip), np.asarray(t.end), float(t.radius)) for t in gt.scenario.tools}
    tools = []
    for oid, (tip, end, radius) in shapes.items():
        gt_tool = next((t for t in (gt.scenario.tools if gt else []) if t.object_id == oid), None)
        if tool_motion == "truth" or oid not in tool_tf:
            if gt_tool is None:
                raise DataError(f"tool {oid}: no reconstructed motion and no ground-truth trajectory")
            transforms = np.asarray(gt_tool.transforms, dtype=np.float64)[:T]
        else:
            transforms = tool_tf[oid]
        if gt_tool is not None:
            contact = gt_tool.contact
        else:
            klass = next((o["class"] for o in objects if o["id"] == oid), "")
            grasps = scenario.grasping == "all" or (scenario.grasping == "graspers" and "grasp" in str(klass))
            contact = "grasp" if grasps else "sticky"
        # Where the video does not show the instrument (out of view, occluded), its pose is held and it is
        # not drawn; the benchmark's ground truth draws its tools in every frame.
        visible = None
        if gt is None and masks is not None:
            visible = [bool((m == oid).any()) for m in masks[:T]]
        tools.append({"object_id": oid, "tip": np.asarray(tip).tolist(), "end": np.asarray(end).tolist(),
                      "radius": float(radius), "transforms": transforms.tolist(), "contact": contact,
                      "visible": visible})
    doc["scenario"]["tools"] = tools
    doc["colliders"] = [f.to_json() for f in fits]
    if gt is None:
        from endogsim.scene.motion import tool_speed
        from endogsim.scene.schema import ToolCapsule

        # Substeps: the CFL rule for the tool speed now; the materials' wave speed is added at run time.
        speed = tool_speed([ToolCapsule(**t) for t in tools], frame_dt)
        n = max(1, math.ceil(frame_dt * speed / (0.5 * spec.scenario.box_size / ident.grid)))
        doc["scenario"]["identification"] = doc["scenario"]["ground_truth"] = asdict(
            replace(ident, substeps=n, dt=frame_dt / n))
    ident_doc = doc["scenario"]["identification"]
    if abs(frame_dt - ident_doc["dt"] * ident_doc["substeps"]) > 1e-9:
        # The identification discretisation must cover one frame interval exactly.
        sub = max(int(ident_doc["substeps"]), math.ceil(frame_dt / ident_doc["dt"] - 1e-9))
        ident_doc["substeps"], ident_doc["dt"] = sub, frame_dt / sub

    # Tracks: the reconstruction's own trajectories of a sample of tissue Gaussians.
    idx = sample_tracks(g0.object_ids, g0.opacities, [o["id"] for o in objects if not o["rigid"]])
    positions = torch.stack([rec.gaussians_at(t, include_tools=True).means[idx] for t in range(T)])

    if out.exists() and not (out / "scene.json").is_file() and any(out.iterdir()):
        raise DataError(f"{out} exists and is not a scene folder; choose another output folder")
    with atomic_folder(out) as tmp:
        (tmp / "images").mkdir()
        for t in range(T):
            rgb8 = (np.clip(frames[t], 0, 1) * 255 + 0.5).astype(np.uint8)
            cv2.imwrite(str(tmp / "images" / f"frame-{t:06d}.color.png"), cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR))
        if masks is not None:
            (tmp / "object_masks").mkdir()
            doc["files"]["object_masks"] = "object_masks/frame-%06d.png"
            for t in range(T):
                cv2.imwrite(str(tmp / "object_masks" / f"frame-{t:06d}.png"), np.clip(masks[t], 0, 65535).astype(np.uint16))
        if gt is not None and gt.files.get("flow") and (Path(truth) / (gt.files["flow"] % 0)).is_file():
            (tmp / "flow").mkdir()
            for key in ("flow", "flow_valid"):
                pat = gt.files.get(key)
                if not pat:
                    continue
                doc["files"][key] = pat
                for t in range(T - 1):
                    src = Path(truth) / (pat % t)
                    if src.is_file():
                        shutil.copyfile(src, tmp / (pat % t))
        if rec.field_of_view is not None:  # renders are black outside the endoscope's circle, as filmed
            doc["files"]["field_of_view"] = "field_of_view.png"
            cv2.imwrite(str(tmp / "field_of_view.png"), rec.field_of_view.cpu().numpy().astype(np.uint8) * 255)
        write_ply(g0.detach(), tmp / "gaussians_t0.ply")
        write_tissue_tracks(tmp / "tracks.npz", TissueTracks(idx, positions))
        write_json_atomic(tmp / "scene.json", doc)
    return out


def _instance_masks(recon_run: Path, T: int, size: tuple[int, int]) -> np.ndarray | None:
    """The reconstruction's object masks (tool classes split into instruments), [T, H, W] int32, or None
    when the run did not keep them."""
    from endogsim.io.images import read_grey, resize_frames

    folder = recon_run / "object_masks"
    if not (folder / "frame-000000.png").is_file():
        return None
    m = np.stack([read_grey(folder / f"frame-{t:06d}.png").astype(np.int32) for t in range(T)])
    return resize_frames(m, size, nearest=True)
