"""Per-object materials as the simulator reads them: arrays indexed by object id.

:class:`ObjectMaterials` holds, for every object id 0..M-1 (``M = max id + 1``; ids no particle carries
get harmless values), Young's modulus E (Pa), Poisson's ratio nu, density (kg/m^3), the constitutive model
(an id of :mod:`endogsim.physics.constitutive`) and the von Mises yield stress (Pa; 0 = purely elastic).
E, nu and density may require gradients: :func:`endogsim.physics.mpm_rollout` differentiates through them.

    mats = ObjectMaterials.of(E=[0, 5e3], nu=[0, 0.45], density=[1, 1060], model=["fixed_corotated", "neo_hookean"])
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch

from endogsim.errors import MaterialError
from endogsim.physics.constitutive import model_id

__all__ = ["ObjectMaterials"]


@dataclass
class ObjectMaterials:
    """Materials per object id.

    Attributes:
        E: [M] Young's modulus (Pa); may require grad.
        nu: [M] Poisson's ratio; may require grad.
        density: [M] kg/m^3; may require grad.
        model: [M] int64 constitutive model ids (:func:`endogsim.physics.constitutive.model_id`); -1 for an
            object the simulator cannot integrate (rigid, fluid), refused if particles carry it.
        yield_stress: [M] von Mises yield stress (Pa); 0 = purely elastic.
    """

    E: torch.Tensor
    nu: torch.Tensor
    density: torch.Tensor
    model: torch.Tensor
    yield_stress: torch.Tensor

    #: The fields gradients flow to, in the order the simulator's autograd op takes them.
    DIFFERENTIABLE = ("E", "nu", "density")

    def __post_init__(self) -> None:
        M = self.E.shape[0] if self.E.ndim == 1 else -1
        for name in (f.name for f in fields(self)):
            a = getattr(self, name)
            if a.ndim != 1 or a.shape[0] != M:
                raise MaterialError(f"ObjectMaterials.{name} has shape {tuple(a.shape)}; every field must be [M] "
                                    f"with M = {self.E.shape[0] if self.E.ndim else '?'} objects")

    def __len__(self) -> int:
        return self.E.shape[0]

    def detached(self) -> "ObjectMaterials":
        """A copy without gradients (cloned: later in-place changes of these tensors do not reach it)."""
        return ObjectMaterials(**{f.name: getattr(self, f.name).detach().clone() for f in fields(self)})

    @staticmethod
    def of(E, nu, density, model: str | Sequence[str] = "fixed_corotated",
           yield_stress=None) -> "ObjectMaterials":
        """From per-object sequences or tensors (tensors keep their graph); ``model`` one name for all or
        one per object; ``yield_stress`` None (elastic) or per object (Pa, 0 or None entries elastic)."""
        def as_t(a):
            return a if isinstance(a, torch.Tensor) else torch.as_tensor(np.asarray(a, np.float64))

        E, nu, density = (as_t(a).reshape(-1) for a in (E, nu, density))
        M = E.shape[0]
        names = [model] * M if isinstance(model, str) else list(model)
        if len(names) != M:
            raise MaterialError(f"{len(names)} constitutive models for {M} objects")
        ys = torch.zeros(M, dtype=torch.float64) if yield_stress is None else torch.as_tensor(
            [0.0 if y is None else float(y) for y in yield_stress], dtype=torch.float64)
        return ObjectMaterials(E, nu, density, torch.tensor([model_id(n) for n in names], dtype=torch.int64), ys)

    def used(self, object_ids: torch.Tensor) -> "ObjectMaterials":
        """The entries of the ids in ``object_ids`` (detached, float64), in ascending id order; refuses ids
        outside 0..M-1."""
        ids = torch.unique(object_ids.detach().cpu()).long()
        if int(ids.min()) < 0 or int(ids.max()) >= len(self):
            raise MaterialError(f"particle object ids span [{int(ids.min())}, {int(ids.max())}], "
                                f"but materials are given for ids 0..{len(self) - 1}")
        unsimulated = [int(i) for i in ids if int(self.model[i]) < 0]
        if unsimulated:
            raise MaterialError(f"particles carry object id(s) {unsimulated} whose material model the simulator "
                                "does not implement (rigid or fluid objects have no particles)")
        pick = lambda a: a.detach().cpu().double()[ids]  # noqa: E731
        return ObjectMaterials(pick(self.E), pick(self.nu), pick(self.density), self.model.cpu()[ids],
                               pick(self.yield_stress))
