"""``endogsim demo``: the built-in demonstration on procedural data (no data, no weights, no network)."""

from __future__ import annotations

from pathlib import Path

import typer

from endogsim.cli.common import user_errors


def register(app: typer.Typer) -> None:
    """Add ``demo`` to the root ``app``."""

    @app.command("demo")
    @user_errors
    def demo_cmd(
        out: Path = typer.Option(Path("demo"), "--out", "-o", help="Output folder."),
        frames: int = typer.Option(48, "--frames", help="Frames of the preview render."),
        width: int = typer.Option(320, "--width", help="Image width (pixels); height keeps 5:4."),
    ) -> None:
        """Render a built-in procedural tissue + instrument scene under a moving camera and tool:
        OUT/render.mp4 and OUT/frames/*.png."""
        from endogsim.cli.common import console, print_table, progress
        from endogsim.pipeline.preview import PreviewConfig, render_preview

        if frames < 2 or width < 32:
            raise typer.BadParameter("--frames must be >= 2 and --width >= 32")
        cfg = PreviewConfig(width=width, height=round(width * 0.8), frames=frames)
        with progress() as bar:
            task = bar.add_task("render preview", total=frames)
            summary = render_preview(out, cfg, progress=lambda k, n: bar.update(task, completed=k))
        print_table("endogsim demo", ["output", "value"],
                    [("video", summary["video"]), ("frames", summary["frames_dir"]),
                     ("Gaussians", summary["num_gaussians"]),
                     ("seconds per frame", f"{summary['seconds_per_frame']:.2f}")])
        console.print(f"wrote {out}")
