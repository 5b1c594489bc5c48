"""Constitutive models of the simulator: one module per model, and a name -> id registry.

A model is a Kirchhoff stress tau(F) = P F^T of the deformation gradient F with Lame parameters (mu,
lambda), written twice: a Warp ``@wp.func`` for the kernels and a PyTorch function for the pure-PyTorch
reference solver (:mod:`endogsim.physics.reference`), which the tests hold the kernels to. Every particle
reads the model of its object, so one simulation can hold neo-Hookean liver next to fixed-corotated fat.

Add a model with a module of its own that calls :func:`register_model` and one import line below; the
kernels dispatch over the registry when they are compiled (``wp.static``), so register before the first
simulation of a process.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import warp as wp

from endogsim.errors import MaterialError

__all__ = ["ConstitutiveModel", "MODELS", "register_model", "model_id", "model_names", "stress_torch"]


@dataclass(frozen=True)
class ConstitutiveModel:
    """One hyperelastic model.

    Attributes:
        name: the key used in material files (``MaterialRecord.model``).
        stress: Warp function (F: mat33, R: mat33, mu: float, lam: float) -> Kirchhoff stress tau (mat33),
            in the kernels' units (sim-box moduli). R is the polar rotation of F when ``uses_rotation``, else
            the identity (the kernel computes it once, so backward passes do not recompute it per call level).
        reference: PyTorch function (F [N,3,3], mu [N], lam [N]) -> tau [N,3,3] (any units, float64).
        description: one line for help texts.
        uses_rotation: whether ``stress`` reads R.
        stress_adjoint: optional Warp function (F, R, mu, lam, adj_tau: mat33) -> (adj_F: mat33, adj_mu, adj_lam),
            the adjoint of ``stress`` (R held fixed). With it the identification's backward pass runs the
            hand-written adjoint of the particle kernel (:func:`endogsim.physics.transfer_adjoints.
            particle_momentum_adjoint`) instead of Warp's generated one, which replays the kernel (3x its
            forward); without it (or with ``uses_rotation``), Warp's.
    """

    name: str
    stress: wp.Function
    reference: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]
    description: str
    uses_rotation: bool = False
    stress_adjoint: wp.Function | None = None

    @property
    def hand_adjoint(self) -> bool:
        """Whether the backward pass may use the hand-written particle-kernel adjoint for this model."""
        return self.stress_adjoint is not None and not self.uses_rotation


#: Registered models in id order (a particle's model id indexes this list).
MODELS: list[ConstitutiveModel] = []


def register_model(model: ConstitutiveModel) -> ConstitutiveModel:
    """Add ``model`` (its id is its position); a name registered twice is refused."""
    if any(m.name == model.name for m in MODELS):
        raise MaterialError(f"constitutive model {model.name!r} is already registered")
    MODELS.append(model)
    return model


def model_names() -> list[str]:
    return [m.name for m in MODELS]


def model_id(name: str) -> int:
    """The id of model ``name``; MaterialError naming the registered models otherwise."""
    for i, m in enumerate(MODELS):
        if m.name == name:
            return i
    raise MaterialError(f"constitutive model {name!r} is not simulated; choose one of {', '.join(model_names())}")


def stress_torch(model_ids: torch.Tensor, F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Reference Kirchhoff stress [N, 3, 3] of particles with per-particle model ids [N] (PyTorch)."""
    tau = torch.zeros_like(F)
    for i, m in enumerate(MODELS):
        sel = model_ids == i
        if bool(sel.any()):
            tau[sel] = m.reference(F[sel], mu[sel], lam[sel])
    return tau


# Built-in models, in id order.
from endogsim.physics.constitutive import fixed_corotated, neo_hookean, stvk  # noqa: E402,F401
