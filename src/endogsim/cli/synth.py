"""``endogsim synth``: benchmark scenes with ground-truth materials (procedural or from real frames)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from endogsim.cli.common import output_folder, user_errors


def register(app: typer.Typer) -> None:
    """Add ``synth`` to ``app``."""

    @app.command("synth")
    @user_errors
    def synth(
        scene: Optional[str] = typer.Argument(None, help="Suite scene: tiny, press, pull, two_tissues, stomach, "
                                              "gallbladder (see --list). With --from: a name for the scene."),
        out: Optional[Path] = typer.Option(None, "--out", "-o", callback=output_folder,
                                 help="Output folder (EndoNeRF layout + ground truth)."),
        seed: int = typer.Option(0, "--seed", min=0, help="Seed for textures and material perturbations."),
        frames: Optional[int] = typer.Option(None, "--frames", help="Number of frames (default: the scene's)."),
        scale: Optional[float] = typer.Option(None, "--scale",
                                              help="Image-size factor (procedural, default 1) or downscale of the "
                                                   "real frames (--from, default: 256 px wide)."),
        from_dir: Optional[Path] = typer.Option(None, "--from", help="Build the scene from a real data folder "
                                                "(EndoNeRF or CholecSeg8K layout)."),
        interaction: str = typer.Option("press", "--interaction", help="With --from: 'press' or 'pull'."),
        list_scenes: bool = typer.Option(False, "--list", help="List the suite's scenes and exit."),
    ) -> None:
        """Simulate a benchmark scene and write frames, depth, masks, ground-truth flow, scene.json, PLY."""
        from endogsim.cli.common import console, print_table, progress
        from endogsim.errors import DataError
        from endogsim.synth.suite import load_suite

        if list_scenes:
            suite = load_suite()
            rows = []
            for name, s in suite["scenes"].items():
                mats = ", ".join(f"{o['name']} E={o['E'] / 1000:g} kPa nu={o['nu']}" for o in s["objects"])
                rows.append((name, mats, s["description"]))
            print_table("Benchmark suite", ["scene", "ground truth", "description"], rows)
            return
        if out is None:
            raise DataError("--out DIR is required (the folder to write the scene to)")
        if scene is None and from_dir is None:
            raise DataError("give a scene name (see `endogsim synth --list`) or --from DATA_DIR")
        from endogsim.io.runfolder import run_folder
        from endogsim.synth.generate import synthesize

        with run_folder(out, "synth"), progress() as bar:
            tasks: dict[str, int] = {}

            def cb(stage: str, done: int, total: int) -> None:
                if stage not in tasks:
                    tasks[stage] = bar.add_task(stage, total=total)
                bar.update(tasks[stage], completed=done)

            if from_dir is not None:
                path = synthesize(scene or Path(from_dir).name, out, seed=seed, frames=frames, scale=scale,
                                  from_dir=from_dir, progress=cb, interaction=interaction)
            else:
                path = synthesize(scene, out, seed=seed, frames=frames, scale=scale, progress=cb)
        from endogsim.scene.schema import load_scene_spec

        sc = load_scene_spec(path).scenario
        gt, idn = sc.ground_truth, sc.identification
        console.print(f"wrote {path} (ground truth: grid {gt.grid}^3, {gt.substeps} substeps of {gt.dt:.2g} s; "
                      f"identification: grid {idn.grid}^3, substeps by the CFL rule at run time, >= {idn.substeps})")
