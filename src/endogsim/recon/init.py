"""Initial Gaussians from depth and masks.

* Tissue: pixels of the first training frame on a ``stride`` grid, back-projected with their depth and
  the intrinsics K, coloured by the pixel. Then, for every later training frame, grid pixels that are
  tissue there but were never tissue before (hidden by a tool, or outside the labels, in all earlier
  frames) are back-projected from that frame: the tissue a tool uncovers gets Gaussians too. With a
  fixed endoscope "before" is the same pixel; with a moving one (``flows`` and ``rotations`` given) the
  seen-so-far mask is carried from frame to frame by the backward optical flow, so the tissue that
  enters the field of view at the border counts as new as well, and new points are rotated from their
  frame's camera into the world (frame 0's camera) by the initial camera rotation.
* Tools: each tool object starts from its first training frame where it covers enough pixels (its
  *reference* frame), back-projected likewise; with non-metric depth it is placed at
  ``tool_depth_factor`` times the tissue depth (instruments are between the camera and the tissue).
  Per-frame translations start from the motion of the mask centroid, in-plane rotations from the change
  of the mask's principal axis; frames where the tool is not visible (it left the view, is occluded, or
  the frame is held out) start from the interpolation of its visible neighbours, or the nearest visible
  pose beyond them (:func:`~endogsim.recon.tools.fill_untrained_frames`): held, never extrapolated.

Every Gaussian gets the object id of its pixel. Spacing: a Gaussian's standard deviation is ``scale``
(default 0.6) times the back-projected grid spacing, so neighbours overlap and the first render has no
holes. A smaller ``scale`` still covers the image (the 2D footprint reaches ~3 sigma) with fewer
(pixel, Gaussian) pairs per pixel, which is what the CPU rasteriser's cost grows with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from endogsim.gaussians.model import Gaussians, quat_to_rotmat
from endogsim.recon.tools import axis_angle_to_quat, fill_untrained_frames

__all__ = ["backproject", "InitResult", "initial_gaussians"]

MIN_TOOL_PIXELS = 20


def backproject(u: np.ndarray, v: np.ndarray, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points [M, 3] (metres) of pixel centres (u + 0.5, v + 0.5) at depths ``z`` [M].

    Args:
        u, v: [M] integer pixel column and row.
        z: [M] depth (metres, camera z).
        K: [3, 3] intrinsics.
    """
    x = (u + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (v + 0.5 - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], -1)


def _points(frame: np.ndarray, depth: np.ndarray, ids: np.ndarray, select: np.ndarray, K: np.ndarray,
            stride: int, scale: float) -> tuple[np.ndarray, ...]:
    """Points, colours, ids, standard deviations and pixel centres [M, 2] of the ``select`` pixels."""
    v, u = np.nonzero(select)
    z = depth[v, u]
    pts = backproject(u, v, z, K)
    sigma = scale * stride * z / K[0, 0]
    return pts, frame[v, u], ids[v, u], sigma, np.stack([u + 0.5, v + 0.5], 1).astype(np.float32)


def _carry_mask(seen: np.ndarray, bwd: np.ndarray) -> np.ndarray:
    """``seen`` [H, W] bool of a frame, moved into the next frame by ``bwd`` [H, W, 2], the flow from the
    next frame back to this one (a pixel p of the next frame was at p + bwd(p)); outside the image: unseen."""
    import cv2

    H, W = seen.shape
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    x, y = xs + bwd[..., 0], ys + bwd[..., 1]
    # flow that ends less than a pixel outside is noise at the edge, not tissue entering the view
    x = np.where((x > -1.5) & (x < W + 0.5), np.clip(x, 0, W - 1), x)
    y = np.where((y > -1.5) & (y < H + 0.5), np.clip(y, 0, H - 1), y)
    moved = cv2.remap(seen.astype(np.uint8), x, y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return moved > 0


def _camera_to_world(pts: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Points [M, 3] in the camera of a frame whose world->camera rotation is the axis-angle ``rotation``
    [3] (radians), in world coordinates (x_world = R^T x_cam)."""
    R = quat_to_rotmat(axis_angle_to_quat(torch.as_tensor(rotation, dtype=torch.float32))[None])[0].numpy()
    return pts @ R


def _gaussians(pts, cols, ids, sigma, opacity: float, sh_degree: int) -> Gaussians:
    return Gaussians.from_points(torch.as_tensor(pts, dtype=torch.float32), torch.as_tensor(cols, dtype=torch.float32),
                                 torch.as_tensor(sigma, dtype=torch.float32), torch.as_tensor(ids, dtype=torch.int64),
                                 opacity=opacity, sh_degree=sh_degree)


def _principal_angle(mask: np.ndarray) -> float:
    v, u = np.nonzero(mask)
    u, v = u - u.mean(), v - v.mean()
    return 0.5 * math.atan2(2 * (u * v).mean(), (u * u).mean() - (v * v).mean())


@dataclass
class InitResult:
    """Initial state. tissue/tools: Gaussians; tool_ids [K]; centers [K, 3] (metres); ref_frames [K];
    init_translation [K, T, 3] (metres); init_rotation [K, T, 3] (axis-angle, radians);
    visible [K, T] bool (the tool has mask pixels in that training frame); tissue_pixels [N_tissue, 2]
    pixel centre each tissue Gaussian was back-projected from, in frame tissue_frames [N_tissue]."""

    tissue: Gaussians
    tools: Gaussians
    tool_ids: list[int]
    centers: torch.Tensor
    ref_frames: list[int]
    init_translation: torch.Tensor
    init_rotation: torch.Tensor
    visible: torch.Tensor
    n_disoccluded: int
    tissue_pixels: np.ndarray
    tissue_frames: np.ndarray


def initial_gaussians(prep, stride: int = 2, opacity: float = 0.7, sh_degree: int = 0,
                      tool_depth_factor: float = 0.85, scale: float = 0.6,
                      flows: list[np.ndarray] | None = None, rotations: np.ndarray | None = None) -> InitResult:
    """Initial tissue and tool Gaussians of a :class:`~endogsim.recon.data.PreparedScene`.

    Args:
        prep: the prepared scene.
        stride: back-project every ``stride``-th pixel in x and y.
        scale: initial standard deviation in units of the grid spacing.
        flows: for a moving endoscope, the backward flows between consecutive training frames
            (``bwd`` of :func:`~endogsim.priors.tracks.consecutive_flows`), which carry the seen-so-far mask.
        rotations: for a moving endoscope, [T, 3] initial world->camera rotations (axis-angle, radians;
            :func:`~endogsim.priors.camera.estimate_camera_rotations`) placing later frames' points.
    """
    sc = prep.scene
    T, H, W = sc.num_frames, sc.height, sc.width
    K = sc.K
    grid = np.zeros((H, W), dtype=bool)
    grid[stride // 2:: stride, stride // 2:: stride] = True
    depth = prep.depth
    ids = sc.object_masks
    train = prep.train

    # tissue of the first training frame, then what later frames uncover
    f0 = train[0]
    seen = prep.tissue[f0].copy()
    parts = [_points(sc.frames[f0], depth[f0], ids[f0], grid & prep.tissue[f0] & (depth[f0] > 0), K, stride, scale)]
    part_frames = [f0]
    n_dis = 0
    for i, t in enumerate(train[1:]):
        if flows is not None:
            seen = _carry_mask(seen, flows[i])
        new = grid & prep.tissue[t] & ~seen & (depth[t] > 0)
        if new.any():
            pts, *rest = _points(sc.frames[t], depth[t], ids[t], new, K, stride, scale)
            if rotations is not None:
                pts = _camera_to_world(pts, rotations[t])
            parts.append((pts, *rest))
            part_frames.append(t)
            n_dis += int(new.sum())
        seen |= prep.tissue[t]
    cat = [np.concatenate([p[i] for p in parts]) for i in range(5)]
    tissue = _gaussians(*cat[:4], opacity, sh_degree)
    tissue_frames = np.concatenate([np.full(len(p[0]), f, dtype=np.int64) for p, f in zip(parts, part_frames)])

    # tools
    tool_ids, centers, refs, tools = [], [], [], []
    trans = torch.zeros(len(prep.tool_ids), T, 3)
    rot = torch.zeros(len(prep.tool_ids), T, 3)
    visible = torch.zeros(len(prep.tool_ids), T, dtype=torch.bool)
    for oid in prep.tool_ids:
        counts = [(ids[t] == oid).sum() for t in train]
        ok = [t for t, c in zip(train, counts) if c >= MIN_TOOL_PIXELS]
        if not ok:
            continue
        k = len(tool_ids)
        ref = ok[0]
        m = ids[ref] == oid
        zmap = depth[ref] if prep.depth_metric else depth[ref] * tool_depth_factor
        sel = m & (zmap > 0)
        sub = sel & grid if (sel & grid).sum() >= MIN_TOOL_PIXELS else sel
        pts, cols, oids, sigma, _ = _points(sc.frames[ref], zmap, ids[ref], sub, K, stride, scale)
        tools.append(_gaussians(pts, cols, oids, sigma, opacity, sh_degree))
        c = pts.mean(0)
        tool_ids.append(oid)
        centers.append(c)
        refs.append(ref)
        v0, u0 = np.nonzero(m)
        uc0, vc0 = u0.mean(), v0.mean()
        a0 = _principal_angle(m)
        zc = float(c[2])
        for t in ok:
            mt = ids[t] == oid
            vt, ut = np.nonzero(mt)
            d = backproject(np.array([ut.mean()]), np.array([vt.mean()]), np.array([zc]), K)[0] - \
                backproject(np.array([uc0]), np.array([vc0]), np.array([zc]), K)[0]
            trans[k, t] = torch.as_tensor(d, dtype=torch.float32)
            da = (_principal_angle(mt) - a0 + math.pi / 2) % math.pi - math.pi / 2
            rot[k, t, 2] = da  # about the optical axis (image-plane rotation)
            visible[k, t] = True
    nk = len(tool_ids)
    trans, rot, visible = trans[:nk], rot[:nk], visible[:nk]
    fill_untrained_frames([trans, rot], visible)
    if tools:
        tool_g = Gaussians.concat(tools)
    else:
        tool_g = _gaussians(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0,), np.int64), np.zeros((0,)), opacity, sh_degree)
    return InitResult(tissue, tool_g, tool_ids,
                      torch.as_tensor(np.array(centers).reshape(nk, 3), dtype=torch.float32), refs,
                      trans, rot, visible, n_dis, cat[4], tissue_frames)
