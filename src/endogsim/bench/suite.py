"""``endogsim bench suite``: the benchmark suite and the paper's tables, in this process or on a Ray cluster.

For every suite scene (``endogsim/data/benchmark_suite.json``; ``tiny`` is a test scene and is not in the
default list) :func:`run_scene` synthesizes the scene once (cached under the scenes folder), then identifies
its materials from the ``manual`` and the ``prior`` initialisation, each with optimisation off (iters 0:
the initial guess scored) and on; on ``two_tissues`` it adds one run with a single global material.
Only the full method's run (``prior_on``) measures the 90% intervals and identifiability of every parameter
(:mod:`endogsim.identify.uncertainty`, about ten forward simulations per object); the others skip them.
The tables:

  Table 2  per scene (prior initialisation, optimisation on: the full method): RE, EPE, |E/E_true - 1|
           (median over the scene's objects), the share of the scene's objects whose true E and true nu lie
           in their 90% interval, how many are identifiable, seconds per iteration, the iterations run (and
           what stopped them) and the seconds of the whole identification; the last row is the suite (RE, EPE
           and seconds averaged over the scenes as in the paper; the others over every deformable object)
  Table 2, per object: identified and true E and nu, |E/E_true - 1|, the 90% intervals, their widths and
           the identifiable flags; its note gives the suite's interval coverage (E, nu and both pooled) and
           mean widths (decades of E)
  Table 3  initialisation x optimisation: RE / EPE / FID averaged over the scenes (FID only with a local
           Inception weights file, else "n/a")
  Ablation object-wise material field vs one global material on ``two_tissues``

RE = mean relative error of E, nu, G, K against the ground truth; EPE in pixels against the ground-truth
flow.

The figures do not depend on the machine's speed: every optimised run does its :data:`DEFAULT_ITERS`
iterations (or ``--iters``) unless the loss's own rules end it sooner, and no time budget cuts it
(identification's own default, a 480-s safety stop, let a 2-core CPU's load decide how many iterations a
scene got; docs/IDENTIFICATION.md section 4). ``--time-budget`` puts a stop back; Table 2 then names the
runs it cut. ``--runs`` measures a subset of the runs (the full method alone: ``--runs prior_on``).

``--ray`` runs :func:`run_scene` for the scenes in parallel as Ray tasks (one CPU each), on a local cluster
started for the run or on ``--ray-address ADDRESS``; without it they run one after the other here.

A suite takes about 40 minutes on a 2-core CPU (hours at ``--refine 1.5``), so it resumes: each scene's record
is written to ``WORK/NAME/scene_result.json`` when the scene is done, and a later run into the same work folder
reuses it when everything the record depends on is the same (the settings, the synthesized scene's files and
this package's code); ``--fresh`` runs every scene again.

``--seed S`` runs the suite on another texture, relief and noise of every scene (the same experiment on another
surface: the instrument's path follows the relief, :mod:`endogsim.synth.scenes`); the figures of record are seed
0's. A seed whose ground truth the generator refuses (it tears a bite out or parts the tissue: numerical
fracture, :class:`~endogsim.errors.GroundTruthRefused`) is no fair test at that seed: the scene is left out of the
tables, and Table 2's note names it and why.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Sequence

from endogsim.bench.identify import SCENES_CACHE
from endogsim.errors import EndoGSimError, GroundTruthRefused
from endogsim.identify.config import DEFAULT_REFINED_CORRECTION
from endogsim.io.atomic import write_json_atomic
from endogsim.io.runfolder import code_digest, json_digest, tree_digest

__all__ = ["run_scene", "scene_or_refusal", "run_suite", "suite_tables", "object_results", "interval_summary",
           "suite_objects", "DEFAULT_ITERS", "RUN_KEYS"]

RUNS = (("manual", False), ("manual", True), ("prior", False), ("prior", True))
ABLATION_SCENE = "two_tissues"


def run_key(init: str, on: bool) -> str:
    """The key (and run folder) of the run from ``init`` with optimisation ``on`` or off, e.g. "prior_on"."""
    return f"{init}_{'on' if on else 'off'}"


#: Every run key :func:`run_scene` knows: the four of :data:`RUNS` and the global-material ablation.
RUN_KEYS = tuple(run_key(init, on) for init, on in RUNS) + ("global_on",)
FULL_METHOD = run_key("prior", True)
#: Iterations of an optimised run. With no time budget (module docstring) a scene's full method then takes
#: 5-12 minutes on a 2-core CPU (docs/IDENTIFICATION.md section 4 has each scene's seconds per iteration).
DEFAULT_ITERS = 10


def check_coarser_than_ground_truth(scenes: Sequence[str], refine: float,
                                    refined_correction: float | None = None) -> None:
    """Refuse identifying suite ``scenes`` refined ``refine`` times, or correcting the estimate to that refined
    ``refined_correction`` times more, when that is at least as fine as their ground truth was simulated
    (``ground_truth_refine``): a fit at the truth's own discretisation hides the simulator's error (an inverse
    crime)."""
    from endogsim.synth.suite import scene_spec

    finest = refine * (refined_correction or 1.0)
    as_fine = [s for s in scenes if finest >= scene_spec(s)["ground_truth_refine"]]
    if as_fine:
        what = f"--refine {refine:g}" + (f" with --refined-correction {refined_correction:g}" if refined_correction
                                         else "")
        raise EndoGSimError(f"{what} identifies {', '.join(as_fine)} at least as finely ({finest:g}x) as their "
                            "ground truth was simulated: a fit at the truth's own discretisation hides the simulator's "
                            "error (an inverse crime); use factors whose product lies below the scenes' "
                            "ground_truth_refine (--refined-correction 0: no correction)")


def _default_scenes() -> list[str]:
    from endogsim.synth.suite import SMALL_SCENES, suite_scene_names

    return [n for n in suite_scene_names() if n not in SMALL_SCENES]


def run_scene(name: str, scenes_dir: str | os.PathLike, work_dir: str | os.PathLike, iters: int = DEFAULT_ITERS,
              frames: int | None = None, render_scale: float = 0.5, global_ablation: bool | None = None,
              fid_weights: str | None = None, threads: int | None = None, runs: Sequence[str] | None = None,
              time_budget: float | None = None, optimizer: str = "rprop", refine: float = 1.0,
              refined_correction: float | None = DEFAULT_REFINED_CORRECTION,
              device: str = "cpu", fresh: bool = False, workers: int | None = None, seed: int = 0) -> dict:
    """Synthesize (or reuse) scene ``name`` and run its identifications (or reuse their stored record); the unit
    of work of both paths.

    Args:
        name: suite scene.
        scenes_dir: cache of synthesized scenes (``NAME`` or ``NAME_fFRAMES``).
        work_dir: run folders go to ``work_dir/NAME/{manual,prior}_{off,on}`` (and ``global_on``;
            ``NAME_seedS`` for a seed other than 0).
        iters: optimisation iterations of the "on" runs.
        frames: synthesize only this many frames (default: the suite's).
        render_scale: identification render scale.
        global_ablation: add the global-material run (default: only on ``two_tissues``).
        fid_weights: local Inception weights; FID of every run's simulated vs observed frames.
        threads: torch threads in this process (Ray tasks use 1 so parallel scenes do not oversubscribe).
        runs: the run keys to do (of :data:`RUN_KEYS`; default all, ``global_on`` only where the ablation
            runs).
        time_budget: identification's safety stop in seconds (None: none; the module docstring says why).
        optimizer: identification's optimiser (``IdentifyConfig.optimizer``; the default's figures are the
            suite's).
        refine: identify at the scene's identification discretisation refined by this factor
            (``IdentifyConfig.refine``); it must stay coarser than the ground truth's simulation.
        refined_correction: the estimate's refined correction (``IdentifyConfig.refined_correction``; default
            identification's, None: none); ``refine`` times this must stay coarser than the ground truth's
            simulation too.
        device: identification's simulator and renderer ("cpu" or "cuda"; ``IdentifyConfig.device``). The
            ground truth is synthesized on the CPU either way.
        fresh: run the identifications even where ``work_dir/NAME/scene_result.json`` holds a record made with
            the same settings, scene and code (module docstring).
        workers: simulations run side by side (:func:`~endogsim.warp_runtime.simulations_side_by_side`; None: one
            per torch thread). The results do not depend on it, only the time does.
        seed: the scene's seed (:func:`~endogsim.bench.identify.ensure_scene`; 0: the suite's figures).
    Raises:
        GroundTruthRefused: the generator refuses this seed's ground truth (:func:`scene_or_refusal` records it).
    Returns:
        {"scene", "seed", "folder", "runs": {key: {re_mean, re_E, re_nu, e_rel_error_mean, e_rel_error_median, epe,
        psnr, ssim, fid, seconds (optimisation), iterations, seconds_per_iteration, stopped, stopped_by_budget,
        wall_seconds (the whole identification: optimisation, intervals and evaluation), stage_seconds (its
        stages', metrics.json's), materials}},
        "wall_seconds" (of the run that made the record), "reused" (whether this call reused it)};
        ``materials`` is :func:`object_results` (intervals only in ``prior_on``).
    """
    import torch

    from endogsim.bench.identify import ensure_scene
    from endogsim.identify import IdentifyConfig, run_identify
    from endogsim.scene.folder import load_sim_scene
    from endogsim.warp_runtime import simulations_side_by_side

    if threads:
        torch.set_num_threads(threads)
    check_coarser_than_ground_truth([name], refine, refined_correction)
    t0 = time.perf_counter()
    work = Path(work_dir) / (name if seed == 0 else f"{name}_seed{seed}")
    folder = ensure_scene(name, Path(scenes_dir), frames, seed=seed)
    plan = [(run_key(init, on), init, on, False) for init, on in RUNS]
    if global_ablation if global_ablation is not None else name == ABLATION_SCENE:
        plan.append(("global_on", "prior", True, True))
    plan = [p for p in plan if runs is None or p[0] in runs]
    record_file = work / "scene_result.json"
    signature = json_digest({"scene": name, "seed": seed, "scene_files": tree_digest(folder), "code": code_digest(),
                             "runs": [p[0] for p in plan], "iters": iters, "frames": frames,
                             "render_scale": render_scale, "fid_weights": tree_digest(fid_weights) if fid_weights
                             else None, "time_budget": time_budget, "optimizer": optimizer, "refine": refine,
                             "refined_correction": refined_correction, "device": device})
    if not fresh and record_file.is_file():
        try:
            record = json.loads(record_file.read_text())
        except ValueError:  # a damaged record is made again
            record = None
        if isinstance(record, dict) and record.get("signature") == signature:
            return {**record["result"], "reused": True}
    problem = load_sim_scene(folder, refine=refine, device=device)
    net = None
    if fid_weights:
        from endogsim.evaluate.fid import load_inception

        net = load_inception(fid_weights)
    truth = {o.name: (o.E, o.nu) for o in problem.spec.objects if not o.rigid and o.has_material}
    done = {}
    for key, init, on, glob in plan:
        cfg = IdentifyConfig(iters=iters if on else 0, render_scale=render_scale, global_material=glob,
                             intervals=key == FULL_METHOD, time_budget=time_budget, optimizer=optimizer,
                             refine=refine, refined_correction=refined_correction, device=device)
        t_run = time.perf_counter()
        with simulations_side_by_side(workers):
            m = run_identify(folder, work / key, init=init, config=cfg, resume=False, video=False, problem=problem)
        rec = {k: m.get(k, math.nan) for k in ("re_mean", "re_E", "re_nu", "e_rel_error_mean", "e_rel_error_median",
                                               "epe", "psnr", "ssim", "seconds", "iterations")}
        rec["seconds_per_iteration"] = m["seconds"] / m["iterations"] if m.get("iterations") else None
        rec["stopped"] = m.get("stopped")
        rec["stopped_by_budget"] = m.get("stopped_by_budget", False)
        rec["wall_seconds"] = time.perf_counter() - t_run
        rec["stage_seconds"] = m.get("stage_seconds")
        rec["materials"] = object_results(m, truth)
        rec["fid"] = _run_fid(problem, work / key, net, cfg) if net is not None else None
        done[key] = rec
    result = {"scene": name, "seed": seed, "folder": str(folder), "runs": done,
              "wall_seconds": time.perf_counter() - t0}
    write_json_atomic(record_file, {"signature": signature, "result": result})
    return {**result, "reused": False}


def scene_or_refusal(**kwargs) -> dict:
    """:func:`run_scene` (``kwargs`` its arguments), or where the generator refuses the scene's ground truth at
    this seed, the record {"scene", "seed", "refused": why} (the suite leaves the scene out and names it)."""
    try:
        return run_scene(**kwargs)
    except GroundTruthRefused as exc:
        return {"scene": kwargs["name"], "seed": kwargs.get("seed", 0), "refused": str(exc)}


def object_results(metrics: dict, truth: dict[str, tuple[float, float]]) -> dict[str, dict]:
    """Per deformable object of a run's ``metrics.json``: what was identified against the truth.

    Args:
        metrics: :func:`endogsim.identify.run_identify`'s metrics.
        truth: {object name: (E Pa, nu)} of the ground truth.
    Returns:
        {name: {"E", "nu" (identified; Pa), "source", "E_true", "nu_true", "e_rel_error" (|E/E_true - 1|),
        "E_interval" ([lo, hi] Pa), "nu_interval", "E_interval_statistical", "nu_interval_statistical" (the
        frame-to-frame noise alone, before the discretisation error widened them; the interval itself where
        none was measured), "E_identifiable", "nu_identifiable"}}; None where the run did not measure it (no
        truth, intervals off or no iteration run).
    """
    out = {}
    for name, v in metrics["materials"].items():
        if v["rigid"]:
            continue
        iv = metrics.get("intervals", {}).get(name, {})
        ok = metrics.get("identifiable", {}).get(name, {})
        E_true, nu_true = truth.get(name, (None, None))

        def statistical(what: str) -> list[float] | None:  # no discretisation error measured: the same interval
            return (ok[what].get("statistical_interval") or iv.get(what)) if what in ok else None

        out[name] = {"E": v["E"], "nu": v["nu"], "source": v.get("source"), "E_true": E_true, "nu_true": nu_true,
                     "e_rel_error": metrics.get("re_objects", {}).get(name, {}).get("e_rel_error"),
                     "E_interval": iv.get("E"), "nu_interval": iv.get("nu"),
                     "E_interval_statistical": statistical("E"), "nu_interval_statistical": statistical("nu"),
                     "E_identifiable": ok.get("E", {}).get("identifiable"),
                     "nu_identifiable": ok.get("nu", {}).get("identifiable")}
    return out


def interval_summary(objects: list[dict]) -> dict:
    """Coverage and width of the 90% intervals over ``objects`` (records of :func:`object_results`).

    Returns:
        {"objects", "e_rel_error_median", "coverage_E", "coverage_nu", "coverage" (E and nu intervals
        pooled), "n_E", "n_nu" (intervals measured with a truth to check), "mean_width_E_decades",
        "mean_width_nu", "identifiable_E", "identifiable_nu" (counts), "coverage_statistical_E",
        "coverage_statistical_nu", "coverage_statistical" (the same for the intervals of the frame-to-frame
        noise alone, where the discretisation error was measured)}; NaN where nothing was measured.
    """
    import statistics

    def inside(o: dict, what: str, kind: str = "") -> bool | None:
        iv, true = o.get(f"{what}_interval{kind}"), o[f"{what}_true"]
        return None if iv is None or true is None else bool(iv[0] <= true <= iv[1])

    hits = {w: [h for h in (inside(o, w) for o in objects) if h is not None] for w in ("E", "nu")}
    stat = {w: [h for h in (inside(o, w, "_statistical") for o in objects) if h is not None] for w in ("E", "nu")}
    frac = lambda xs: sum(xs) / len(xs) if xs else math.nan  # noqa: E731
    errs = [o["e_rel_error"] for o in objects if o["e_rel_error"] is not None]
    return {
        "objects": len(objects),
        "e_rel_error_median": statistics.median(errs) if errs else math.nan,
        "coverage_E": frac(hits["E"]), "coverage_nu": frac(hits["nu"]), "coverage": frac(hits["E"] + hits["nu"]),
        "n_E": len(hits["E"]), "n_nu": len(hits["nu"]),
        "mean_width_E_decades": _mean([math.log10(o["E_interval"][1] / o["E_interval"][0])
                                       for o in objects if o["E_interval"] is not None]),
        "mean_width_nu": _mean([o["nu_interval"][1] - o["nu_interval"][0]
                                for o in objects if o["nu_interval"] is not None]),
        "identifiable_E": sum(bool(o["E_identifiable"]) for o in objects),
        "identifiable_nu": sum(bool(o["nu_identifiable"]) for o in objects),
        "coverage_statistical_E": frac(stat["E"]), "coverage_statistical_nu": frac(stat["nu"]),
        "coverage_statistical": frac(stat["E"] + stat["nu"]),
    }


def _run_fid(problem, run_dir: Path, net, config) -> float:
    """FID between the observed frames and the frames simulated with the run's identified materials (on the
    scene planned at its initial materials, as the run simulated them)."""
    from endogsim.evaluate.fid import fid
    from endogsim.identify.optimize import planned_for
    from endogsim.identify.report import evaluate_field
    from endogsim.materials.field import MaterialField

    planned = planned_for(problem, MaterialField.load(run_dir / "materials_init.json"), config)
    ev = evaluate_field(planned, MaterialField.load(run_dir / "materials_identified.json"))
    return fid(problem.frames, ev.rgb, net=net)


def _ray_map(kwargs_list: list[dict], address: str | None, log) -> list[dict]:
    """:func:`scene_or_refusal` over ``kwargs_list`` as Ray tasks; results in input order."""
    try:
        import ray
    except ImportError:
        raise EndoGSimError("--ray needs Ray, which is not installed: pip install 'endogsim[ray]'") from None
    started = not ray.is_initialized()
    if started:
        # One CPU per scene; the workers inherit this interpreter (and so the installed endogsim).
        env = {"env_vars": {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}}
        if address:
            ray.init(address=address, runtime_env=env, log_to_driver=False)
        else:
            ray.init(include_dashboard=False, runtime_env=env, log_to_driver=False)
    try:
        log(f"ray: {ray.cluster_resources().get('CPU', 0):.0f} CPUs, {len(kwargs_list)} scene tasks")
        task = ray.remote(num_cpus=1, max_retries=0)(scene_or_refusal)
        refs = [task.remote(**{**kw, "threads": 1}) for kw in kwargs_list]
        try:
            return ray.get(refs)
        except ray.exceptions.RayTaskError as exc:
            cause = getattr(exc, "cause", None)
            if isinstance(cause, EndoGSimError):
                raise cause from None
            raise
    finally:
        if started:
            ray.shutdown()


def run_suite(scenes: list[str] | None = None, scenes_dir: str | os.PathLike = SCENES_CACHE,
              work_dir: str | os.PathLike = "bench_suite_runs", iters: int | None = None, quick: bool = False,
              frames: int | None = None, fid_weights: str | None = None, ray: bool = False,
              ray_address: str | None = None, threads: int | None = None, runs: Sequence[str] | None = None,
              time_budget: float | None = None, optimizer: str = "rprop", refine: float = 1.0,
              refined_correction: float | None = DEFAULT_REFINED_CORRECTION,
              device: str = "cpu", fresh: bool = False, workers: int | None = None, seed: int = 0,
              log=print) -> dict:
    """Run the suite (module docstring) and build the tables.

    Args:
        scenes: suite scenes (default: every suite scene except ``tiny``; ``--quick``: ``tiny``).
        iters: iterations of the optimised runs (default :data:`DEFAULT_ITERS`; quick 2).
        quick: ``tiny``, 4 frames, 2 iterations: a smoke run of the whole machinery (minutes on a CPU).
        frames: frames to synthesize per scene (default: the suite's; quick 4).
        ray, ray_address: run the scenes as Ray tasks (local cluster unless an address is given).
        threads: torch threads of the in-process path (Ray tasks always use 1). On a CPU shared with other
            work, 1 can be several times faster than torch's default pool.
        runs: run keys to do (of :data:`RUN_KEYS`, with ``prior_on``: Table 2 is its; default all).
        time_budget: each identification's safety stop in seconds (default None: none).
        optimizer: identification's optimiser (default "rprop", the suite's figures; "lm": docs/IDENTIFICATION.md
            section 4).
        refine: identify at each scene's identification discretisation refined by this factor (default 1;
            below the ground truth's 2).
        refined_correction: the estimates' refined correction (``IdentifyConfig.refined_correction``; default
            identification's, 1.5; None: none); ``refine`` times this must stay below the ground truth's 2 too.
        workers: simulations run side by side in the in-process path (None: one per torch thread; Ray tasks
            one); the results do not depend on it.
        device: identification's device ("cpu" or "cuda"): the same computation in another order of
            floating-point sums.
        fresh: run every scene again, even one whose stored record this run could reuse (module docstring).
        seed: every scene's seed (default 0, the figures of record; module docstring).
    Returns:
        {"settings", "scenes": {name: run_scene(...)}, "refused": {name: why} (scenes left out: the generator
        refused their ground truth at this seed), "tables": suite_tables(...), "summary":
        interval_summary(...) over the suite's objects (full method), "wall_seconds"}
    """
    from endogsim.synth.suite import suite_scene_names

    t0 = time.perf_counter()
    scenes = list(scenes) if scenes else (["tiny"] if quick else _default_scenes())
    unknown = [s for s in scenes if s not in suite_scene_names()]
    if unknown:
        raise EndoGSimError(f"unknown suite scene(s) {', '.join(unknown)}; choose from {', '.join(suite_scene_names())}")
    if runs is not None:
        runs = list(runs)
        wrong = [r for r in runs if r not in RUN_KEYS]
        if wrong or FULL_METHOD not in runs:
            raise EndoGSimError(f"runs {', '.join(runs)}: choose among {', '.join(RUN_KEYS)}, with {FULL_METHOD} "
                                "(the full method, whose run every table starts from)")
    from endogsim.identify.config import IdentifyConfig
    from endogsim.physics.engine import resolve_device

    # bad options, and a device this machine lacks, are refused before any scene (the config does not check
    # the device: that needs Warp)
    IdentifyConfig(optimizer=optimizer, refine=refine, refined_correction=refined_correction)
    resolve_device(device)
    check_coarser_than_ground_truth(scenes, refine, refined_correction)  # every scene's, before the first one's work
    n_it = iters if iters is not None else (2 if quick else DEFAULT_ITERS)
    n_fr = frames if frames is not None else (4 if quick else None)
    kw = [dict(name=s, scenes_dir=str(scenes_dir), work_dir=str(work_dir), iters=n_it, frames=n_fr,
               fid_weights=str(fid_weights) if fid_weights else None, runs=runs, time_budget=time_budget,
               optimizer=optimizer, refine=refine, refined_correction=refined_correction, device=device, fresh=fresh,
               seed=seed)
          for s in scenes]
    if fid_weights:  # fail before hours of work, not after
        from endogsim.evaluate.fid import load_inception

        load_inception(fid_weights)
    if ray:
        results = _ray_map(kw, ray_address, log)
    else:
        results = []
        for k in kw:
            log(f"scene {k['name']} ...")
            results.append(scene_or_refusal(**k, threads=threads, workers=workers))
    per_scene = {r["scene"]: r for r in results if "refused" not in r}
    refused = {r["scene"]: r["refused"] for r in results if "refused" in r}
    for r in results:
        if "refused" in r:
            log(f"  {r['scene']}: left out, its ground truth refused at seed {seed}")
            continue
        log(f"  {r['scene']}: {r['wall_seconds']:.0f} s" + (" (its stored record: the same settings, scene and "
                                                           "code)" if r["reused"] else ""))
    return {"settings": {"scenes": scenes, "iters": n_it, "frames": n_fr, "quick": quick, "ray": ray,
                         "ray_address": ray_address, "fid": bool(fid_weights), "runs": runs or list(RUN_KEYS),
                         "time_budget": time_budget, "optimizer": optimizer, "refine": refine,
                         "refined_correction": refined_correction, "device": device, "workers": workers,
                         "seed": seed},
            "scenes": per_scene, "refused": refused, "tables": suite_tables(per_scene, refused),
            "summary": interval_summary(suite_objects(per_scene)), "wall_seconds": time.perf_counter() - t0}


def _mean(vals: list[float]) -> float:
    vals = [v for v in vals if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return sum(vals) / len(vals) if vals else math.nan


def suite_objects(per_scene: dict[str, dict]) -> list[dict]:
    """Every deformable object of the suite as the full method (``prior_on``) identified it
    (:func:`object_results` records)."""
    return [o for r in per_scene.values() for o in r["runs"][FULL_METHOD]["materials"].values()]


def _interval_text(iv: list[float] | None, spec: str) -> tuple:
    return ("-", "-") if iv is None else (format(iv[0], spec), format(iv[1], spec))


def _flag(v: bool | None) -> str:
    return "-" if v is None else ("yes" if v else "no")


def _identifiable_text(objs: list[dict]) -> str:
    """"k/n, k'/n": identifiable E and nu among the objects where it was measured ("-": nowhere)."""
    parts = []
    for w in ("E", "nu"):
        flags = [o[f"{w}_identifiable"] for o in objs if o[f"{w}_identifiable"] is not None]
        parts.append(f"{sum(flags)}/{len(flags)}" if flags else "-")
    return ", ".join(parts)


def suite_tables(per_scene: dict[str, dict], refused: dict[str, str] | None = None) -> dict:
    """Table 2, its per-object intervals, Table 3 and the material-field ablation from :func:`run_scene`
    results; ``refused`` ({name: why}, scenes whose ground truth the generator refused) are named in Table 2's
    note."""
    names = list(per_scene)
    full = {n: per_scene[n]["runs"][FULL_METHOD] for n in names}
    rows2, rows_obj = [], []
    for n in names:
        r, objs = full[n], list(full[n]["materials"].values())
        sm = interval_summary(objs)
        rows2.append([n, r["re_mean"], r["epe"], sm["e_rel_error_median"], sm["coverage_E"], sm["coverage_nu"],
                      _identifiable_text(objs), r.get("seconds_per_iteration"),
                      f"{r.get('iterations')} ({r.get('stopped')})", r.get("wall_seconds")])
        for obj, o in full[n]["materials"].items():
            width = None if o["E_interval"] is None else math.log10(o["E_interval"][1] / o["E_interval"][0])
            rows_obj.append([n, obj, o["E_true"], o["E"], o["e_rel_error"], *_interval_text(o["E_interval"], ".4g"),
                             width, _flag(o["E_identifiable"]), o["nu_true"], o["nu"],
                             *_interval_text(o["nu_interval"], ".3f"), _flag(o["nu_identifiable"])])
    summary = interval_summary(suite_objects(per_scene))
    if rows2:
        rows2.append(["suite", _mean([r[1] for r in rows2]), _mean([r[2] for r in rows2]),
                      summary["e_rel_error_median"], summary["coverage_E"], summary["coverage_nu"],
                      _identifiable_text(suite_objects(per_scene)), _mean([r[7] for r in rows2]), "-",
                      _mean([r[9] for r in rows2])])
    cut = [f"{n} ({key})" for n in names for key, r in per_scene[n]["runs"].items() if r.get("stopped_by_budget")]
    cover = (f"true value inside its 90% interval: E {summary['coverage_E']:.2f} of {summary['n_E']}, nu "
             f"{summary['coverage_nu']:.2f} of {summary['n_nu']}, pooled {summary['coverage']:.2f} (nominal 0.90); "
             f"mean width: E {summary['mean_width_E_decades']:.3g} decades, nu {summary['mean_width_nu']:.3g}")
    if not math.isnan(summary["coverage_statistical"]):
        cover += (f"; with the frame-to-frame noise alone (no discretisation error) E "
                  f"{summary['coverage_statistical_E']:.2f}, nu {summary['coverage_statistical_nu']:.2f}, pooled "
                  f"{summary['coverage_statistical']:.2f}")
    rows3 = []
    for init, on in RUNS:
        key = run_key(init, on)
        if not all(key in per_scene[n]["runs"] for n in names):
            continue  # not measured (--runs)
        fids = [per_scene[n]["runs"][key]["fid"] for n in names]
        rows3.append([init, "on" if on else "off", _mean([per_scene[n]["runs"][key]["re_mean"] for n in names]),
                      _mean([per_scene[n]["runs"][key]["epe"] for n in names]),
                      _mean(fids) if any(f is not None for f in fids) else "n/a"])
    abl = {"title": f"Material field ablation on {ABLATION_SCENE}",
           "columns": ["variant", "RE", "EPE (px)", "identified (E Pa / nu)"], "rows": []}
    src = next((per_scene[n] for n in names if "global_on" in per_scene[n]["runs"]), None)
    if src is None:
        abl["note"] = ("not run: " + (f"{ABLATION_SCENE} is not among the scenes" if ABLATION_SCENE not in names
                                      else "--runs left out global_on"))
    else:
        abl["title"] = f"Material field ablation on {src['scene']}"
        for key, label in ((FULL_METHOD, "object-wise material field"), ("global_on", "one global material")):
            r = src["runs"][key]
            mats = "; ".join(f"{n} {v['E']:.4g} / {v['nu']:.3f}" for n, v in r["materials"].items())
            abl["rows"].append([label, r["re_mean"], r["epe"], mats])
    return {
        "table2": {"title": "Table 2: identification per scene (prior init, optimisation on)",
                   "columns": ["scene", "RE", "EPE (px)", "|E/E_true-1| (median)", "E in 90%", "nu in 90%",
                               "identifiable (E, nu)", "s/iter", "iterations (stopped)", "identify s"], "rows": rows2,
                   "note": "suite row: RE, EPE, s/iter and identify s averaged over the scenes, the other columns "
                           "over every deformable object; 'in 90%': share of the objects whose true value lies in "
                           "its 90% interval; identify s: the whole identification (iterations, intervals, "
                           "evaluation); "
                           + (f"cut by the time budget: {', '.join(cut)}" if cut else "no run was cut by a time "
                              "budget")
                           + "".join(f"; LEFT OUT, its ground truth refused (no fair test at this seed): {n}: {why}"
                                     for n, why in (refused or {}).items())},
        "table2_objects": {"title": "Table 2 per object: identified vs true materials and 90% intervals",
                           "columns": ["scene", "object", "E true (Pa)", "E (Pa)", "|E/E_true-1|", "E 90% lo (Pa)",
                                       "E 90% hi (Pa)", "E width (decades)", "E identifiable", "nu true", "nu",
                                       "nu 90% lo", "nu 90% hi", "nu identifiable"],
                           "rows": rows_obj, "note": cover},
        "table3": {"title": "Table 3: initialisation x optimisation (mean over scenes)",
                   "columns": ["init", "optimisation", "RE", "EPE (px)", "FID"], "rows": rows3},
        "ablation": abl,
    }
