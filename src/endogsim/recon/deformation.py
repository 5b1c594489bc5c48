"""The deformation field of the tissue: HexPlane encoder + multi-head tiny-MLP decoder (Endo-4DGS).

For a canonical Gaussian (mu, q, log s, opacity logit, colour) and a time t:

    h = MLP(HexPlane(mu, t))
    mu'  = mu + extent * D_mu(h)          (position, metres; decoded in units of the scene extent)
    q'   = q + D_q(h)                     (rotation, unnormalised quaternion, as 4DGaussians)
    log s' = log s + D_s(h)               (scale)
    [o'  = o + D_o(h)]                    (opacity logit, optional)
    [c'  = c + D_c(h)]                    (DC colour, optional: lighting changes)

The last layer of every head starts at zero, so the untrained field is the identity: the coarse (static)
stage's Gaussians render unchanged when the deformation stage begins.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn as nn

from endogsim.gaussians.model import Gaussians
from endogsim.recon.hexplane import HexPlane

__all__ = ["DeformationConfig", "DeformationField"]


@dataclass
class DeformationConfig:
    """Architecture of the deformation field (saved with the weights so a run can be reloaded).

    Attributes:
        feature_dim: channels per HexPlane plane.
        resolution: base spatial plane resolution (x, y, z).
        time_resolution: plane resolution along t (0: half the number of frames, at least 2).
        multires: spatial resolution multipliers of the levels.
        width: hidden width of the MLPs.
        depth: hidden layers of the shared feature MLP.
        deform_opacity: add an opacity head.
        deform_color: add a DC-colour head.
    """

    feature_dim: int = 16
    resolution: tuple[int, int, int] = (32, 32, 32)
    time_resolution: int = 0
    multires: tuple[int, ...] = (1, 2)
    width: int = 64
    depth: int = 1
    deform_opacity: bool = False
    deform_color: bool = False


def _head(width: int, out: int) -> nn.Sequential:
    head = nn.Sequential(nn.ReLU(), nn.Linear(width, width), nn.ReLU(), nn.Linear(width, out))
    nn.init.zeros_(head[-1].weight)
    nn.init.zeros_(head[-1].bias)
    return head


class DeformationField(nn.Module):
    """Time-dependent deformation of canonical Gaussians.

    Args:
        config: architecture.
        bounds: [2, 3] box of the canonical Gaussians (metres), padded by the caller.
        time_range: (t0, t1) seconds.
        num_frames: T, used when ``config.time_resolution`` is 0.
    """

    def __init__(self, config: DeformationConfig, bounds: torch.Tensor, time_range: tuple[float, float],
                 num_frames: int) -> None:
        super().__init__()
        self.config = config
        tres = config.time_resolution or max(2, num_frames // 2)
        self.hexplane = HexPlane(bounds, time_range, config.feature_dim, tuple(config.resolution), tres,
                                 tuple(config.multires))
        layers: list[nn.Module] = [nn.Linear(self.hexplane.out_dim, config.width)]
        for _ in range(config.depth - 1):
            layers += [nn.ReLU(), nn.Linear(config.width, config.width)]
        self.feature_mlp = nn.Sequential(*layers)
        self.head_pos = _head(config.width, 3)
        self.head_rot = _head(config.width, 4)
        self.head_scale = _head(config.width, 3)
        self.head_opacity = _head(config.width, 1) if config.deform_opacity else None
        self.head_color = _head(config.width, 3) if config.deform_color else None
        b = torch.as_tensor(bounds, dtype=torch.float32)
        self.register_buffer("extent", (b[1] - b[0]).max().reshape(()).clone())

    def forward(self, g: Gaussians, t: float | torch.Tensor) -> Gaussians:
        """The Gaussians ``g`` (canonical, [N] each) deformed to time ``t`` (seconds); differentiable."""
        h = self.feature_mlp(self.hexplane(g.means, t))
        means = g.means + self.extent * self.head_pos(h)
        quats = g.quats + self.head_rot(h)
        log_scales = g.log_scales + self.head_scale(h)
        opacity = g.opacity_logits + self.head_opacity(h)[:, 0] if self.head_opacity is not None else g.opacity_logits
        sh = g.sh
        if self.head_color is not None:
            sh = torch.cat([sh[:, :1] + self.head_color(h)[:, None], sh[:, 1:]], 1)
        return Gaussians(means, quats, log_scales, opacity, sh, g.object_ids)

    def regularization(self, w_tv: float, w_time_smooth: float, w_time_l1: float) -> torch.Tensor:
        """Weighted sum of the HexPlane regularisers (K-Planes / 4DGaussians)."""
        hp = self.hexplane
        return w_tv * hp.plane_tv() + w_time_smooth * hp.time_smoothness() + w_time_l1 * hp.time_l1()

    def export(self) -> dict:
        """Everything needed to rebuild the field: ``torch.save`` this, reload with :meth:`from_export`."""
        return {"config": asdict(self.config), "bounds": self.hexplane.bounds.clone(),
                "time_range": self.hexplane.time_range.tolist(),
                "time_resolution": self.hexplane.levels[0][3].shape[-2], "state_dict": self.state_dict()}

    @staticmethod
    def from_export(data: dict) -> "DeformationField":
        cfg = dict(data["config"])
        cfg["resolution"] = tuple(cfg["resolution"])
        cfg["multires"] = tuple(cfg["multires"])
        cfg["time_resolution"] = int(data["time_resolution"])
        field = DeformationField(DeformationConfig(**cfg), data["bounds"], tuple(data["time_range"]), 2)
        field.load_state_dict(data["state_dict"])
        return field
