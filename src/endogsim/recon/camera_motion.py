"""Per-frame pose of a moving endoscope.

The world frame is the camera of frame 0 (as for a fixed endoscope, so ``frame0.ply`` and the simulator
need no extra transform). Frame t's world->camera transform is a rigid motion of the world about its
origin, ``x_cam = R(r_t) x + T_t``, i.e. exactly a :class:`~endogsim.recon.tools.ToolMotion` of one
object pivoting at the origin: its rotation/translation parameters, smoothness term and interpolation
of untrained frames are reused unchanged. Frame 0 is held at the identity (its gradient is zeroed),
which fixes the gauge.
"""

from __future__ import annotations

import torch

from endogsim.gaussians.camera import Camera
from endogsim.recon.tools import ToolMotion

__all__ = ["CameraMotion", "hold_frame0"]


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

    def camera(self, base: Camera, frame: int) -> Camera:
        """``base`` (intrinsics, size) looking from frame ``frame``'s pose."""
        return Camera(base.K, base.width, base.height, self.viewmat(frame))
