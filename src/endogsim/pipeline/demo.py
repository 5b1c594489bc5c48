"""``endogsim demo``: the whole pipeline on a built-in procedural scene, with ground truth to compare against.

1. synthesise the ``tiny`` benchmark scene (simulated with known materials): the "observed" video;
2. :func:`~endogsim.pipeline.run.run_pipeline` on its frames alone: reconstruct, build the scenario with the
   benchmark's boundary settings, initialise materials from the prior, identify, simulate a new interaction,
   write the report;
3. print the recovered vs ground-truth materials.

Outputs in OUT: ``render.mp4`` and ``frames/`` (the observed video, slowed to at most 10 frames/s), ``scene_truth/`` (the synthesized scene),
``run/`` (the run folder, with ``run/report.html``), ``summary.json``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from endogsim.identify.config import IdentifyConfig
from endogsim.io.atomic import write_json_atomic
from endogsim.recon.config import ReconConfig

__all__ = ["DemoConfig", "run_demo"]


@dataclass
class DemoConfig:
    """Demo settings; the defaults finish in a few minutes on a 2-core CPU.

    Attributes:
        scene: benchmark scene to synthesise.
        frames: frames of the synthesized video (None: the scene's default).
        seed: synthesis seed.
        recon: ReconConfig overrides for the reconstruction stage.
        identify: IdentifyConfig overrides for the identification stage.
        interaction: the new interaction simulated with the identified materials.
        tool_motion: "truth" (the benchmark protocol: identification gets the ground truth's boundary settings,
            tool trajectory included) or "reconstructed" (the tool's tracked motion, as on a real video).
    """

    scene: str = "tiny"
    frames: int | None = None
    seed: int = 0
    # Time budgets keep the whole demo within about 10 minutes on a 2-core CPU; each stage stops at its
    # budget with its best result so far.
    recon: ReconConfig = field(default_factory=lambda: ReconConfig(resolution_scale=1.0, iters=600, time_budget_s=180.0))
    identify: IdentifyConfig = field(default_factory=lambda: IdentifyConfig(iters=10, time_budget=180.0))
    interaction: str | None = "poke"
    tool_motion: str = "truth"


def run_demo(out: str | Path, cfg: DemoConfig = DemoConfig(),
             on_stage: Callable[[str, str], None] | None = None) -> dict:
    """Run (or resume) the demo into ``out``; returns the summary (also written to ``out/summary.json``)."""
    from endogsim.io.video_writer import write_frames_png, write_video
    from endogsim.materials.field import MaterialField
    from endogsim.pipeline.run import PipelineConfig, run_pipeline
    from endogsim.scene.schema import load_scene_spec
    from endogsim.synth import synthesize

    out = Path(out)
    t0 = time.perf_counter()
    truth_dir = out / "scene_truth"
    if not (truth_dir / "scene.json").is_file():
        if on_stage:
            on_stage("synthesize", "start")
        synthesize(cfg.scene, truth_dir, seed=cfg.seed, frames=cfg.frames)
        from endogsim.scene.folder import read_observations

        truth = load_scene_spec(truth_dir)
        frames, *_ = read_observations(truth_dir, truth, truth.frames)
        # Slow motion: the simulated clip spans a fraction of a second.
        write_video(frames, out / "render.mp4", fps=min(10.0, 1.0 / truth.scenario.frame_dt))
        write_frames_png(frames, out / "frames")
        if on_stage:
            on_stage("synthesize", "done")
    truth = load_scene_spec(truth_dir)
    state = run_pipeline(truth_dir, out / "run",
                         PipelineConfig(materials_backend="prior", recon=cfg.recon, identify=cfg.identify,
                                        interaction=cfg.interaction, tool_motion=cfg.tool_motion),
                         truth=truth_dir, on_stage=on_stage)
    ident = state["stages"]["identify"]
    init_field = MaterialField.load(out / "run" / "identify" / "materials_init.json")
    rows = []
    for o in truth.objects:
        if o.rigid:
            continue
        got = ident.get("materials", {}).get(o.name, {})
        rows.append({"object": o.name, "E_true": o.E, "E_init": init_field[o.id].E, "E_identified": got.get("E"),
                     "nu_true": o.nu, "nu_init": init_field[o.id].nu, "nu_identified": got.get("nu")})
    summary = {
        "seconds": round(time.perf_counter() - t0, 1),  # this invocation (less when resuming)
        "pipeline_seconds": round(sum(v.get("seconds", 0.0) for v in state["stages"].values()), 1),
        "materials": rows,
        "re_mean": ident.get("re_mean"), "epe": ident.get("epe"),
        "re_mean_init": ident.get("init_metrics", {}).get("re_mean"),
        "recon_psnr_masked": state["stages"]["reconstruct"].get("psnr_masked"),
        "report": state["stages"].get("report", {}).get("report"),
        "stage_seconds": {k: v.get("seconds") for k, v in state["stages"].items()},
    }
    write_json_atomic(out / "summary.json", summary)
    return summary
