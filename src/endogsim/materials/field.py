"""The object-wise material field: one record per object, JSON in physical units, and its optimisation view.

The simulator indexes per-object arrays by object id, so :meth:`MaterialField.simulator_materials` returns
:class:`~endogsim.physics.materials.ObjectMaterials` of length ``max(object_id) + 1``, each record's
constitutive model and yield stress included.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, model_validator

from endogsim.errors import MaterialError
from endogsim.io.atomic import write_json_atomic
from endogsim.physics.constitutive import model_names as constitutive_model_names
from endogsim.physics.materials import ObjectMaterials

#: Material kinds the simulator does not integrate as elastic solids (rigid instruments, fluids).
NON_SIMULATED_MODELS = ("rigid", "fluid")
Regime = Literal["in_vivo", "ex_vivo_tensile"]


class MaterialRecord(BaseModel):
    """The material of one object. E, E_min/E_max and yield_stress in Pa, density in kg/m^3.

    ``model`` is a constitutive model the simulator implements (:mod:`endogsim.physics.constitutive`:
    "neo_hookean", "fixed_corotated", ...) or "rigid" / "fluid"; ``yield_stress`` (von Mises) makes the
    object elastoplastic, None keeps it elastic.

    ``source`` says where the value came from: "manual", "prior", "mllm:<model>", "replay:<model>",
    "prior (mllm fallback: <reason>)" or "identified".
    """

    model_config = ConfigDict(extra="forbid")

    name: str
    object_id: int
    klass: str
    model: str = "neo_hookean"
    rigid: bool = False
    E: float
    nu: float
    density: float
    E_min: float | None = None
    E_max: float | None = None
    yield_stress: float | None = None
    source: str = "manual"
    confidence: float | None = None
    regime: Regime = "in_vivo"

    @model_validator(mode="after")
    def _physical(self) -> "MaterialRecord":
        # MaterialError is not a ValueError, so pydantic lets it through unchanged to the user.
        who = f"material of object {self.object_id} ({self.name!r})"
        if not math.isfinite(self.E) or self.E <= 0:
            raise MaterialError(f"{who}: Young's modulus E = {self.E} Pa must be finite and > 0")
        if not math.isfinite(self.nu) or not (-1.0 < self.nu < 0.5):
            raise MaterialError(f"{who}: Poisson ratio nu = {self.nu} must lie in (-1, 0.5)")
        if not math.isfinite(self.density) or self.density <= 0:
            raise MaterialError(f"{who}: density = {self.density} kg/m^3 must be finite and > 0")
        for k in ("E_min", "E_max"):
            v = getattr(self, k)
            if v is not None and (not math.isfinite(v) or v <= 0):
                raise MaterialError(f"{who}: {k} = {v} Pa must be finite and > 0")
        if self.E_min is not None and self.E_max is not None and self.E_min > self.E_max:
            raise MaterialError(f"{who}: E range [{self.E_min}, {self.E_max}] Pa is empty")
        if self.confidence is not None and not (0.0 <= self.confidence <= 1.0):
            raise MaterialError(f"{who}: confidence {self.confidence} must lie in [0, 1]")
        if self.model == "rigid" and not self.rigid:
            raise MaterialError(f"{who}: model 'rigid' needs rigid = true")
        known = constitutive_model_names() + list(NON_SIMULATED_MODELS)
        if self.model not in known:
            raise MaterialError(f"{who}: material model {self.model!r} is not one of {', '.join(known)}")
        if self.yield_stress is not None and (not math.isfinite(self.yield_stress) or self.yield_stress <= 0):
            raise MaterialError(f"{who}: yield_stress = {self.yield_stress} Pa must be finite and > 0 (or null)")
        return self


@dataclass
class MaterialParams:
    """The optimisation view of a field (see :meth:`MaterialField.to_params`).

    Attributes:
        log10_E: [M] log10 of E in Pa, requires_grad; M = number of deformable objects (1 if global).
        nu_raw: [M] unconstrained Poisson parameter, nu = lo + (hi - lo) * sigmoid(nu_raw); requires_grad.
        object_ids: ids of the deformable objects, in order; with ``global_material`` every one maps to slot 0.
        nu_bounds: (lo, hi) of the sigmoid map.
        global_material: True if all deformable objects share one (E, nu) pair.
    """

    log10_E: torch.Tensor
    nu_raw: torch.Tensor
    object_ids: list[int]
    nu_bounds: tuple[float, float]
    global_material: bool = False

    def slot(self, object_id: int) -> int:
        return 0 if self.global_material else self.object_ids.index(object_id)

    def E(self) -> torch.Tensor:
        """[M] Young's modulus in Pa (differentiable)."""
        return torch.pow(10.0, self.log10_E)

    def nu(self) -> torch.Tensor:
        """[M] Poisson ratio in (lo, hi) (differentiable)."""
        lo, hi = self.nu_bounds
        return lo + (hi - lo) * torch.sigmoid(self.nu_raw)


def nu_to_raw(nu: float, lo: float, hi: float) -> float:
    """Inverse of nu = lo + (hi - lo) sigmoid(raw); nu is clamped just inside (lo, hi)."""
    eps = 1e-6 * (hi - lo)
    t = (min(max(nu, lo + eps), hi - eps) - lo) / (hi - lo)
    return math.log(t / (1.0 - t))


@dataclass
class MaterialField:
    """All objects' materials. ``records`` has one entry per object id (ids unique)."""

    records: list[MaterialRecord]
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        ids = [r.object_id for r in self.records]
        if len(set(ids)) != len(ids):
            raise MaterialError(f"material field: duplicate object ids {sorted(ids)}")
        if any(i < 0 for i in ids):
            raise MaterialError(f"material field: negative object id in {sorted(ids)}")
        self.records = sorted(self.records, key=lambda r: r.object_id)

    # ---- lookup -------------------------------------------------------------------------------------------------
    def __getitem__(self, object_id: int) -> MaterialRecord:
        for r in self.records:
            if r.object_id == object_id:
                return r
        raise MaterialError(f"material field has no object id {object_id} (ids: {[r.object_id for r in self.records]})")

    @property
    def deformable(self) -> list[MaterialRecord]:
        return [r for r in self.records if not r.rigid]

    # ---- JSON ---------------------------------------------------------------------------------------------------
    def to_json(self) -> dict:
        return {"units": {"E": "Pa", "density": "kg/m^3"}, "meta": self.meta,
                "objects": [r.model_dump() for r in self.records]}

    @classmethod
    def from_json(cls, obj: dict, where: str = "material field") -> "MaterialField":
        if not isinstance(obj, dict) or not isinstance(obj.get("objects"), list):
            raise MaterialError(f"{where}: expected a JSON object with an 'objects' list")
        recs = []
        for i, o in enumerate(obj["objects"]):
            try:
                recs.append(MaterialRecord.model_validate(o))
            except MaterialError as exc:  # a value the record refuses: name the file and the entry
                raise MaterialError(f"{where}: objects[{i}]: {exc}") from None
            except Exception as exc:  # pydantic ValidationError: name the entry, one line per field
                errors = getattr(exc, "errors", None)
                what = "; ".join(f"{'.'.join(str(k) for k in e['loc'])}: {e['msg']} (got {e.get('input')!r:.40})"
                                 for e in errors()) if callable(errors) else str(exc)
                raise MaterialError(f"{where}: objects[{i}] is malformed: {what}") from None
        return cls(recs, meta=dict(obj.get("meta") or {}))

    def save(self, path: str | Path) -> Path:

        return write_json_atomic(path, self.to_json())

    @classmethod
    def load(cls, path: str | Path) -> "MaterialField":
        path = Path(path)
        try:
            obj = json.loads(path.read_text())
        except FileNotFoundError:
            raise MaterialError(f"{path}: material file not found") from None
        except json.JSONDecodeError as exc:
            raise MaterialError(f"{path}: not valid JSON ({exc})") from None
        return cls.from_json(obj, where=str(path))

    # ---- arrays for the simulator -------------------------------------------------------------------------------
    def simulator_materials(self, params: MaterialParams | None = None) -> ObjectMaterials:
        """Per-object arrays for the simulator (length max id + 1): E [Pa], nu, density [kg/m^3], the
        constitutive model and the yield stress of every record.

        Args:
            params: optional optimisation view; its (differentiable) E and nu replace the deformable records'.
        Ids without a record get E = nu = density = NaN so that a particle carrying one is refused by the
        simulator, not simulated silently; records whose model the simulator does not implement ("rigid",
        "fluid") get model id -1, refused likewise if particles carry them.
        """
        n = max((r.object_id for r in self.records), default=-1) + 1
        E, nu, rho, ys = (np.full(n, np.nan) for _ in range(4))
        model = np.full(n, -1, dtype=np.int64)
        simulated = constitutive_model_names()
        for r in self.records:
            i = r.object_id
            E[i], nu[i], rho[i], ys[i] = r.E, r.nu, r.density, r.yield_stress or 0.0
            model[i] = simulated.index(r.model) if r.model in simulated else -1
        t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
        E_t, nu_t = t(E), t(nu)
        if params is not None:
            # Scatter differentiable values into the per-object table (torch.where keeps the graph).
            idx = torch.zeros(n, dtype=torch.long)
            mask = torch.zeros(n, dtype=torch.bool)
            for oid in params.object_ids:
                idx[oid], mask[oid] = params.slot(oid), True
            E_t = torch.where(mask, params.E().double()[idx], E_t)
            nu_t = torch.where(mask, params.nu().double()[idx], nu_t)
        return ObjectMaterials(E_t, nu_t, t(rho), torch.as_tensor(model), t(np.nan_to_num(ys)))

    # ---- optimisation view --------------------------------------------------------------------------------------
    def to_params(
        self, global_material: bool = False, nu_bounds: tuple[float, float] = (0.0, 0.499), device: str | torch.device = "cpu"
    ) -> MaterialParams:
        """log10 E and raw nu per deformable object as leaf tensors with requires_grad; rigid objects stay frozen.

        ``global_material`` ties every deformable object to one shared pair (the "without material field"
        ablation), initialised at the geometric mean of E and the mean nu.
        """
        lo, hi = nu_bounds
        if not (-1.0 < lo < hi < 0.5):
            raise MaterialError(f"nu bounds ({lo}, {hi}) must satisfy -1 < lo < hi < 0.5")
        defo = self.deformable
        ids = [r.object_id for r in defo]
        if global_material and defo:
            log_e = [float(np.mean([math.log10(r.E) for r in defo]))]
            nus = [float(np.mean([r.nu for r in defo]))]
        else:
            log_e = [math.log10(r.E) for r in defo]
            nus = [r.nu for r in defo]
        raw = [nu_to_raw(v, lo, hi) for v in nus]
        t = lambda v: torch.tensor(v, dtype=torch.float64, device=device).requires_grad_(True)  # noqa: E731
        return MaterialParams(t(log_e), t(raw), ids, (lo, hi), global_material)

    def from_params(self, params: MaterialParams, source: str = "identified") -> "MaterialField":
        """A new field with the deformable objects' E, nu taken from ``params`` (source ``identified``)."""
        E = params.E().detach().cpu().numpy()
        nu = params.nu().detach().cpu().numpy()
        recs = []
        for r in self.records:
            if not r.rigid and r.object_id in params.object_ids:
                s = params.slot(r.object_id)
                r = r.model_copy(update={"E": float(E[s]), "nu": float(nu[s]), "source": source, "confidence": None})
                r = MaterialRecord.model_validate(r.model_dump())  # re-check physical bounds
            recs.append(r)
        return MaterialField(recs, meta=dict(self.meta))
