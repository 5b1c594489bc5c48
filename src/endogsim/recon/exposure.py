"""Per-frame exposure of a moving endoscope.

The light source rides on the endoscope, so when the camera moves the tissue brightens or darkens as a
whole (auto-exposure does the rest): CholecSeg8K's clip varies by ~4% in mean intensity between frames.
A static set of Gaussian colours cannot express that; a per-frame affine colour map can, per channel:

    rgb_t = rgb * exp(g_t) + b_t        g_t, b_t: [3] (log gain, bias)

Frame 0 is held at the identity (the Gaussians' colours are frame 0's), which fixes the gauge, as for
:class:`~endogsim.recon.camera_motion.CameraMotion`. Frames never trained (test frames) take the values
interpolated between their training neighbours.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from endogsim.recon.camera_motion import hold_frame0
from endogsim.recon.tools import fill_untrained_frames

__all__ = ["FrameExposure", "apply_exposure"]


def apply_exposure(rgb: torch.Tensor, log_gain: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``rgb`` [..., 3] mapped by one frame's exposure: ``rgb * exp(log_gain) + bias`` (both [3])."""
    return rgb * torch.exp(log_gain) + bias


class FrameExposure(nn.Module):
    """Log gain and bias [1, T, 3] of every frame (frame 0: identity; the per-frame layout of
    :class:`~endogsim.recon.tools.ToolMotion`, one object)."""

    def __init__(self, num_frames: int) -> None:
        super().__init__()
        self.log_gain = nn.Parameter(torch.zeros(1, num_frames, 3))
        self.bias = nn.Parameter(torch.zeros(1, num_frames, 3))
        self.log_gain.register_hook(hold_frame0)
        self.bias.register_hook(hold_frame0)

    @property
    def num_frames(self) -> int:
        return self.log_gain.shape[1]

    def forward(self, rgb: torch.Tensor, frame: int) -> torch.Tensor:
        """[H, W, 3] render ``rgb`` as frame ``frame``'s camera exposed it (differentiable)."""
        return apply_exposure(rgb, self.log_gain[0, frame], self.bias[0, frame])

    @torch.no_grad()
    def interpolate_missing(self, trained: torch.Tensor, times: torch.Tensor | None = None) -> None:
        """Fill the frames never trained (``trained`` [T] bool False) from their training neighbours,
        interpolating in ``times`` [T] (default: the frame index)."""
        fill_untrained_frames([self.log_gain, self.bias], trained[None], times)
