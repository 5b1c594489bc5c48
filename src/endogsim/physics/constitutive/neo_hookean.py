"""Compressible neo-Hookean elasticity: needs no SVD or polar decomposition, so its gradient is exact.

    tau = mu (F F^T - I) + lambda ln J I,   J = det F (kept >= 1e-4 so an inverted particle pushes back
    instead of producing NaN).
"""

from __future__ import annotations

import torch
import warp as wp

from endogsim.physics.constitutive import ConstitutiveModel, register_model


@wp.func
def neo_hookean_stress(F: wp.mat33, R: wp.mat33, mu: float, lam: float):
    J = wp.determinant(F)
    I = wp.identity(n=3, dtype=float)
    return mu * (F * wp.transpose(F) - I) + lam * wp.log(wp.max(J, 1.0e-4)) * I


def neo_hookean_torch(F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    J = torch.linalg.det(F).clamp_min(1e-4)
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    return mu[:, None, None] * (F @ F.mT - eye) + (lam * torch.log(J))[:, None, None] * eye


register_model(ConstitutiveModel("neo_hookean", neo_hookean_stress, neo_hookean_torch,
                                 "compressible neo-Hookean (no SVD: exact gradients)"))
