"""Per-frame pose of a moving endoscope.

The world frame is the camera of frame 0 (as for a fixed endoscope, so ``frame0.ply`` and the simulator
need no extra transform). Frame t's world->camera transform is a rigid motion of the world about its
origin, ``x_cam = R(r_t) x + T_t``, i.e. exactly a :class:`~endogsim.recon.tools.ToolMotion` of one
object pivoting at the origin: its rotation/translation parameters, smoothness term and interpolation
of untrained frames are reused unchanged. Frame 0 is held at the identity (its gradient is zeroed),
which fixes the gauge.
"""

from __future__ import annotations

import math
from typing import Callable

import torch

from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import rotmat_to_quat
from endogsim.recon.params import log_linear_lr
from endogsim.recon.tools import ToolMotion, quat_to_axis_angle

__all__ = ["CameraMotion", "hold_frame0", "refine_pose"]


def hold_frame0(grad: torch.Tensor) -> torch.Tensor:
    """Gradient hook of a per-frame parameter [K, T, C]: frame 0 never moves (it fixes the gauge)."""
    grad = grad.clone()
    grad[:, 0] = 0
    return grad


class CameraMotion(ToolMotion):
    """World->camera transforms of T frames (frame 0: identity).

    Args:
        num_frames: T.
        init_rotation: optional [T, 3] axis-angle (radians) of each frame's world->camera rotation,
            e.g. from :func:`endogsim.priors.camera.estimate_camera_rotations`.
    """

    def __init__(self, num_frames: int, init_rotation: torch.Tensor | None = None) -> None:
        super().__init__([-1], torch.zeros(1, 3), num_frames)
        if init_rotation is not None:
            with torch.no_grad():
                self.rotation[0] = torch.as_tensor(init_rotation, dtype=torch.float32)
                self.rotation[0, 0] = 0
        self.rotation.register_hook(hold_frame0)
        self.translation.register_hook(hold_frame0)

    def viewmat(self, frame: int) -> torch.Tensor:
        """[4, 4] world->camera transform of ``frame`` (differentiable)."""
        return self.transforms()[0, frame]

    @torch.no_grad()
    def set_viewmat(self, frame: int, viewmat: torch.Tensor) -> None:
        """Make ``frame``'s pose the rigid [4, 4] world->camera transform ``viewmat``."""
        self.rotation[0, frame] = quat_to_axis_angle(rotmat_to_quat(viewmat[None, :3, :3]))[0]
        self.translation[0, frame] = viewmat[:3, 3]  # the pivot is the origin: x_cam = R x + T

    def camera(self, base: Camera, frame: int) -> Camera:
        """``base`` (intrinsics, size) looking from frame ``frame``'s pose."""
        return Camera(base.K, base.width, base.height, self.viewmat(frame))


def refine_pose(loss_of_viewmat: Callable[[torch.Tensor], torch.Tensor], viewmat: torch.Tensor, length_scale: float,
                steps: int = 100, lr: float = 2e-3, lr_final: float = 2e-5) -> tuple[torch.Tensor, torch.Tensor]:
    """One camera pose refined alone against an image, everything else frozen.

    This is the test-time pose optimisation of BARF and NoPe-NeRF: a held-out frame of a video without
    camera poses has no pose to render it from but the interpolation of its neighbours', and a jerky
    hand-held endoscope moves off that line. The correction is a rigid motion of the camera
    (:class:`ToolMotion` of one object pivoting at the camera origin), stepped by Adam at a rate decaying
    log-linearly from ``lr`` to ``lr_final``.

    Args:
        loss_of_viewmat: differentiable loss of a [4, 4] world->camera transform (render and compare).
        viewmat: [4, 4] starting world->camera transform.
        length_scale: metres per unit of translation step (the scene extent).
        steps: Adam steps.
        lr, lr_final: step sizes, radians for the rotation and ``length_scale`` units for the translation.

    Returns:
        The [4, 4] transform (detached) of lowest loss among the start and the ``steps`` iterates, and its
        correction's [2] (rotation angle in radians, translation length in metres), so a refinement never
        ends worse than it began by its own loss.
    """
    correction = ToolMotion([-1], torch.zeros(1, 3), 1).to(viewmat.device)
    opt = torch.optim.Adam([{"params": [correction.rotation], "lr": lr, "name": "rot"},
                            {"params": [correction.translation], "lr": lr * length_scale, "name": "trans"}])
    viewmat = viewmat.detach()
    best_loss, best_pose, best_size = math.inf, viewmat, torch.zeros(2, device=viewmat.device)
    for i in range(steps + 1):
        pose = correction.transforms()[0, 0] @ viewmat
        loss = loss_of_viewmat(pose)
        value = float(loss.detach())
        if value < best_loss:  # Adam's steps need not descend: keep the best pose seen, the start included
            best_loss, best_pose = value, pose.detach()
            best_size = torch.stack([correction.rotation[0, 0].norm(), correction.translation[0, 0].norm()]).detach()
        if i == steps:
            break
        rate = log_linear_lr(i / max(steps - 1, 1), lr, lr_final)
        for g in opt.param_groups:
            g["lr"] = rate * (length_scale if g["name"] == "trans" else 1.0)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return best_pose, best_size
