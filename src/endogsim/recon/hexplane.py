"""HexPlane spatio-temporal encoder (K-Planes / 4DGaussians / Endo-4DGS).

A 4D field over (x, y, z, t) factorised into six 2D feature planes: xy, xz, yz (space) and xt, yt, zt
(space-time). The feature of a point is the element-wise *product* of its six bilinearly sampled plane
features, at each of several resolutions, the resolutions *concatenated*. Time planes start at 1 so an
untrained field is time-independent (the product leaves the spatial features unchanged).

Coordinates are normalised to [-1, 1] with an axis-aligned box (``bounds``, metres) and the time span
(seconds); points outside the box read the border value. On CPU the sampling runs in Warp kernels
(:mod:`endogsim.recon.hexplane_warp`); ``grid_sample`` is the reference and the path elsewhere.

Regularisers (K-Planes): :meth:`HexPlane.plane_tv` (first differences on every plane: spatial
smoothness), :meth:`HexPlane.time_smoothness` (second differences along t: smooth motion) and
:meth:`HexPlane.time_l1` (|1 - time plane|: prefer static).
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["HexPlane", "PLANE_AXES"]

#: Axis pairs of the six planes; 0, 1, 2 = x, y, z and 3 = t.
PLANE_AXES = ((0, 1), (0, 2), (1, 2), (0, 3), (1, 3), (2, 3))
#: PLANE_AXES as the two [6] int32 index vectors (first axes, second axes) the Warp sampler takes.
_PLANE_AXES_INT32 = tuple(torch.tensor([ax[i] for ax in PLANE_AXES], dtype=torch.int32) for i in (0, 1))


class HexPlane(nn.Module):
    """Multi-resolution six-plane feature field.

    Args:
        bounds: [2, 3] (min, max) corners of the box the planes cover (metres).
        time_range: (t0, t1) seconds mapped to [-1, 1].
        feature_dim: channels per plane.
        resolution: (Rx, Ry, Rz) base spatial resolution of the planes.
        time_resolution: base resolution along t (e.g. half the number of frames).
        multires: spatial resolution multipliers, one level each (time resolution is not multiplied).
    """

    def __init__(self, bounds: torch.Tensor, time_range: tuple[float, float], feature_dim: int = 16,
                 resolution: tuple[int, int, int] = (32, 32, 32), time_resolution: int = 16,
                 multires: tuple[int, ...] = (1, 2)) -> None:
        super().__init__()
        self.register_buffer("bounds", torch.as_tensor(bounds, dtype=torch.float32).clone())
        self.register_buffer("time_range", torch.tensor([float(time_range[0]), float(time_range[1])]))
        self.feature_dim = feature_dim
        self.multires = tuple(multires)
        self.levels = nn.ModuleList()
        for m in self.multires:
            res = [r * m for r in resolution] + [time_resolution]
            planes = nn.ParameterList()
            for a, b in PLANE_AXES:
                # plane [1, C, R_b, R_a]: grid_sample reads (coord_a, coord_b) as (x, y)
                if b == 3:
                    init = torch.ones(1, feature_dim, res[b], res[a])
                else:
                    init = torch.empty(1, feature_dim, res[b], res[a]).uniform_(0.1, 0.5)
                planes.append(nn.Parameter(init))
            self.levels.append(planes)

    @property
    def out_dim(self) -> int:
        return self.feature_dim * len(self.multires)

    def normalize(self, xyz: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
        """[N, 4] coordinates in [-1, 1] from points [N, 3] (metres) and time(s) (seconds, scalar or [N])."""
        lo, hi = self.bounds[0], self.bounds[1]
        p = (xyz - lo) / (hi - lo).clamp_min(1e-9) * 2 - 1
        t0, t1 = self.time_range[0], self.time_range[1]
        tt = torch.as_tensor(t, dtype=xyz.dtype, device=xyz.device)
        tn = ((tt - t0) / (t1 - t0).clamp_min(1e-9) * 2 - 1).expand(xyz.shape[0])
        return torch.cat([p, tn[:, None]], 1).clamp(-1, 1)

    def forward(self, xyz: torch.Tensor, t: torch.Tensor | float, backend: str = "auto") -> torch.Tensor:
        """Features [N, out_dim] of points ``xyz`` [N, 3] (metres) at time ``t`` (seconds: a scalar or [N]).

        ``backend``: "torch" (``grid_sample``, the reference), "warp" (:mod:`endogsim.recon.hexplane_warp`,
        float32) or "auto": warp for float32 on CPU, where it is several times faster, torch otherwise.
        """
        coords = self.normalize(xyz, t)
        if backend == "warp" or (backend == "auto" and xyz.device.type == "cpu" and xyz.dtype == torch.float32):
            from endogsim.recon.hexplane_warp import hexplane_features_warp

            return hexplane_features_warp(coords, list(self._planes(None)), _PLANE_AXES_INT32)
        feats = []
        for planes in self.levels:
            f = None
            for (a, b), plane in zip(PLANE_AXES, planes):
                grid = coords[:, [a, b]].view(1, -1, 1, 2).to(plane.dtype)
                s = F.grid_sample(plane, grid, mode="bilinear", padding_mode="border", align_corners=True)
                s = s.view(self.feature_dim, -1).t()
                f = s if f is None else f * s
            feats.append(f)
        return torch.cat(feats, 1)

    def _planes(self, time: bool | None):
        for planes in self.levels:
            for (a, b), plane in zip(PLANE_AXES, planes):
                if time is None or (b == 3) == time:
                    yield plane

    def plane_tv(self) -> torch.Tensor:
        """Total variation (mean squared first differences) over all planes, both directions."""
        total = 0.0
        for p in self._planes(None):
            total = total + (p[..., 1:, :] - p[..., :-1, :]).square().mean() + (p[..., :, 1:] - p[..., :, :-1]).square().mean()
        return total

    def time_smoothness(self) -> torch.Tensor:
        """Mean squared second difference along t of the space-time planes (t is the plane's rows)."""
        total = 0.0
        for p in self._planes(True):
            if p.shape[-2] >= 3:
                total = total + (p[..., 2:, :] - 2 * p[..., 1:-1, :] + p[..., :-2, :]).square().mean()
        return total

    def time_l1(self) -> torch.Tensor:
        """Mean |1 - plane| of the space-time planes (pulls towards a static field)."""
        return sum((1 - p).abs().mean() for p in self._planes(True))
