"""The end-to-end run: reconstruct -> scenario -> materials -> identify -> simulate -> report.

Each stage reads and writes plain files in its own sub-folder of the run folder (DESIGN.md section 2):

  RUN/recon/        ``endogsim reconstruct`` output (Gaussians, deformation, tool trajectories, metrics)
  RUN/scene/        the simulation-ready scene folder (:func:`scene_from_reconstruction`)
  RUN/identify/     ``endogsim identify`` output (identified materials, metrics, plots, comparison video)
  RUN/simulate/     a new interaction simulated with the identified materials (video, PLY sequence)
  RUN/report.html   the run report
  RUN/run.json      which stages are done, their seconds and key results (written atomically)

A stage counts as done only once ``run.json`` says so; an interrupted stage starts again (reconstruction and
identification then continue from their own checkpoints), so ``run`` can always be re-invoked to resume.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal, get_args

from endogsim.errors import DataError
from endogsim.identify.config import IdentifyConfig
from endogsim.io.atomic import write_json_atomic
from endogsim.recon.config import ReconConfig

#: Where identification's tool colliders get their motion: the reconstruction, or a ground truth (benchmark).
ToolMotion = Literal["reconstructed", "truth"]

__all__ = ["PipelineConfig", "run_pipeline", "STAGES"]

STAGES = ("reconstruct", "scenario", "identify", "simulate", "report")


@dataclass
class PipelineConfig:
    """Options of :func:`run_pipeline` (each stage keeps its own typed config).

    Attributes:
        materials_backend: initial materials: manual | prior | mllm | replay | a material JSON file.
        recon: the reconstruction stage's :class:`~endogsim.recon.config.ReconConfig`.
        identify: the identification stage's :class:`~endogsim.identify.IdentifyConfig`.
        interaction: the new interaction of the simulate stage (a built-in name or a JSON file); None skips it.
        tool_motion: tool collider motion for identification: "reconstructed" or "truth" (benchmark only).
        video: write videos (comparison, simulation).
    """

    materials_backend: str = "prior"
    recon: ReconConfig = field(default_factory=ReconConfig)
    identify: IdentifyConfig = field(default_factory=IdentifyConfig)
    interaction: str | None = "poke"
    tool_motion: ToolMotion = "reconstructed"
    video: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.recon, dict):
            self.recon = ReconConfig.from_dict(self.recon)
        if isinstance(self.identify, dict):
            self.identify = IdentifyConfig.from_json(self.identify)
        if self.tool_motion not in get_args(ToolMotion):
            raise DataError(f"tool_motion {self.tool_motion!r} must be 'reconstructed' or 'truth'")


def _load_state(path: Path) -> dict:
    if path.is_file():
        try:
            return json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise DataError(f"{path}: unreadable run state ({exc}); delete it to start the run over") from exc
    return {"stages": {}}


def run_pipeline(
    data: str | Path,
    out: str | Path,
    config: PipelineConfig | None = None,
    *,
    truth: str | Path | None = None,
    on_stage: Callable[[str, str], None] | None = None,
    stop_after: str | None = None,
) -> dict:
    """Run (or resume) every stage on a dataset folder; returns ``run.json``'s content.

    Args:
        data: a dataset folder the loaders read (EndoNeRF, CholecSeg8K, ``endogsim synth`` output) or a video.
        out: the run folder.
        config: pipeline options.
        truth: a ground-truth scene folder (``endogsim synth``) for the benchmark protocol: its boundary settings,
            materials and flow are used for the scenario and for the metrics.
        on_stage: callback(stage, "start" | "done" | "skip") for progress display.
        stop_after: test hook: stop after this stage.
    """

    cfg = config or PipelineConfig()
    data, out = Path(data), Path(out)
    if not data.exists():
        raise DataError(f"{data}: no such dataset folder or video")
    out.mkdir(parents=True, exist_ok=True)
    state_path = out / "run.json"
    state = _load_state(state_path)
    state.update({"data": str(data), "truth": str(truth) if truth else None, "config": asdict(cfg)})

    def stage(name: str, fn: Callable[[], dict]) -> dict:
        if state["stages"].get(name, {}).get("done"):
            if on_stage:
                on_stage(name, "skip")
            return state["stages"][name]
        if on_stage:
            on_stage(name, "start")
        t0 = time.perf_counter()
        result = fn()
        state["stages"][name] = {"done": True, "seconds": round(time.perf_counter() - t0, 2), **result}
        write_json_atomic(state_path, state)
        if on_stage:
            on_stage(name, "done")
        return state["stages"][name]

    def reconstruct_stage() -> dict:
        from endogsim.recon.train import reconstruct

        m = reconstruct(data, out / "recon", cfg.recon)
        return {k: m[k] for k in ("psnr_masked", "psnr_endonerf", "ssim", "training_seconds", "num_gaussians") if k in m}

    def scenario_stage() -> dict:
        from endogsim.pipeline.scene_from_recon import scene_from_reconstruction

        scene_from_reconstruction(out / "recon", data, out / "scene", truth=truth, tool_motion=cfg.tool_motion)
        return {"scene": str(out / "scene")}

    def identify_stage() -> dict:
        from endogsim.identify import run_identify

        m = run_identify(out / "scene", out / "identify", init=cfg.materials_backend,
                         config=cfg.identify, video=cfg.video, evaluate_init=truth is not None)
        keep = ("re_mean", "re_E", "re_nu", "epe", "psnr", "ssim", "iterations", "seconds", "materials")
        return {k: m[k] for k in keep if k in m} | ({"init_metrics": m["init_metrics"]} if "init_metrics" in m else {})

    def simulate_stage() -> dict:
        if cfg.interaction is None:
            return {"skipped": True}
        from endogsim.pipeline.simulate import simulate_interaction

        summary = simulate_interaction(out / "scene", cfg.interaction, out / "identify" / "materials_identified.json",
                                       out / "simulate")
        return {"interaction": cfg.interaction, "summary": summary}

    def report_stage() -> dict:
        from endogsim.evaluate.report_html import write_report

        sims = [out / "simulate"] if (out / "simulate" / "summary.json").is_file() else []
        return {"report": str(write_report(out / "identify", simulations=sims, out=out / "report.html"))}

    steps = {"reconstruct": reconstruct_stage, "scenario": scenario_stage, "identify": identify_stage,
             "simulate": simulate_stage, "report": report_stage}
    for name in STAGES:
        stage(name, steps[name])
        if stop_after == name:
            break
    return state
