"""Simulate a new tool interaction (:mod:`endogsim.pipeline.interaction`) on a scene with given (e.g.
identified) materials.

:func:`simulate_interaction` writes to ``out``:
  simulation.mp4              the rendered simulation (full resolution)
  frames/frame_%04d.png       the same frames as PNG
  ply/frame_%04d.ply          the Gaussians of every frame (3DGS layout with object ids)
  summary.json                scene, interaction (with resolved points), materials, numerics (``discretisation``:
                              the factor simulated at, grid, particles, substeps),
                              displacement statistics (mm), whether a grasp's bite held (``grasp_bites``),
                              timings, file list
  interaction.json, materials.json   the inputs actually used
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from endogsim.errors import DataError, MaterialError, SimulationError
from endogsim.gaussians.model import covariance_to_scale_rot
from endogsim.io.atomic import write_json_atomic
from endogsim.io.runfolder import run_folder
from endogsim.materials.field import MaterialField
from endogsim.pipeline.interaction import Interaction, Located, load_interaction

__all__ = ["resolve_scene", "surface_point", "build_interaction", "identified_refine", "identified_substeps",
           "simulate_interaction"]

def resolve_scene(path: str | Path) -> tuple[Path, Path | None]:
    """The scene folder and the default materials file for a scene folder or a run folder.

    A scene folder has ``scene.json`` (no default materials). A run folder has the identified materials
    (``materials_identified.json`` of ``endogsim identify``, or ``identify/materials_identified.json`` of
    ``endogsim run``) and either a ``scene/`` subfolder with ``scene.json`` or a ``metrics.json`` whose
    ``folder`` names the scene (or ``folder_from_run``, relative to the run folder, when both were moved).
    """
    p = Path(path)
    if (p / "scene.json").is_file():
        return p, None
    mats = next((m for m in (p / "materials_identified.json", p / "identify" / "materials_identified.json")
                 if m.is_file()), None)
    if (p / "scene" / "scene.json").is_file():
        return p / "scene", mats
    if (p / "metrics.json").is_file():
        try:
            metrics = json.loads((p / "metrics.json").read_text())
            named, relative = metrics.get("folder", ""), metrics.get("folder_from_run")
        except (ValueError, AttributeError) as exc:
            raise DataError(f"{p / 'metrics.json'}: not a JSON object ({exc}); re-run the identification") from exc
        if not named:
            raise DataError(f"{p}: its metrics.json names no scene folder (an `endogsim reconstruct` run?); give a "
                            "scene folder, or an `endogsim identify` / `endogsim run` folder")
        if not isinstance(named, str) or not isinstance(relative, (str, type(None))):
            raise DataError(f"{p / 'metrics.json'}: 'folder' is {named!r}, not the scene folder's path")
        for folder in (Path(named), p / (relative or named)):  # as written, or moved with its run folder
            if (folder / "scene.json").is_file():
                return folder, mats
        raise DataError(f"{p}/metrics.json names scene folder {named!r}, which has no scene.json")
    raise DataError(f"{p}: neither a scene folder (scene.json) nor a run folder (metrics.json / scene/)")


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


def surface_point(problem, loc: Located) -> np.ndarray:
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
    spacing = problem.spec.scenario.spacing(problem.spec.scenario.identification)
    near = np.linalg.norm(x[:, :2] - target, axis=1) <= 1.5 * spacing
    if not near.any():
        raise DataError(f"at = [{u}, {v}] lies off the tissue of scene {problem.spec.name!r} (no particle within "
                        f"{1.5 * spacing * 1e3:.1f} mm of the image-plane point)")
    cam = problem.camera.center().double().numpy()
    cand = x[near]
    return cand[np.argmin(np.linalg.norm(cand - cam, axis=1))]


def _check_inside_box(problem, inter: Interaction, what: str, part: str, path: np.ndarray) -> None:
    """Refuse an interaction that moves ``what`` (its ``part`` following ``path`` [T, 3], metres) out of the
    simulation box or into its walls: the simulator would lose it (no contact, no force) without a word."""
    box, cells = problem.scenario.box, problem.mpm.wall_padding
    lo = np.asarray(box.lo, float) + cells * box.size / problem.mpm.grid_res
    hi = np.asarray(box.lo, float) + box.size - cells * box.size / problem.mpm.grid_res
    out = (path < lo) | (path > hi)
    if out.any():
        t, k = np.argwhere(out)[0]
        axis = "xyz"[k]
        raise DataError(f"interaction {inter.name!r} moves {what} out of the simulation box of scene "
                        f"{problem.spec.name!r}: at frame {t} its {part} is at {axis} = {path[t, k]:.4f} m, outside "
                        f"[{lo[k]:.4f}, {hi[k]:.4f}] m (the {box.size:g} m box less its {cells}-cell walls); "
                        "make the offsets smaller (the box is not grown)")


def build_interaction(problem, inter: Interaction):
    """The problem with the interaction's scenario, tool transforms and Gaussians, and resolved points.

    Returns:
        (new problem, info dict with the resolved world points in metres).
    """
    from endogsim.physics import GRASP_MARGIN, ExternalForce, capsule_collider, grasped_particles
    from endogsim.scene.motion import tool_offsets, translations
    from endogsim.scene.particles import tool_colliders

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
    free = ~problem.scenario.held(problem.particles.x.double().numpy())
    if inter.grasp is not None:
        p = surface_point(problem, inter.grasp)
        info["grasp_point"] = p.tolist()
        off = tool_offsets([list(k) for k in inter.grasp.keyframes], T)
        # The grasp holds the free tissue within its sphere (and GRASP_MARGIN) and carries it along.
        holds = grasped_particles(problem.particles.x, p, inter.grasp.radius, free=free)
        if len(holds) == 0:
            raise DataError(f"grasp: no free tissue particle within {inter.grasp.radius + GRASP_MARGIN} m of "
                            f"{p.tolist()}")
        info["grasp_particles"] = int(len(holds))
        grasp_collider = capsule_collider(p, p, inter.grasp.radius, translations(off), dx, holds)
        if inter.grasp.with_tool and tools:
            tid = first_tool(None)
            if tid in driven:
                raise DataError("grasp.with_tool moves the tool that 'tool' already drives; set with_tool false")
            driven[tid] = (p - np.asarray(tools[tid].tip, float)) + off

    for tid, shift in driven.items():
        _check_inside_box(problem, inter, f"tool {problem.spec.object(tid).name!r} (id {tid})", "tip",
                          np.asarray(tools[tid].tip, float) + shift)
    if inter.grasp is not None:
        _check_inside_box(problem, inter, "the grasp", "point", np.asarray(info["grasp_point"]) + off)

    tool_tf, hidden = {}, []
    for tid in tools:
        if tid in driven:
            tool_tf[tid] = torch.as_tensor(translations(driven[tid]))
        elif inter.scene_tool == "static":
            tool_tf[tid] = torch.as_tensor(translations(np.zeros((T, 3))))
        else:
            hidden.append(tid)
    if grasp_collider is not None:  # the grasp's tissue is not also the bite of a grasping tool beside it
        free = free.copy()
        free[grasp_collider.holds.numpy()] = False
    colliders = tool_colliders([tools[tid] for tid in tool_tf], problem.particles, free, dx, tool_tf)
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
                                    t_start=f.t_start, t_end=math.inf if f.t_end is None else f.t_end))

    g = problem.gaussians
    if hidden:
        hide = torch.isin(g.object_ids, torch.tensor(hidden))
        g = g.with_(opacity_logits=torch.where(hide, torch.full_like(g.opacity_logits, -30.0), g.opacity_logits))
    info["hidden_tools"] = hidden
    # A border that followed the clip's tracks holds still: the interaction's frames were never filmed.
    scenario = replace(problem.scenario.boundary_still(T), forces=forces, colliders=colliders)
    # A new interaction is not the video: its instruments are drawn in every frame it simulates, and it is
    # seen by frame 0's camera (the world frame) as frame 0 exposed it (the video's visibility, camera path
    # and exposure are about the filmed frames, and the interaction may be longer).
    return replace(problem, scenario=scenario, tool_transforms=tool_tf, gaussians=g, tool_visible={}, viewmats=None,
                   exposure=None), info


# ------------------------------------------------------------------------------------------------------
# Running it
# ------------------------------------------------------------------------------------------------------


def _materials(problem, materials: str | Path | MaterialField | None, default: Path | None) -> MaterialField:
    """The field to simulate with: a field, a JSON file, "truth" (scene.json), or an initialiser name."""
    from endogsim.identify.run import INIT_CHOICES, check_field_objects, initial_field

    if materials is None:
        materials = default if default is not None else "prior"
    if isinstance(materials, MaterialField):
        fld = materials
    elif str(materials) == "truth":
        fld = MaterialField([o.material_record() for o in problem.spec.objects])
    elif str(materials) in INIT_CHOICES:
        fld, _ = initial_field(problem, str(materials))
    else:
        fld = MaterialField.load(materials)
    check_field_objects(problem, fld, str(materials) if not isinstance(materials, MaterialField) else "materials")
    have = {r.object_id for r in fld.records}
    missing = [f"{problem.spec.object(i).name} ({i})" for i in problem.deformable_ids if i not in have]
    if missing:
        raise MaterialError(f"the materials have no record for deformable object(s) {', '.join(missing)}")
    return fld


def identified_refine(materials: str | Path | MaterialField | None) -> float:
    """The factor on the scene's identification discretisation that ``materials`` were identified at: the
    ``refine`` its identification recorded in the field's meta, 1 for a field without one (the truth, an
    initialiser, a hand-written file, or one identified before the factor was recorded)."""
    from endogsim.identify.run import INIT_CHOICES

    if isinstance(materials, MaterialField):
        return float(materials.meta.get("refine", 1.0))
    if materials is None or str(materials) == "truth" or str(materials) in INIT_CHOICES \
            or not Path(materials).is_file():  # a missing file is refused, with its name, where it is read
        return 1.0
    return float(MaterialField.load(materials).meta.get("refine", 1.0))


def identified_substeps(fld: MaterialField, refine: float, where: str = "the materials") -> int:
    """The floor of substeps per frame ``fld`` was identified with (its meta's ``substeps``), where it is simulated
    at the discretisation it was identified at (its ``refine``); else 0 (no floor beyond the scene's own: the
    truth, an initialiser, a hand-written file, another discretisation). Identification plans its time step
    once, at its initial materials (:func:`~endogsim.identify.optimize.planned_for`); a softer identified field
    would take fewer substeps by the CFL rule alone and move otherwise than identification saw it move.
    ``where`` names the field in the error a bad record gets (its file)."""
    count = fld.meta.get("substeps")
    if count is None or float(fld.meta.get("refine", 1.0)) != float(refine):
        return 0
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise MaterialError(f"{where}: meta 'substeps' is {count!r}, not a count of substeps per frame (>= 1)")
    return count


def simulate_interaction(
    scene: str | Path,
    interaction: str | Path | dict | Interaction,
    materials: str | Path | MaterialField | None = None,
    out: str | Path = "simulation",
    fps: float = 10.0,
    write_ply_sequence: bool = True,
    device: str = "cpu",
    progress=None,
    refine: float | None = None,
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
        refine: simulate at the scene's identification discretisation refined by this factor; None: the
            factor the materials were identified at (:func:`identified_refine`: an identified E belongs to
            the discretisation it was fitted at), with at least the substeps it was fitted with there
            (:func:`identified_substeps`).
    Returns:
        the summary dict (also ``out/summary.json``).
    Raises:
        DataError (bad scene / interaction, a tool moved out of the simulation box, ``out`` in use by another
        command), MaterialError (materials, or records for objects the scene does not have), SimulationError
        (unstable or diverged simulation). Inputs are checked before anything is written.
    """
    from endogsim.scene.folder import load_sim_scene

    out = Path(out)
    inter = load_interaction(interaction)
    folder, default_mats = resolve_scene(scene)
    if out.resolve() in (Path(folder).resolve(), Path(scene).resolve()):
        raise DataError(f"{out}: --out is the scene (or run) folder itself; name a new folder for the simulation")
    named = materials if materials is not None else default_mats  # the run folder's materials by default
    if refine is None:
        refine = identified_refine(named)
    base = load_sim_scene(folder, device=device, refine=refine)
    fld = _materials(base, materials, default_mats)
    problem, info = build_interaction(base, inter)
    where = "the materials" if named is None or isinstance(named, MaterialField) else str(named)
    problem = problem.with_substeps_at_least(identified_substeps(fld, refine, where))
    with run_folder(out, "simulate"):
        return _simulate_and_write(problem, inter, fld, info, folder, out, fps, write_ply_sequence, progress,
                                   refine)


def _bite_records(problem, positions: torch.Tensor) -> list[dict]:
    """:func:`endogsim.physics.bite_records` of a simulation of ``problem`` (``positions`` [T, P, 3] metres)."""
    from endogsim.physics import bite_records

    spacing = float(problem.particles.volume.double().median()) ** (1.0 / 3.0)  # each particle stands for spacing^3
    return bite_records(problem.particles.x, positions, problem.scenario.colliders, spacing,
                        problem.scenario.box.size / problem.mpm.grid_res)


def _simulate_and_write(problem, inter: Interaction, fld: MaterialField, info: dict, folder: Path, out: Path,
                        fps: float, write_ply_sequence: bool, progress, refine: float) -> dict:
    """Run the built interaction and write ``out`` (see :func:`simulate_interaction`)."""
    from endogsim.gaussians.ply import write_ply
    from endogsim.identify.report import discretisation_record
    from endogsim.io.video_writer import write_frames_png, write_video
    from endogsim.physics import simulate
    from endogsim.scene.forward import frame_gaussians, render_sequence

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
    bites = _bite_records(problem, res.positions)
    inter_json = inter.model_dump(mode="json")
    write_json_atomic(out / "interaction.json", inter_json)
    fld.save(out / "materials.json")
    summary = {
        "scene": problem.spec.name, "scene_folder": str(folder), "interaction": inter_json, "resolved": info,
        "materials": {r.name: {"object_id": r.object_id, "E": r.E, "nu": r.nu, "density": r.density,
                               "rigid": r.rigid, "source": r.source} for r in fld.records},
        "frames": T, "frame_dt": problem.mpm.frame_dt, "substeps": res.substeps, "dt": res.dt,
        "particles": len(problem.particles), "gaussians": len(problem.gaussians),
        "discretisation": discretisation_record(problem, refine, fld),
        "displacement": displacement, "grasp_bites": bites,
        "mean_flow_px": float(r.flow.norm(dim=-1).mean()) if r.flow.numel() else 0.0,
        "seconds": {"simulate": t_sim, "render_and_write": t_render},
        "units": {"E": "Pa", "density": "kg/m^3", "frame_dt": "s", "dt": "s", "displacement": "mm"},
        "files": {"video": video.name, "frames": [f"frames/{p.name}" for p in pngs],
                  "ply": [f"ply/{p.name}" for p in plys], "interaction": "interaction.json",
                  "materials": "materials.json"},
    }
    write_json_atomic(out / "summary.json", summary)
    return summary
