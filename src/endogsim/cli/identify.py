"""``endogsim identify`` and ``endogsim bench identify``: material identification from a scene folder."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Optional

import typer

from endogsim.cli.common import (
    OPTIMIZER_HELP,
    REFINE_HELP,
    REFINED_CORRECTION_HELP,
    TIME_BUDGET_HELP,
    output_folder,
    print_budget_stops,
    time_budget_option,
    user_errors,
)
from endogsim.identify.config import IdentifyConfig
from endogsim.priors.flow import FlowConfig

_DEFAULT = IdentifyConfig()  # the CLI shows and uses the library's defaults


def register(app: typer.Typer) -> None:
    """Add ``identify`` to the root ``app``."""

    @app.command("identify")
    @user_errors
    def identify_cmd(
        scene: Path = typer.Argument(..., help="Scene folder with scene.json (e.g. from `endogsim synth`)."),
        out: Path = typer.Option(..., "--out", "-o", callback=output_folder,
                                 help="Run folder (outputs and checkpoint; resumes if present)."),
        init: str = typer.Option("prior", "--init", help="manual | prior | mllm | replay | a materials JSON file."),
        loss: str = typer.Option(_DEFAULT.loss, "--loss", help="joint (render + 0.1 flow) | joint_track (+ 0.1 "
                                 "track) | render | flow | track."),
        grad_mode: str = typer.Option(_DEFAULT.grad_mode, "--grad-mode", help="last_substep | frame | full."),
        iters: int = typer.Option(_DEFAULT.iters, "--iters", help="Most optimisation iterations (0: evaluate the init only)."),
        global_material: bool = typer.Option(False, "--global-material",
                                              help="One (E, nu) for every deformable object (ablation)."),
        optimizer: str = typer.Option(_DEFAULT.optimizer, "--optimizer", help=OPTIMIZER_HELP),
        lr: float = typer.Option(_DEFAULT.lr, "--lr", help="First step on log10 E (decades; nu's is 3x in raw units)."),
        render_scale: float = typer.Option(_DEFAULT.render_scale, "--render-scale",
                                           help="Render/compare at this fraction of the image size."),
        frames: Optional[int] = typer.Option(None, "--frames", help="Use only the first N frames."),
        time_budget: Optional[float] = typer.Option(_DEFAULT.time_budget, "--time-budget", help=TIME_BUDGET_HELP),
        frame_stride: Optional[int] = typer.Option(None, "--frame-stride",
                                                   help="Compare every k-th frame (and its flow); the simulation runs "
                                                        "through all. Default: 2 where that compares at least 10 "
                                                        "frames, else 1."),
        coarse_factor: float = typer.Option(_DEFAULT.coarse_factor, "--coarse-factor",
                                            help="The discretisation error in each 90% interval: the optimum found "
                                                 "again on a grid this fraction as fine (0: not measured, the "
                                                 "interval holds the video's noise alone)."),
        refine: float = typer.Option(_DEFAULT.refine, "--refine", help=REFINE_HELP),
        refined_correction: float = typer.Option(_DEFAULT.refined_correction, "--refined-correction",
                                                 help=REFINED_CORRECTION_HELP),
        flow: str = typer.Option("dis_fine", "--flow", help="Observed-flow estimator: dis_fine | dis | raft."),
        flow_weights: Optional[str] = typer.Option(None, "--flow-weights", help="Local RAFT weights file."),
        device: str = typer.Option("cpu", "--device", help="cpu | cuda (simulator and renderer)."),
        no_video: bool = typer.Option(False, "--no-video", help="Skip comparison.mp4."),
        fresh: bool = typer.Option(False, "--fresh", help="Ignore a checkpoint in --out and start over."),
    ) -> None:
        """Refine E and nu of the deformable objects so the simulated, rendered scene matches the video
        (appearance and optical flow). Writes identified materials, metrics.json, plots, a video, a summary."""
        from endogsim.cli.common import console, print_table, progress, with_interval
        from endogsim.evaluate.report_html import correction_text, force_scale_text
        from endogsim.identify import run_identify

        cfg = IdentifyConfig(loss=loss, grad_mode=grad_mode, iters=iters, global_material=global_material, lr=lr,
                             optimizer=optimizer,
                             render_scale=render_scale, frames=frames, frame_stride=frame_stride,
                             flow=FlowConfig(flow, flow_weights), device=device, **time_budget_option(time_budget),
                             coarse_factor=coarse_factor or None, refine=refine,
                             refined_correction=refined_correction or None)
        with progress() as bar:
            task = bar.add_task("identify", total=max(iters, 1))
            trials: list = []  # the interval trials' task, added when the iterations end (their count is open)
            lock = threading.Lock()  # trials end on worker threads

            def start_trials() -> None:
                with lock:
                    if not trials:
                        bar.update(task, completed=max(iters, 1))
                        trials.append(bar.add_task("intervals", total=None))

            def cb(k: int, total: int, rec: dict) -> None:
                E = ", ".join(f"{v:.4g}" for v in rec["E"].values())
                nu = ", ".join(f"{v:.3f}" for v in rec["nu"].values())
                bar.update(task, completed=k, description=f"identify (loss {rec['loss']:.4g}; E {E} Pa; nu {nu})")
                if rec.get("converged") or k >= total:
                    start_trials()

            def trial_done(t: dict) -> None:
                start_trials()
                unit = " Pa" if t["parameter"] == "E" else ""
                bar.update(trials[0], advance=1, description=f"intervals ({t['object']} {t['parameter']} "
                                                             f"{t['value']:.4g}{unit}, {t['grid']} grid"
                                                             f"{', ' + t['at'] if t.get('at') else ''})")

            m = run_identify(scene, out, init=init, config=cfg, resume=not fresh, progress=cb, video=not no_video,
                             on_trial=trial_done)
            bar.update(task, completed=max(iters, 1))
            for t in bar.tasks:
                if t.id in trials:  # every trial ended: the count is known
                    bar.update(t.id, total=t.completed, description="intervals")
        # The source says whether the video moved the value (identified, a one-sided estimate) or not (prior);
        # the interval what the video and the discretisation leave open around it.
        ivs = m.get("intervals", {})
        rows = [(name, with_interval(v["E"], ivs.get(name, {}).get("E"), ".4g"),
                 with_interval(v["nu"], ivs.get(name, {}).get("nu"), ".3f"),
                 "rigid (frozen)" if v["rigid"] else v.get("source", "-"))
                for name, v in m["materials"].items()]
        print_table(f"Materials of {m['scene']} ({m['iterations']} iterations, {m['stopped']}, {m['seconds']:.0f} s)",
                    ["object", "E [90% interval] (Pa)", "nu [90% interval]", "source"], rows)
        scores = [("EPE (px)", m["epe"]), ("PSNR (dB)", m["psnr"]), ("SSIM", m["ssim"])]
        if "re_mean" in m:
            scores = [("RE E", m["re_E"]), ("RE nu", m["re_nu"]), ("RE G", m["re_G"]), ("RE K", m["re_K"]),
                      ("RE mean", m["re_mean"])] + scores
        print_table("Scores", ["metric", "value"], scores)
        console.print(f"E's scale: {force_scale_text(m['force_scales'])}")
        if m["stopped"] == "time_budget":
            print_budget_stops({"identification": m["iterations"]})
        if m.get("refined_correction") is not None:
            console.print(f"refined correction: {correction_text(m['refined_correction'])}")
        console.print(f"wrote {out}")

