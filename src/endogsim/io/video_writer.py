"""Write frame sequences as H.264 mp4 (libx264, yuv420p) or numbered PNGs, atomically."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from endogsim.errors import DataError
from endogsim.io.atomic import atomic_path


def _to_uint8(frames) -> np.ndarray:
    """[T, H, W, 3] float in [0, 1] or uint8 (numpy or torch) -> uint8 numpy."""
    if hasattr(frames, "detach"):
        frames = frames.detach().cpu().numpy()
    frames = np.asarray(frames)
    if frames.ndim == 3:  # a single frame
        frames = frames[None]
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] == 0:
        raise DataError(f"frames must be [T, H, W, 3] with T >= 1, got shape {frames.shape}")
    if frames.dtype == np.uint8:
        return np.ascontiguousarray(frames)
    if not np.isfinite(frames).all():
        raise DataError("frames contain NaN or inf")
    return (np.clip(frames, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_video(frames, path: str | os.PathLike, fps: float = 25.0, quality: int = 8) -> Path:
    """Write ``frames`` [T, H, W, 3] (float in [0, 1] or uint8) to an H.264 mp4 at ``fps`` frames/s.

    Odd widths/heights are padded by one edge pixel (yuv420p needs even sizes). The file appears
    only when complete (written to a temporary file in the same folder, then renamed).
    """
    import imageio_ffmpeg

    path = Path(path)
    if not 0 < fps <= 1000:
        raise DataError(f"{path}: fps must lie in (0, 1000], got {fps}")
    f = _to_uint8(frames)
    t, h, w, _ = f.shape
    ph, pw = h % 2, w % 2
    if ph or pw:
        f = np.pad(f, ((0, 0), (0, ph), (0, pw), (0, 0)), mode="edge")
    with atomic_path(path, suffix=path.suffix or ".mp4") as tmp:
        writer = imageio_ffmpeg.write_frames(
            str(tmp), (w + pw, h + ph), fps=float(fps), codec="libx264", pix_fmt_out="yuv420p",
            quality=quality, macro_block_size=1, ffmpeg_log_level="error",
        )
        writer.send(None)
        for frame in f:
            writer.send(np.ascontiguousarray(frame))
        writer.close()
    return path


def write_frames_png(frames, folder: str | os.PathLike, pattern: str = "frame_{:04d}.png") -> list[Path]:
    """Write ``frames`` [T, H, W, 3] (float in [0, 1] or uint8) as PNGs named ``pattern.format(i)``.

    Each file is written to a temporary name and renamed, so a reader never sees half an image.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i, frame in enumerate(_to_uint8(frames)):
        p = folder / pattern.format(i)
        with atomic_path(p) as tmp:
            if not cv2.imwrite(str(tmp), np.ascontiguousarray(frame[..., ::-1])):
                raise DataError(f"{p}: could not write PNG")
        out.append(p)
    return out
