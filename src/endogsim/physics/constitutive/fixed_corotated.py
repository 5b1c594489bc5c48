"""Fixed corotated elasticity (Stomakhin et al. 2012): the paper's and PhysGaussian's "jelly".

    tau = 2 mu (F - R) F^T + lambda (J - 1) J I,   R = polar rotation of F, J = det F.
"""

from __future__ import annotations

import torch
import warp as wp

from endogsim.physics.constitutive import ConstitutiveModel, register_model
from endogsim.physics.polar import polar_rotation_torch


@wp.func
def fixed_corotated_stress(F: wp.mat33, R: wp.mat33, mu: float, lam: float):
    J = wp.determinant(F)
    return 2.0 * mu * (F - R) * wp.transpose(F) + lam * (J - 1.0) * J * wp.identity(n=3, dtype=float)


def fixed_corotated_torch(F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    R = polar_rotation_torch(F)
    J = torch.linalg.det(F)
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    return 2 * mu[:, None, None] * (F - R) @ F.mT + (lam * (J - 1) * J)[:, None, None] * eye


register_model(ConstitutiveModel("fixed_corotated", fixed_corotated_stress, fixed_corotated_torch,
                                 "fixed corotated (PhysGaussian's jelly; the paper's)", uses_rotation=True))
