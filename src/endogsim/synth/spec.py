"""Typed records of the benchmark: the suite file's scene specs and a synthesized folder's ``scene.json``.

``scene.json`` (written by :func:`endogsim.synth.synthesize`) holds everything identification needs to
rebuild the exact scenario; :func:`load_scene_truth` reads it back into :class:`SceneTruth`.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from endogsim.errors import DataError

__all__ = [
    "ObjectTruth", "ToolTruth", "SimSettings", "ScenarioTruth", "CameraTruth", "SceneTruth",
    "load_suite", "suite_scene_names", "scene_spec", "load_scene_truth",
]

SCENE_JSON_VERSION = 1
# Bump when the ground truth a seed produces changes (simulator physics, suite numerics): cached scenes
# with another revision are synthesized again (endogsim.bench.identify.ensure_scene).
GENERATOR_REVISION = 2


@dataclass
class ObjectTruth:
    """One object's ground truth. ``E`` in Pa, ``density`` in kg/m^3; ``klass`` is the prior-table key."""

    id: int
    name: str
    klass: str
    rigid: bool
    E: float
    nu: float
    density: float
    model: str = "fixed_corotated"


@dataclass
class ToolTruth:
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
class ScenarioTruth:
    """The scenario: sim box (world corner ``box_lo`` and edge ``box_size`` in metres; world -> sim is
    (x - box_lo) / box_size), gravity (m/s^2, world), boundary conditions, tools, the particle layout and
    two discretisations: ``ground_truth`` (used to make the video) and ``identification`` (defaults)."""

    box_lo: list[float]
    box_size: float
    gravity: list[float]
    frame_dt: float
    damping: float
    boundary_conditions: list[dict[str, Any]]
    tools: list[ToolTruth]
    particle_spacing: float
    extrusion: dict[str, Any]
    ground_truth: SimSettings
    identification: SimSettings


@dataclass
class CameraTruth:
    """Pinhole camera: K [3][3] pixels, image size, world->camera ``viewmat`` [4][4] (identity)."""

    K: list[list[float]]
    width: int
    height: int
    viewmat: list[list[float]]


@dataclass
class SceneTruth:
    """The parsed ``scene.json`` of a synthesized scene folder."""

    name: str
    seed: int
    frames: int
    objects: list[ObjectTruth]
    scenario: ScenarioTruth
    camera: CameraTruth
    depth_scale: float
    files: dict[str, str] = field(default_factory=dict)
    source: str = "procedural"
    version: int = SCENE_JSON_VERSION
    generator: int = GENERATOR_REVISION

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        for o in d["objects"]:
            o["class"] = o.pop("klass")
        return d

    @property
    def deformable(self) -> list[ObjectTruth]:
        return [o for o in self.objects if not o.rigid]

    def object(self, name_or_id: str | int) -> ObjectTruth:
        for o in self.objects:
            if o.id == name_or_id or o.name == name_or_id:
                return o
        raise DataError(f"scene {self.name!r} has no object {name_or_id!r}")


def load_scene_truth(path: str | Path) -> SceneTruth:
    """Read ``scene.json`` (or the folder holding it) into a :class:`SceneTruth`."""
    p = Path(path)
    if p.is_dir():
        p = p / "scene.json"
    if not p.is_file():
        raise DataError(f"{p}: no scene.json (make one with `endogsim synth`)")
    try:
        d = json.loads(p.read_text())
        objects = [ObjectTruth(**{("klass" if k == "class" else k): v for k, v in o.items()}) for o in d["objects"]]
        sc = dict(d["scenario"])
        sc["tools"] = [ToolTruth(**t) for t in sc["tools"]]
        sc["ground_truth"] = SimSettings(**sc["ground_truth"])
        sc["identification"] = SimSettings(**sc["identification"])
        return SceneTruth(
            name=d["name"], seed=d["seed"], frames=d["frames"], objects=objects, scenario=ScenarioTruth(**sc),
            camera=CameraTruth(**d["camera"]), depth_scale=d["depth_scale"], files=d.get("files", {}),
            source=d.get("source", "procedural"), version=d.get("version", SCENE_JSON_VERSION),
            generator=d.get("generator", 1),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{p}: malformed scene.json ({exc})") from exc


def load_suite() -> dict[str, Any]:
    """The packaged suite file ``endogsim/data/benchmark_suite.json`` as a dict."""
    text = resources.files("endogsim").joinpath("data/benchmark_suite.json").read_text()
    return json.loads(text)


def suite_scene_names() -> list[str]:
    return list(load_suite()["scenes"])


def scene_spec(name: str) -> dict[str, Any]:
    """The suite entry of scene ``name`` with the suite defaults filled in."""
    suite = load_suite()
    if name not in suite["scenes"]:
        raise DataError(f"unknown benchmark scene {name!r}; choose one of {', '.join(suite['scenes'])} "
                        "or use --from DATA_DIR")
    spec = dict(suite["defaults"])
    spec.update(suite["scenes"][name])
    spec["name"] = name
    return spec
