"""The schema of a scene folder's ``scene.json``: objects, camera, and the scenario to simulate.

A scene folder is written by :func:`endogsim.synth.synthesize` (a benchmark scene, whose objects carry
their ground-truth materials) or by :func:`endogsim.pipeline.scene_from_reconstruction` (a real video,
whose materials are unknown: ``E``, ``nu``, ``density`` null). It holds everything identification and
simulation need to rebuild the scenario; :func:`load_scene_spec` reads it back into :class:`SceneSpec`.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from endogsim.errors import DataError

__all__ = ["SceneObject", "ToolCapsule", "SimSettings", "ScenarioSpec", "CameraSpec", "SceneSpec", "load_scene_spec"]

SCENE_JSON_VERSION = 1


@dataclass
class SceneObject:
    """One object of the scene: id (in masks, Gaussians, particles), name, prior-table class, rigid flag,
    and its ground-truth material where known (a benchmark scene; null for a real video): ``E`` in Pa,
    ``nu``, ``density`` in kg/m^3, constitutive ``model``."""

    id: int
    name: str
    klass: str
    rigid: bool
    E: float | None = None
    nu: float | None = None
    density: float | None = None
    model: str = "fixed_corotated"


@dataclass
class ToolCapsule:
    """A kinematic tool collider: capsule from ``tip`` to ``end`` (metres, frame 0) of ``radius`` (metres);
    ``transforms`` [T][4][4] rigid world transforms per frame (frame 0 = identity); sticky contact."""

    object_id: int
    tip: list[float]
    end: list[float]
    radius: float
    transforms: list[list[list[float]]]
    contact: str = "sticky"

    def matrices(self) -> np.ndarray:
        """[T, 4, 4] float64 world transforms per frame."""
        return np.asarray(self.transforms, dtype=np.float64)


@dataclass
class SimSettings:
    """MPM discretisation: ``grid`` cells per edge of the cubic sim box, substep ``dt`` (s), ``substeps`` per
    frame, and the largest CFL number c_p dt / dx over the deformable objects at these settings."""

    grid: int
    dt: float
    substeps: int
    cfl: float


@dataclass
class ScenarioSpec:
    """The scenario: sim box (world corner ``box_lo`` and edge ``box_size`` in metres; world -> sim is
    (x - box_lo) / box_size), gravity (m/s^2, world), boundary conditions, tools, the particle layout and
    two discretisations: ``ground_truth`` (used to make the video) and ``identification`` (defaults)."""

    box_lo: list[float]
    box_size: float
    gravity: list[float]
    frame_dt: float
    damping: float
    boundary_conditions: list[dict[str, Any]]
    tools: list[ToolCapsule]
    particle_spacing: float
    extrusion: dict[str, Any]
    ground_truth: SimSettings
    identification: SimSettings


@dataclass
class CameraSpec:
    """Pinhole camera: K [3][3] pixels, image size, world->camera ``viewmat`` [4][4] (identity)."""

    K: list[list[float]]
    width: int
    height: int
    viewmat: list[list[float]]


@dataclass
class SceneSpec:
    """The parsed ``scene.json`` of a synthesized scene folder."""

    name: str
    seed: int
    frames: int
    objects: list[SceneObject]
    scenario: ScenarioSpec
    camera: CameraSpec
    depth_scale: float
    files: dict[str, str] = field(default_factory=dict)
    source: str = "procedural"
    version: int = SCENE_JSON_VERSION
    generator: int = 0

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        for o in d["objects"]:
            o["class"] = o.pop("klass")
        return d

    @property
    def deformable(self) -> list[SceneObject]:
        return [o for o in self.objects if not o.rigid]

    def object(self, name_or_id: str | int) -> SceneObject:
        for o in self.objects:
            if o.id == name_or_id or o.name == name_or_id:
                return o
        raise DataError(f"scene {self.name!r} has no object {name_or_id!r}")


def load_scene_spec(path: str | Path) -> SceneSpec:
    """Read ``scene.json`` (or the folder holding it) into a :class:`SceneSpec`."""
    p = Path(path)
    if p.is_dir():
        p = p / "scene.json"
    if not p.is_file():
        raise DataError(f"{p}: no scene.json (make one with `endogsim synth`)")
    try:
        d = json.loads(p.read_text())
        objects = [SceneObject(**{("klass" if k == "class" else k): v for k, v in o.items()}) for o in d["objects"]]
        sc = dict(d["scenario"])
        sc["tools"] = [ToolCapsule(**t) for t in sc["tools"]]
        sc["ground_truth"] = SimSettings(**sc["ground_truth"])
        sc["identification"] = SimSettings(**sc["identification"])
        return SceneSpec(
            name=d["name"], seed=d["seed"], frames=d["frames"], objects=objects, scenario=ScenarioSpec(**sc),
            camera=CameraSpec(**d["camera"]), depth_scale=d["depth_scale"], files=d.get("files", {}),
            source=d.get("source", "procedural"), version=d.get("version", SCENE_JSON_VERSION),
            generator=d.get("generator", 0),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{p}: malformed scene.json ({exc})") from exc
