"""Real spherical harmonics up to degree 3, in the 3D Gaussian Splatting / gsplat convention.

The basis order, signs and constants are those of the reference 3DGS CUDA code, so colours from a PLY
written by any 3DGS trainer render the same here as there. Colour = max(SH(dir) + 0.5, 0).
"""

from __future__ import annotations

import torch

from endogsim.errors import ModelError
from endogsim.gaussians.model import SH_C0, sh_degree_from_count

SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """The real SH basis functions evaluated at unit directions.

    Args:
        degree: 0..3.
        dirs: [N, 3] directions (any length; normalised here).
    Returns:
        [N, (degree + 1)^2] basis values.
    """
    if not 0 <= degree <= 3:
        raise ModelError(f"SH degree {degree} is not in 0..3")
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int | None = None) -> torch.Tensor:
    """Raw SH value (before the +0.5 offset) per colour channel.

    Args:
        coeffs: [N, K, 3] coefficients, K = (d + 1)^2 for some d in 0..3; coeffs[:, 0] is the DC term.
        dirs: [N, 3] viewing directions (camera centre -> Gaussian), any length.
        degree: degree to evaluate (<= the one K implies); default: all of K.
    Returns:
        [N, 3] SH values.
    """
    full = sh_degree_from_count(coeffs.shape[1])
    degree = full if degree is None else degree
    if degree > full:
        raise ModelError(f"SH degree {degree} requested but only {coeffs.shape[1]} coefficients are stored")
    basis = sh_basis(degree, dirs)  # [N, K']
    return torch.einsum("nk,nkc->nc", basis, coeffs[:, : basis.shape[1]])


def sh_to_rgb(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int | None = None) -> torch.Tensor:
    """Colour [N, 3] seen along ``dirs`` [N, 3]: max(SH + 0.5, 0), as in 3DGS and gsplat."""
    return torch.clamp_min(eval_sh(coeffs, dirs, degree) + 0.5, 0.0)
