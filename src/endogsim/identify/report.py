"""Evaluate identified materials and write a run folder.

Run folder written by :func:`write_outputs` (every file atomically):
  materials_identified.json   the identified material field (E Pa, nu, density kg/m^3; MaterialField JSON)
  materials_init.json         the field it started from
  metrics.json                RE (per object and mean, ``re_mean``) and |E/E_true - 1| (``e_rel_error_*``)
                              where the scene has ground truth; ``intervals`` (90%) and ``identifiable``
                              (per object and parameter, with the evidence); ``epe`` (px), ``psnr`` (dB),
                              ``ssim``, ``seconds`` (the iterations), ``stage_seconds`` (wall time of
                              each stage), ``iterations``, final loss, settings
  history.json                per-iteration loss, parameters, gradients
  loss.png, parameters.png    loss and parameter trajectories
  comparison.mp4              observed | simulated | flow error (|U_sim - U_gt| or, without ground truth,
                              |U_sim - U_observed|; colour scale 0..1 px)
  summary.txt                 a short text summary
  observed_flow.npz, checkpoint.pt   the cached observed flow and the resumable optimiser state
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from endogsim.determinism import deterministic
from endogsim.evaluate.flow_metrics import epe as epe_metric
from endogsim.evaluate.image_metrics import psnr, ssim
from endogsim.evaluate.material_metrics import scene_relative_errors
from endogsim.evaluate.plots import plot_loss, plot_parameters
from endogsim.evaluate.report_html import (
    correction_text,
    discretisation_text,
    force_scale_text,
    settling_text,
    simulated_at_text,
)
from endogsim.identify.config import IdentifyConfig
from endogsim.identify.loss import observed_flow as estimate_observed_flow
from endogsim.identify.optimize import IdentifyResult
from endogsim.identify.uncertainty import ParameterInterval
from endogsim.io.atomic import write_json_atomic, write_text_atomic
from endogsim.materials.field import MaterialField
from endogsim.physics import SETTLING_TOLERANCE
from endogsim.scene.coverage import Coverage, check_coverage, tissue_coverage
from endogsim.scene.folder import SimScene
from endogsim.scene.forward import Simulations, in_field_of_view, render_sequence

__all__ = ["Evaluation", "evaluate_field", "reference_observed_flow", "material_errors", "settling_record",
           "write_outputs"]

FLOW_ERROR_RANGE = 1.0  # pixels mapped to the top of the colour scale in the video


@dataclass
class Evaluation:
    """A forward simulation with given materials, rendered at full resolution, and its scores.

    Attributes:
        rgb: [T, H, W, 3] simulated frames; flow: [T-1, H, W, 2] Gaussian flow (pixels).
        epe: mean end-point error (px) over tissue pixels against the reference flow: the ground truth when
            the scene has it, else the observed flow estimate (``epe_reference`` says which); NaN with neither.
        psnr, ssim: simulated vs observed frames (all frames, whole image).
        flow_error: [T-1, H, W] |flow - reference| (px).
        coverage: the tissue's rendered coverage per frame (:mod:`endogsim.scene.coverage`).
        epe_reference: "ground truth", "observed flow" or "none".
        settling_left: the largest particle motion (metres) over the last settling frame
            (:attr:`endogsim.physics.SimResult.settling_left`).
    """

    rgb: np.ndarray
    flow: np.ndarray
    epe: float
    psnr: float
    ssim: float
    flow_error: np.ndarray
    coverage: Coverage
    epe_reference: str = "ground truth"
    settling_left: float = 0.0


@deterministic()  # the same numbers wherever it runs (identification evaluates it on a worker thread)
def evaluate_field(problem: SimScene, fld: MaterialField, observed_flow: np.ndarray | None = None,
                   known: Simulations | None = None) -> Evaluation:
    """Simulate ``fld`` (no gradients; substeps from the CFL rule), render, and score it. A simulation of the
    same materials in ``known`` (e.g. :attr:`IdentifyResult.simulations`) is used instead of simulating again."""
    with torch.no_grad():
        mats = fld.simulator_materials()
        res = None if known is None else known.find(mats, problem.simulator())
        if res is None:
            res = problem.simulator().simulate(mats)
        r = render_sequence(problem, res.positions, res.F, problem.camera)
        cov = tissue_coverage(problem, res.positions, res.F, problem.camera.scaled(0.5))
    rgb = r.rgb.clamp(0, 1).numpy()
    flow = r.flow.numpy()
    obs = problem.frames
    p = psnr(torch.from_numpy(rgb), torch.from_numpy(obs))
    s = ssim(torch.from_numpy(rgb), torch.from_numpy(obs))
    tissue = None
    if problem.object_masks is not None:
        on = np.isin(problem.object_masks, problem.deformable_ids)
        tissue = on[:-1] & on[1:]
    if problem.gt_flow is not None:
        ref, src = problem.gt_flow, "ground truth"
        valid = problem.gt_flow_valid if tissue is None else problem.gt_flow_valid & tissue
    elif observed_flow is not None:
        ref, src, valid = observed_flow, "observed flow", tissue
    else:
        ref, src, valid = None, "none", None
    e = math.nan if ref is None else epe_metric(flow, ref, valid)
    err = flow_error_map(problem, flow, ref)
    return Evaluation(rgb, flow, float(e), float(p), float(s), err, cov, src, res.settling_left)


def flow_error_map(problem: SimScene, flow: np.ndarray, reference: np.ndarray | None) -> np.ndarray:
    """|``flow`` - ``reference``| [T-1, H, W] (px; against zero without a reference) where the camera films:
    0 outside the endoscope's field of view, where the observed flow's estimate bleeds into the black border
    and no score counts it (EPE is over tissue pixels)."""
    err = np.linalg.norm(flow - (np.zeros_like(flow) if reference is None else reference), axis=-1)
    return in_field_of_view(problem, torch.from_numpy(err)[..., None])[..., 0].numpy()


def discretisation_record(problem: SimScene, refine: float, field: MaterialField | None = None) -> dict:
    """metrics.json's ``discretisation``: what identification simulated at. {"refine" (the factor on the
    scene's identification discretisation), "grid" (cells per edge of the sim box), "cell_m" (metres),
    "particle_spacing_m", "particles", "substeps" (per frame, the least: identification's count planned at its
    initial materials (:func:`~endogsim.identify.optimize.planned_for`), else the scene's floor; a material that
    needs more by the CFL rule simulates at more), "substeps_at_materials" (per frame, what ``field`` simulates at;
    None without one)}."""
    s = problem.settings
    at = None
    if field is not None:
        at = problem.simulator().timestep(field.simulator_materials(), problem.particles.v).substeps
    return {"refine": float(refine), "grid": int(s.grid), "cell_m": problem.scenario.box.size / s.grid,
            "particle_spacing_m": s.particle_spacing, "particles": len(problem.particles),
            "substeps": int(problem.mpm.substeps_per_frame),
            "substeps_at_materials": at}


def correction_record(result: IdentifyResult, field_refine: float) -> dict | None:
    """metrics.json's ``refined_correction``: :class:`~endogsim.identify.refined_correction.Correction`'s
    record, with ``applied`` (whether it moved the materials) and the refined ``discretisation``
    (:func:`discretisation_record` at ``field_refine``, the factor the field belongs to; None where the correction
    took no step). None: no correction was made."""
    c = result.correction
    if c is None:
        return None
    at = None if result.refined is None else discretisation_record(result.refined, field_refine, result.field)
    return {**c.to_json(), "applied": result.refined is not None, "discretisation": at}


def settling_record(problem: SimScene, settling_left: float) -> dict:
    """What the settling before frame 0 left (``settling_left``: :attr:`endogsim.physics.SimResult.
    settling_left`, metres): {"frames", "gravity" (whether gravity acted: without it the settling relaxes the
    tissue against the instruments at their frame-0 pose), "last_frame_motion_m", "cells" (of the grid), "settled"
    (at most "tolerance_cells", :data:`SETTLING_TOLERANCE`)}."""
    cells = problem.scenario.settling_cells(settling_left, problem.mpm.grid_res)
    return {"frames": problem.scenario.settle_frames, "gravity": any(float(g) != 0.0 for g in problem.scenario.gravity),
            "last_frame_motion_m": settling_left, "cells": cells,
            "settled": bool(cells <= SETTLING_TOLERANCE), "tolerance_cells": SETTLING_TOLERANCE}


def force_scale_record(problem: SimScene) -> dict:
    """metrics.json's ``force_scales``: what gives E an absolute scale in this scene's simulations.

    Kinematic instruments and held borders prescribe displacements, which alone fix nu and the ratios of E,
    not E (DESIGN.md section 10): E is set against the tissue's weight, its inertia (against its damping) and
    any applied force. An identified E holds for the values here; on a real video they are the scenario's
    assumptions (docs/REAL_VIDEO.md sections 3 and 17), and E moves with them. {"gravity_m_s2" [3] (the scene's
    frame), "frame_dt_s", "damping_per_s" (grid velocity damping), "mass_scaling" (inertia multiplied by it;
    weight and damping forces unchanged), "applied_forces", "impulses", "kinematic_instruments", "scales": those
    present of "weight", "inertia", "applied force"}."""
    sc, mpm = problem.scenario, problem.mpm
    forces = [f for f in sc.forces if not f.impulse]
    impulses = [f for f in sc.forces if f.impulse]
    gravity = [float(v) for v in sc.gravity]
    scales = (["weight"] if any(gravity) else []) + ["inertia"] + (["applied force"] if sc.forces else [])
    return {"gravity_m_s2": gravity, "frame_dt_s": float(mpm.frame_dt), "damping_per_s": float(mpm.damping),
            "mass_scaling": float(sc.mass_scaling), "applied_forces": len(forces), "impulses": len(impulses),
            "kinematic_instruments": len(sc.colliders), "scales": scales}


def material_errors(problem: SimScene, fld: MaterialField) -> dict | None:
    """RE of the deformable objects against ``scene.json``'s ground truth (every synthesized scene has it)."""
    if not problem.has_ground_truth:
        return None
    truth = {o.name: (o.E, o.nu) for o in problem.spec.objects if not o.rigid}
    est = {o.name: (fld[o.id].E, fld[o.id].nu) for o in problem.spec.objects if not o.rigid}
    return scene_relative_errors(est, truth)


def _colormap(err: np.ndarray, vmax: float) -> np.ndarray:
    import cv2

    u8 = (np.clip(err / vmax, 0, 1) * 255).astype(np.uint8)
    return cv2.applyColorMap(u8, cv2.COLORMAP_INFERNO)[..., ::-1].astype(np.float32) / 255.0


def interval_table(intervals: list[ParameterInterval]) -> dict:
    """{object name: {"E": [lo, hi] Pa, "nu": [lo, hi]}} of the 90% intervals."""
    out: dict = {}
    for iv in intervals:
        out.setdefault(iv.name, {})[iv.parameter] = iv.interval
    return out


def interval_lines(intervals: list[ParameterInterval]) -> list[str]:
    """summary.txt's lines for one object's 90% intervals, printed under that object's own line (with the noise
    and discretisation parts where the discretisation was measured)."""
    lines = []
    for iv in intervals:
        unit = " Pa" if iv.parameter == "E" else ""
        lines.append(f"    {iv.parameter} 90% interval [{iv.interval[0]:.4g}, {iv.interval[1]:.4g}]{unit}: "
                     f"{'identifiable' if iv.identifiable else 'NOT identifiable'} ({iv.reason})")
        if iv.discretisation is not None:
            lo, hi = iv.statistical_interval
            lines.append(f"      of which the video's noise [{lo:.4g}, {hi:.4g}]{unit}; the discretisation "
                         f"{discretisation_text(iv.parameter, iv.discretisation, iv.search_box)}")
    return lines


def identifiable_table(intervals: list[ParameterInterval]) -> dict:
    """{object name: {parameter: {"identifiable": bool, "reason", "interval", "statistical_interval",
    "discretisation", "search_box", "best", "prior_check", "evidence"}}} (as in :class:`ParameterInterval`; the
    statistical interval and the discretisation None where the discretisation error was not measured, the prior
    check None where no one-sided exclusion of the prior was checked). ``evidence`` holds the slice through the
    optimum and ``partner_slices``, the slices at the ends of a partner's interval where the video does not
    determine it."""
    out: dict = {}
    for iv in intervals:
        out.setdefault(iv.name, {})[iv.parameter] = {
            "identifiable": iv.identifiable, "reason": iv.reason, "interval": iv.interval,
            "statistical_interval": iv.statistical_interval, "discretisation": iv.discretisation,
            "search_box": iv.search_box, "best": iv.best, "prior_check": iv.prior_check,
            "evidence": {"first_gradient": iv.first_gradient, "critical_z": iv.critical_z,
                         "significant_z": iv.significant_z, "min_relative_rise": iv.min_relative_rise,
                         "slice": _slice_json(iv.slice),
                         "partner_slices": [{**p, "slice": _slice_json(p["slice"])} for p in iv.partner_slices]}}
    return out


def _slice_json(records: list[list[float]]) -> list[dict]:
    """A slice's [[value, Delta L, SE, z], ...] as records."""
    return [{"value": v, "delta_loss": d, "noise": se, "z": z} for v, d, se, z in records]


def comparison_frames(observed: np.ndarray, simulated: np.ndarray, flow_error: np.ndarray) -> np.ndarray:
    """[T, H, 3W, 3] frames: observed | simulated | flow error (inferno, 0..1 px; last frame repeats)."""
    T = observed.shape[0]
    errs = [flow_error[min(t, flow_error.shape[0] - 1)] for t in range(T)] if flow_error.shape[0] else \
        [np.zeros(observed.shape[1:3]) for _ in range(T)]
    return np.stack([np.concatenate([observed[t], simulated[t], _colormap(errs[t], FLOW_ERROR_RANGE)], 1)
                     for t in range(T)])


def reference_observed_flow(problem: SimScene, config: IdentifyConfig, run_dir: str | Path) -> np.ndarray | None:
    """The observed flow [T-1, H, W, 2] (px) an evaluation of ``problem`` compares with: identification's own
    estimate, read through its cache in ``run_dir`` (keyed by the frames and the estimator, so a stale file is
    never served; :func:`~endogsim.identify.loss.observed_flow`). None where the scene has ground-truth flow,
    which :func:`evaluate_field` uses instead."""
    if problem.gt_flow is not None:
        return None
    return estimate_observed_flow(problem.frames, config.flow, Path(run_dir) / "observed_flow.npz")


def write_outputs(run_dir: str | Path, problem: SimScene, result: IdentifyResult, config: IdentifyConfig,
                  init_name: str, video: bool = True, evaluate_init: bool = False) -> dict:
    """Evaluate the identified field (unless ``result.evaluation`` holds its evaluation) and write the run
    folder (see the module docstring). Returns metrics."""
    from endogsim.io.video_writer import write_video

    run = Path(run_dir)
    run.mkdir(parents=True, exist_ok=True)
    # "refine" and "substeps": the discretisation the field belongs to (the refined one after a correction that
    # moved it) and the floor of substeps per frame it was fitted with there; `endogsim simulate` simulates it so
    refine = config.refine * (result.correction.factor if result.refined is not None else 1.0)
    fitted = next(pb for pb in (result.refined, result.scene, problem) if pb is not None)
    result.field.meta = {**result.field.meta, "identified_from": str(problem.folder), "init": init_name,
                         "refine": float(refine), "substeps": int(fitted.mpm.substeps_per_frame)}
    result.field.save(run / "materials_identified.json")
    result.init_field.save(run / "materials_init.json")
    write_json_atomic(run / "history.json", result.history)
    ev, t_eval = result.evaluation, time.perf_counter()
    # The observed flow (pulling: 41 MB) is read only for an evaluation still to make.
    to_evaluate = evaluate_init or not isinstance(ev, Evaluation)
    obs_flow = reference_observed_flow(problem, config, run) if to_evaluate else None
    if not isinstance(ev, Evaluation):  # where the field belongs
        ev = (evaluate_field(problem, result.field, obs_flow, result.simulations) if result.refined is None else
              evaluate_field(result.refined, result.field, obs_flow, result.refined_simulations))
    # Wall time by stage: the iterations (over resumes), the intervals and the refined correction (this call),
    # and the evaluation left to do here (none where it ran beside the intervals' trials).
    stage_seconds = {"iterations": result.seconds, **result.stage_seconds,
                     "evaluation": time.perf_counter() - t_eval}
    re = material_errors(problem, result.field)
    stride = config.stride(problem.num_frames)
    metrics: dict = {
        "scene": problem.spec.name, "folder": str(Path(problem.folder).resolve()),
        "folder_from_run": os.path.relpath(Path(problem.folder).resolve(), Path(run_dir).resolve()), "init": init_name,
        "loss": config.loss, "grad_mode": config.grad_mode, "global_material": config.global_material,
        "frame_stride": stride,  # the one used (the config's None: automatic)
        "iterations": result.iterations, "best_iteration": result.best_iteration, "best_loss": result.best_loss,
        "stopped": result.stopped, "stopped_by_budget": result.stopped == "time_budget", "seconds": result.seconds,
        "stage_seconds": stage_seconds,
        "epe": ev.epe, "epe_reference": ev.epe_reference, "psnr": ev.psnr, "ssim": ev.ssim,
        "coverage": ev.coverage.to_json(), "settling": settling_record(problem, ev.settling_left),
        "discretisation": discretisation_record(problem, config.refine, result.field),
        "force_scales": force_scale_record(problem),
        "refined_correction": correction_record(result, refine),
        "materials": {r.name: {"object_id": r.object_id, "E": r.E, "nu": r.nu, "density": r.density, "rigid": r.rigid,
                               "model": r.model, "source": r.source}
                      for r in result.field.records},
        "intervals": interval_table(result.intervals),
        "identifiable": identifiable_table(result.intervals),
        "units": {"E": "Pa", "density": "kg/m^3", "epe": "px", "psnr": "dB", "seconds": "s", "intervals": "90%"},
        "notes": result.notes, "config": config.to_json(),
    }
    if re is not None:
        metrics.update({k: v for k, v in re.items() if k != "objects"})
        metrics["re_objects"] = re["objects"]
    if evaluate_init:
        ev0 = evaluate_field(problem, result.init_field, obs_flow, result.simulations)
        re0 = material_errors(problem, result.init_field)
        metrics["init_metrics"] = {"epe": ev0.epe, "psnr": ev0.psnr, "ssim": ev0.ssim,
                                   **({"re_mean": re0["re_mean"]} if re0 else {})}
    write_json_atomic(run / "metrics.json", metrics)

    names = {str(o.id): o.name for o in problem.spec.objects}
    truth = {str(o.id): (o.E, o.nu) for o in problem.spec.objects if not o.rigid} if problem.has_ground_truth else {}
    if result.history:
        plot_loss(result.history, run / "loss.png", result.best_iteration, title=f"{problem.spec.name}: {config.loss} loss")
        plot_parameters(result.history, run / "parameters.png", names, truth)
    if video:
        write_video(comparison_frames(problem.frames, ev.rgb, ev.flow_error), run / "comparison.mp4", fps=10)
    lines = [f"EndoGSim identification of {problem.folder} ({problem.spec.name})",
             f"init {init_name}; loss {config.loss}; grad mode {config.grad_mode}; "
             f"{'global material' if config.global_material else 'object-wise material field'}; "
             f"{len(range(0, problem.num_frames, stride))} of {problem.num_frames} frames compared (stride {stride})",
             f"{result.iterations} iterations ({result.stopped}), best at iteration {result.best_iteration}, "
             f"{result.seconds:.1f} s",
             f"simulated at {simulated_at_text(metrics['discretisation'])}",
             f"E's scale: {force_scale_text(metrics['force_scales'])}"]
    if metrics["refined_correction"] is not None:
        lines.append(f"refined correction: {correction_text(metrics['refined_correction'])}")
    for r in result.field.records:
        init = result.init_field[r.object_id]
        kind = "rigid (frozen)" if r.rigid else f"{r.source}; from E {init.E:.4g} Pa, nu {init.nu:.3f}"
        lines.append(f"  {r.name} (id {r.object_id}): E = {r.E:.4g} Pa, nu = {r.nu:.3f}  [{kind}]")
        lines += interval_lines([iv for iv in result.intervals if iv.object_id == r.object_id])
    if re is not None:
        lines.append(f"RE: E {re['re_E']:.3f}, nu {re['re_nu']:.3f}, G {re['re_G']:.3f}, K {re['re_K']:.3f}; "
                     f"mean {re['re_mean']:.3f}; |E/E_true - 1| mean {re['e_rel_error_mean']:.3f}, "
                     f"median {re['e_rel_error_median']:.3f}")
    lines.append(f"EPE {ev.epe:.3f} px (against the {ev.epe_reference}), PSNR {ev.psnr:.2f} dB, SSIM {ev.ssim:.4f}")
    oid, frame, drop = ev.coverage.worst()
    lines.append(f"tissue coverage: largest drop {100 * drop:.2f}% of the footprint beyond the video's own"
                 + (f" ({problem.spec.object(oid).name}, frame {frame})" if oid is not None and drop > 0 else ""))
    settle = metrics["settling"]
    if settle["frames"]:
        lines.append(f"settling: {settling_text(settle)}")
    lines += [f"note: {n}" for n in result.notes]
    write_text_atomic(run / "summary.txt", "\n".join(lines) + "\n")
    check_coverage(ev.coverage, problem)  # after writing: the run folder shows the tear
    return metrics
