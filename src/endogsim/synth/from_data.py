"""Benchmark scenes from real frames (``endogsim synth --from DATA_DIR``).

Frame 0 of a real sequence becomes ground-truth Gaussians (one flat Gaussian per downscaled pixel, coloured
by the pixel), the segmentation gives object ids, each tissue object gets ground-truth materials (the prior
value of its class, perturbed deterministically from the seed), and a synthetic rigid tool presses or pulls
the largest tissue object. Simulation and writing are shared with the procedural scenes.

Frame 0 is read with :func:`endogsim.io.load_scene` (any registered dataset format, with the loaders'
intrinsics: EndoNeRF's focal, else their default field of view), its segmentation giving the classes:
EndoNeRF-style tool masks (tissue 1, tool 31) or CholecSeg8K class ids.

Depth: when the folder has ``depth/`` its values are used as *relative* depth, rescaled so the median is
the nominal distance. Without depth (both shared excerpts) it is the reconstruction's offline fallback, a
smooth bowl seen from inside at ``nominal_depth`` (0.07 m; :func:`endogsim.priors.depth.fallback_depth`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from endogsim.errors import DataError
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians
from endogsim.io.images import resize
from endogsim.io.labels import (
    CHOLECSEG8K_LABELS,
    CHOLECSEG8K_NON_OBJECTS,
    CHOLECSEG8K_UNLABELLED_VALUE,
    UNLABELLED,
)
from endogsim.materials.prior import prior_entry
from endogsim.priors.depth import fallback_depth
from endogsim.scene.motion import tool_capsule, tool_offsets
from endogsim.scene.schema import SceneObject
from endogsim.synth import procedural as proc
from endogsim.synth.scenes import BuiltScene, scene_discretisations
from endogsim.synth.suite import load_suite

__all__ = ["build_from_data", "CHOLECSEG_CLASSES", "read_first_frame"]

# CholecSeg8K class id -> (name, prior class, is_tool), from the loader's class table (names are the prior
# classes); the field-of-view border is dropped and 255 (unlabelled pixels) becomes a generic tissue.
CHOLECSEG_CLASSES = {lab.id: (lab.klass, lab.klass, lab.is_tool) for lab in CHOLECSEG8K_LABELS.values()
                     if lab.id not in CHOLECSEG8K_NON_OBJECTS}
CHOLECSEG_CLASSES[CHOLECSEG8K_UNLABELLED_VALUE] = ("unlabelled", "unknown_tissue", False)
THICKNESS = 0.008  # metres of tissue behind the visible surface
BORDER = 0.005  # metres of the anchored band along each tissue object's outline

def _prior(klass: str, is_tool: bool = False) -> tuple[float, float, float, str]:
    """(E Pa, nu, density kg/m^3, where from) of a class, in the in-vivo regime."""
    key, e = prior_entry(klass, is_tool)
    return float(e["in_vivo"]["E"]), float(e["nu"]), float(e["density"]), f"prior table ({key})"


def read_first_frame(data_dir: Path) -> dict:
    """Frame 0 of a real scene, read through :func:`endogsim.io.load_scene` (any registered format):
    rgb [H,W,3] float in [0,1], classes [H,W] int (class id; 1 = tissue / 31 = tool for EndoNeRF-style tool
    masks; 255 unlabelled), depth [H,W] or None (relative units), K [3,3] (pixels), and the labels
    {class id: (name, prior class, is_tool)}."""
    from endogsim.io.formats import detect_format, load_scene

    d = Path(data_dir)
    if not d.exists():
        raise DataError(f"--from {d}: no such folder")
    scene = load_scene(d, max_frames=1)
    H, W = scene.height, scene.width
    if scene.object_masks is None:
        classes = np.ones((H, W), np.int64)
    elif set(scene.labels) <= {0, 1}:  # EndoNeRF-style tool masks: 0 tissue, 1 tool
        classes = np.where(scene.object_masks[0] == 1, 31, 1).astype(np.int64)
    else:
        classes = np.where(scene.object_masks[0] == UNLABELLED, CHOLECSEG8K_UNLABELLED_VALUE,
                           scene.object_masks[0]).astype(np.int64)
    labels = ({1: ("tissue", "unknown_tissue", False), 31: ("tool", "instrument", True)} if set(scene.labels) <= {0, 1}
              else CHOLECSEG_CLASSES)
    return {"format": detect_format(d), "rgb": scene.frames[0], "classes": classes, "depth": None if scene.depth is None else scene.depth[0],
            "K": scene.K, "labels": labels}


def build_from_data(data_dir, name: str | None = None, seed: int = 0, frames: int | None = None,
                    scale: float | None = None, interaction: str = "press", nominal_depth: float = 0.07,
                    width: int = 256) -> BuiltScene:
    """Build a benchmark scene from frame 0 of a real sequence.

    Args:
        data_dir: EndoNeRF or CholecSeg8K folder. name: scene name (default: the folder's name).
        seed: material perturbation seed. frames: rendered frames (default 12).
        scale: image downscale factor (default: so the width is ``width`` pixels).
        interaction: "press" (the tool indents the largest tissue object) or "pull" (grasps and lifts it).
        nominal_depth: distance (metres) of the depth fallback / median of relative depth.
    """
    import cv2

    if interaction not in ("press", "pull"):
        raise DataError(f"--interaction must be 'press' or 'pull', got {interaction!r}")
    data_dir = Path(data_dir)
    fr = read_first_frame(data_dir)
    H0, W0 = fr["rgb"].shape[:2]
    s = scale if scale is not None else width / W0
    if not (0 < s <= 1.0):
        raise DataError(f"--scale for --from must be in (0, 1] (a downscale), got {s}")
    W, H = max(16, round(W0 * s)), max(16, round(H0 * s))
    rgb = resize(fr["rgb"], (W, H))
    classes = resize(fr["classes"].astype(np.int32), (W, H), nearest=True).astype(np.int64)
    focal = float(fr["K"][0, 0]) * W / W0  # the loader's intrinsics (its default field of view without any)
    cam = Camera.from_focal(focal, W, H)
    if fr["depth"] is not None:
        rel = resize(fr["depth"], (W, H), nearest=True)
        med = np.median(rel[rel > 0]) if (rel > 0).any() else 1.0
        depth = np.where(rel > 0, rel / med * nominal_depth, nominal_depth)
        depth_source = "data (relative, median rescaled to nominal_depth)"
    else:
        depth = fallback_depth(cam.K.double().numpy(), W, H, 1, nominal_depth)[0].astype(np.float64)
        depth_source = f"fallback bowl at {nominal_depth} m (endogsim.priors.depth.fallback_depth)"

    labels = fr["labels"]
    T = int(frames if frames is not None else 12)
    if T < 2:
        raise DataError(f"--frames must be at least 2, got {T}")
    keep = ~np.isin(classes, list(CHOLECSEG8K_NON_OBJECTS))
    present = [c for c in np.unique(classes[keep]).tolist() if c in labels]
    unknown = set(np.unique(classes[keep]).tolist()) - set(labels)
    if unknown:
        raise DataError(f"{data_dir}: unknown class ids {sorted(unknown)} in the segmentation")

    # Ground-truth materials: the class prior, E perturbed by a factor in [1/1.5, 1.5]; nu capped at 0.45
    # (near-incompressible values would need far smaller substeps, DESIGN.md section 4) minus up to 0.04.
    suite = load_suite()["defaults"]
    objects: list[SceneObject] = []
    mat_sources = set()
    for cid in present:
        nm, klass, is_tool = labels[cid]
        E, nu, rho, where = _prior(klass, is_tool)
        mat_sources.add(where.split(" (")[0])
        if not is_tool:
            rng = np.random.default_rng([seed, cid])
            E = E * 1.5 ** rng.uniform(-1, 1)
            nu = float(min(nu, 0.45) - rng.uniform(0.0, 0.04))
        objects.append(SceneObject(id=int(cid), name=nm, klass=klass, rigid=is_tool, E=float(E), nu=nu, density=rho))

    # Back-project every pixel: one flat Gaussian per pixel, facing the camera.
    ys, xs = np.mgrid[0:H, 0:W]
    z = depth
    px = np.stack([(xs + 0.5 - W / 2) / focal * z, (ys + 0.5 - H / 2) / focal * z, z], -1)
    foot = z / focal  # metres per pixel
    sel = keep.ravel()
    pts = px.reshape(-1, 3)[sel]
    col = rgb.reshape(-1, 3)[sel]
    ids = classes.ravel()[sel]
    sc = 0.7 * foot.ravel()[sel]
    g = Gaussians.from_points(torch.tensor(pts, dtype=torch.float32), torch.tensor(col, dtype=torch.float32),
                              torch.tensor(np.stack([sc, sc, 0.5 * sc], 1), dtype=torch.float32), object_ids=0)
    g = g.with_(object_ids=torch.tensor(ids, dtype=torch.int64))
    tool_ids = {o.id for o in objects if o.rigid}
    soft = [o for o in objects if not o.rigid]
    if not soft:
        raise DataError(f"{data_dir}: frame 0 shows no tissue to simulate")

    # The synthetic tool touches the tissue object with the deepest interior point, at that point
    # (away from object boundaries and the field-of-view border).
    def interior(o):
        return cv2.distanceTransform(np.pad(classes == o.id, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]

    target = max(soft, key=lambda o: float(interior(o).max()))
    inner = interior(target)
    cy, cx = np.unravel_index(np.argmax(inner), inner.shape)
    contact = px[cy, cx]
    radius = 0.004
    ray = contact / np.linalg.norm(contact)
    tip = contact - 0.001 * ray + np.array([0, 0, -radius + 0.003])
    end = tip + np.array([0.04 if cx < W / 2 else -0.04, -0.03, -0.035])
    end[2] = max(end[2], 0.012)
    if interaction == "press":
        kf = [[0, 0, 0, 0], [0.6, 0, 0, 0.006], [1.0, 0.002, 0.001, 0.006]]
    else:
        kf = [[0, 0, 0, 0], [0.6, 0, 0, -0.006], [1.0, 0.002, -0.001, -0.007]]
    tool_obj_id = max(o.id for o in objects) + 1 if 31 in tool_ids or 32 in tool_ids else 31
    if tool_obj_id in {o.id for o in objects}:
        tool_obj_id = max(o.id for o in objects) + 1
    objects.append(SceneObject(id=tool_obj_id, name="synthetic_tool", klass="instrument", rigid=True,
                               E=2.0e11, nu=0.3, density=7850.0))
    tool_g = proc.tool_gaussians(tip, end, radius, 0.6 * float(np.median(foot)) * 2, tool_obj_id, seed=seed,
                                 jaw=interaction == "pull")
    offsets = tool_offsets(kf, T)
    tool = tool_capsule(tool_obj_id, tip, end, radius, offsets, contact="grasp" if interaction == "pull" else "sticky")

    # Cubic sim box around the tissue's slab (its surface and the same surface THICKNESS behind) and the
    # tool's path, with room for the walls.
    surface = pts[~np.isin(ids, list(tool_ids))]
    slab = np.concatenate([surface, surface * (1 + THICKNESS / np.linalg.norm(surface, axis=1, keepdims=True))])
    lo = np.minimum(slab.min(0), tip + offsets.min(0))
    hi = np.maximum(slab.max(0), tip + offsets.max(0))
    size = float((hi - lo).max()) * 1.15 + 0.004
    box_lo = (lo + hi) / 2 - size / 2
    gt, idn = scene_discretisations(suite, objects, size, [tool], THICKNESS)

    allg = Gaussians.concat([g, tool_g])
    n_g = len(g)
    is_tissue = np.zeros(len(allg), bool)
    is_tissue[:n_g] = ~np.isin(ids, list(tool_ids))
    is_tool = np.zeros(len(allg), bool)
    is_tool[n_g:] = True
    name = name or data_dir.name
    return BuiltScene(
        name=name, camera=cam, frames=T, frame_dt=suite["frame_dt"], gaussians=allg, tissue_gaussians=is_tissue,
        tool_gaussians={tool_obj_id: is_tool}, objects=objects, tools=[tool], box_lo=box_lo, box_size=size,
        gravity=np.asarray(suite["gravity"], float), damping=suite["damping"], ground_truth=gt, identification=idn,
        settle_frames=int(suite["settle_frames"]), settle_damping=suite.get("settle_damping"),
        boundary_conditions=[{"type": "box_walls", "cells": 2},
                             {"type": "anchors", "object": "all_tissue", "back_face": "fixed", "border": BORDER,
                              **({"release": {"center": contact[:2].tolist(), "radius": 0.02}} if interaction == "pull" else {})},
                             {"type": "static", "objects": [labels[c][0] for c in present if labels[c][2]]}],
        extrusion={"along": "viewing_rays", "thickness": THICKNESS}, source=str(data_dir),
        extra={"depth_source": depth_source, "interaction": interaction, "downscale": s,
               "layout": fr["format"], "material_source": f"{', '.join(sorted(mat_sources))} x deterministic perturbation (seed {seed}), "
                                  "substeps from the CFL rule"},
    )
