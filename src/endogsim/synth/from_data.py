"""Benchmark scenes from real frames (``endogsim synth --from DATA_DIR``).

Frame 0 of a real sequence becomes ground-truth Gaussians (one flat Gaussian per downscaled pixel, coloured
by the pixel), the segmentation gives object ids, each tissue object gets ground-truth materials (the prior
value of its class, perturbed deterministically from the seed), and a synthetic rigid tool presses or pulls
the largest tissue object. Simulation and writing are shared with the procedural scenes.

Readers (frame 0 only, so no full-sequence loader is needed):
  * EndoNeRF layout: ``images/`` (sorted), optional ``masks/`` (255 = tool), optional ``depth/``,
    ``poses_bounds.npy`` (focal in column 14; principal point at the image centre).
  * CholecSeg8K layout: ``frames/frame_N_endo.png`` + ``frame_N_endo_watershed_mask.png`` (class ids);
    no intrinsics (a 70 degree horizontal field of view is assumed).

Depth: when the folder has ``depth/`` its values are used as *relative* depth, rescaled so the median is
the nominal distance. Without depth (both shared excerpts) the documented fallback is a smooth bowl seen
from inside: z = D (1 - 0.25 r^2) with D = ``nominal_depth`` (0.07 m) and r the distance from the image
centre normalised to 1 at the corners (the centre of the cavity is farthest away).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from endogsim.errors import DataError
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians
from endogsim.io.labels import CHOLECSEG8K_LABELS, CHOLECSEG8K_NON_OBJECTS, CHOLECSEG8K_UNLABELLED_VALUE
from endogsim.materials.prior import prior_entry
from endogsim.synth import procedural as proc
from endogsim.physics import MPMConfig, max_stable_E
from endogsim.synth.scenes import BuiltScene, ground_truth_and_identification, tissue_from_surface, tool_offsets, tool_truth
from endogsim.synth.spec import ObjectTruth, load_suite

__all__ = ["build_from_data", "CHOLECSEG_CLASSES", "read_first_frame"]

# CholecSeg8K class id -> (name, prior class, is_tool), from the loader's class table (names are the prior
# classes); the field-of-view border is dropped and 255 (unlabelled pixels) becomes a generic tissue.
CHOLECSEG_CLASSES = {lab.id: (lab.klass, lab.klass, lab.is_tool) for lab in CHOLECSEG8K_LABELS.values()
                     if lab.id not in CHOLECSEG8K_NON_OBJECTS}
CHOLECSEG_CLASSES[CHOLECSEG8K_UNLABELLED_VALUE] = ("unlabelled", "unknown_tissue", False)
PAPER_SUBSTEPS = 25  # the paper's 25 x 2e-4 s per 5 ms frame

def _prior(klass: str, is_tool: bool = False) -> tuple[float, float, float, str]:
    """(E Pa, nu, density kg/m^3, where from) of a class, in the in-vivo regime."""
    key, e = prior_entry(klass, is_tool)
    return float(e["in_vivo"]["E"]), float(e["nu"]), float(e["density"]), f"prior table ({key})"


def _imread_rgb(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DataError(f"{path}: cannot read image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


def read_first_frame(data_dir: Path) -> dict:
    """Frame 0 of a real scene: rgb [H,W,3] float in [0,1], classes [H,W] int (class id, or 1 = tissue /
    31 = tool when only a tool mask exists), depth [H,W] or None (relative units), focal (px) or None."""
    import cv2

    d = Path(data_dir)
    if not d.is_dir():
        raise DataError(f"--from {d}: no such folder")
    if (d / "images").is_dir():
        imgs = sorted(p for p in (d / "images").iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
        if not imgs:
            raise DataError(f"{d / 'images'}: no frames")
        rgb = _imread_rgb(imgs[0])
        H, W = rgb.shape[:2]
        classes = np.ones((H, W), np.int64)
        masks = sorted((d / "masks").glob("*.png")) if (d / "masks").is_dir() else []
        if masks:
            m = cv2.imread(str(masks[0]), cv2.IMREAD_GRAYSCALE)
            classes[m > 127] = 31
        depth = None
        depths = sorted((d / "depth").glob("*.png")) if (d / "depth").is_dir() else []
        if depths:
            depth = cv2.imread(str(depths[0]), cv2.IMREAD_UNCHANGED).astype(np.float64)
        focal = None
        if (d / "poses_bounds.npy").is_file():
            pb = np.load(d / "poses_bounds.npy")
            if pb.ndim != 2 or pb.shape[1] != 17:
                raise DataError(f"{d / 'poses_bounds.npy'}: expected shape (N, 17), got {pb.shape}")
            focal = float(pb[0, 14]) * W / float(pb[0, 9])  # focal is given for the stored width
        return {"rgb": rgb, "classes": classes, "depth": depth, "focal": focal, "layout": "endonerf",
                "labels": {1: ("tissue", "unknown_tissue", False), 31: ("tool", "instrument", True)}}
    if (d / "frames").is_dir():
        frames = sorted((d / "frames").glob("frame_*_endo.png"), key=lambda p: int(p.stem.split("_")[1]))
        if not frames:
            raise DataError(f"{d / 'frames'}: no frame_N_endo.png files (CholecSeg8K layout)")
        rgb = _imread_rgb(frames[0])
        mpath = frames[0].with_name(frames[0].stem + "_watershed_mask.png")
        if not mpath.is_file():
            raise DataError(f"{mpath}: missing CholecSeg8K mask for {frames[0].name}")
        classes = cv2.imread(str(mpath), cv2.IMREAD_GRAYSCALE).astype(np.int64)
        return {"rgb": rgb, "classes": classes, "depth": None, "focal": None, "layout": "cholecseg8k",
                "labels": CHOLECSEG_CLASSES}
    raise DataError(f"--from {d}: neither an EndoNeRF folder (images/) nor a CholecSeg8K clip (frames/)")


def _bowl_depth(H: int, W: int, nominal: float) -> np.ndarray:
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    r2 = ((xs + 0.5 - W / 2) ** 2 + (ys + 0.5 - H / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
    return nominal * (1 - 0.25 * r2)


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
    rgb = cv2.resize(fr["rgb"], (W, H), interpolation=cv2.INTER_AREA)
    classes = cv2.resize(fr["classes"].astype(np.uint8 if fr["classes"].max() < 256 else np.uint16), (W, H),
                         interpolation=cv2.INTER_NEAREST).astype(np.int64)
    if fr["focal"] is not None:
        focal = fr["focal"] * W / W0
        cam = Camera.from_focal(focal, W, H)
    else:
        cam = proc.endoscope_camera(W, H, 70.0)
        focal = float(cam.K[0, 0])
    if fr["depth"] is not None:
        rel = cv2.resize(fr["depth"], (W, H), interpolation=cv2.INTER_NEAREST)
        med = np.median(rel[rel > 0]) if (rel > 0).any() else 1.0
        depth = np.where(rel > 0, rel / med * nominal_depth, nominal_depth)
        depth_source = "data (relative, median rescaled to nominal_depth)"
    else:
        depth = _bowl_depth(H, W, nominal_depth)
        depth_source = f"fallback bowl z = {nominal_depth} (1 - 0.25 r^2)"

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
    ident = load_suite()["defaults"]
    objects: list[ObjectTruth] = []
    mat_sources = set()
    for cid in present:
        nm, klass, is_tool = labels[cid]
        E, nu, rho, where = _prior(klass, is_tool)
        mat_sources.add(where.split(" (")[0])
        if not is_tool:
            rng = np.random.default_rng([seed, cid])
            E = E * 1.5 ** rng.uniform(-1, 1)
            nu = float(min(nu, 0.45) - rng.uniform(0.0, 0.04))
        objects.append(ObjectTruth(id=int(cid), name=nm, klass=klass, rigid=is_tool, E=float(E), nu=nu, density=rho))

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

    # Particles on a coarser pixel lattice, extruded along the rays; anchored at the back and near the
    # field-of-view border (distance transform of the kept region, in metres).
    p_sp = 0.0025
    stride = max(1, round(p_sp / float(np.median(foot))))
    edge_px = cv2.distanceTransform(np.pad(keep, 1).astype(np.uint8), cv2.DIST_L2, 5)[1:-1, 1:-1]
    lattice = np.zeros((H, W), bool)
    lattice[stride // 2::stride, stride // 2::stride] = True
    parts = []
    for o in soft:
        m = lattice & (classes == o.id)
        if not m.any():
            continue
        part = tissue_from_surface(px[m], edge_px[m] * foot[m], 0.008, p_sp,
                                   {"back_face": True, "border": 0.005}, o.id, cam)
        parts.append(part)
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

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
        rel = np.linalg.norm(cat["x"][:, :2] - contact[None, :2], axis=1) < 0.02
        back_layer = cat["anchored"] & rel & (np.linalg.norm(cat["x"], axis=1) > np.linalg.norm(contact) + 0.004)
        cat["anchored"] = cat["anchored"] & ~back_layer
    tool_obj_id = max(o.id for o in objects) + 1 if 31 in tool_ids or 32 in tool_ids else 31
    if tool_obj_id in {o.id for o in objects}:
        tool_obj_id = max(o.id for o in objects) + 1
    objects.append(ObjectTruth(id=tool_obj_id, name="synthetic_tool", klass="instrument", rigid=True,
                               E=2.0e11, nu=0.3, density=7850.0))
    tool_g = proc.tool_gaussians(tip, end, radius, 0.6 * float(np.median(foot)) * 2, tool_obj_id, seed=seed,
                                 jaw=interaction == "pull")
    offsets = tool_offsets(kf, T)
    tool = tool_truth(tool_obj_id, tip, end, radius, offsets)

    # Cubic sim box around the particles and the tool's path through the tissue.
    tissue_pts = np.concatenate([cat["x"], pts[~np.isin(ids, list(tool_ids))]])
    lo = np.minimum(tissue_pts.min(0), (tip + offsets.min(0)))
    hi = np.maximum(tissue_pts.max(0), (tip + offsets.max(0)))
    coarsest = min(int(ident["gt_grid"]), int(ident["ident_grid"]))  # 3 wall cells of either grid stay clear
    size = float((hi - lo).max()) / (1 - 2 * 3 / coarsest) + 0.004
    box_lo = (lo + hi) / 2 - size / 2

    # Keep every object inside the stability limit (CFL <= 0.45) of the paper's 25 substeps per frame, the
    # coarser of it and the suite's identification dt: the materials then stay simulable at either.
    substeps = min(PAPER_SUBSTEPS, max(1, round(ident["frame_dt"] / ident["ident_dt"])))
    ident_cfg = MPMConfig(grid_res=int(ident["ident_grid"]), frame_dt=float(ident["frame_dt"]),
                          substeps_per_frame=substeps, cfl_number=0.45)
    for o in soft:
        o.E = min(o.E, max_stable_E(o.nu, o.density, ident_cfg, size))
    gt, idn = ground_truth_and_identification(ident, objects, size, [tool], name or data_dir.name)

    allg = Gaussians.concat([g, tool_g])
    n_g = len(g)
    is_tissue = np.zeros(len(allg), bool)
    is_tissue[:n_g] = ~np.isin(ids, list(tool_ids))
    is_tool = np.zeros(len(allg), bool)
    is_tool[n_g:] = True
    name = name or data_dir.name
    return BuiltScene(
        name=name, camera=cam, frames=T, frame_dt=ident["frame_dt"], gaussians=allg, tissue_gaussians=is_tissue,
        tool_gaussians={tool_obj_id: is_tool}, particles=cat["x"], particle_ids=cat["ids"], particle_vol=cat["vol"],
        anchored=cat["anchored"], objects=objects, tools=[tool], box_lo=box_lo, box_size=size,
        gravity=np.asarray(ident["gravity"], float), damping=ident["damping"], ground_truth=gt, identification=idn,
        boundary_conditions=[{"type": "box_walls", "cells": 2},
                             {"type": "anchors", "object": "all_tissue", "back_face": True, "border": 0.005,
                              **({"release": {"center": contact[:2].tolist(), "radius": 0.02}} if interaction == "pull" else {})},
                             {"type": "static", "objects": [labels[c][0] for c in present if labels[c][2]]}],
        extrusion={"along": "viewing_rays", "thickness": 0.008}, particle_spacing=p_sp, source=str(data_dir),
        extra={"depth_source": depth_source, "interaction": interaction, "downscale": s,
               "layout": fr["layout"], "material_source": f"{', '.join(sorted(mat_sources))} x deterministic perturbation (seed {seed}), "
                                  "E capped at CFL 0.45 for the identification defaults"},
    )
