"""``endogsim bench convergence``: is identification's discretisation converged?

For each suite scene, the ground-truth simulation (true surfaces filled with particles, ground-truth
materials, settling, tools, forces) runs twice: at identification's default discretisation (grid from the
tissue's thickness, two particles per cell and axis, substeps from the CFL rule) and refined 2x (2x the
grid, half the particle spacing, 2x the substeps, :func:`endogsim.scene.discretisation.refine`). The tissue
Gaussians follow the particles of each run; the figure is

    rms_change = sqrt(mean_{t,g} |u_default - u_refined|^2) / sqrt(mean_{t,g} |u_refined|^2),

with u(t) = m_g(t) - m_g(0) the motion of Gaussian g over the clip (RMS over Gaussians and frames;
``rms_motion_mm`` is the refined run's, ``rms_motion_default_mm`` the default's: a change near 1 with a
default motion near 0 is a tool that moves the tissue only in the refined run). ``refine`` takes the
refinement apart: only the substeps (is the motion converged in time at identification's grid?), only
the particles, or only the grid (with the substeps its CFL rule then asks for). A
material fitted with a discretisation that a 2x refinement changes by more than a few percent is a property
of the discretisation, not of the tissue (DESIGN.md section 10). The target is ``rms_change <=``
:data:`TARGET_RMS_CHANGE` on every scene; each case says whether it is met (``converged``).
"""

from __future__ import annotations

import time
from dataclasses import replace

import torch

from endogsim.scene.discretisation import REFINE_PARTS

__all__ = ["TARGET_RMS_CHANGE", "REFINE_PARTS", "motion_of", "convergence_case", "refinement_sequence", "run_bench"]

#: The issue's target: a 2x refinement changes the motion by at most this (RMS, relative).
TARGET_RMS_CHANGE = 0.05


def motion_of(b, settings) -> tuple[torch.Tensor, int, int]:
    """Tissue Gaussian centres [T, G, 3] (metres) of built scene ``b`` simulated at ``settings``, and the
    particle count and substeps per frame it took."""
    from endogsim.physics import bind_gaussians, drive_gaussians, simulate
    from endogsim.synth.generate import ground_truth_problem

    filled, materials, scenario, config = ground_truth_problem(replace(b, ground_truth=settings))
    res = simulate(filled.particles, materials, scenario, config, b.frames)
    tissue = b.gaussians.subset(torch.from_numpy(b.tissue_gaussians))
    binding = bind_gaussians(tissue.means, tissue.object_ids, filled.particles)
    means = torch.stack([drive_gaussians(tissue, binding, res.positions[t], res.F[t], rotate_colors=False)[0]
                         for t in range(b.frames)])
    return means.double(), len(filled.particles), res.substeps


def _refined(b, factor: int, parts: tuple[str, ...] = REFINE_PARTS):
    """Identification's discretisation of built scene ``b`` at its true materials
    (:meth:`~endogsim.synth.scenes.BuiltScene.identification_at_truth`) refined ``factor`` times (1: itself) in
    ``parts`` (:func:`endogsim.scene.discretisation.refine`): factor 2 is the ground truth's discretisation."""
    from endogsim.scene.discretisation import refine
    from endogsim.scene.motion import tool_speed

    planned = b.identification_at_truth()
    if factor == 1:
        return planned
    return refine(planned, b.objects, b.box_size, b.frame_dt, tool_speed(b.tools, b.frame_dt), factor, parts=parts)


def _rms_change(coarse: torch.Tensor, fine: torch.Tensor) -> float:
    """RMS difference of two motions [T, G, 3] relative to the RMS of the second (module docstring)."""
    u_c, u_f = coarse - coarse[:1], fine - fine[:1]
    return float((u_c - u_f).square().sum(-1).mean().sqrt() / u_f.square().sum(-1).mean().sqrt().clamp_min(1e-12))


def _rms_mm(m: torch.Tensor) -> float:
    return 1e3 * float((m - m[:1]).square().sum(-1).mean().sqrt())


def convergence_case(name: str, frames: int | None = None, factor: int = 2,
                     refine: tuple[str, ...] = REFINE_PARTS, seed: int = 0) -> dict:
    """The RMS motion change of suite scene ``name`` (built with ``seed``: its texture and relief) between
    identification's discretisation and its ``factor``-times refinement of the ``refine`` parts of
    :data:`REFINE_PARTS` (see the module docstring)."""
    from endogsim.synth.scenes import build_procedural

    b = build_procedural(name, seed=seed, frames=frames)
    fine = _refined(b, factor, refine)
    t0 = time.perf_counter()
    coarse, n_coarse, sub_coarse = motion_of(b, _refined(b, 1))
    t1 = time.perf_counter()
    refined, n_fine, sub_fine = motion_of(b, fine)
    t2 = time.perf_counter()
    change = _rms_change(coarse, refined)
    return {"scene": name, "seed": seed, "frames": b.frames, "factor": factor, "refine": list(refine),
            "particles": n_coarse, "grid": b.identification.grid, "substeps": sub_coarse,
            "particle_spacing_mm": 1e3 * b.identification.particle_spacing,
            "refined_particles": n_fine, "refined_grid": fine.grid, "refined_substeps": sub_fine,
            "rms_motion_mm": _rms_mm(refined), "rms_motion_default_mm": _rms_mm(coarse), "rms_change": change,
            "converged": change <= TARGET_RMS_CHANGE,
            "seconds": round(t1 - t0, 1), "refined_seconds": round(t2 - t1, 1)}


def refinement_sequence(name: str, factors: list[int], frames: int | None = None, seed: int = 0) -> dict:
    """Suite scene ``name`` at identification's discretisation refined by each of ``factors`` (increasing;
    1 is the default itself), and the RMS motion change from each level to the next: how fast the motion
    settles under refinement (a change that does not fall does not converge).

    Returns:
        {"scene", "seed", "frames", "factors", "grid", "particles", "substeps", "rms_motion_mm", "seconds": one per
        level; "changes": one per pair of consecutive levels}
    """
    from endogsim.synth.scenes import build_procedural

    b = build_procedural(name, seed=seed, frames=frames)
    out = {"scene": name, "seed": seed, "frames": b.frames, "factors": list(factors), "grid": [], "particles": [],
           "substeps": [], "rms_motion_mm": [], "seconds": []}
    motions = []
    for f in factors:
        settings = _refined(b, f)
        t0 = time.perf_counter()
        m, n, sub = motion_of(b, settings)
        motions.append(m)
        out["grid"].append(settings.grid)
        out["particles"].append(n)
        out["substeps"].append(sub)
        out["rms_motion_mm"].append(_rms_mm(m))
        out["seconds"].append(round(time.perf_counter() - t0, 1))
    out["changes"] = [_rms_change(a, c) for a, c in zip(motions[:-1], motions[1:])]
    return out


def run_bench(scenes: list[str], frames: int | None = None, factor: int = 2, log=None,
              levels: list[int] | None = None, refine: tuple[str, ...] = REFINE_PARTS, seed: int = 0) -> dict:
    """:func:`convergence_case` for every scene in ``scenes`` (suite names; checked before any work) refining
    the ``refine`` parts, or with ``levels`` (increasing refinement factors from 1, every part) its
    :func:`refinement_sequence` instead; every scene built with ``seed`` (0: the figures of record; another
    seed is the same scene on another texture and relief).

    Returns:
        {"cases": [convergence_case(...), ...] or "sequences": [refinement_sequence(...), ...], "settings":
        {scenes, frames, factor and refine, or levels, target_rms_change, seed, generator_revision, push_contact_cells,
        threads}}
    """
    from endogsim.errors import DataError
    from endogsim.physics.particles import PUSH_CONTACT_CELLS
    from endogsim.synth.suite import GENERATOR_REVISION, suite_scene_names

    unknown = [s for s in scenes if s not in suite_scene_names()]
    if unknown:
        raise DataError(f"unknown suite scene(s) {', '.join(unknown)}; choose from {', '.join(suite_scene_names())}")
    if levels is None and factor < 2:
        raise DataError(f"refinement factor {factor} must be >= 2")
    if not refine or set(refine) - set(REFINE_PARTS):
        raise DataError(f"refine {', '.join(refine) or 'nothing'}: choose one or more of {', '.join(REFINE_PARTS)}")
    if levels is not None and set(refine) != set(REFINE_PARTS):
        raise DataError("a refinement sequence (levels) refines every part; refine one part with a factor instead")
    if levels is not None and (len(levels) < 2 or levels[0] != 1 or any(b <= a for a, b in zip(levels, levels[1:]))):
        raise DataError(f"refinement levels {levels} must start at 1 and increase (e.g. 1,2,3)")
    settings = {"scenes": list(scenes), "frames": frames, "target_rms_change": TARGET_RMS_CHANGE, "seed": seed,
                "generator_revision": GENERATOR_REVISION, "push_contact_cells": PUSH_CONTACT_CELLS,
                "threads": torch.get_num_threads()}
    if levels is not None:
        key, extra = "sequences", {"levels": list(levels)}

        def measure(name: str) -> dict:
            return refinement_sequence(name, levels, frames, seed)

        def describe(q: dict) -> str:
            return (f"rms changes {', '.join(f'{c:.3f}' for c in q['changes'])} "
                    f"({' -> '.join(f'{f}x' for f in levels)}; {sum(q['seconds']):.0f} s)")
    else:
        key, extra = "cases", {"factor": factor, "refine": list(refine)}

        def measure(name: str) -> dict:
            return convergence_case(name, frames, factor, refine, seed)

        def describe(c: dict) -> str:
            return (f"rms change {c['rms_change']:.3f} ({c['particles']} particles, grid {c['grid']}; "
                    f"{c['seconds'] + c['refined_seconds']:.0f} s)")
    results = []
    for name in scenes:
        results.append(measure(name))
        if log is not None:
            log(f"{name}: {describe(results[-1])}")
    return {key: results, "settings": {**settings, **extra}}
