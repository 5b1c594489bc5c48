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


@wp.func
def neo_hookean_stress_adjoint(F: wp.mat33, R: wp.mat33, mu: float, lam: float, adj_tau: wp.mat33):
    """d/dF, d/dmu, d/dlam of adj_tau : tau (d ln J / dF = F^-T; the clamp passes no gradient)."""
    J = wp.determinant(F)
    I = wp.identity(n=3, dtype=float)
    tr = wp.trace(adj_tau)
    adj_F = mu * ((adj_tau + wp.transpose(adj_tau)) * F)
    if J > 1.0e-4:
        adj_F = adj_F + (lam * tr) * wp.transpose(wp.inverse(F))
    adj_mu = wp.ddot(adj_tau, F * wp.transpose(F) - I)
    adj_lam = tr * wp.log(wp.max(J, 1.0e-4))
    return adj_F, adj_mu, adj_lam


def neo_hookean_torch(F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    J = torch.linalg.det(F).clamp_min(1e-4)
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    return mu[:, None, None] * (F @ F.mT - eye) + (lam * torch.log(J))[:, None, None] * eye


register_model(ConstitutiveModel("neo_hookean", neo_hookean_stress, neo_hookean_torch,
                                 "compressible neo-Hookean (no SVD: exact gradients)",
                                 stress_adjoint=neo_hookean_stress_adjoint))
