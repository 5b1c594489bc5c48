"""Tissue tracks: where the 4D reconstruction saw points of the tissue go, for identification's track term.

A reconstruction moves every tissue Gaussian through the clip with its deformation field. Those
trajectories are the reconstruction's own estimate of the tissue's motion, fitted to every pixel of every
frame, and they carry the motion signal directly: the render term sees motion only through texture
gradients, which the reconstruction's render residual swamps (DESIGN.md section 10). A scene folder built
from a reconstruction keeps a sample of them in ``tracks.npz``:

    index      [N] int64     the tracked Gaussians, as indices into ``gaussians_t0.ply``
    positions  [T, N, 3]     their centres at every frame (metres, world = frame 0's camera frame)

The track term (:mod:`endogsim.identify.loss`) compares their projections with the projections of the
same Gaussians driven by the simulated particles, in pixels: depth from a monocular reconstruction is the
least trustworthy coordinate, and the image plane is what the video measures.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from endogsim.errors import DataError
from endogsim.io.atomic import save_npz_atomic

__all__ = ["TissueTracks", "MAX_TRACKS", "carry_by", "sample_tracks", "write_tissue_tracks", "read_tissue_tracks"]

#: Tracked Gaussians kept per scene: enough to cover the tissue at a few pixels' spacing, few enough that
#: the file and the term stay small (a 63-frame clip: 3 MB).
MAX_TRACKS = 4000


@dataclass
class TissueTracks:
    """Reconstructed trajectories of some tissue Gaussians.

    Attributes:
        index: [N] int64 indices into the scene's Gaussians (``gaussians_t0.ply`` order).
        positions: [T, N, 3] float32 centres per frame (metres, world).
    """

    index: torch.Tensor
    positions: torch.Tensor

    def first(self, frames: int) -> "TissueTracks":
        """The tracks over the first ``frames`` frames."""
        return TissueTracks(self.index, self.positions[:frames])

    def carry(self, points: np.ndarray, use: np.ndarray | None = None, neighbours: int = 8) -> np.ndarray:
        """[T, N, 3] paths of world points ``points`` [N, 3] (metres, where they are at frame 0) moved by
        these tracks (:func:`carry_by`; only those where ``use`` [N_tracks] bool is set; default all)."""
        pos = self.positions.double().numpy()
        return carry_by(pos if use is None else pos[:, np.asarray(use, bool)], points, neighbours)


def carry_by(paths: np.ndarray, points: np.ndarray, neighbours: int = 8) -> np.ndarray:
    """[T, N, 3] paths of points ``points`` [N, 3] (metres, where they are at frame 0) carried by other points'
    ``paths`` [T, M, 3]: each by the inverse-square-distance weighted displacement of its ``neighbours``
    nearest of them at frame 0."""
    from scipy.spatial import cKDTree

    if paths.shape[1] == 0:
        raise DataError("no tissue track to carry points by")
    k = min(neighbours, paths.shape[1])
    dist, nn = cKDTree(paths[0]).query(np.asarray(points, float), k=k)
    dist, nn = dist.reshape(len(points), k), nn.reshape(len(points), k)
    w = 1.0 / np.maximum(dist, 1e-6) ** 2
    w /= w.sum(1, keepdims=True)
    return points[None] + np.einsum("nk,tnkc->tnc", w, paths[:, nn] - paths[0][nn])

def sample_tracks(object_ids: torch.Tensor, opacities: torch.Tensor, tissue_ids: list[int],
                  max_tracks: int = MAX_TRACKS, min_opacity: float = 0.5) -> torch.Tensor:
    """Indices [N] of the Gaussians to track: opaque ones of the tissue objects, evenly strided (deterministic),
    at most ``max_tracks``."""
    keep = torch.isin(object_ids, torch.as_tensor(tissue_ids)) & (opacities.detach() >= min_opacity)
    idx = torch.nonzero(keep).flatten()
    if len(idx) > max_tracks:
        idx = idx[torch.linspace(0, len(idx) - 1, max_tracks).round().long()]
    return idx


def write_tissue_tracks(path: str | Path, tracks: TissueTracks) -> Path:
    """Write ``tracks`` to an .npz (atomically)."""
    return save_npz_atomic(path, index=tracks.index.cpu().numpy().astype(np.int64),
                           positions=tracks.positions.detach().cpu().numpy().astype(np.float32))


def read_tissue_tracks(path: str | Path, num_gaussians: int, frames: int) -> TissueTracks:
    """Read ``tracks.npz``, checked against the scene: indices within its ``num_gaussians`` Gaussians and at
    least ``frames`` frames of finite positions (only those are kept)."""
    p = Path(path)
    try:
        with np.load(p) as d:
            index, pos = d["index"].astype(np.int64), d["positions"].astype(np.float32)
    except (OSError, KeyError, ValueError) as exc:
        raise DataError(f"{p}: unreadable tissue tracks ({exc})") from None
    if index.ndim != 1 or pos.ndim != 3 or pos.shape[1:] != (len(index), 3):
        raise DataError(f"{p}: positions {pos.shape} do not match index {index.shape} (expected [T, N, 3], [N])")
    if len(index) and (index.min() < 0 or index.max() >= num_gaussians):
        raise DataError(f"{p}: track indices outside the scene's {num_gaussians} Gaussians")
    if pos.shape[0] < frames:
        raise DataError(f"{p}: {pos.shape[0]} frames of tracks for a {frames}-frame scene")
    if not np.isfinite(pos[:frames]).all():
        raise DataError(f"{p}: non-finite track positions")
    return TissueTracks(torch.from_numpy(index), torch.from_numpy(pos[:frames]))
