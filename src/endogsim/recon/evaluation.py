"""Evaluation of a reconstruction on its held-out frames (PSNR / SSIM under both protocols, renders).

A moving endoscope has no pose for a held-out frame but the interpolation of its training neighbours';
:func:`evaluate_frames` can register each such pose to its frame with the model frozen (BARF's and
NoPe-NeRF's test-time pose optimisation) before scoring.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from endogsim.evaluate.image_metrics import mse, psnr, psnr_endonerf, ssim
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians
from endogsim.gaussians.render import render_gaussians
from endogsim.recon.camera_motion import refine_pose

if TYPE_CHECKING:
    from endogsim.recon.train import Trainer

__all__ = ["evaluate_frames", "registered_view", "fill_untrained_cameras"]


def fill_untrained_cameras(tr: "Trainer") -> None:
    """Test frames are never trained: their camera poses and exposures come from the neighbouring
    training frames."""
    trained = torch.zeros(len(tr.times), dtype=torch.bool)
    trained[tr.prep.train] = True
    for part in (tr.camera_motion, tr.exposure):
        if part is not None:
            part.interpolate_missing(trained.to(tr.device), tr.times)

def registered_view(tr: "Trainer", frame: int, g: Gaussians) -> tuple[Camera, torch.Tensor]:
    """``frame``'s camera after refining its pose alone against the frame's tissue pixels with the model
    frozen (:func:`~endogsim.recon.camera_motion.refine_pose`), and the correction's [2] (radians,
    metres). ``g``: the tissue Gaussians at ``frame`` (:meth:`Trainer.gaussians_at`, without tools).

    The pose minimises the masked squared error of the image that is scored (exposed, clamped to [0, 1]),
    as BARF's test-time registration does: minimising another error (L1) can lower the PSNR it is judged by.
    """
    gt, m = tr.frames[frame], tr.tissue_mask[frame]

    def loss(viewmat: torch.Tensor) -> torch.Tensor:
        cam = Camera(tr.camera.K, tr.camera.width, tr.camera.height, viewmat)
        return mse(tr.expose(render_gaussians(g, cam, backend=tr.cfg.backend).rgb, frame).clamp(0, 1), gt, m)

    with torch.enable_grad():
        viewmat, size = refine_pose(loss, tr.view(frame).viewmat, tr.extent, tr.cfg.test_pose_steps)
    return Camera(tr.camera.K, tr.camera.width, tr.camera.height, viewmat), size

@torch.no_grad()
def evaluate_frames(tr: "Trainer", frames: list[int], render_dir: Path | None = None,
                    register_poses: bool = False) -> dict:
    """Test metrics on ``frames`` (tissue render vs image); writes PNG renders when ``render_dir``.

    A moving endoscope has no pose for a held-out frame but the interpolation of its training
    neighbours'. With ``register_poses`` (and ``test_pose_steps`` > 0) each test frame's pose is then
    registered to the frame with the model frozen (:func:`registered_view`) and kept in the camera
    motion; every metric and render uses it. The metrics from the interpolated poses stay under
    ``psnr_masked_interpolated_pose`` and ``ssim_masked_interpolated_pose``, and ``pose_alignment``
    lists each correction. Without registration (or with a fixed camera) the interpolated pose is
    the test pose.
    """
    from endogsim.io.video_writer import write_frames_png

    fill_untrained_cameras(tr)
    res = {"psnr_masked": [], "psnr_endonerf": [], "ssim_masked": [], "ssim_endonerf": [], "psnr_full": []}
    register_poses = register_poses and tr.camera_motion is not None and tr.cfg.test_pose_steps > 0
    if register_poses:
        res |= {"psnr_masked_interpolated_pose": [], "ssim_masked_interpolated_pose": []}
        corrections = []
    renders, full = [], []
    for t in frames:
        tissue = tr.gaussians_at(t, False)
        cam = tr.view(t)
        gt = tr.frames[t]
        m, tool = tr.tissue_mask[t], tr.tool_mask[t]
        if register_poses:
            interpolated = tr.expose(render_gaussians(tissue, cam, backend=tr.cfg.backend).rgb, t).clamp(0, 1)
            res["psnr_masked_interpolated_pose"].append(psnr(interpolated, gt, m))
            res["ssim_masked_interpolated_pose"].append(ssim(interpolated, gt, m))
            cam, size = registered_view(tr, t, tissue)
            tr.camera_motion.set_viewmat(t, cam.viewmat)
            corrections.append({"frame": t, "rotation_deg": round(math.degrees(float(size[0])), 4),
                                "translation_m": round(float(size[1]), 7)})
        pred = tr.expose(render_gaussians(tissue, cam, backend=tr.cfg.backend).rgb, t).clamp(0, 1)
        res["psnr_masked"].append(psnr(pred, gt, m))
        res["ssim_masked"].append(ssim(pred, gt, m))
        res["psnr_endonerf"].append(psnr_endonerf(pred, gt, tool))
        keep = (1 - tool)[..., None]
        res["ssim_endonerf"].append(ssim(pred * keep, gt * keep))
        renders.append(pred.cpu().numpy())
        whole = pred
        if tr.tools is not None:
            whole = render_gaussians(tr.gaussians_at(t, True), cam, backend=tr.cfg.backend).rgb
            whole = tr.expose(whole, t).clamp(0, 1)
            full.append(whole.cpu().numpy())
        valid = ((tr.tissue_mask[t] + tool) > 0).float()  # leave out background / unlabelled
        res["psnr_full"].append(psnr(whole, gt, valid))
    if render_dir is not None:
        for sub, imgs in (("test", renders), ("test_full", full)):
            for t, img in zip(frames, imgs):
                write_frames_png(img[None], render_dir / sub, pattern=f"frame_{t:04d}.png")
    out = {k: float(np.mean(v)) if v else float("nan") for k, v in res.items()} | {"per_frame": res}
    if register_poses:
        out["pose_alignment"] = corrections
    return out
