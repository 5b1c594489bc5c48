"""The schema of a scene folder's ``scene.json``: objects, camera, and the scenario to simulate.

A scene folder is written by :func:`endogsim.synth.synthesize` (a benchmark scene, whose objects carry
their ground-truth materials) or by :func:`endogsim.pipeline.scene_from_reconstruction` (a real video,
whose materials are unknown: ``E``, ``nu``, ``density`` null). It holds everything identification and
simulation need to rebuild the scenario; :func:`load_scene_spec` reads it back into :class:`SceneSpec` and
checks it: ground-truth materials are possible ones (the checks of
:class:`~endogsim.materials.field.MaterialRecord`), the images cover ``frames``, and every path in
``files`` stays inside the folder.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from endogsim.errors import DataError, MaterialError
from endogsim.materials.field import MaterialRecord

__all__ = ["SceneObject", "ToolCapsule", "SimSettings", "ObjectBoundary", "ScenarioSpec", "CameraSpec", "SceneSpec",
           "load_scene_spec", "scene_spec_from_json", "IMAGES_PATTERN"]

SCENE_JSON_VERSION = 2

#: Where a scene folder's frames are (``files.images``, with one %d for the frame number) unless it says.
IMAGES_PATTERN = "images/frame-%06d.color.png"


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

    @property
    def has_material(self) -> bool:
        """Whether the ground-truth material is given (E, nu and density)."""
        return self.E is not None and self.nu is not None and self.density is not None

    def material_record(self) -> MaterialRecord:
        """The ground-truth material as a :class:`~endogsim.materials.field.MaterialRecord` (source "ground
        truth"; its checks apply: E > 0, -1 < nu < 0.5, density > 0, a known model)."""
        if not self.has_material:
            raise MaterialError(f"object {self.name!r} (id {self.id}) has no ground-truth material (E, nu, density)")
        return MaterialRecord(name=self.name, object_id=self.id, klass=self.klass, rigid=self.rigid,
                              model="rigid" if self.rigid else self.model, E=self.E, nu=self.nu,
                              density=self.density, source="ground truth")


@dataclass
class ToolCapsule:
    """A kinematic tool collider: capsule from ``tip`` to ``end`` (metres, frame 0) of ``radius`` (metres);
    ``transforms`` [T][4][4] rigid world transforms per frame (frame 0 = identity). ``contact``: "sticky"
    (the capsule pushes the tissue it touches) or "grasp" (a grasper: besides pushing, its jaws hold the
    tissue within :data:`endogsim.physics.particles.GRASP_MARGIN` of its tip sphere at frame 0, which then
    moves rigidly with it). ``visible`` [T] bool: the frames where the video shows the instrument (None: every
    frame); where it does not (it left the view, or is occluded), its collider keeps its held pose but its
    Gaussians are not rendered, as in the video."""

    object_id: int
    tip: list[float]
    end: list[float]
    radius: float
    transforms: list[list[list[float]]]
    contact: Literal["sticky", "grasp"] = "sticky"
    visible: list[bool] | None = None

    def __post_init__(self) -> None:
        if self.contact not in ("sticky", "grasp"):
            raise ValueError(f"tool {self.object_id}: contact {self.contact!r} is not sticky|grasp")
        if self.visible is not None and not all(isinstance(v, bool) for v in self.visible):
            raise ValueError(f"tool {self.object_id}: visible must be a list of true/false per frame")

    def matrices(self) -> np.ndarray:
        """[T, 4, 4] float64 world transforms per frame."""
        return np.asarray(self.transforms, dtype=np.float64)


@dataclass
class SimSettings:
    """MPM discretisation: ``grid`` cells per edge of the cubic sim box, substep ``dt`` (s), ``substeps`` per
    frame (the least; the CFL rule may take more for stiffer materials), the largest CFL number c_p dt / dx
    over the deformable objects at these settings, and the ``particle_spacing`` (metres) of the lattice
    that fills the tissue (half a cell: two particles per cell and axis)."""

    grid: int
    dt: float
    substeps: int
    cfl: float
    particle_spacing: float | None = None

    @staticmethod
    def from_json(d: dict[str, Any]) -> "SimSettings":
        """From scene.json, where an unknown CFL number (NaN: materials not known yet) is written null."""
        d = {k: v for k, v in d.items() if k != "non_finite"}
        if d.get("cfl") is None:
            d["cfl"] = float("nan")
        return SimSettings(**d)


@dataclass
class ObjectBoundary:
    """The boundary conditions of one deformable object (a ``{"type": "anchors", "object": NAME, ...}`` entry
    of ``scenario.boundary_conditions``).

    Attributes:
        back_face: what holds the hidden back of the tissue (the deepest particle layer of its slab):
            "fixed" (glued to the anatomy behind), "support" (resting on it: pushed, never pulled, so it can be
            lifted off; pressed, it slides with Coulomb friction ``support_friction``, or without one does not
            slide), "slip_support" (the same without friction: wet tissue on wet anatomy) or "free".
        border: width (metres) of the band along the object's outline that is held (the tissue goes on
            beyond the view); 0 for none.
        border_motion: how the band is held: "still" (at rest) or "tracked" (it follows the reconstruction's
            tracks of the tissue there, ``tracks.npz``: what moves the tissue beyond the view moves the band).
        release: (centre [x, y] metres, radius metres) of a disc where the back face is free, or None.
        support_friction: Coulomb coefficient of a "support" back face (``support_friction``; None: it sticks
            while pressed; see :class:`endogsim.physics.Anchor`).
    """

    back_face: str = "fixed"
    border: float = 0.0
    release: tuple[tuple[float, float], float] | None = None
    border_motion: str = "still"
    support_friction: float | None = None

    @staticmethod
    def from_json(d: dict[str, Any]) -> "ObjectBoundary":
        back = d.get("back_face", False)
        back = {True: "fixed", False: "free"}.get(back, back) if isinstance(back, bool) else str(back)
        if back not in ("fixed", "support", "slip_support", "free"):
            raise DataError(f"boundary condition back_face {back!r} is not fixed|support|slip_support|free")
        rel = d.get("release")
        release = None if rel is None else ((float(rel["center"][0]), float(rel["center"][1])), float(rel["radius"]))
        motion = str(d.get("border_motion", "still"))
        if motion not in ("still", "tracked"):
            raise DataError(f"boundary condition border_motion {motion!r} is not still|tracked")
        mu = d.get("support_friction")
        if mu is not None and (back != "support" or not isinstance(mu, (int, float)) or isinstance(mu, bool)
                               or not (math.isfinite(mu) and mu >= 0)):
            raise DataError(f"boundary condition support_friction {mu!r} must be a number >= 0, for a back_face "
                            f"'support' (this one is {back!r})")
        return ObjectBoundary(back, float(d.get("border", 0.0)), release, motion,
                              None if mu is None else float(mu))


@dataclass
class ScenarioSpec:
    """The scenario: sim box (world corner ``box_lo`` and edge ``box_size`` in metres; world -> sim is
    (x - box_lo) / box_size), gravity (m/s^2, world), damping (1/s), boundary conditions, tools, the
    tissue's thickness behind its visible surface (``extrusion``), the settling before frame 0 and two
    discretisations: ``ground_truth`` (used to make the video; finer) and ``identification`` (defaults).

    ``settle_frames``: frames simulated before frame 0 under gravity with the tools still, so that frame 0
    is the tissue's equilibrium, with grid damping ``settle_damping`` (1/s; None: ``damping``) to reach it
    in those few frames (see :class:`endogsim.physics.Scenario`).
    ``mass_scaling``: quasi-static mass scaling of identification's simulations (see
    :class:`endogsim.physics.Scenario`; 1 = none).
    ``forces``: what else drives the tissue; an impulse (the paper's protocol) is
    ``{"type": "impulse", "object": NAME, "center": [x, y, z], "radius": m, "velocity": [vx, vy, vz] m/s,
    "t_start": s}``: every particle of the object within ``radius`` of ``center`` gets the velocity at t_start.
    """

    box_lo: list[float]
    box_size: float
    gravity: list[float]
    frame_dt: float
    damping: float
    boundary_conditions: list[dict[str, Any]]
    tools: list[ToolCapsule]
    extrusion: dict[str, Any]
    ground_truth: SimSettings
    identification: SimSettings
    settle_frames: int = 0
    settle_damping: float | None = None
    forces: list[dict[str, Any]] = field(default_factory=list)
    mass_scaling: float = 1.0
    particle_spacing: float | None = None  # scene.json version 1: the one spacing of both discretisations

    def thickness(self, name: str) -> float:
        """The slab thickness (metres) of object ``name`` behind its visible surface (0: a solid sample)."""
        thick = self.extrusion.get("thickness", 0.0) if isinstance(self.extrusion, dict) else 0.0
        return float(thick.get(name, 0.0)) if isinstance(thick, dict) else float(thick)

    def boundary(self, name: str) -> ObjectBoundary:
        """The boundary conditions of object ``name`` (or of "all_tissue"); none when unlisted."""
        for b in self.boundary_conditions:
            if b.get("type") == "anchors" and b.get("object") in (name, "all_tissue"):
                return ObjectBoundary.from_json(b)
        return ObjectBoundary(back_face="free")

    def spacing(self, settings: SimSettings) -> float:
        """The particle spacing (metres) of a discretisation: its own, or half its cell."""
        if settings.particle_spacing:
            return float(settings.particle_spacing)
        return float(self.particle_spacing) if self.particle_spacing else self.box_size / settings.grid / 2


@dataclass
class CameraSpec:
    """Pinhole camera: K [3][3] pixels, image size, world->camera ``viewmat`` [4][4] of frame 0 (the world is
    frame 0's camera frame: identity), and for a moving endoscope ``viewmats`` [T][4][4], the world->camera
    transform of every frame (None: the camera is still), and ``exposure``, how each frame's camera exposed
    the Gaussians' colours (a moving endoscope's light and auto-exposure, learnt by the reconstruction:
    :mod:`endogsim.recon.exposure`): {"log_gain": [T][3], "bias": [T][3]}, rgb_t = rgb * exp(log_gain_t) +
    bias_t (None: every frame as frame 0)."""

    K: list[list[float]]
    width: int
    height: int
    viewmat: list[list[float]]
    viewmats: list[list[list[float]]] | None = None
    exposure: dict[str, list[list[float]]] | None = None


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

    @property
    def rigid(self) -> list[SceneObject]:
        """The rigid objects: the instruments."""
        return [o for o in self.objects if o.rigid]

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
    except ValueError as exc:
        raise DataError(f"{p}: malformed scene.json ({exc})") from exc
    spec = scene_spec_from_json(d, p)
    _check_files(spec, p)
    return spec


def scene_spec_from_json(d: dict[str, Any], where: str | Path = "scene.json") -> SceneSpec:
    """A :class:`SceneSpec` from the parsed JSON of a ``scene.json`` (``where`` names it in errors), its
    ground-truth materials checked."""
    p = Path(where)
    try:
        objects = [SceneObject(**{("klass" if k == "class" else k): v for k, v in o.items()}) for o in d["objects"]]
        sc = dict(d["scenario"])
        sc["tools"] = [ToolCapsule(**t) for t in sc["tools"]]
        sc["ground_truth"] = SimSettings.from_json(sc["ground_truth"])
        sc["identification"] = SimSettings.from_json(sc["identification"])
        spec = SceneSpec(
            name=d["name"], seed=d["seed"], frames=d["frames"], objects=objects, scenario=ScenarioSpec(**sc),
            camera=CameraSpec(**d["camera"]), depth_scale=d["depth_scale"], files=d.get("files", {}),
            source=d.get("source", "procedural"), version=d.get("version", SCENE_JSON_VERSION),
            generator=d.get("generator", 0),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{p}: malformed scene.json ({exc})") from exc
    _check_materials(spec, p)
    _check_geometry(spec, p)
    return spec


def _check_materials(spec: SceneSpec, path: Path) -> None:
    """Ground-truth materials are numbers (or all null: unknown) that pass :class:`MaterialRecord`'s checks."""
    for o in spec.objects:
        given = {k: getattr(o, k) for k in ("E", "nu", "density") if getattr(o, k) is not None}
        for k, v in given.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise DataError(f"{path}: object {o.name!r} has {k} = {v!r}; it must be a number (null when unknown)")
        if given and len(given) < 3:
            raise DataError(f"{path}: object {o.name!r} gives {', '.join(given)} but not all of E, nu and density "
                            "(give all three, or null for all when unknown)")
        if given:
            try:
                o.material_record()
            except MaterialError as exc:
                raise MaterialError(f"{path}: impossible ground truth: {exc}") from None


def _numbers(value: Any, shape: tuple[int, ...], what: str, path: Path) -> np.ndarray:
    """``value`` as a float array of ``shape`` with finite entries, else a DataError naming ``what``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != shape or not np.isfinite(a).all():
        dims = " x ".join(str(n) for n in shape) or "one"
        raise DataError(f"{path}: {what} = {value!r:.80} must be {dims} finite number(s)")
    return a


def _positive(value: Any, what: str, path: Path, integer: bool = False, least: float = 0.0,
              zero: bool = False) -> None:
    """``value`` is a finite number (an integer if ``integer``) above ``least`` (or equal to it if ``zero``)."""
    ok = not isinstance(value, bool) and isinstance(value, int if integer else (int, float))
    if not ok or not math.isfinite(value) or value < least or (value == least and not zero):
        kind = "an integer" if integer else "a number"
        raise DataError(f"{path}: {what} = {value!r} must be {kind} {'>=' if zero else '>'} {least:g}")


#: The kinds of ``scenario.boundary_conditions`` entries: anchors and box walls act; "static" records the
#: objects a scene made from real data keeps still (``synth --from``; they are rigid and never move).
BOUNDARY_TYPES = ("anchors", "box_walls", "static")


def _check_geometry(spec: SceneSpec, path: Path) -> None:
    """The scenario, tools and camera of ``scene.json`` are numbers of the right shapes and signs, and every
    boundary condition and force names an object the scene has: a typo would otherwise be simulated as a
    different experiment without a word (or fail deep inside the simulator)."""
    sc = spec.scenario
    ids = [o.id for o in spec.objects]
    if any(isinstance(i, bool) or not isinstance(i, int) for i in ids) or len(set(ids)) != len(ids):
        raise DataError(f"{path}: object ids {ids} must be distinct integers")
    _positive(spec.depth_scale, "depth_scale", path)
    _numbers(sc.box_lo, (3,), "scenario.box_lo", path)
    _positive(sc.box_size, "scenario.box_size (m)", path)
    _numbers(sc.gravity, (3,), "scenario.gravity (m/s^2)", path)
    _positive(sc.frame_dt, "scenario.frame_dt (s)", path)
    _positive(sc.damping, "scenario.damping (1/s)", path, zero=True)
    _positive(sc.mass_scaling, "scenario.mass_scaling", path)
    if isinstance(sc.settle_frames, bool) or not isinstance(sc.settle_frames, int) or sc.settle_frames < 0:
        raise DataError(f"{path}: scenario.settle_frames = {sc.settle_frames!r} must be an integer >= 0")
    for name, st in (("ground_truth", sc.ground_truth), ("identification", sc.identification)):
        _positive(st.grid, f"scenario.{name}.grid", path, integer=True, least=3)
        _positive(st.substeps, f"scenario.{name}.substeps", path, integer=True)
        _positive(st.dt, f"scenario.{name}.dt (s)", path)
        if st.particle_spacing is not None:
            _positive(st.particle_spacing, f"scenario.{name}.particle_spacing (m)", path)
    names = {o.name for o in spec.objects} | {"all_tissue"}
    for b in sc.boundary_conditions:
        if not isinstance(b, dict) or b.get("type") not in BOUNDARY_TYPES:
            raise DataError(f"{path}: boundary condition {b!r:.80} must be an object whose type is one of "
                            f"{', '.join(BOUNDARY_TYPES)}")
        if b["type"] == "anchors":
            if b.get("object") not in names:
                raise DataError(f"{path}: boundary condition {b!r:.80} names object {b.get('object')!r}, which the "
                                f"scene does not have (one of {', '.join(sorted(names))})")
            try:
                border = ObjectBoundary.from_json(b).border
            except (TypeError, ValueError, KeyError, DataError) as exc:
                raise DataError(f"{path}: boundary condition {b!r:.80}: {exc}") from None
            _positive(border, "an anchors border (m)", path, zero=True)
        elif "cells" in b:
            _positive(b["cells"], "box_walls.cells", path, integer=True)
    for f in sc.forces:
        if not isinstance(f, dict) or f.get("type") != "impulse":
            raise DataError(f"{path}: force {f!r:.80} must be an object of type 'impulse'")
        if f.get("object") not in names:
            raise DataError(f"{path}: force {f!r:.80} names object {f.get('object')!r}, which the scene does not have")
        _numbers(f.get("center"), (3,), "an impulse's center (m)", path)
        _numbers(f.get("velocity"), (3,), "an impulse's velocity (m/s)", path)
        _positive(f.get("radius"), "an impulse's radius (m)", path)
    for t in sc.tools:
        what = f"tool {t.object_id}"
        _numbers(t.tip, (3,), f"{what} tip (m)", path)
        _numbers(t.end, (3,), f"{what} end (m)", path)
        _positive(t.radius, f"{what} radius (m)", path)
        frames = len(t.transforms) if isinstance(t.transforms, list) else 0
        _numbers(t.transforms, (frames, 4, 4), f"{what} transforms", path)
    cam = spec.camera
    K = _numbers(cam.K, (3, 3), "camera.K (pixels)", path)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise DataError(f"{path}: camera.K has focal lengths {K[0, 0]:g}, {K[1, 1]:g} px; they must be > 0")
    _positive(cam.width, "camera.width (px)", path, integer=True)
    _positive(cam.height, "camera.height (px)", path, integer=True)
    _numbers(cam.viewmat, (4, 4), "camera.viewmat", path)
    if cam.viewmats is not None:
        frames = len(cam.viewmats) if isinstance(cam.viewmats, list) else 0
        _numbers(cam.viewmats, (frames, 4, 4), "camera.viewmats", path)
    if cam.exposure is not None:
        if not isinstance(cam.exposure, dict) or set(cam.exposure) != {"log_gain", "bias"}:
            raise DataError(f"{path}: camera.exposure = {cam.exposure!r:.80} must be an object with 'log_gain' "
                            "and 'bias'")
        for key in ("log_gain", "bias"):
            _numbers(cam.exposure[key], (spec.frames, 3), f"camera.exposure.{key}", path)


def _check_files(spec: SceneSpec, path: Path) -> None:
    """``frames`` is a count the images cover, and every path in ``files`` stays inside the scene folder."""
    folder = path.parent.resolve()
    if isinstance(spec.frames, bool) or not isinstance(spec.frames, int) or spec.frames < 2:
        raise DataError(f"{path}: frames = {spec.frames!r} must be an integer >= 2")
    for key, pattern in spec.files.items():
        if not isinstance(pattern, str) or not pattern:
            raise DataError(f"{path}: files.{key} = {pattern!r} must be a path inside the scene folder")
        target = (folder / pattern).resolve()
        if Path(pattern).is_absolute() or not target.is_relative_to(folder):
            raise DataError(f"{path}: files.{key} = {pattern!r} points outside the scene folder {folder}; paths in "
                            "'files' must stay inside it")
    images = spec.files.get("images", IMAGES_PATTERN)
    try:
        last = folder / (images % (spec.frames - 1))
    except (TypeError, ValueError):
        raise DataError(f"{path}: files.images = {images!r} must hold one %d for the frame number") from None
    if not last.is_file():
        first_missing = next(t for t in range(spec.frames) if not (folder / (images % t)).is_file())
        raise DataError(f"{path}: frames = {spec.frames}, but its images end at frame {first_missing - 1} "
                        f"({images % first_missing} is missing)")
