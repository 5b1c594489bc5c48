"""``endogsim demo`` and ``endogsim run``: the end-to-end pipeline (no data, weights or network needed for the demo)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from endogsim.cli.common import (
    DEVICE_HELP,
    OPTIMIZER_HELP,
    REFINE_HELP,
    REFINED_CORRECTION_HELP,
    TIME_BUDGET_HELP,
    output_folder,
    print_budget_stops,
    time_budget_option,
    user_errors,
)


def _stage_printer():
    from endogsim.cli.common import console

    def on_stage(name: str, status: str) -> None:
        if status == "start":
            console.print(f"[bold]{name}[/bold] ...")
        elif status == "skip":
            console.print(f"[dim]{name}: done earlier, skipped[/dim]")
        else:
            console.print(f"{name}: done")

    return on_stage


#: ``--grasping`` of ``run`` and ``validate`` (:attr:`endogsim.pipeline.scene_from_recon.RealScenario.grasping`).
_GRASPING_HELP = ("Which instruments hold the tissue their jaws close on (the others push): graspers (by class) | "
                  "all (data without instrument classes, e.g. EndoNeRF pulling) | none.")

#: ``--border-motion`` of ``run`` and ``validate`` (``RealScenario.border_motion``).
_BORDER_HELP = ("How the band along the tissue's outline is held: tracked (it follows the reconstruction's tracks of "
                "the tissue there: what moves the tissue beyond the view) | still (held at rest).")

#: ``--support-friction`` of ``run`` and ``validate`` (``RealScenario.support_friction``).
_FRICTION_HELP = ("Coulomb coefficient of the support behind the tissue: pressed on it, the tissue slides once its "
                  "tangential speed beats this times the normal speed it loses (0: frictionless).")


#: ``--gravity``, ``--gravity-direction``, ``--damping`` and ``--mass-scaling`` of ``run`` and ``validate``: the
#: scenario's force scales, which set E's scale (``RealScenario``; metrics.json ``force_scales``).
_FORCE_SCALE_NOTE = (" It sets the scale of the E found: prescribed motion alone fixes nu and the ratios of E, not E "
                     "(docs/REAL_VIDEO.md sections 3 and 17).")
_GRAVITY_HELP = "Gravity's magnitude (m/s^2; 0: none). Default 9.81." + _FORCE_SCALE_NOTE
_GRAVITY_DIRECTION_HELP = ("Gravity's direction as x,y,z in frame 0's camera coordinates (+x image right, +y image "
                           "down, +z along the view), e.g. from the robot's kinematics. Default 0,1,0: the "
                           "laparoscope's upright view." + _FORCE_SCALE_NOTE)
_DAMPING_HELP = "Grid velocity damping of the tissue (1/s). Default 100: over-damped, as on EndoNeRF pulling." + (
    _FORCE_SCALE_NOTE)
_MASS_SCALING_HELP = ("Quasi-static mass scaling k >= 1: the tissue's inertia x k, weight and damping forces "
                      "unchanged, substeps / sqrt(k). Default 4; 1 for fast motion, where inertia matters."
                      + _FORCE_SCALE_NOTE)


def _real_scenario(grasping: str, border_motion: str, support_friction: float, gravity: float | None,
                   gravity_direction: str | None, damping: float | None, mass_scaling: float | None):
    """The real-video scenario of ``run`` and ``validate``: its defaults but for the options given (a bad value is
    refused here, before any work)."""
    from endogsim.errors import DataError
    from endogsim.pipeline.scene_from_recon import RealScenario

    given = {"grasping": grasping, "border_motion": border_motion, "support_friction": support_friction}
    if gravity_direction is not None:
        try:
            given["gravity_direction"] = tuple(float(v) for v in gravity_direction.split(","))
        except ValueError:
            raise DataError(f"--gravity-direction {gravity_direction!r}: give three numbers x,y,z") from None
    given.update({k: v for k, v in (("gravity", gravity), ("damping", damping), ("mass_scaling", mass_scaling))
                  if v is not None})
    return RealScenario(**given)


#: ``--optimizer`` of ``run`` and ``validate`` (:data:`endogsim.pipeline.run.PIPELINE_OPTIMIZER`).
#: The default is named here, not imported: the pipeline's module pulls in torch, and the CLI starts without it
#: (tests/test_io.py checks that the two agree).
_PIPELINE_OPTIMIZER_HELP = ("The calibration's optimiser, default lm (it stops by its tolerance, where rprop, "
                            "identify's default, runs on for its iterations): " + OPTIMIZER_HELP)


def _identify_config(iters: int | None, optimizer: str | None, refine: float = 1.0, device: str = "cpu",
                     time_budget: float | None = None, refined_correction: float | None = None):
    """The identification (calibration) settings of ``run`` and ``validate``: the pipeline's defaults but for the
    options given (an unknown optimiser, a bad factor or a device this machine lacks is refused here, before
    any work)."""
    from endogsim.physics.engine import resolve_device
    from endogsim.pipeline.run import pipeline_identify

    given = (("iters", iters), ("optimizer", optimizer), ("refine", refine), ("device", resolve_device(device)))
    correction = {} if refined_correction is None else {"refined_correction": refined_correction or None}
    return pipeline_identify(**{k: v for k, v in given if v is not None}, **correction,
                             **time_budget_option(time_budget))


def register(app: typer.Typer) -> None:
    """Add ``demo`` and ``run`` to the root ``app``."""

    @app.command("demo")
    @user_errors
    def demo_cmd(
        out: Path = typer.Option(Path("demo"), "--out", "-o", callback=output_folder,
                                 help="Output folder (re-run to resume)."),
        scene: Optional[str] = typer.Option(None, "--scene", help="Benchmark scene to synthesise (see `endogsim "
                                            "synth --help`; default tiny_lift, a grasper lifting a tissue patch; "
                                            "tiny: a probe pressing it)."),
        seed: int = typer.Option(0, "--seed", help="Seed of the synthesized scene, the reconstruction and the "
                                 "identification (same seed and thread count: same results, at any speed)."),
        threads: int = typer.Option(1, "--threads", help="Torch threads for the demo. 1: the same numbers on every "
                                    "machine; more: faster, but CPU sums run in another order and the answer can "
                                    "differ."),
        workers: Optional[int] = typer.Option(None, "--workers", help="Simulations run side by side in "
                                              "identification (default: one per core). The results do not "
                                              "depend on it."),
        recon_iters: Optional[int] = typer.Option(None, "--recon-iters", help="Reconstruction iterations."),
        identify_iters: Optional[int] = typer.Option(None, "--identify-iters", help="Identification iterations."),
        preview: bool = typer.Option(False, "--preview", help="Only render the procedural scene under a moving "
                                     "camera and tool (seconds): OUT/render.mp4 and OUT/frames/."),
        frames: int = typer.Option(48, "--preview-frames", help="Frames of the --preview render."),
    ) -> None:
        """The whole pipeline on a built-in procedural scene: synthesise a video with known materials, reconstruct
        it from the frames alone, initialise materials from the prior, identify them, simulate a new
        interaction, write OUT/run/report.html, and print recovered vs ground-truth materials."""
        from endogsim.cli.common import console, fmt_optional, print_table, progress, with_interval

        if preview:
            from endogsim.pipeline.preview import PreviewConfig, render_preview

            if frames < 2:
                raise typer.BadParameter("--preview-frames must be >= 2")
            with progress() as bar:
                task = bar.add_task("render preview", total=frames)
                summary = render_preview(out, PreviewConfig(frames=frames),
                                         progress=lambda k, n: bar.update(task, completed=k))
            console.print(f"wrote {summary['video']} and {summary['frames_dir']}/ ({summary['num_gaussians']} Gaussians)")
            return

        from dataclasses import replace

        from endogsim.pipeline.demo import DemoConfig, run_demo

        cfg = DemoConfig(seed=seed, threads=threads, workers=workers)  # checks both >= 1
        if scene is not None:
            cfg.scene = scene
        if recon_iters is not None:
            cfg.recon = replace(cfg.recon, iters=recon_iters)
        if identify_iters is not None:
            cfg.identify = replace(cfg.identify, iters=identify_iters)
        s = run_demo(out, cfg, on_stage=_stage_printer())
        # "result", not "identified": a parameter the video does not determine keeps its prior (see "source")
        print_table("Recovered vs ground-truth materials",
                    ["object", "E true (Pa)", "E prior (Pa)", "E result [90% interval] (Pa)", "nu true", "nu prior",
                     "nu result [90% interval]", "source"],
                    [(r["object"], f"{r['E_true']:.4g}", fmt_optional(r["E_init"], ".4g"),
                      with_interval(r["E_identified"], r.get("E_interval"), ".4g"), f"{r['nu_true']:.3f}",
                      fmt_optional(r["nu_init"], ".3f"), with_interval(r["nu_identified"], r.get("nu_interval"), ".3f"),
                      r.get("source") or "-") for r in s["materials"]])
        print_table("Scores", ["metric", "value"],
                    [("RE mean, prior init", fmt_optional(s["re_mean_init"], ".3f")),
                     ("RE mean, result", fmt_optional(s["re_mean"], ".3f")),
                     ("EPE (px), result", fmt_optional(s["epe"], ".3f")),
                     ("reconstruction PSNR, masked (dB)", fmt_optional(s["recon_psnr_masked"], ".2f")),
                     ("seed", str(s["seed"])),
                     ("pipeline seconds (all stages after synthesis)", f"{s['pipeline_seconds']:.0f}"),
                     ("seconds of this invocation", f"{s['seconds']:.0f}")])
        print_budget_stops({k: s["iterations"][k] for k, stopped in s["stopped_by_budget"].items() if stopped})
        console.print(f"report: {s['report']}")

    @app.command("run")
    @user_errors
    def run_cmd(
        data: Path = typer.Argument(..., help="Dataset folder (EndoNeRF, CholecSeg8K, `endogsim synth` output) or video."),
        out: Path = typer.Option(..., "--out", "-o", callback=output_folder,
                                 help="Run folder (re-run to resume the stages not yet done)."),
        materials_backend: str = typer.Option("prior", "--materials-backend",
                                              help="manual | prior | mllm | replay | a material JSON file."),
        truth: Optional[Path] = typer.Option(None, "--truth", help="Ground-truth scene folder (benchmark protocol)."),
        interaction: str = typer.Option("poke", "--interaction", help="New interaction to simulate (name or JSON; "
                                        "'none' to skip)."),
        recon_iters: Optional[int] = typer.Option(None, "--recon-iters", help="Reconstruction iterations."),
        identify_iters: Optional[int] = typer.Option(None, "--identify-iters", help="Identification iterations."),
        optimizer: Optional[str] = typer.Option(None, "--optimizer", help=_PIPELINE_OPTIMIZER_HELP),
        refine: float = typer.Option(1.0, "--refine", help=REFINE_HELP),
        refined_correction: Optional[float] = typer.Option(None, "--refined-correction",
                                                           help=REFINED_CORRECTION_HELP),
        device: str = typer.Option("cpu", "--device", help=DEVICE_HELP),
        time_budget: Optional[float] = typer.Option(None, "--time-budget", help=TIME_BUDGET_HELP + " Default: "
                                                    "the pipeline's, 480 s."),
        resolution_scale: Optional[float] = typer.Option(None, "--resolution-scale", help="Reconstruction image scale."),
        fresh: bool = typer.Option(False, "--fresh", help="Start every stage over (ignore what RUN holds)."),
        grasping: str = typer.Option("graspers", "--grasping", help=_GRASPING_HELP),
        border_motion: str = typer.Option("tracked", "--border-motion", help=_BORDER_HELP),
        support_friction: float = typer.Option(1.0, "--support-friction", help=_FRICTION_HELP),
        gravity: Optional[float] = typer.Option(None, "--gravity", help=_GRAVITY_HELP),
        gravity_direction: Optional[str] = typer.Option(None, "--gravity-direction", help=_GRAVITY_DIRECTION_HELP),
        damping: Optional[float] = typer.Option(None, "--damping", help=_DAMPING_HELP),
        mass_scaling: Optional[float] = typer.Option(None, "--mass-scaling", help=_MASS_SCALING_HELP),
    ) -> None:
        """Reconstruct, initialise materials, identify, simulate a new interaction and report, resuming the
        stages already done."""
        from endogsim.cli.common import console
        from endogsim.pipeline.run import PipelineConfig, run_pipeline
        from endogsim.recon.config import ReconConfig

        recon = {k: v for k, v in (("iters", recon_iters), ("resolution_scale", resolution_scale)) if v is not None}
        ident = _identify_config(identify_iters, optimizer, refine, device, time_budget, refined_correction)
        cfg = PipelineConfig(materials_backend=materials_backend, recon=ReconConfig.from_dict(recon), identify=ident,
                             interaction=None if interaction == "none" else interaction,
                             scenario=_real_scenario(grasping, border_motion, support_friction, gravity,
                                                     gravity_direction, damping, mass_scaling))
        state = run_pipeline(data, out, cfg, truth=truth, on_stage=_stage_printer(), fresh=fresh)
        print_budget_stops({k: v.get("iterations") for k, v in state["stages"].items() if v.get("stopped_by_budget")})
        console.print(f"report: {state['stages'].get('report', {}).get('report')}")


    @app.command("validate")
    @user_errors
    def validate_cmd(
        data: Path = typer.Argument(..., help="Dataset folder (EndoNeRF, CholecSeg8K, `endogsim synth` output) or video."),
        out: Path = typer.Option(..., "--out", "-o", callback=output_folder,
                                 help="Run folder (its reconstruction and scenario are reused)."),
        train_fraction: float = typer.Option(0.67, "--train-fraction", help="Share of the frames to calibrate on."),
        json_out: Optional[Path] = typer.Option(None, "--json", help="Also write the result JSON here."),
        materials_backend: str = typer.Option("prior", "--materials-backend",
                                              help="Initial materials (and the 'prior' baseline): manual | prior | "
                                                   "mllm | replay | a material JSON file."),
        recon_iters: Optional[int] = typer.Option(None, "--recon-iters", help="Reconstruction iterations."),
        identify_iters: Optional[int] = typer.Option(None, "--identify-iters", help="Calibration iterations."),
        optimizer: Optional[str] = typer.Option(None, "--optimizer", help=_PIPELINE_OPTIMIZER_HELP),
        refine: float = typer.Option(1.0, "--refine", help=REFINE_HELP),
        refined_correction: Optional[float] = typer.Option(None, "--refined-correction",
                                                           help=REFINED_CORRECTION_HELP),
        device: str = typer.Option("cpu", "--device", help=DEVICE_HELP),
        time_budget: Optional[float] = typer.Option(None, "--time-budget", help=TIME_BUDGET_HELP + " Default: "
                                                    "the pipeline's, 480 s."),
        resolution_scale: Optional[float] = typer.Option(None, "--resolution-scale", help="Reconstruction image scale."),
        recon_run: Optional[Path] = typer.Option(None, "--recon", help="Use this `endogsim reconstruct` run folder of "
                                                 "DATA instead of reconstructing into OUT/recon."),
        grasping: str = typer.Option("graspers", "--grasping", help=_GRASPING_HELP),
        border_motion: str = typer.Option("tracked", "--border-motion", help=_BORDER_HELP),
        support_friction: float = typer.Option(1.0, "--support-friction", help=_FRICTION_HELP),
        gravity: Optional[float] = typer.Option(None, "--gravity", help=_GRAVITY_HELP),
        gravity_direction: Optional[str] = typer.Option(None, "--gravity-direction", help=_GRAVITY_DIRECTION_HELP),
        damping: Optional[float] = typer.Option(None, "--damping", help=_DAMPING_HELP),
        mass_scaling: Optional[float] = typer.Option(None, "--mass-scaling", help=_MASS_SCALING_HELP),
    ) -> None:
        """Calibrate the materials on the first frames of a video, predict the held-out rest with the tracked
        instrument motion, and compare with the filmed frames (EPE against the observed flow, masked PSNR)
        next to the prior, zero-motion and reconstruction baselines. Writes OUT/validate/validate.json and
        OUT/report.html."""
        from endogsim.cli.common import console, print_table
        from endogsim.errors import DataError
        from endogsim.evaluate.report_html import force_scale_text
        from endogsim.io.atomic import write_json_atomic
        from endogsim.pipeline.run import PipelineConfig
        from endogsim.pipeline.validate import (
            ValidateConfig,
            run_validate,
            validation_table,
        )
        from endogsim.recon.config import ReconConfig

        if json_out is not None and json_out.is_dir():
            raise DataError(f"{json_out}: --json names a folder; give the JSON file to write")
        recon = {k: v for k, v in (("iters", recon_iters), ("resolution_scale", resolution_scale)) if v is not None}
        ident = _identify_config(identify_iters, optimizer, refine, device, time_budget, refined_correction)
        cfg = ValidateConfig(train_fraction=train_fraction, init=materials_backend, recon_run=recon_run,
                             pipeline=PipelineConfig(recon=ReconConfig.from_dict(recon), identify=ident, interaction=None,
                                                     scenario=_real_scenario(grasping, border_motion,
                                                                             support_friction, gravity,
                                                                             gravity_direction, damping,
                                                                             mass_scaling)))
        res = run_validate(data, out, cfg, on_stage=_stage_printer(), log=lambda m: console.print(m))
        cols, rows = validation_table(res)
        print_table(f"Held-out frames {res['train_frames']}..{res['train_frames'] + res['test_frames'] - 1} of "
                    f"{data.name} (calibrated on the first {res['train_frames']})", cols, rows)
        for name, params in res["identifiable"].items():
            for par, v in params.items():  # the value kept (a prior where the video says nothing), then the optimum
                kept = res["materials"].get(name, {}).get(par, v["best"])
                console.print(f"{name} {par}: {kept:.4g} (loss least at {v['best']:.4g}), 90% interval "
                              f"[{v['interval'][0]:.4g}, {v['interval'][1]:.4g}] "
                              f"({'identifiable' if v['identifiable'] else 'NOT identifiable'}: {v['reason']})")
        if res["calibration"]["stopped"] == "time_budget":
            print_budget_stops({"calibration": res["calibration"]["iterations"]})
        if res.get("force_scales"):
            console.print(f"E's scale: {force_scale_text(res['force_scales'])}")
        console.print(f"{res['seconds']:.0f} s; report: {out / 'report.html'}")
        if json_out is not None:
            write_json_atomic(json_out, res)
            console.print(f"wrote {json_out}")
