"""``endogsim simulate`` (a new tool interaction with given materials) and ``endogsim report`` (HTML report)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from endogsim.cli.common import REFINE_WHAT, output_folder, user_errors


def register(app: typer.Typer) -> None:
    """Add ``simulate`` and ``report`` to the root ``app``."""

    @app.command("simulate")
    @user_errors
    def simulate_cmd(
        scene: Path = typer.Argument(..., help="Scene folder (scene.json) or run folder (uses its identified materials)."),
        interaction: str = typer.Option(..., "--interaction", "-i",
                                        help="Built-in name (poke, press, pull, push_force) or an interaction JSON file."),
        materials: Optional[str] = typer.Option(None, "--materials", "-m",
                                                help="Material JSON file, 'truth' (scene.json), or an initialiser "
                                                     "(prior, manual); default: the run's identified materials, else prior."),
        out: Path = typer.Option(..., "--out", "-o", callback=output_folder,
                                 help="Output folder (video, frames, PLY sequence, summary.json)."),
        frames: Optional[int] = typer.Option(None, "--frames", help="Override the interaction's frame count."),
        fps: float = typer.Option(10.0, "--fps", help="Video frame rate."),
        no_ply: bool = typer.Option(False, "--no-ply", help="Skip the PLY sequence."),
        device: str = typer.Option("cpu", "--device", help="cpu | cuda (simulator)."),
        refine: Optional[float] = typer.Option(None, "--refine", help=REFINE_WHAT + ". Default: the factor the "
                                               "materials were identified at (1 for the truth or a prior), with at "
                                               "least the substeps per frame they were identified with there."),
    ) -> None:
        """Simulate a new interaction (tool trajectory, force on a region, or grasp-and-pull) on a scene with
        given materials; writes simulation.mp4, frames/*.png, ply/*.ply and summary.json."""
        from endogsim.cli.common import console, print_table
        from endogsim.pipeline.interaction import load_interaction
        from endogsim.pipeline.simulate import simulate_interaction

        inter = load_interaction(interaction)
        if frames is not None:  # validated like a file's value (2 to 400 frames)
            inter = load_interaction({**inter.model_dump(), "frames": frames}, where=f"--frames {frames}")
        with console.status(f"simulating {inter.name} ..."):
            s = simulate_interaction(scene, inter, materials, out, fps=fps, write_ply_sequence=not no_ply,
                                     device=device, refine=refine)
        print_table(f"{inter.name} on {s['scene']} ({s['frames']} frames, {s['substeps']} substeps/frame)",
                    ["object", "E (Pa)", "nu", "source", "max displacement (mm)", "at last frame (mm)"],
                    [(n, v["E"], f"{v['nu']:.3f}", v["source"], s["displacement"][n]["max_mm"],
                      s["displacement"][n]["max_last_mm"]) for n, v in s["materials"].items() if not v["rigid"]])
        for b in s["grasp_bites"]:
            if b["torn"]:
                console.print(f"[yellow]the grasp's bite tore out of the tissue (numerical fracture): by frame "
                              f"{b['frame_of_max']} the tissue around it lies {b['ring_cells_max']:.2f} grid cells "
                              f"(median) from it, beyond {b['tolerance_cells']:g}; pull less far or less fast[/yellow]")
        console.print(f"wrote {out} (simulate {s['seconds']['simulate']:.1f} s, render + write "
                      f"{s['seconds']['render_and_write']:.1f} s)")

    @app.command("report")
    @user_errors
    def report_cmd(
        run: Path = typer.Argument(..., help="Run folder of `endogsim identify` (metrics.json)."),
        simulation: Optional[list[Path]] = typer.Option(None, "--simulation", "-s",
                                                        help="An `endogsim simulate` output folder to include (repeatable)."),
        out: Optional[Path] = typer.Option(None, "--out", "-o", help="HTML file (default RUN/report.html)."),
        fid_weights: Optional[Path] = typer.Option(None, "--fid-weights",
                                                   help="Local Inception-v3 weights for FID (else FID is n/a)."),
    ) -> None:
        """Write an HTML report (viewable offline) of a run: videos, flow error maps, plots, materials, metrics."""
        from endogsim.cli.common import console
        from endogsim.evaluate.report_html import write_report

        path = write_report(run, simulations=simulation or [], out=out, fid_weights=fid_weights)
        console.print(f"wrote {path}")
