"""The Gaussian splat model shared by every stage.

Parameters are stored unconstrained, as in 3D Gaussian Splatting: log-scales, opacity logits and
unnormalised quaternions (w, x, y, z), so an optimiser can update them freely. Colour is a set of
real spherical-harmonic coefficients per Gaussian, degree 0 to 3.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import torch

from endogsim.errors import ModelError

SH_C0 = 0.28209479177387814  # Y_0^0: colour = SH_C0 * f_dc + 0.5 at degree 0


def sh_coeff_count(degree: int) -> int:
    """Number of SH coefficients per colour channel at ``degree`` (1, 4, 9 or 16)."""
    return (degree + 1) ** 2


def sh_degree_from_count(count: int) -> int:
    degree = math.isqrt(count) - 1
    if (degree + 1) ** 2 != count or not 0 <= degree <= 3:
        raise ModelError(f"{count} SH coefficients per channel is not (d+1)^2 for a degree d in 0..3")
    return degree


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """Degree-0 coefficient that renders as ``rgb`` in [0, 1]: any shape [..., 3]."""
    return (rgb - 0.5) / SH_C0


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from quaternions.

    Args:
        quats: [N, 4] quaternions (w, x, y, z), any norm (normalised here).
    Returns:
        [N, 3, 3] rotation matrices.
    """
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Quaternions (w, x, y, z) with w >= 0 from rotation matrices [N, 3, 3] -> [N, 4]."""
    m = R
    t = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # Shepperd's method: pick the largest of 4 candidate denominators for stability.
    cands = torch.stack(
        [1 + t, 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
         1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]],
        dim=-1,
    )
    k = cands.argmax(dim=-1)
    s = torch.sqrt(cands.gather(-1, k[..., None]).squeeze(-1).clamp_min(1e-12)) * 2
    qs = [
        torch.stack([s / 4, (m[..., 2, 1] - m[..., 1, 2]) / s, (m[..., 0, 2] - m[..., 2, 0]) / s, (m[..., 1, 0] - m[..., 0, 1]) / s], -1),
        torch.stack([(m[..., 2, 1] - m[..., 1, 2]) / s, s / 4, (m[..., 0, 1] + m[..., 1, 0]) / s, (m[..., 0, 2] + m[..., 2, 0]) / s], -1),
        torch.stack([(m[..., 0, 2] - m[..., 2, 0]) / s, (m[..., 0, 1] + m[..., 1, 0]) / s, s / 4, (m[..., 1, 2] + m[..., 2, 1]) / s], -1),
        torch.stack([(m[..., 1, 0] - m[..., 0, 1]) / s, (m[..., 0, 2] + m[..., 2, 0]) / s, (m[..., 1, 2] + m[..., 2, 1]) / s, s / 4], -1),
    ]
    q = torch.stack(qs, dim=-2).gather(-2, k[..., None, None].expand(*k.shape, 1, 4)).squeeze(-2)
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0)


def covariance_from_scale_rot(scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """3D covariances Sigma = R S S^T R^T.

    Args:
        scales: [N, 3] standard deviations along the Gaussian's axes (metres, positive).
        quats: [N, 4] quaternions (w, x, y, z).
    Returns:
        [N, 3, 3] symmetric positive-definite covariances (metres^2).
    """
    M = quat_to_rotmat(quats) * scales[..., None, :]
    return M @ M.transpose(-1, -2)


def covariance_to_scale_rot(covs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Log axis scales [N, 3] (log metres) and quaternions [N, 4] (w, x, y, z) of covariances [N, 3, 3].

    The inverse of :func:`covariance_from_scale_rot` (eigen-decomposition; the eigenvector frame is made
    right-handed so it is a rotation): a deformed Gaussian (covariance F Sigma F^T) written back as a model.
    """
    sym = 0.5 * (covs + covs.mT).double()
    evals, evecs = torch.linalg.eigh(sym)
    flip = torch.linalg.det(evecs) < 0
    evecs[flip, :, 0] = -evecs[flip, :, 0]
    log_scales = 0.5 * torch.log(evals.clamp_min(1e-24))
    return log_scales.to(covs.dtype), rotmat_to_quat(evecs).to(covs.dtype)


@dataclass
class Gaussians:
    """A set of N Gaussian splats.

    Attributes:
        means: [N, 3] centres in world coordinates (metres).
        quats: [N, 4] rotations as quaternions (w, x, y, z), unnormalised.
        log_scales: [N, 3] natural log of the axis standard deviations (metres).
        opacity_logits: [N] logit of opacity.
        sh: [N, K, 3] SH coefficients, K = (degree + 1)^2; sh[:, 0] is the DC term.
        object_ids: [N] int64 object id of each Gaussian (see the scene's label table).
    """

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor
    object_ids: torch.Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expect = {
            "means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,), "object_ids": (n,),
        }
        for name, shape in expect.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ModelError(f"Gaussians.{name} has shape {tuple(getattr(self, name).shape)}, expected {shape}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ModelError(f"Gaussians.sh has shape {tuple(self.sh.shape)}, expected ({n}, K, 3)")
        sh_degree_from_count(self.sh.shape[1])

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_count(self.sh.shape[1])

    @property
    def scales(self) -> torch.Tensor:
        """[N, 3] axis standard deviations (metres)."""
        return self.log_scales.exp()

    @property
    def opacities(self) -> torch.Tensor:
        """[N] opacities in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def colors_dc(self) -> torch.Tensor:
        """[N, 3] view-independent colour (degree-0 SH) in [0, 1] before clamping."""
        return self.sh[:, 0] * SH_C0 + 0.5

    def covariances(self) -> torch.Tensor:
        """[N, 3, 3] world-space covariances."""
        return covariance_from_scale_rot(self.scales, self.quats)

    def to(self, device: torch.device | str) -> "Gaussians":
        return Gaussians(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})

    def detach(self) -> "Gaussians":
        return Gaussians(**{f.name: getattr(self, f.name).detach() for f in fields(self)})

    def subset(self, index: torch.Tensor) -> "Gaussians":
        """The Gaussians selected by a boolean mask [N] or an index tensor."""
        return Gaussians(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def with_(self, **changes: torch.Tensor) -> "Gaussians":
        """A copy with some attributes replaced (shapes are checked again)."""
        return replace(self, **changes)

    @staticmethod
    def concat(parts: list["Gaussians"]) -> "Gaussians":
        degree = max(p.sh_degree for p in parts)
        k = sh_coeff_count(degree)
        padded = [p.with_(sh=torch.nn.functional.pad(p.sh, (0, 0, 0, k - p.sh.shape[1]))) for p in parts]
        return Gaussians(**{f.name: torch.cat([getattr(p, f.name) for p in padded]) for f in fields(Gaussians)})

    @staticmethod
    def from_points(
        points: torch.Tensor,
        colors: torch.Tensor,
        scales: torch.Tensor | float,
        object_ids: torch.Tensor | int = 0,
        opacity: float = 0.95,
        sh_degree: int = 0,
    ) -> "Gaussians":
        """Isotropic Gaussians at ``points`` [N, 3] with colours [N, 3] in [0, 1].

        ``scales`` is a per-point [N] or [N, 3] standard deviation, or one value for all (metres).
        """
        n = points.shape[0]
        dtype = points.dtype
        s = torch.as_tensor(scales, dtype=dtype).expand(n) if not torch.is_tensor(scales) or scales.ndim == 0 else scales
        s = s[:, None].expand(n, 3) if s.ndim == 1 else s
        sh = torch.zeros(n, sh_coeff_count(sh_degree), 3, dtype=dtype)
        sh[:, 0] = rgb_to_sh_dc(colors.to(dtype))
        ids = torch.as_tensor(object_ids, dtype=torch.int64).expand(n).clone()
        quats = torch.zeros(n, 4, dtype=dtype)
        quats[:, 0] = 1
        logit = math.log(opacity / (1 - opacity))
        return Gaussians(points.clone(), quats, s.log().clone(), torch.full((n,), logit, dtype=dtype), sh, ids)
