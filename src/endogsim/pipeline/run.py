"""The end-to-end run: reconstruct -> scenario -> materials -> identify -> simulate -> report.

Each stage reads and writes plain files in its own sub-folder of the run folder (DESIGN.md section 2):

  RUN/recon/        ``endogsim reconstruct`` output (Gaussians, deformation, tool trajectories, metrics)
  RUN/scene/        the simulation-ready scene folder (:func:`scene_from_reconstruction`)
  RUN/identify/     ``endogsim identify`` output (identified materials, metrics, plots, comparison video)
  RUN/simulate/     a new interaction simulated with the identified materials (video, PLY sequence)
  RUN/report.html   the run report
  RUN/run.json      which stages are done, their seconds and key results (written atomically)

A stage counts as done only while ``run.json`` says so *and* its inputs and outputs are still the ones it
recorded: the digest of its options and of the earlier stages' outputs (the dataset's content for the
reconstruction), and the digest of its own output folder or file. Otherwise it runs again, and so does every
later stage; an interrupted stage starts again (reconstruction and identification then continue from their
own checkpoints, which refuse other data or settings), so ``run`` can always be re-invoked to resume.
``fresh`` starts every stage over. The run folder is locked while ``run`` works on it.
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
from endogsim.io.runfolder import json_digest, run_folder, tree_digest
from endogsim.pipeline.scene_from_recon import RealScenario
from endogsim.recon.config import ReconConfig

__all__ = ["PIPELINE_OPTIMIZER", "PipelineConfig", "STAGES", "pipeline_identify", "run_pipeline"]

#: Where identification's tool colliders get their motion: the reconstruction, or a ground truth (benchmark).
ToolMotion = Literal["reconstructed", "truth"]

#: The optimiser the pipeline calibrates with (``endogsim run``, ``endogsim validate``): Levenberg-Marquardt. On
#: both real clips it stops by its tolerance (EndoNeRF pulling's 63 frames: 5 iterations in 300 s; CholecSeg8K's
#: 20 calibration frames: 4 in 281 s), where Rprop, the library's default, runs up to the 480-s time budget on
#: pulling (7 or 8 iterations, as the machine's speed lets the last one start) and is cut by it on CholecSeg8K,
#: so that its answer depends on the machine's speed; the held-out predictions are as good or better
#: (docs/REAL_VIDEO.md section 14). The synthetic suite and the demo keep Rprop: on their contact-rugged losses
#: this local method does worse (docs/IDENTIFICATION.md section 2).
PIPELINE_OPTIMIZER = "lm"


def pipeline_identify(**options) -> IdentifyConfig:
    """The pipeline's identification settings: the library's defaults with :data:`PIPELINE_OPTIMIZER`, but for
    the ``options`` given (:class:`~endogsim.identify.IdentifyConfig` fields, e.g. ``iters``, ``optimizer``)."""
    return IdentifyConfig.from_json({"optimizer": PIPELINE_OPTIMIZER, **options})


STAGES = ("reconstruct", "scenario", "identify", "simulate", "report")
#: Each stage's output, relative to the run folder: what its "done" is checked against.
OUTPUTS = {"reconstruct": "recon", "scenario": "scene", "identify": "identify", "simulate": "simulate",
           "report": "report.html"}


@dataclass
class PipelineConfig:
    """Options of :func:`run_pipeline` (each stage keeps its own typed config).

    Attributes:
        materials_backend: initial materials: manual | prior | mllm | replay | a material JSON file.
        recon: the reconstruction stage's :class:`~endogsim.recon.config.ReconConfig`.
        identify: the identification stage's :class:`~endogsim.identify.IdentifyConfig` (default, and for a dict
            the fields it leaves out, :func:`pipeline_identify`: Levenberg-Marquardt).
        scenario: the scenario of a real video (thickness, anchors, gravity, damping, ...; unused with a
            ground truth), :class:`~endogsim.pipeline.scene_from_recon.RealScenario`.
        interaction: the new interaction of the simulate stage (a built-in name or a JSON file); None skips it.
        tool_motion: tool collider motion for identification: "reconstructed" or "truth" (benchmark only).
        video: write videos (comparison, simulation).
    """

    materials_backend: str = "prior"
    recon: ReconConfig = field(default_factory=ReconConfig)
    identify: IdentifyConfig = field(default_factory=pipeline_identify)
    scenario: RealScenario = field(default_factory=RealScenario)
    interaction: str | None = "poke"
    tool_motion: ToolMotion = "reconstructed"
    video: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.recon, dict):
            self.recon = ReconConfig.from_dict(self.recon)
        if isinstance(self.identify, dict):
            self.identify = pipeline_identify(**self.identify)
        if isinstance(self.scenario, dict):
            self.scenario = RealScenario(**{k: tuple(v) if isinstance(v, list) else v for k, v in self.scenario.items()})
        if self.tool_motion not in get_args(ToolMotion):
            raise DataError(f"tool_motion {self.tool_motion!r} must be 'reconstructed' or 'truth'")
        # Checked now, not after the half-hour reconstruction that comes before the stages using them.
        from endogsim.identify.run import check_init
        from endogsim.pipeline.interaction import load_interaction

        check_init(self.materials_backend, "--materials-backend")
        if self.interaction is not None:
            load_interaction(self.interaction)


def _load_state(path: Path) -> dict:
    if not path.is_file():
        return {"stages": {}}
    try:
        state = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DataError(f"{path}: unreadable run state ({exc}); delete it to start the run over") from exc
    stages = state.get("stages") if isinstance(state, dict) else None
    if not isinstance(stages, dict) or not all(isinstance(r, dict) for r in stages.values()):
        raise DataError(f"{path}: not a run state (it needs a \"stages\" object of stage records); delete it or "
                        "use --fresh to start the run over")
    return state


def run_pipeline(
    data: str | Path,
    out: str | Path,
    config: PipelineConfig | None = None,
    *,
    truth: str | Path | None = None,
    on_stage: Callable[[str, str], None] | None = None,
    stop_after: str | None = None,
    fresh: bool = False,
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
        fresh: start every stage over (checkpoints of the reconstruction and the identification too).
    """

    cfg = config or PipelineConfig()
    data, out = Path(data), Path(out)
    if not data.exists():
        raise DataError(f"{data}: no such dataset folder or video")
    if truth is not None:
        from endogsim.scene.schema import load_scene_spec

        load_scene_spec(truth)  # a ground truth that cannot be read fails now, not after the reconstruction
    from endogsim.warp_runtime import KERNEL_MODULES, kernels_built_aside

    # The reconstruction builds the renderer's and the HexPlane sampler's kernels; identification's are
    # built meanwhile in another process (on a machine's first run).
    aside = [KERNEL_MODULES[k] for k in ("simulate", "adjoints")] if cfg.identify.device == "cpu" else []
    with run_folder(out, "run"), kernels_built_aside(aside):
        return _run_stages(data, out, cfg, truth, on_stage, stop_after, fresh)


def _run_stages(data: Path, out: Path, cfg: PipelineConfig, truth: str | Path | None,
                on_stage: Callable[[str, str], None] | None, stop_after: str | None, fresh: bool) -> dict:
    state_path = out / "run.json"
    state = {"stages": {}} if fresh else _outputs_here(_load_state(state_path), out)
    state.update({"data": str(data), "truth": str(truth) if truth else None, "config": asdict(cfg)})
    # What each stage is made from besides the earlier stages' outputs (files by content digest).
    options = {"reconstruct": {"data": tree_digest(data, exclude=out), "recon": asdict(cfg.recon)},
               "scenario": {"truth": None if truth is None else tree_digest(truth), "tool_motion": cfg.tool_motion,
                            "scenario": asdict(cfg.scenario)},
               "identify": {"init": cfg.materials_backend, "init_file": tree_digest(cfg.materials_backend),
                            "identify": asdict(cfg.identify), "video": cfg.video},
               "simulate": {"interaction": cfg.interaction}, "report": {}}
    upstream: list[str | None] = []  # output digests of the stages before

    def stage(name: str, fn: Callable[[], dict]) -> dict:
        inputs = json_digest([options[name], upstream])
        rec = state["stages"].get(name, {})
        if rec.get("done") and rec.get("inputs") == inputs and rec.get("outputs") == tree_digest(out / OUTPUTS[name]):
            if on_stage:
                on_stage(name, "skip")
            upstream.append(rec["outputs"])
            return rec
        if on_stage:
            on_stage(name, "start")
        t0 = time.perf_counter()
        result = fn()
        outputs = tree_digest(out / OUTPUTS[name])
        state["stages"][name] = {"done": True, "seconds": round(time.perf_counter() - t0, 2), **result,
                                 "inputs": inputs, "outputs": outputs}
        write_json_atomic(state_path, state)
        if on_stage:
            on_stage(name, "done")
        upstream.append(outputs)
        return state["stages"][name]

    def reconstruct_stage() -> dict:
        from endogsim.recon.train import reconstruct

        m = reconstruct(data, out / "recon", cfg.recon, resume=not fresh)
        keep = ("psnr_masked", "psnr_endonerf", "ssim", "training_seconds", "iterations", "stopped_by_budget",
                "num_gaussians", "data_notes")
        return {k: m[k] for k in keep if k in m}

    def scenario_stage() -> dict:
        from endogsim.pipeline.scene_from_recon import scene_from_reconstruction

        scene_from_reconstruction(out / "recon", data, out / "scene", truth=truth, tool_motion=cfg.tool_motion,
                                  scenario=cfg.scenario)
        return {"scene": str(out / "scene")}

    def identify_stage() -> dict:
        from endogsim.identify import run_identify

        m = run_identify(out / "scene", out / "identify", init=cfg.materials_backend,
                         config=cfg.identify, video=cfg.video, evaluate_init=truth is not None, resume=not fresh)
        keep = ("re_mean", "re_E", "re_nu", "epe", "psnr", "ssim", "iterations", "stopped", "stopped_by_budget",
                "materials", "intervals")
        # metrics.json's "seconds" times the iterations only; the stage's own "seconds" (its wall time,
        # intervals and outputs included) must not be replaced by it.
        return ({k: m[k] for k in keep if k in m} | {"optimisation_seconds": m.get("seconds")}
                | ({"init_metrics": m["init_metrics"]} if "init_metrics" in m else {}))

    def simulate_stage() -> dict:
        if cfg.interaction is None:
            return {"skipped": True}
        from endogsim.pipeline.simulate import simulate_interaction

        # at the discretisation the materials belong to: the identification's, or the refined one a correction
        # moved them to
        summary = simulate_interaction(out / "scene", cfg.interaction, out / "identify" / "materials_identified.json",
                                       out / "simulate", device=cfg.identify.device)
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
    write_json_atomic(state_path, state)  # a resume that skipped every stage names the outputs where they are
    return state


def _outputs_here(state: dict, out: Path) -> dict:
    """``state`` (run.json) with the stored paths of the stages' outputs under the run folder ``out``: a run
    folder moved after it finished resumes with its stages skipped, and the paths stored then name the old
    place."""
    for name, key in (("scenario", "scene"), ("report", "report")):
        if key in state["stages"].get(name, {}):
            state["stages"][name][key] = str(out / OUTPUTS[name])
    summary = state["stages"].get("simulate", {}).get("summary")
    if isinstance(summary, dict) and "scene_folder" in summary:  # the simulate stage's own record of its scene
        summary["scene_folder"] = str(out / OUTPUTS["scenario"])
    return state
