"""``endogsim info DATA``: a summary of a dataset as the loaders see it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from endogsim.cli.common import console, print_table, user_errors


@user_errors
def info(
    data: Path = typer.Argument(..., help="EndoNeRF folder, CholecSeg8K clip folder or video file."),
    downscale: float = typer.Option(1.0, "--downscale", help="Reduce resolution by this factor (>= 1)."),
    max_frames: int = typer.Option(None, "--max-frames", help="Read only the first N frames."),
) -> None:
    """Print format, resolution, timing, intrinsics, depth and per-object statistics of DATA."""
    from endogsim.io.formats import detect_format, load_scene

    fmt = detect_format(data)
    s = load_scene(data, downscale=downscale, max_frames=max_frames)
    dur = float(s.times[-1]) if s.num_frames > 1 else 0.0
    fps = (s.num_frames - 1) / dur if dur > 0 else float("nan")
    K = s.K
    rows = [
        ("format", fmt), ("source", s.source), ("frames", s.num_frames),
        ("resolution", f"{s.width}x{s.height} (downscale {s.downscale:g})"),
        ("fps / duration", f"{fps:.3g} fps / {dur:.3g} s"),
        ("intrinsics", f"fx={K[0, 0]:.2f} fy={K[1, 1]:.2f} cx={K[0, 2]:.2f} cy={K[1, 2]:.2f} px"),
    ]
    if s.depth is not None:
        valid = s.depth > 0
        rng = f"{s.depth[valid].min():.4g}..{s.depth[valid].max():.4g} m" if valid.any() else "none valid"
        rows.append(("depth", f"yes, valid {valid.mean():.1%}, range {rng}"))
    else:
        rows.append(("depth", "no"))
    rows.append(("masks", "yes" if s.object_masks is not None else "no (all pixels tissue id 0)"))
    rows += [("note", n) for n in s.notes]
    print_table("Scene", ["field", "value"], rows)

    if s.object_masks is not None:
        ids, counts = np.unique(s.object_masks, return_counts=True)
        total = s.object_masks.size
        obj_rows = []
        for i, c in zip(ids.tolist(), counts.tolist()):
            lab = s.labels.get(i)
            kind = ("unlabelled" if lab is None else "tool" if lab.is_tool
                    else "background" if lab.klass == "background" else "tissue")
            name = s.name_of(i) if i >= 0 else "unlabelled"
            obj_rows.append((i, name, kind, lab.klass if lab else "-", f"{c / total:.2%}"))
        print_table("Objects", ["id", "name", "tool/tissue", "class", "pixel fraction"], obj_rows)
    else:
        console.print("Objects: no masks; one tissue object (id 0, class unknown_tissue).")


def register(app: typer.Typer) -> None:
    """Add ``info`` to ``app``."""
    app.command("info")(info)
