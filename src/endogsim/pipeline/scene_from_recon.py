"""From a 4D reconstruction to a simulation-ready scene folder (the "Scenario" stage of DESIGN.md section 2).

:func:`scene_from_reconstruction` writes a folder in the layout of ``endogsim synth`` (so ``endogsim identify``
and ``endogsim simulate`` read it unchanged):

  images/frame-%06d.color.png   the observed frames at the reconstruction's resolution
  object_masks/frame-%06d.png   object id per pixel (when the data has masks)
  gaussians_t0.ply              the reconstructed Gaussians of frame 0, with object ids
  scene.json                    objects, camera, and the scenario: sim box, boundary conditions, tool
                                colliders (a capsule fitted to each tool's Gaussians, moved by the tool's
                                reconstructed per-frame rigid transforms), discretisation

Two ways to get the scenario:
  * ``truth`` given (the benchmark protocol, DESIGN.md section 8): the ground-truth scene's boundary settings
    (sim box, anchors, extrusion, gravity, tool capsule shape) and its ground-truth materials and flow are
    reused; the Gaussians come from the reconstruction, the tool motion from the reconstruction or (the
    paper's "same boundary settings") from the ground truth.
  * no ``truth`` (real video): everything is derived from the reconstruction with :class:`ScenarioDefaults`.
    Gravity defaults to zero: frame 0 is observed at rest under unknown loads (insufflation, attachments),
    so switching gravity on at t = 0 would make the tissue sag in a way the video never shows.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from endogsim.errors import DataError
from endogsim.gaussians.model import Gaussians
from endogsim.io.atomic import atomic_folder, write_json_atomic

__all__ = ["ScenarioDefaults", "scene_from_reconstruction", "fit_tool_capsule"]


@dataclass(frozen=True)
class ScenarioDefaults:
    """Scenario of a real (no ground truth) reconstruction.

    Attributes:
        thickness: extrusion of the visible tissue surface along the viewing rays (metres).
        border: width of the anchored band along each tissue object's outline (metres).
        box_margin: free space around the tissue in the sim box, as a fraction of its extent per side.
        grid: identification grid cells per box edge (paper: 50).
        substeps: substeps per frame (raised automatically to cover the frame interval).
        dt: substep (s). 1e-4 rather than the paper's 2e-4: at under one particle per cell the MPM is not
            converged in dt at 2e-4 and identification then favours too stiff a material (see the benchmark
            suite's description).
        gravity: world (camera-frame) gravity (m/s^2); see the module docstring for why it is off.
        damping: grid velocity damping per second.
    """

    thickness: float = 0.006
    border: float = 0.004
    box_margin: float = 0.25
    grid: int = 50
    substeps: int = 50
    dt: float = 1e-4
    gravity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    damping: float = 0.0


def fit_tool_capsule(points: np.ndarray, camera_center: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """A capsule (tip [3], end [3], radius m) around a tool's Gaussians seen from one side.

    The axis is the principal direction of the points; the radius is half the tool's width across the
    axis and the viewing ray; the axis sits that far behind the visible surface (the points lie on the
    near half of the shaft). ``tip`` is the end farther from the camera (the working end).
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
    c_axis = c + ray * (2.0 / math.pi) * radius  # centroid of a half cylinder's surface is 2r/pi off the axis
    s = (pts - c) @ axis
    a, b = c_axis + axis * np.percentile(s, 1), c_axis + axis * np.percentile(s, 99)
    tip, end = (a, b) if np.linalg.norm(a - cam) >= np.linalg.norm(b - cam) else (b, a)
    return tip, end, radius


def _relative_transforms(M: np.ndarray) -> np.ndarray:
    """[T, 4, 4] canonical -> frame t transforms to frame 0 -> frame t transforms (frame 0 = identity)."""
    return M @ np.linalg.inv(M[0])[None]


def scene_from_reconstruction(
    recon_run: str | Path,
    data: str | Path,
    out: str | Path,
    *,
    truth: str | Path | None = None,
    tool_motion: str = "reconstructed",
    defaults: ScenarioDefaults = ScenarioDefaults(),
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
        defaults: the scenario of a real video (ignored where ``truth`` gives a value).
        name: scene name (default: the data folder's name).
    Returns:
        ``out``.
    """
    import cv2

    from endogsim.gaussians.ply import write_ply
    from endogsim.io import load_scene
    from endogsim.io.images import resize_frames
    from endogsim.physics import max_stable_E  # noqa: F401 - imported to fail early without Warp
    from endogsim.recon.model import load_reconstruction
    from endogsim.scene.schema import load_scene_spec

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
    masks = None
    if scene.object_masks is not None:
        masks = resize_frames(scene.object_masks[:T].astype(np.int32), (cam.width, cam.height), nearest=True)

    gt = load_scene_spec(truth) if truth is not None else None
    if gt is not None and (gt.camera.width, gt.camera.height) != (cam.width, cam.height):
        raise DataError(f"{truth}: ground truth is {gt.camera.width}x{gt.camera.height} but the reconstruction is "
                        f"{cam.width}x{cam.height}; reconstruct with --resolution-scale 1 for the benchmark")
    if gt is not None and gt.frames < T:
        raise DataError(f"{truth}: ground truth has {gt.frames} frames, the reconstruction {T}")

    # Tools: capsule colliders fitted to the reconstructed tool Gaussians at frame 0.
    tools = []
    for oid in tool_ids:
        sel = g0.object_ids == oid
        if int(sel.sum()) < 4:
            continue
        gt_tool = next((t for t in (gt.scenario.tools if gt else []) if t.object_id == oid), None)
        if gt_tool is not None:  # benchmark protocol: the ground truth's collider shape
            tip, end, radius = np.asarray(gt_tool.tip), np.asarray(gt_tool.end), float(gt_tool.radius)
        else:
            tip, end, radius = fit_tool_capsule(g0.means[sel].detach().double().numpy())
        if tool_motion == "truth" or oid not in tool_tf:
            if gt_tool is None:
                raise DataError(f"tool {oid}: no reconstructed motion and no ground-truth trajectory")
            transforms = np.asarray(gt_tool.transforms, dtype=np.float64)[:T]
        else:
            transforms = tool_tf[oid]
        tools.append({"object_id": oid, "tip": tip.tolist(), "end": end.tolist(), "radius": radius,
                      "transforms": transforms.tolist(), "contact": "sticky"})

    if gt is not None:
        objects = [dict(asdict(o)) for o in gt.objects]
        for o in objects:
            o["class"] = o.pop("klass")
        scenario = json.loads(json.dumps(asdict(gt.scenario)))
        scenario["tools"] = tools
        frame_dt = gt.scenario.frame_dt
    else:
        objects = [{"id": i, "name": rec.labels[i].name if i in rec.labels else f"object_{i}",
                    "class": rec.labels[i].klass if i in rec.labels else "unknown_tissue",
                    "rigid": i in tool_ids, "E": None, "nu": None, "density": None, "model": "fixed_corotated"}
                   for i in tissue_ids + [t["object_id"] for t in tools]]
        times = rec.times.double().numpy()
        frame_dt = float(np.median(np.diff(times))) if T > 1 else 1 / 30
        tissue_pts = g0.means[torch.isin(g0.object_ids, torch.tensor(tissue_ids))].detach().double().numpy()
        rays = tissue_pts / np.linalg.norm(tissue_pts, axis=1, keepdims=True)
        extent_pts = np.concatenate([tissue_pts, tissue_pts + defaults.thickness * rays])
        lo, hi = extent_pts.min(0), extent_pts.max(0)
        size = float((hi - lo).max() * (1 + 2 * defaults.box_margin))
        box_lo = ((lo + hi) / 2 - size / 2).tolist()
        dx = size / defaults.grid
        scenario = {
            "box_lo": box_lo, "box_size": size, "gravity": list(defaults.gravity), "frame_dt": frame_dt,
            "damping": defaults.damping,
            "boundary_conditions": [{"type": "box_walls", "cells": 2}] + [
                {"type": "anchors", "object": o["name"], "back_face": True, "border": defaults.border}
                for o in objects if not o["rigid"]],
            "tools": tools, "particle_spacing": dx,
            "extrusion": {"along": "viewing_rays", "thickness": {o["name"]: defaults.thickness
                                                                for o in objects if not o["rigid"]}},
            "ground_truth": {"grid": defaults.grid, "dt": defaults.dt, "substeps": defaults.substeps, "cfl": float("nan")},
            "identification": {"grid": defaults.grid, "dt": defaults.dt, "substeps": defaults.substeps,
                               "cfl": float("nan")},
        }
    if abs(frame_dt - scenario["identification"]["dt"] * scenario["identification"]["substeps"]) > 1e-9:
        # The identification discretisation must cover one frame interval exactly.
        sub = max(int(scenario["identification"]["substeps"]), math.ceil(frame_dt / scenario["identification"]["dt"] - 1e-9))
        scenario["identification"]["substeps"] = sub
        scenario["identification"]["dt"] = frame_dt / sub

    if out.exists() and not (out / "scene.json").is_file() and any(out.iterdir()):
        raise DataError(f"{out} exists and is not a scene folder; choose another output folder")
    files = {"images": "images/frame-%06d.color.png", "gaussians_t0": "gaussians_t0.ply"}
    with atomic_folder(out) as tmp:
        (tmp / "images").mkdir()
        for t in range(T):
            rgb8 = (np.clip(frames[t], 0, 1) * 255 + 0.5).astype(np.uint8)
            cv2.imwrite(str(tmp / "images" / f"frame-{t:06d}.color.png"), cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR))
        if masks is not None:
            (tmp / "object_masks").mkdir()
            files["object_masks"] = "object_masks/frame-%06d.png"
            for t in range(T):
                cv2.imwrite(str(tmp / "object_masks" / f"frame-{t:06d}.png"), np.clip(masks[t], 0, 65535).astype(np.uint16))
        if gt is not None and gt.files.get("flow") and (Path(truth) / (gt.files["flow"] % 0)).is_file():
            (tmp / "flow").mkdir()
            for key in ("flow", "flow_valid"):
                pat = gt.files.get(key)
                if not pat:
                    continue
                files[key] = pat
                for t in range(T - 1):
                    src = Path(truth) / (pat % t)
                    if src.is_file():
                        shutil.copyfile(src, tmp / (pat % t))
        write_ply(g0.detach(), tmp / "gaussians_t0.ply")
        K = cam.K.double().tolist()
        doc = {
            "name": name or (gt.name if gt is not None else data.name), "seed": gt.seed if gt is not None else 0, "frames": T, "objects": objects,
            "scenario": scenario,
            "camera": {"K": K, "width": cam.width, "height": cam.height, "viewmat": np.eye(4).tolist()},
            "depth_scale": gt.depth_scale if gt is not None else 10000.0, "files": files,
            "source": "reconstruction+truth" if gt is not None else "reconstruction",
            "reconstruction": str(recon_run), "data": str(data), "tool_motion": tool_motion,
        }
        write_json_atomic(tmp / "scene.json", doc)
    return out
