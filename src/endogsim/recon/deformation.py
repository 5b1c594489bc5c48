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
import torch.nn.functional as F

from endogsim.errors import DataError
from endogsim.gaussians.model import Gaussians
from endogsim.recon.hexplane import HexPlane
from endogsim.typed import check_typed_fields

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

    def __post_init__(self) -> None:
        check_typed_fields(self, "deformation.")
        if len(self.resolution) != 3 or min(self.resolution) < 2:
            raise DataError(f"deformation.resolution {list(self.resolution)} must be 3 integers >= 2 (x, y, z)")
        if not self.multires or min(self.multires) < 1:
            raise DataError(f"deformation.multires {list(self.multires)} must be integers >= 1, at least one")
        if self.time_resolution == 1 or self.time_resolution < 0:
            raise DataError(f"deformation.time_resolution {self.time_resolution} must be >= 2 (or 0: automatic)")
        for name, least in (("feature_dim", 1), ("width", 1), ("depth", 0)):
            if getattr(self, name) < least:
                raise DataError(f"deformation.{name} {getattr(self, name)} must be >= {least}")


class _Heads(nn.Module):
    """The decoder heads, each ``ReLU -> Linear(width, width) -> ReLU -> Linear(width, out_k)``.

    The heads share their input, so their hidden layers run as one GEMM of width ``width * n_heads``, and
    their output layers as one GEMM with the block-diagonal matrix of the heads' weights: the same function
    as separate heads, at a fraction of the cost on a CPU (slicing the wide hidden layer per head would make
    autograd zero-fill and sum a copy of it for every head). The output layers start at zero so the
    untrained field is the identity.
    """

    def __init__(self, width: int, outs: dict[str, int]) -> None:
        super().__init__()
        self.names = list(outs)
        self.width = width
        self.hidden = nn.Linear(width, width * len(outs))
        self.out = nn.ModuleDict({name: nn.Linear(width, k) for name, k in outs.items()})
        for layer in self.out.values():
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def forward(self, h: torch.Tensor) -> dict[str, torch.Tensor]:
        hidden = torch.relu(self.hidden(torch.relu(h)))
        layers = [self.out[name] for name in self.names]
        weight = torch.block_diag(*(layer.weight for layer in layers))  # [sum of outs, width * n_heads]
        bias = torch.cat([layer.bias for layer in layers])
        outs = F.linear(hidden, weight, bias).split([layer.out_features for layer in layers], 1)
        return dict(zip(self.names, outs))


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
        outs = {"pos": 3, "rot": 4, "scale": 3}
        if config.deform_opacity:
            outs["opacity"] = 1
        if config.deform_color:
            outs["color"] = 3
        self.heads = _Heads(config.width, outs)
        b = torch.as_tensor(bounds, dtype=torch.float32)
        self.register_buffer("extent", (b[1] - b[0]).max().reshape(()).clone())

    def forward(self, g: Gaussians, t: float | torch.Tensor) -> Gaussians:
        """The Gaussians ``g`` (canonical, [N] each) deformed to time ``t`` (seconds: a scalar, or [N], one
        per Gaussian); differentiable."""
        d = self.heads(self.feature_mlp(self.hexplane(g.means, t)))
        means = g.means + self.extent * d["pos"]
        quats = g.quats + d["rot"]
        log_scales = g.log_scales + d["scale"]
        opacity = g.opacity_logits + d["opacity"][:, 0] if "opacity" in d else g.opacity_logits
        sh = g.sh
        if "color" in d:
            sh = torch.cat([sh[:, :1] + d["color"][:, None], sh[:, 1:]], 1)
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
        field.load_state_dict(_fuse_legacy_heads(dict(data["state_dict"]), field.heads.names))
        return field


def _fuse_legacy_heads(state: dict, names: list[str]) -> dict:
    """Convert the state dict of run folders written before the heads were fused (one ``head_<name>``
    Sequential per head) to the fused layout of :class:`_Heads`."""
    if f"head_{names[0]}.1.weight" not in state:
        return state
    state["heads.hidden.weight"] = torch.cat([state.pop(f"head_{n}.1.weight") for n in names])
    state["heads.hidden.bias"] = torch.cat([state.pop(f"head_{n}.1.bias") for n in names])
    for n in names:
        state[f"heads.out.{n}.weight"] = state.pop(f"head_{n}.3.weight")
        state[f"heads.out.{n}.bias"] = state.pop(f"head_{n}.3.bias")
    return state
