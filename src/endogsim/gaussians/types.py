"""Types shared by the renderer and its backends: numerical conventions and what a render returns.

Kept apart from :mod:`endogsim.gaussians.render` so that every backend (PyTorch, Warp, gsplat) imports
them without importing the dispatcher that imports the backends.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

__all__ = ["RasterConfig", "RenderOutput"]


@dataclass(frozen=True)
class RasterConfig:
    """Numerical conventions shared by every backend (they match gsplat's defaults, classic mode).

    Attributes:
        eps2d: dilation added to the 2D covariance (pixels^2); 0.3 makes every splat at least ~1 px wide.
        near_plane: Gaussians closer than this camera depth are culled (metres).
        far_plane: Gaussians farther than this camera depth are culled (metres).
        radius_clip: Gaussians whose 2D radius is <= this in both axes are culled (pixels).
        alpha_min: pairs with alpha below this are skipped (1/255).
        alpha_max: alpha is clamped to this (0.99) so 1 - alpha never vanishes.
        transmittance_min: compositing stops before the transmittance would drop to this (1e-4).
        max_pairs_per_chunk: bound on (pixel, Gaussian) pairs composited at once; sets the transient
            memory (~150 bytes per pair of a band).
    """

    eps2d: float = 0.3
    near_plane: float = 1e-3
    far_plane: float = 1e10
    radius_clip: float = 0.0
    alpha_min: float = 1.0 / 255.0
    alpha_max: float = 0.99
    transmittance_min: float = 1e-4
    max_pairs_per_chunk: int = 2_000_000



@dataclass
class RenderOutput:
    """What one render returns.

    Attributes:
        rgb: [H, W, 3] colour, background composited behind.
        depth: [H, W] expected camera z (metres), normalised by alpha; 0 where alpha is 0.
        alpha: [H, W] accumulated opacity in [0, 1].
        features: [H, W, F] composited extra channels (not normalised, no background), or None.
        meta: backend details: ``backend`` (str), ``means2d`` [N, 2] (pixels), ``radii`` [N, 2] int32
            (0 = culled), ``depths`` [N] camera z (metres), ``n_pairs`` (int: candidate (pixel, Gaussian)
            pairs of the torch backend, (tile, Gaussian) entries of warp and gsplat).
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    features: torch.Tensor | None = None
    meta: dict[str, Any] = field(default_factory=dict)
