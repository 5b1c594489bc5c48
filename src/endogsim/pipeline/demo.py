"""``endogsim demo``: the whole pipeline on a built-in procedural scene, with ground truth to compare against.

1. synthesise the ``tiny_lift`` benchmark scene (:data:`DEMO_SCENE`, simulated with known materials): the
   "observed" video;
2. :func:`~endogsim.pipeline.run.run_pipeline` on its frames alone: reconstruct, build the scenario with the
   benchmark's boundary settings, initialise materials from the prior, identify, simulate a new interaction,
   write the report;
3. print the recovered vs ground-truth materials.

What it computes depends on ``DemoConfig`` and its ``seed`` only, never on the machine's speed: every stage
runs a fixed number of iterations on schedules that count iterations. The time budgets are safety stops,
several times what the stages take on a 2-core CPU; a stage they stop says so (``stopped_by_budget`` in its
metrics and in ``summary.json``), and its result is then the fixed-iteration run cut short.

Outputs in OUT: ``render.mp4`` and ``frames/`` (the observed video, slowed to at most 10 frames/s), ``scene_truth/`` (the synthesized scene),
``run/`` (the run folder, with ``run/report.html``), ``summary.json``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from endogsim.identify.config import IdentifyConfig
from endogsim.io.atomic import write_json_atomic
from endogsim.recon.config import ReconConfig
from endogsim.synth.suite import DEMO_SCENE

__all__ = ["DemoConfig", "run_demo", "synthesize_observed"]


@dataclass
class DemoConfig:
    """Demo settings; the defaults finish in a few minutes on a 2-core CPU.

    Attributes:
        scene: benchmark scene to synthesise.
        frames: frames of the synthesized video (None: the scene's default).
        seed: the demo's seed: the synthesized scene's (textures, perturbations, noise) and the
            reconstruction's and identification's (their ``seed`` fields are set to it). The same seed gives
            the same results; another seed another texture and relief, reached as deep by the same instrument path.
        recon: ReconConfig of the reconstruction stage (a dict: its fields over the defaults).
        identify: IdentifyConfig of the identification stage (a dict: its fields over the defaults).
        interaction: the new interaction simulated with the identified materials.
        tool_motion: "truth" (the benchmark protocol: identification gets the ground truth's boundary settings,
            tool trajectory included) or "reconstructed" (the tool's tracked motion, as on a real video).
        threads: torch threads (and Warp CPU bands) for the whole demo, or None for the process's setting. The
            thread count decides the order in which CPU reductions sum, and identification's nearly flat loss
            can turn an 8th-digit difference into another answer; 1 (the default) gives every machine the same
            numbers (the demo's published figures are one-thread runs; a demo takes 2.5-3 min that way on a
            2-core CPU, its second core building Warp's kernels on a machine's first run).
        workers: simulations identification runs side by side (an interval's trials, the backward pass's
            recomputed segments, the refined correction's simulations), or None for one per core of this machine
            (:func:`~endogsim.warp_runtime.cpu_cores`). Each simulation computes what it would alone: the results
            do not depend on it, only the time does.
    """

    scene: str = DEMO_SCENE
    frames: int | None = None
    seed: int = 0
    # Fixed iteration counts (tiny_lift's reconstruction stage, 600 iterations, takes ~60 s on a 2-core CPU);
    # the time budgets are only safety stops, far beyond that.
    recon: ReconConfig = field(default_factory=lambda: ReconConfig(resolution_scale=1.0, iters=600, time_budget_s=900.0))
    identify: IdentifyConfig = field(default_factory=lambda: IdentifyConfig(iters=10, time_budget=900.0))
    interaction: str | None = "poke"
    tool_motion: str = "truth"
    threads: int | None = 1
    workers: int | None = None

    def __post_init__(self) -> None:
        for name in ("threads", "workers"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                from endogsim.errors import DataError

                raise DataError(f"DemoConfig.{name} = {getattr(self, name)} must be >= 1 (or None)")
        if isinstance(self.recon, dict):
            self.recon = ReconConfig.from_dict(self.recon)
        if isinstance(self.identify, dict):
            self.identify = IdentifyConfig.from_json(self.identify)


def synthesize_observed(out: Path, cfg: DemoConfig, on_stage: Callable[[str, str], None] | None = None) -> Path:
    """Step 1: synthesize ``cfg.scene`` with ``cfg.seed`` into ``out/scene_truth`` (kept when already there),
    with the observed video as ``out/render.mp4`` and ``out/frames/``; returns the scene folder."""
    from endogsim.io.video_writer import write_frames_png, write_video
    from endogsim.scene.folder import read_observations
    from endogsim.scene.schema import load_scene_spec
    from endogsim.synth import synthesize

    truth_dir = Path(out) / "scene_truth"
    if (truth_dir / "scene.json").is_file():
        return truth_dir
    if on_stage:
        on_stage("synthesize", "start")
    synthesize(cfg.scene, truth_dir, seed=cfg.seed, frames=cfg.frames)
    truth = load_scene_spec(truth_dir)
    frames, *_ = read_observations(truth_dir, truth, truth.frames)
    # Slow motion: the simulated clip spans a fraction of a second.
    write_video(frames, Path(out) / "render.mp4", fps=min(10.0, 1.0 / truth.scenario.frame_dt))
    write_frames_png(frames, Path(out) / "frames")
    if on_stage:
        on_stage("synthesize", "done")
    return truth_dir


def run_demo(out: str | Path, cfg: DemoConfig = DemoConfig(),
             on_stage: Callable[[str, str], None] | None = None) -> dict:
    """Run (or resume) the demo into ``out`` with ``cfg.threads`` torch threads and ``cfg.workers``
    simulations side by side; returns the summary (also written to ``out/summary.json``)."""
    from endogsim.warp_runtime import (
        KERNEL_MODULES,
        cpu_cores,
        kernels_built_aside,
        simulations_side_by_side,
        torch_threads,
    )

    # The synthesis builds the simulator's kernels; the later stages' kernels are built meanwhile on a core
    # the one-thread demo leaves idle (on a machine's first run, ~20 s of Warp builds).
    workers = cfg.workers if cfg.workers is not None else cpu_cores()
    with torch_threads(cfg.threads), simulations_side_by_side(workers), \
            kernels_built_aside([KERNEL_MODULES[k] for k in ("render", "hexplane", "adjoints")]):
        return _run_demo(out, cfg, on_stage, workers)


def _run_demo(out: str | Path, cfg: DemoConfig, on_stage: Callable[[str, str], None] | None, workers: int) -> dict:
    from endogsim.materials.field import MaterialField
    from endogsim.pipeline.run import PipelineConfig, run_pipeline
    from endogsim.scene.schema import load_scene_spec

    out = Path(out)
    t0 = time.perf_counter()
    truth_dir = synthesize_observed(out, cfg, on_stage)
    truth = load_scene_spec(truth_dir)
    if (truth.name, truth.seed) != (cfg.scene, cfg.seed):
        from endogsim.errors import DataError

        raise DataError(f"{truth_dir} holds scene {truth.name!r} synthesized with seed {truth.seed}, not {cfg.scene!r} "
                        f"with seed {cfg.seed}: use another --out")
    state = run_pipeline(truth_dir, out / "run",
                         PipelineConfig(materials_backend="prior", recon=replace(cfg.recon, seed=cfg.seed),
                                        identify=replace(cfg.identify, seed=cfg.seed),
                                        interaction=cfg.interaction, tool_motion=cfg.tool_motion),
                         truth=truth_dir, on_stage=on_stage)
    ident = state["stages"]["identify"]
    init_field = MaterialField.load(out / "run" / "identify" / "materials_init.json")
    rows = []
    for o in truth.objects:
        if o.rigid:
            continue
        got = ident.get("materials", {}).get(o.name, {})
        iv = ident.get("intervals", {}).get(o.name, {})
        rows.append({"object": o.name, "E_true": o.E, "E_init": init_field[o.id].E, "E_identified": got.get("E"),
                     "nu_true": o.nu, "nu_init": init_field[o.id].nu, "nu_identified": got.get("nu"),
                     "E_interval": iv.get("E"), "nu_interval": iv.get("nu"), "source": got.get("source")})
    summary = {
        "seed": cfg.seed,
        "threads": torch.get_num_threads(),
        "workers": workers,
        "seconds": round(time.perf_counter() - t0, 1),  # this invocation (less when resuming)
        "pipeline_seconds": round(sum(v.get("seconds", 0.0) for v in state["stages"].values()), 1),
        "materials": rows,
        "re_mean": ident.get("re_mean"), "epe": ident.get("epe"),
        "re_mean_init": ident.get("init_metrics", {}).get("re_mean"),
        "recon_psnr_masked": state["stages"]["reconstruct"].get("psnr_masked"),
        "report": state["stages"].get("report", {}).get("report"),
        "stage_seconds": {k: v.get("seconds") for k, v in state["stages"].items()},
        "iterations": {k: state["stages"][k].get("iterations") for k in ("reconstruct", "identify")},
        "stopped_by_budget": {k: bool(state["stages"][k].get("stopped_by_budget"))
                              for k in ("reconstruct", "identify")},
    }
    write_json_atomic(out / "summary.json", summary)
    return summary
