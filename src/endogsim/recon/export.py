"""Export of a trained reconstruction: the run folder's files (see :mod:`endogsim.recon.model` for the list)
and ``metrics.json``."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from endogsim.gaussians.model import Gaussians
from endogsim.io.atomic import (
    atomic_folder,
    save_npz_atomic,
    save_torch_atomic,
    write_json_atomic,
)
from endogsim.recon.evaluation import evaluate_frames

if TYPE_CHECKING:
    from endogsim.recon.train import Trainer

__all__ = ["export_run", "write_object_masks"]


def write_object_masks(folder: Path, masks: np.ndarray | None) -> None:
    """The masks the reconstruction used (one id per instrument after the instance split), as
    ``frame-%06d.png`` 16-bit ids: the ids of ``objects.json``, 65535 for pixels of no object (unlabelled, or
    a dropped speck of a tool class). Scene folders built from the run read them."""
    import cv2

    if masks is None:
        return
    with atomic_folder(folder) as tmp:
        for t, m in enumerate(masks):
            cv2.imwrite(str(tmp / f"frame-{t:06d}.png"), np.where(m < 0, 65535, m).astype(np.uint16))


def export_run(tr: "Trainer") -> dict:
    """Write every run output of the trainer's run folder (see :mod:`endogsim.recon.model`) and return the
    metrics (also ``metrics.json``)."""
    from endogsim.gaussians.ply import write_ply

    out, sc = tr.out, tr.prep.scene
    if tr.motion is not None:
        trained = tr.tool_visible.clone()
        for t in tr.prep.test:
            trained[:, t] = False
        tr.motion.interpolate_missing(trained, tr.times)
    # first, as it fixes the test frames' camera poses that the files below hold
    ev = evaluate_frames(tr, tr.prep.test, out / "renders", register_poses=True)
    tissue = tr.tissue.gaussians().detach().to("cpu")
    tools = tr.tools.gaussians().detach().to("cpu") if tr.tools is not None else None
    canonical = Gaussians.concat([tissue, tools]) if tools is not None else tissue
    write_ply(canonical, out / "canonical.ply")
    write_ply(tr.gaussians_at(0, True).to("cpu"), out / "frame0.ply")
    labels = {str(i): {"name": lab.name, "is_tool": lab.is_tool, "class": lab.klass} for i, lab in sc.labels.items()}
    save_torch_atomic({
        "deformation": {**tr.deformation.export(),
                        "state_dict": {k: v.cpu() for k, v in tr.deformation.state_dict().items()}},
        "tool_motion": None if tr.motion is None else {
            "tool_ids": tr.motion.tool_ids, "state_dict": {k: v.cpu() for k, v in tr.motion.state_dict().items()}},
        "num_tissue": len(tissue), "times": tr.times.cpu(), "labels": labels,
        "viewmats": None if tr.camera_motion is None else tr.camera_motion.transforms()[0].detach().cpu(),
        "exposure": None if tr.exposure is None
        else {k: v.detach().cpu() for k, v in tr.exposure.state_dict().items()},
        "camera": {"K": tr.camera.K.cpu().tolist(), "width": tr.camera.width, "height": tr.camera.height},
        "field_of_view": None if tr.prep.field_of_view is None else torch.as_tensor(tr.prep.field_of_view),
    }, out / "deformation.pt")
    write_json_atomic(out / "objects.json", labels)
    write_object_masks(out / "object_masks", sc.object_masks)
    traj = {}
    if tr.motion is not None:
        M = tr.motion.transforms().detach().cpu().numpy()
        for k, oid in enumerate(tr.motion.tool_ids):
            traj[str(oid)] = {"name": sc.name_of(oid), "reference_frame": tr.init_info["tool_ref_frames"][k],
                              "transforms": M[k].tolist()}
        arrays = {f"object_{oid}": M[k] for k, oid in enumerate(tr.motion.tool_ids)}
    else:
        arrays = {}
    write_json_atomic(out / "tool_trajectories.json", {
        "convention": "per tool: [T, 4, 4] rigid transforms, canonical Gaussians -> frame t, world = camera "
                      "frame of frame 0 (of the fixed endoscope, or of a moving one: see camera_poses), metres",
        "camera_poses": None if tr.camera_motion is None
        else tr.camera_motion.transforms()[0].detach().cpu().tolist(), "times": tr.times.tolist(), "tools": traj})
    save_npz_atomic(out / "tool_trajectories.npz", times=tr.times.numpy(), **arrays)

    per_frame = ev.pop("per_frame")
    metrics = {
        **ev, "ssim": ev["ssim_masked"], "test_frames": tr.prep.test, "per_frame": per_frame,
        "train_frames": len(tr.prep.train),
        "training_seconds": round(tr.elapsed, 2), "iterations": tr.iteration,
        "stopped_by_budget": tr.stopped_by_budget,
        "num_gaussians": len(canonical), "num_tissue_gaussians": len(tissue),
        "num_tool_gaussians": 0 if tools is None else len(tools),
        "resolution": [sc.width, sc.height], "device": str(tr.device),
        "depth_source": tr.prep.depth_source, "segmentation_source": tr.prep.seg_source,
        "track_source": tr.cfg.flow.method if tr.tracks is not None else "none",
        "camera_motion": tr.camera_motion is not None,
        "tissue_pixel_fraction": float(tr.prep.tissue[tr.prep.test].mean()) if tr.prep.test else None,
        "repeated_frames": [] if tr.prep.repeated is None else np.nonzero(tr.prep.repeated)[0].tolist(),
        "data_notes": list(sc.notes),
        "tool_instances": None if tr.prep.instances is None else tr.prep.instances.summary(),
        "protocol": {"psnr_masked": "MSE over tissue pixels (tools, background, unlabelled excluded)",
                     "psnr_endonerf": "tool pixels zeroed in both images, MSE over the whole image",
                     "psnr_full": "tissue + tool models together vs the image, over tissue and tool pixels",
                     "tissue_pixel_fraction": "share of the test frames' pixels the masked metrics cover",
                     "repeated_frames": "frames showing the same instant as the one before (frame-rate "
                                        "conversion), found from the training frames; they share its time",
                     "track_source": "optical flow of the point tracks (training frames only)",
                     "tool_instances": "the instruments the tool classes of the masks were split into (one "
                                       "object each; gaps: frames where one is not seen, its pose there "
                                       "interpolated between the frames around, held beyond the ends)",
                     "pose": "moving endoscope: each test frame's pose is the interpolation of its training "
                             "neighbours' poses registered to the test frame with the model frozen (BARF's "
                             "and NoPe-NeRF's test-time pose optimisation; pose_alignment gives each "
                             "correction); *_interpolated_pose: from the interpolation alone, as is history",
                     "render": "tissue model only (tools are a separate model), except psnr_full",
                     "data_notes": "what the loader assumed or repaired reading the data (also warned)"},
        "init": tr.init_info, "history": tr.history,
    }
    write_json_atomic(out / "metrics.json", metrics)
    return metrics
