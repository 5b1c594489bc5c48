"""Saint Venant-Kirchhoff elasticity: linear stress in the Green strain (large rotations, small strains).

    E_G = (F^T F - I) / 2,   S = 2 mu E_G + lambda tr(E_G) I,   tau = F S F^T.

It softens under strong compression (no barrier against inversion): use it for moderate strains.
"""

from __future__ import annotations

import torch
import warp as wp

from endogsim.physics.constitutive import ConstitutiveModel, register_model


@wp.func
def stvk_stress(F: wp.mat33, R: wp.mat33, mu: float, lam: float):
    I = wp.identity(n=3, dtype=float)
    green = 0.5 * (wp.transpose(F) * F - I)
    S = 2.0 * mu * green + lam * wp.trace(green) * I
    return F * S * wp.transpose(F)


@wp.func
def stvk_stress_adjoint(F: wp.mat33, R: wp.mat33, mu: float, lam: float, adj_tau: wp.mat33):
    """d/dF, d/dmu, d/dlam of adj_tau : tau, through tau = F S F^T and S(E_G)."""
    I = wp.identity(n=3, dtype=float)
    green = 0.5 * (wp.transpose(F) * F - I)
    S = 2.0 * mu * green + lam * wp.trace(green) * I
    adj_S = wp.transpose(F) * adj_tau * F
    adj_green = 2.0 * mu * adj_S + lam * wp.trace(adj_S) * I
    adj_F = (adj_tau + wp.transpose(adj_tau)) * F * S + 0.5 * F * (adj_green + wp.transpose(adj_green))
    return adj_F, 2.0 * wp.ddot(adj_S, green), wp.trace(adj_S) * wp.trace(green)


def stvk_torch(F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    green = 0.5 * (F.mT @ F - eye)
    S = 2 * mu[:, None, None] * green + (lam * green.diagonal(dim1=-2, dim2=-1).sum(-1))[:, None, None] * eye
    return F @ S @ F.mT


register_model(ConstitutiveModel("stvk", stvk_stress, stvk_torch, "Saint Venant-Kirchhoff (Green strain)",
                                 stress_adjoint=stvk_stress_adjoint))
