"""Point tracks from chained optical flow: where each seeded tissue point is in every frame.

Endoscopic tissue moves by tens of pixels over a clip (EndoNeRF ``pulling``: 8 px on average by frame
33 at 320x256, 25 px at the 95th percentile). A photometric loss only sees motion within a Gaussian's
footprint, so a deformation field started at the identity cannot find such motions; tracks give it the
correspondences directly (:mod:`endogsim.recon.train` supervises the projected Gaussian centres with them).

:func:`track_points` chains the flow of a :class:`~endogsim.priors.flow.FlowEstimator` (DIS offline by
default) between consecutive frames of a given list, forward and backward from each point's seed frame,
with bilinear flow lookups at sub-pixel positions. A step is kept only where

* forward and backward flow agree: ``|f(p) + b(p + f(p))|^2 <= 0.01 (|f|^2 + |b|^2) + 0.25`` (px^2;
  Sundaram et al. 2010), which rejects occlusions (tools passing over) and flow failures;
* within :data:`MOTION_BOUNDARY_RADIUS_PX` of a pixel a track may not land on (an instrument, the field of
  view's border) in either frame, the point lies off a motion boundary: ``|grad f_x(p)|^2 + |grad f_y(p)|^2
  <= 0.01 |f(p)|^2 + 0.002`` (Sundaram et al. 2010). A flow estimator smooths an instrument's motion into the
  tissue beside it (DIS: about 1.3 px of error within 5 px of a sliding probe whose tissue stays still, 0.4
  px at 5-15 px, nothing beyond), consistently forward and backward, so the first test keeps those steps;
  this one drops them. It is not applied in the open tissue: there real video's flow noise (specular
  highlights, texture-poor tissue) fails it on about 4% of the steps, and as a lost track is never taken up
  again those losses compound over a clip (EndoNeRF pulling: the tracked share 0.48 -> 0.33 with the test
  everywhere, and the held-out PSNR 0.6 dB lower);
* the point lands inside the image on an allowed pixel (tissue, not tool, not the field-of-view border).

A track that fails a step stays lost in that direction (no re-acquisition: a lost point is ambiguous).
Only the frames in ``frames_used`` are read, so test frames never inform training.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from endogsim.errors import DataError

__all__ = ["PointTracks", "track_points", "flow_lookup", "flow_gradient_sq", "near_forbidden", "consecutive_flows"]

MOTION_BOUNDARY_RADIUS_PX = 16.0
"""How far (pixels) from a forbidden pixel the motion-boundary test applies: past DIS's smear (15 px)."""


@dataclass
class PointTracks:
    """Tracks of K points over T frames.

    Attributes:
        positions: [K, T, 2] float32 pixel coordinates (x, y; pixel (i, j) has its centre at (j + 0.5, i + 0.5));
            meaningful only where ``valid``.
        valid: [K, T] bool, the point was tracked into that frame (always True at its seed frame).
        seed_frame: [K] int64, the frame each point was seeded in.
    """

    positions: torch.Tensor
    valid: torch.Tensor
    seed_frame: torch.Tensor

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def to(self, device: torch.device | str) -> "PointTracks":
        return PointTracks(self.positions.to(device), self.valid.to(device), self.seed_frame.to(device))


def flow_lookup(field: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Bilinear samples [M, C] of an image-like ``field`` [H, W, C] at pixel coordinates ``points`` [M, 2]
    (centres at +0.5); values at the border are repeated outside the image."""
    H, W = field.shape[:2]
    img = torch.as_tensor(np.ascontiguousarray(field), dtype=torch.float32).permute(2, 0, 1)[None]
    grid = torch.as_tensor(points, dtype=torch.float32).clone()
    grid[:, 0] = grid[:, 0] / W * 2 - 1
    grid[:, 1] = grid[:, 1] / H * 2 - 1
    out = F.grid_sample(img, grid[None, None], mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0].T.numpy()


def flow_gradient_sq(flow: np.ndarray) -> np.ndarray:
    """[H, W, 1] squared spatial gradient |grad f_x|^2 + |grad f_y|^2 of a flow field ``flow`` [H, W, 2]
    (pixels; central differences)."""
    out = np.zeros(flow.shape[:2], np.float64)
    for c in range(2):
        for g in np.gradient(flow[..., c].astype(np.float64)):
            out += g * g
    return out[..., None]


def near_forbidden(allowed: np.ndarray, radius: float = MOTION_BOUNDARY_RADIUS_PX) -> np.ndarray:
    """[H, W] bool: pixels within ``radius`` pixels of a pixel that is not ``allowed`` [H, W] (bool)."""
    allowed = np.asarray(allowed, bool)
    if allowed.all():
        return np.zeros(allowed.shape, bool)
    return cv2.distanceTransform(allowed.astype(np.uint8), cv2.DIST_L2, 5) < radius


def _step(points: np.ndarray, fwd: np.ndarray, bwd: np.ndarray, allowed: np.ndarray,
          boundary_gradient_sq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move ``points`` by the flow ``fwd`` [H, W, 2]; returns the new points and which steps are reliable.
    ``boundary_gradient_sq`` [H, W, 1]: the flow's :func:`flow_gradient_sq` where the motion-boundary test
    applies, 0 elsewhere."""
    H, W = allowed.shape
    f = flow_lookup(fwd, points)
    moved = points + f
    b = flow_lookup(bwd, moved)
    consistent = ((f + b) ** 2).sum(1) <= 0.01 * ((f * f).sum(1) + (b * b).sum(1)) + 0.25
    consistent &= flow_lookup(boundary_gradient_sq, points)[:, 0] <= 0.01 * (f * f).sum(1) + 0.002
    inside = (moved[:, 0] >= 0) & (moved[:, 0] < W) & (moved[:, 1] >= 0) & (moved[:, 1] < H)
    xi = np.clip(moved[:, 0].astype(np.int64), 0, W - 1)
    yi = np.clip(moved[:, 1].astype(np.int64), 0, H - 1)
    return moved, consistent & inside & allowed[yi, xi]


def consecutive_flows(frames: np.ndarray, frames_used: list[int], estimator=None
                      ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Forward and backward optical flow between consecutive entries of ``frames_used``.

    Returns:
        (fwd, bwd), each a list of len(frames_used) - 1 fields [H, W, 2] (pixels): ``fwd[i]`` moves a pixel
        of frame ``frames_used[i]`` to frame ``frames_used[i + 1]``, ``bwd[i]`` the reverse.
    """
    from endogsim.priors.flow import DISFlow

    est = estimator or DISFlow("medium")
    used = list(frames_used)
    fwd = [est.estimate(frames[a], frames[b]) for a, b in zip(used[:-1], used[1:])]
    bwd = [est.estimate(frames[b], frames[a]) for a, b in zip(used[:-1], used[1:])]
    return fwd, bwd


def track_points(frames: np.ndarray, allowed: np.ndarray, seeds: np.ndarray, seed_frames: np.ndarray,
                 frames_used: list[int], estimator=None,
                 flows: tuple[list[np.ndarray], list[np.ndarray]] | None = None) -> PointTracks:
    """Track seeded points through ``frames_used`` by chaining optical flow.

    Args:
        frames: [T, H, W, 3] RGB in [0, 1].
        allowed: [T, H, W] bool, pixels a track may land on (tissue).
        seeds: [K, 2] pixel coordinates of the points in their seed frames.
        seed_frames: [K] seed frame of each point; each must be in ``frames_used``.
        frames_used: increasing frame indices to track through (the training frames); the flow is computed
            between consecutive entries only.
        estimator: a :class:`~endogsim.priors.flow.FlowEstimator` (default: DIS, offline).
        flows: the :func:`consecutive_flows` of ``frames_used`` when already computed (``estimator`` unused).
    Returns:
        :class:`PointTracks` over all T frames (frames not in ``frames_used`` are never valid).
    """
    T = frames.shape[0]
    used = list(frames_used)
    if sorted(set(used)) != used:
        raise DataError("track_points: frames_used must be increasing and unique")
    pos_in_list = {f: i for i, f in enumerate(used)}
    seed_frames = np.asarray(seed_frames, dtype=np.int64)
    if not np.isin(seed_frames, used).all():
        raise DataError("track_points: every seed frame must be one of frames_used")
    seeds = np.asarray(seeds, dtype=np.float32)
    K = len(seeds)
    positions = np.zeros((K, T, 2), dtype=np.float32)
    valid = np.zeros((K, T), dtype=bool)
    positions[np.arange(K), seed_frames] = seeds
    valid[np.arange(K), seed_frames] = True
    fwd, bwd = flows if flows is not None else consecutive_flows(frames, used, estimator)
    near = {f: near_forbidden(allowed[f]) for f in used}
    pairs = [(near[a] | near[b])[..., None] for a, b in zip(used[:-1], used[1:])]
    fwd_g2 = [flow_gradient_sq(f) * m for f, m in zip(fwd, pairs)]
    bwd_g2 = [flow_gradient_sq(b) * m for b, m in zip(bwd, pairs)]
    seed_idx = np.array([pos_in_list[int(f)] for f in seed_frames], dtype=np.int64)
    # Forward sweep: a track is live at list position i when seeded at or before i and not yet lost.
    live = np.zeros(K, dtype=bool)
    for i in range(len(used) - 1):
        a, b = used[i], used[i + 1]
        live |= seed_idx == i
        idx = np.nonzero(live)[0]
        if len(idx):
            moved, ok = _step(positions[idx, a], fwd[i], bwd[i], allowed[b], fwd_g2[i])
            positions[idx[ok], b] = moved[ok]
            valid[idx[ok], b] = True
            live[idx[~ok]] = False
    live[:] = False
    for i in range(len(used) - 1, 0, -1):
        a, b = used[i], used[i - 1]
        live |= seed_idx == i
        idx = np.nonzero(live)[0]
        if len(idx):
            moved, ok = _step(positions[idx, a], bwd[i - 1], fwd[i - 1], allowed[b], bwd_g2[i - 1])
            positions[idx[ok], b] = moved[ok]
            valid[idx[ok], b] = True
            live[idx[~ok]] = False
    return PointTracks(torch.as_tensor(positions), torch.as_tensor(valid), torch.as_tensor(seed_frames))
