"""Simulate a new tool interaction on a scene with given (e.g. identified) materials.

An *interaction* (JSON, validated by :class:`Interaction`) says what acts on the tissue, in up to three
sections that may be combined:

  ``tool``   a new trajectory of one of the scene's tool capsules: translation keyframes
             ``[[fraction of the clip, dx, dy, dz], ...]`` (metres, world; the camera looks along +z, so
             dz > 0 pushes into the tissue), optionally after moving the tool tip onto a surface point.
  ``force``  a body acceleration (m/s^2, world) on the particles within ``radius`` metres of a surface
             point, over the time window [t_start, t_end) seconds.
  ``grasp``  a small sticky sphere (radius metres) on a surface point that follows keyframes: grasp and
             pull; with ``with_tool`` the scene's tool tip goes to the grasp point and moves with it.

Surface points are given as ``at = [u, v]`` in [-1, 1]^2 over the (image-plane) bounding box of the
deformable particles (of ``object`` if named), and lie on the side facing the camera; or as a world
``point`` [x, y, z] in metres. Tools not driven by the interaction stay at their frame-0 pose
(``scene_tool = "static"``) or are removed (``"hidden"``: no collider, not rendered).

Built-in interactions live in ``endogsim/data/interactions/NAME.json`` (:func:`builtin_interactions`).

:func:`simulate_interaction` writes to ``out``:
  simulation.mp4              the rendered simulation (full resolution)
  frames/frame_%04d.png       the same frames as PNG
  ply/frame_%04d.ply          the Gaussians of every frame (3DGS layout with object ids)
  summary.json                scene, interaction (with resolved points), materials, numerics,
                              displacement statistics (mm), timings, file list
  interaction.json, materials.json   the inputs actually used
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import replace
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import torch
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from endogsim.errors import DataError, MaterialError, SimulationError
from endogsim.io.atomic import write_json_atomic
from endogsim.materials.field import MaterialField

__all__ = ["Interaction", "ToolSpec", "ForceSpec", "GraspSpec", "builtin_interactions", "load_interaction",
           "resolve_scene", "simulate_interaction", "covariance_to_scale_rot"]

def _check_keyframes(kf: list) -> list:
    if len(kf) < 1 or kf[0][0] != 0.0:
        raise ValueError("keyframes must start with [0, dx, dy, dz]")
    fr = [k[0] for k in kf]
    if any(b <= a for a, b in zip(fr, fr[1:])) or fr[-1] > 1.0:
        raise ValueError(f"keyframe fractions {fr} must increase within [0, 1]")
    if any(not math.isfinite(v) or abs(v) > 0.1 for k in kf for v in k[1:]):
        raise ValueError("keyframe offsets must be finite and at most 0.1 m")
    return kf


# [[fraction of the clip in [0, 1], dx, dy, dz (metres, world)], ...], first fraction 0.
Keyframes = Annotated[list[tuple[float, float, float, float]], AfterValidator(_check_keyframes)]


class _Located(BaseModel):
    """Where on the tissue: ``at`` (normalised [u, v]) or ``point`` (world metres), optionally on ``object``."""

    model_config = ConfigDict(extra="forbid")

    at: tuple[float, float] | None = None
    point: tuple[float, float, float] | None = None
    object: str | int | None = Field(None, description="deformable object (name or id) the point lies on")

    @field_validator("at")
    @classmethod
    def _at_range(cls, v):
        if v is not None and not all(-1.5 <= c <= 1.5 for c in v):
            raise ValueError(f"at = {list(v)} must lie in [-1.5, 1.5]^2 (normalised tissue coordinates)")
        return v


class ToolSpec(_Located):
    """A new trajectory of a scene tool (``tool``: name or id; default the first tool). With ``at`` or
    ``point`` the tool is first translated so that its capsule touches that surface point from the camera side."""

    tool: str | int | None = None
    keyframes: Keyframes


class ForceSpec(_Located):
    """Body acceleration ``acceleration`` (m/s^2, world) on particles within ``radius`` (m) of the point,
    for ``t_start <= t < t_end`` (s)."""

    acceleration: tuple[float, float, float]
    radius: float = Field(0.01, gt=0, le=0.2)
    t_start: float = Field(0.0, ge=0)
    t_end: float = Field(float("inf"), gt=0)

    @model_validator(mode="after")
    def _window(self):
        if not self.t_end > self.t_start:
            raise ValueError(f"force window [{self.t_start}, {self.t_end}) s is empty")
        if not all(math.isfinite(a) and abs(a) <= 1e4 for a in self.acceleration):
            raise ValueError(f"acceleration {list(self.acceleration)} must be finite and at most 1e4 m/s^2")
        return self


class GraspSpec(_Located):
    """A sticky sphere of ``radius`` (m) on the point following ``keyframes`` (grasp and pull)."""

    radius: float = Field(0.003, gt=0, le=0.05)
    keyframes: Keyframes
    with_tool: bool = True


class Interaction(BaseModel):
    """A new interaction to simulate (see the module docstring). ``frames`` counts frame 0."""

    model_config = ConfigDict(extra="forbid")

    name: str = "interaction"
    description: str = ""
    frames: int = Field(16, ge=2, le=400)
    scene_tool: Literal["static", "hidden"] = "static"
    tool: ToolSpec | None = None
    force: ForceSpec | None = None
    grasp: GraspSpec | None = None

    @model_validator(mode="after")
    def _something(self):
        if self.tool is None and self.force is None and self.grasp is None:
            raise ValueError("an interaction needs at least one of 'tool', 'force', 'grasp'")
        return self


def _interaction_dir():
    return resources.files("endogsim").joinpath("data/interactions")


def builtin_interactions() -> list[str]:
    """Names of the packaged interactions (``endogsim/data/interactions/*.json``)."""
    return sorted(p.name[:-5] for p in _interaction_dir().iterdir() if p.name.endswith(".json"))


def load_interaction(spec: str | Path | dict | Interaction) -> Interaction:
    """An :class:`Interaction` from a built-in name, a JSON file, a dict, or an Interaction.

    Raises:
        DataError: unknown name, unreadable file, or a schema violation (the message names the field).
    """
    if isinstance(spec, Interaction):
        return spec
    where = "interaction"
    if isinstance(spec, dict):
        obj = spec
    else:
        p = Path(spec)
        if p.suffix == ".json" or p.is_file():
            if not p.is_file():
                raise DataError(f"{p}: interaction file not found")
            where = str(p)
            text = p.read_text()
        else:
            name = str(spec)
            if name not in builtin_interactions():
                raise DataError(f"unknown interaction {name!r}: give a JSON file or one of {', '.join(builtin_interactions())}")
            where = f"built-in interaction {name!r}"
            text = _interaction_dir().joinpath(f"{name}.json").read_text()
        try:
            obj = json.loads(text)
        except json.JSONDecodeError as exc:
            raise DataError(f"{where}: not valid JSON ({exc})") from None
    try:
        return Interaction.model_validate(obj)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(str(x) for x in e['loc']) or '(top)'}: {e['msg']}" for e in exc.errors())
        raise DataError(f"{where}: invalid interaction ({problems})") from None


def resolve_scene(path: str | Path) -> tuple[Path, Path | None]:
    """The scene folder and the default materials file for a scene folder or a run folder.

    A scene folder has ``scene.json`` (no default materials). A run folder (``endogsim identify``/``run``)
    has ``materials_identified.json`` and either a ``scene/`` subfolder with ``scene.json`` or a
    ``metrics.json`` whose ``folder`` names the scene.
    """
    p = Path(path)
    if (p / "scene.json").is_file():
        return p, None
    mats = p / "materials_identified.json"
    if (p / "scene" / "scene.json").is_file():
        return p / "scene", mats if mats.is_file() else None
    if (p / "metrics.json").is_file():
        folder = Path(json.loads((p / "metrics.json").read_text()).get("folder", ""))
        if (folder / "scene.json").is_file():
            return folder, mats if mats.is_file() else None
        raise DataError(f"{p}/metrics.json names scene folder {str(folder)!r}, which has no scene.json")
    raise DataError(f"{p}: neither a scene folder (scene.json) nor a run folder (metrics.json / scene/)")


def covariance_to_scale_rot(covs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Log axis scales [N, 3] (log metres) and quaternions [N, 4] (w, x, y, z) of covariances [N, 3, 3].

    The inverse of :func:`endogsim.gaussians.model.covariance_from_scale_rot` (eigen-decomposition; the
    eigenvector frame is made right-handed so it is a rotation).
    """
    from endogsim.gaussians.model import rotmat_to_quat

    sym = 0.5 * (covs + covs.mT).double()
    evals, evecs = torch.linalg.eigh(sym)
    flip = torch.linalg.det(evecs) < 0
    evecs[flip, :, 0] = -evecs[flip, :, 0]
    log_scales = 0.5 * torch.log(evals.clamp_min(1e-24))
    return log_scales.to(covs.dtype), rotmat_to_quat(evecs).to(covs.dtype)


# ------------------------------------------------------------------------------------------------------
# Building the scenario
# ------------------------------------------------------------------------------------------------------


def _object_id(problem, ref: str | int | None, deformable: bool) -> int | None:
    if ref is None:
        return None
    try:
        o = problem.spec.object(ref)
    except DataError:
        o = None
    if o is None or o.rigid == deformable:
        kinds = [f"{x.name} ({x.id})" for x in problem.spec.objects if x.rigid != deformable]
        raise DataError(f"scene {problem.spec.name!r} has no {'deformable object' if deformable else 'tool'} "
                        f"{ref!r}; choose one of {', '.join(kinds) or 'none'}")
    return o.id


def surface_point(problem, loc: _Located) -> np.ndarray:
    """World point [3] (metres) of ``loc`` on the camera-facing side of the deformable particles."""
    if loc.point is not None:
        return np.asarray(loc.point, float)
    x = problem.particles.x.double().numpy()
    oid = _object_id(problem, loc.object, deformable=True)
    if oid is not None:
        x = x[problem.particles.object_ids.numpy() == oid]
    u, v = loc.at if loc.at is not None else (0.0, 0.0)
    lo, hi = x[:, :2].min(0), x[:, :2].max(0)
    target = 0.5 * (lo + hi) + np.array([u, v]) * 0.5 * (hi - lo)
    spacing = float(problem.spec.scenario.particle_spacing)
    near = np.linalg.norm(x[:, :2] - target, axis=1) <= 1.5 * spacing
    if not near.any():
        raise DataError(f"at = [{u}, {v}] lies off the tissue of scene {problem.spec.name!r} (no particle within "
                        f"{1.5 * spacing * 1e3:.1f} mm of the image-plane point)")
    cam = problem.camera.center().double().numpy()
    cand = x[near]
    return cand[np.argmin(np.linalg.norm(cand - cam, axis=1))]


def build_interaction(problem, inter: Interaction):
    """The problem with the interaction's scenario, tool transforms and Gaussians, and resolved points.

    Returns:
        (new problem, info dict with the resolved world points in metres).
    """
    from endogsim.physics import ExternalForce, RigidCollider, capsule_collider_points
    from endogsim.scene.motion import tool_offsets, translations

    T = inter.frames
    dx = problem.scenario.box.size / problem.mpm.grid_res
    tools = {t.object_id: t for t in problem.spec.scenario.tools}
    info: dict = {}
    driven: dict[int, np.ndarray] = {}  # tool id -> [T, 3] translation
    cam_dir = lambda p: p / max(np.linalg.norm(p), 1e-12)  # noqa: E731 - camera at the origin looking at p

    def first_tool(ref) -> int:
        tid = _object_id(problem, ref, deformable=False)
        if tid is None:
            if not tools:
                raise DataError(f"scene {problem.spec.name!r} has no tool to move")
            tid = next(iter(tools))
        if tid not in tools:
            raise DataError(f"object {tid} of scene {problem.spec.name!r} is rigid but has no tool capsule")
        return tid

    def touch_offset(tid: int, p: np.ndarray) -> np.ndarray:
        """Translation putting the tool's capsule tip in contact with surface point p, from the camera side."""
        t = tools[tid]
        tip = np.asarray(t.tip, float)
        return p - t.radius * cam_dir(p) - tip

    if inter.tool is not None:
        tid = first_tool(inter.tool.tool)
        start = np.zeros(3)
        if inter.tool.at is not None or inter.tool.point is not None:
            p = surface_point(problem, inter.tool)
            start = touch_offset(tid, p)
            info["tool_point"] = p.tolist()
        driven[tid] = start + tool_offsets([list(k) for k in inter.tool.keyframes], T)
    grasp_collider = None
    if inter.grasp is not None:
        p = surface_point(problem, inter.grasp)
        info["grasp_point"] = p.tolist()
        off = tool_offsets([list(k) for k in inter.grasp.keyframes], T)
        pts, rad = capsule_collider_points(p, p, inter.grasp.radius, dx)
        grasp_collider = RigidCollider(points=torch.as_tensor(pts), transforms=torch.as_tensor(translations(off)), radius=rad)
        if inter.grasp.with_tool and tools:
            tid = first_tool(None)
            if tid in driven:
                raise DataError("grasp.with_tool moves the tool that 'tool' already drives; set with_tool false")
            driven[tid] = (p - np.asarray(tools[tid].tip, float)) + off

    colliders, tool_tf, hidden = [], {}, []
    for tid, t in tools.items():
        if tid in driven:
            tf = torch.as_tensor(translations(driven[tid]))
        elif inter.scene_tool == "static":
            tf = torch.as_tensor(translations(np.zeros((T, 3))))
        else:
            hidden.append(tid)
            continue
        pts, rad = capsule_collider_points(t.tip, t.end, t.radius, dx)
        colliders.append(RigidCollider(points=torch.as_tensor(pts), transforms=tf, radius=rad))
        tool_tf[tid] = tf
    if grasp_collider is not None:
        colliders.append(grasp_collider)

    forces = []
    if inter.force is not None:
        f = inter.force
        p = surface_point(problem, f)
        info["force_point"] = p.tolist()
        x = problem.particles.x.double().numpy()
        mask = np.linalg.norm(x - p, axis=1) <= f.radius
        oid = _object_id(problem, f.object, deformable=True)
        if oid is not None:
            mask &= problem.particles.object_ids.numpy() == oid
        if not mask.any():
            raise DataError(f"force: no particle within {f.radius} m of {p.tolist()}")
        info["force_particles"] = int(mask.sum())
        forces.append(ExternalForce(acceleration=tuple(f.acceleration), particle_mask=torch.as_tensor(mask),
                                    t_start=f.t_start, t_end=f.t_end))

    g = problem.gaussians
    if hidden:
        hide = torch.isin(g.object_ids, torch.tensor(hidden))
        g = g.with_(opacity_logits=torch.where(hide, torch.full_like(g.opacity_logits, -30.0), g.opacity_logits))
    info["hidden_tools"] = hidden
    scenario = replace(problem.scenario, forces=forces, colliders=colliders)
    return replace(problem, scenario=scenario, tool_transforms=tool_tf, gaussians=g), info


# ------------------------------------------------------------------------------------------------------
# Running it
# ------------------------------------------------------------------------------------------------------


def _materials(problem, materials: str | Path | MaterialField | None, default: Path | None) -> MaterialField:
    """The field to simulate with: a field, a JSON file, "truth" (scene.json), or an initialiser name."""
    from endogsim.identify.run import INIT_CHOICES, initial_field
    from endogsim.materials.field import MaterialRecord

    if materials is None:
        materials = default if default is not None else "prior"
    if isinstance(materials, MaterialField):
        fld = materials
    elif str(materials) == "truth":
        fld = MaterialField([MaterialRecord(name=o.name, object_id=o.id, klass=o.klass, rigid=o.rigid,
                                            model="rigid" if o.rigid else o.model, E=o.E, nu=o.nu,
                                            density=o.density, source="ground truth")
                             for o in problem.spec.objects])
    elif str(materials) in INIT_CHOICES:
        fld, _ = initial_field(problem, str(materials))
    else:
        fld = MaterialField.load(materials)
    have = {r.object_id for r in fld.records}
    missing = [f"{problem.spec.object(i).name} ({i})" for i in problem.deformable_ids if i not in have]
    if missing:
        raise MaterialError(f"the materials have no record for deformable object(s) {', '.join(missing)}")
    return fld


def simulate_interaction(
    scene: str | Path,
    interaction: str | Path | dict | Interaction,
    materials: str | Path | MaterialField | None = None,
    out: str | Path = "simulation",
    fps: float = 10.0,
    write_ply_sequence: bool = True,
    device: str = "cpu",
    progress=None,
) -> dict:
    """Simulate ``interaction`` on ``scene`` with ``materials`` and write the outputs (module docstring).

    Args:
        scene: a scene folder (``scene.json``) or a run folder (its identified materials are the default).
        interaction: a built-in name (:func:`builtin_interactions`), a JSON file, a dict or an Interaction.
        materials: a MaterialField, a material JSON file, "truth" (scene.json's ground truth) or an
            initialiser ("prior", "manual", ...); default the run's identified materials, else "prior".
        out: output folder.
        fps: video frame rate.
        write_ply_sequence: write ``ply/frame_%04d.ply``.
        device: simulator device.
        progress: optional callback(stage: str, done: int, total: int).
    Returns:
        the summary dict (also ``out/summary.json``).
    Raises:
        DataError (bad scene / interaction), MaterialError (materials), SimulationError (unstable or
        diverged simulation).
    """
    from endogsim.gaussians.ply import write_ply
    from endogsim.io.video_writer import write_frames_png, write_video
    from endogsim.physics import simulate
    from endogsim.scene.folder import load_sim_scene
    from endogsim.scene.forward import frame_gaussians, render_sequence

    out = Path(out)
    inter = load_interaction(interaction)
    folder, default_mats = resolve_scene(scene)
    base = load_sim_scene(folder, device=device)
    fld = _materials(base, materials, default_mats)
    problem, info = build_interaction(base, inter)
    T = inter.frames

    t0 = time.perf_counter()
    try:
        with torch.no_grad():
            res = simulate(problem.particles, fld.simulator_materials(), problem.scenario, problem.mpm, T)
    except SimulationError as exc:
        raise SimulationError(f"interaction {inter.name!r} on {folder}: {exc}") from None
    if not (torch.isfinite(res.positions).all() and torch.isfinite(res.F).all()):
        raise SimulationError(f"interaction {inter.name!r} on {folder}: the simulation produced NaN/inf")
    t_sim = time.perf_counter() - t0
    if progress:
        progress("simulate", 1, 1)

    t0 = time.perf_counter()
    with torch.no_grad():
        r = render_sequence(problem, res.positions, res.F, problem.camera)
    rgb = r.rgb.clamp(0, 1).numpy()
    if not np.isfinite(rgb).all():
        raise SimulationError(f"interaction {inter.name!r} on {folder}: the rendered frames hold NaN/inf")
    video = write_video(rgb, out / "simulation.mp4", fps=fps)
    pngs = write_frames_png(rgb, out / "frames")
    plys = []
    if write_ply_sequence:
        g = problem.gaussians
        cov0 = g.covariances().float()
        keep = ~torch.isin(g.object_ids, torch.tensor(info["hidden_tools"], dtype=torch.int64))
        with torch.no_grad():
            for t in range(T):
                means, covs = frame_gaussians(problem, res.positions, res.F, cov0, t)
                log_s, quats = covariance_to_scale_rot(covs)
                gt = g.with_(means=means.to(g.means.dtype), log_scales=log_s.to(g.means.dtype),
                             quats=quats.to(g.means.dtype)).subset(keep)
                plys.append(write_ply(gt, out / "ply" / f"frame_{t:04d}.ply"))
                if progress:
                    progress("ply", t + 1, T)
    t_render = time.perf_counter() - t0

    disp = (res.positions - res.positions[:1]).norm(dim=-1)  # [T, P] metres
    ids = problem.particles.object_ids
    displacement = {}
    for oid in problem.deformable_ids:
        d = disp[:, ids == oid]
        displacement[problem.spec.object(oid).name] = {
            "max_mm": float(d.max()) * 1e3, "mean_last_mm": float(d[-1].mean()) * 1e3,
            "max_last_mm": float(d[-1].max()) * 1e3}
    inter_json = inter.model_dump(mode="json")
    write_json_atomic(out / "interaction.json", inter_json)
    fld.save(out / "materials.json")
    summary = {
        "scene": problem.spec.name, "scene_folder": str(folder), "interaction": inter_json, "resolved": info,
        "materials": {r.name: {"object_id": r.object_id, "E": r.E, "nu": r.nu, "density": r.density,
                               "rigid": r.rigid, "source": r.source} for r in fld.records},
        "frames": T, "frame_dt": problem.mpm.frame_dt, "substeps": res.substeps, "dt": res.dt,
        "particles": len(problem.particles), "gaussians": len(problem.gaussians),
        "displacement": displacement, "mean_flow_px": float(r.flow.norm(dim=-1).mean()) if r.flow.numel() else 0.0,
        "seconds": {"simulate": t_sim, "render_and_write": t_render},
        "units": {"E": "Pa", "density": "kg/m^3", "frame_dt": "s", "dt": "s", "displacement": "mm"},
        "files": {"video": video.name, "frames": [f"frames/{p.name}" for p in pngs],
                  "ply": [f"ply/{p.name}" for p in plys], "interaction": "interaction.json",
                  "materials": "materials.json"},
    }
    write_json_atomic(out / "summary.json", summary)
    return summary
