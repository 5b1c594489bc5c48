"""A built-in procedural Gaussian scene and a short camera + tool motion rendered to video.

This is the first stage of ``endogsim demo``: it needs no data and no simulation, and shows that the
Gaussian model, the procedural endoscopy look and the renderer work on this machine.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians

__all__ = ["PreviewConfig", "build_preview_scene", "render_preview"]

TISSUE_ID, TOOL_ID = 1, 2


@dataclass(frozen=True)
class PreviewConfig:
    """Size and motion of the preview render.

    Attributes:
        width, height: image size in pixels.
        frames: number of rendered frames.
        fps: video frame rate.
        spacing: distance between tissue Gaussians (metres); smaller = more Gaussians, slower.
        orbit_deg: half-angle of the camera's sideways arc around the tissue centre (degrees).
        tool_travel: distance the tool tip advances towards the tissue (metres).
        seed: texture seed.
    """

    width: int = 320
    height: int = 256
    frames: int = 48
    fps: float = 24.0
    spacing: float = 0.0015
    orbit_deg: float = 12.0
    tool_travel: float = 0.012
    seed: int = 0


def build_preview_scene(cfg: PreviewConfig = PreviewConfig()) -> tuple[Gaussians, Gaussians, Camera, np.ndarray]:
    """Tissue and tool Gaussians in front of a laparoscope.

    Returns:
        tissue Gaussians (object id 1), tool Gaussians (object id 2, at its start pose), the camera
        (world = camera frame at t = 0) and the orbit centre [3] (metres).
    """
    from endogsim.synth.procedural import (
        bake_lighting,
        endoscope_camera,
        surface_gaussians,
        tissue_surface,
        tool_gaussians,
    )

    camera = endoscope_camera(cfg.width, cfg.height)
    depth = 0.06
    dome = lambda u, v: -0.008 * np.exp(-(u * u + v * v) / 0.012**2)  # noqa: E731 - a bulging organ
    pts, cols, _ = tissue_surface((0.0, 0.0, depth), (0.12, 0.10), cfg.spacing, cfg.seed, height_fn=dome)
    tissue = bake_lighting(surface_gaussians(pts, cols, cfg.spacing, TISSUE_ID), camera, ref_distance=depth)
    tip, end = np.array([0.004, 0.003, depth - 0.022]), np.array([0.05, 0.035, depth - 0.045])
    tool = tool_gaussians(tip, end, radius=0.0025, spacing=cfg.spacing * 0.8, object_id=TOOL_ID, seed=cfg.seed, jaw=True)
    return tissue, tool, camera, np.array([0.0, 0.0, depth])


def _orbit_viewmat(angle: float, center: np.ndarray) -> torch.Tensor:
    """World-to-camera [4, 4] of a camera rotated by ``angle`` (radians) about the y axis through ``center``."""
    c, s = math.cos(angle), math.sin(angle)
    R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # camera-to-world rotation
    cam_pos = center + R @ (-center)  # the t = 0 camera (origin) rotated about the centre
    V = np.eye(4)
    V[:3, :3] = R.T
    V[:3, 3] = -R.T @ cam_pos
    return torch.tensor(V, dtype=torch.float32)


def render_preview(out: str | Path, cfg: PreviewConfig = PreviewConfig(),
                   progress: Callable[[int, int], None] | None = None) -> dict:
    """Render the preview scene with the camera swinging on an arc and the tool advancing and retracting.

    Writes ``out/render.mp4`` and ``out/frames/frame_XXXX.png``; returns a summary dict
    (``video``, ``frames_dir``, ``num_gaussians``, ``seconds_per_frame``).
    """
    import time

    from endogsim.gaussians.render import render_gaussians
    from endogsim.io.video_writer import write_frames_png, write_video

    out = Path(out)
    tissue, tool, camera, center = build_preview_scene(cfg)
    toward_tissue = torch.tensor([-0.046, -0.032, 0.023])
    toward_tissue = toward_tissue / toward_tissue.norm()
    background = torch.tensor([0.05, 0.01, 0.01])
    frames = []
    t0 = time.perf_counter()
    with torch.no_grad():
        for k in range(cfg.frames):
            phase = k / max(cfg.frames - 1, 1)
            angle = math.radians(cfg.orbit_deg) * math.sin(2 * math.pi * phase)
            advance = cfg.tool_travel * math.sin(math.pi * phase)  # in, then out
            moved_tool = tool.with_(means=tool.means + advance * toward_tissue)
            cam = Camera(camera.K, camera.width, camera.height, _orbit_viewmat(angle, center))
            img = render_gaussians(Gaussians.concat([tissue, moved_tool]), cam, background=background).rgb
            frames.append(img.clamp(0, 1).numpy())
            if progress is not None:
                progress(k + 1, cfg.frames)
    seconds = time.perf_counter() - t0
    frames_np = np.stack(frames)
    video = write_video(frames_np, out / "render.mp4", fps=cfg.fps)
    write_frames_png(frames_np, out / "frames")
    return {"video": str(video), "frames_dir": str(out / "frames"), "num_gaussians": len(tissue) + len(tool),
            "seconds_per_frame": seconds / cfg.frames}
