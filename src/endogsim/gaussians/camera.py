"""Pinhole camera in the OpenCV convention (x right, y down, z forward)."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


def project_points(points: torch.Tensor, K: torch.Tensor, viewmats: torch.Tensor) -> torch.Tensor:
    """Pixel coordinates [N, 2] (pixel (i, j) has its centre at (j + 0.5, i + 0.5)) of world points, as the
    renderer projects Gaussian centres; differentiable.

    Args:
        points: [N, 3] world points (metres).
        K: [3, 3] intrinsics (pixels).
        viewmats: [4, 4] world->camera transform, or [N, 4, 4], one per point.
    """
    V = viewmats.to(points)
    if V.ndim == 2:
        p = points @ V[:3, :3].T + V[:3, 3]
    else:
        p = (V[:, :3, :3] @ points[..., None])[..., 0] + V[:, :3, 3]
    K = K.to(points)
    return p[:, :2] / p[:, 2:3].clamp_min(1e-9) * torch.stack([K[0, 0], K[1, 1]]) + torch.stack([K[0, 2], K[1, 2]])


@dataclass
class Camera:
    """A pinhole camera.

    Attributes:
        K: [3, 3] intrinsics in pixels (fx, fy, cx, cy); pixel centres sit at integer + 0.5.
        width: image width in pixels.
        height: image height in pixels.
        viewmat: [4, 4] world-to-camera transform. Identity for a fixed endoscope (world = camera frame).
    """

    K: torch.Tensor
    width: int
    height: int
    viewmat: torch.Tensor = field(default_factory=lambda: torch.eye(4))

    def center(self) -> torch.Tensor:
        """[3] camera centre in world coordinates (metres): -R^T t of the world-to-camera ``viewmat``."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (0.5 halves width and height)."""
        K = self.K.clone()
        K[:2] *= factor
        return Camera(K, round(self.width * factor), round(self.height * factor), self.viewmat.clone())

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """Pixel coordinates [N, 2] of world points [N, 3] (metres) seen by this camera (:func:`project_points`)."""
        return project_points(points, self.K, self.viewmat)

    def to(self, device: torch.device | str) -> "Camera":
        return Camera(self.K.to(device), self.width, self.height, self.viewmat.to(device))

    @staticmethod
    def from_intrinsics(K, width: int, height: int) -> "Camera":
        """A fixed camera (world = camera frame) with intrinsics ``K`` [3, 3] (pixels, any array type)."""
        return Camera(torch.as_tensor(K, dtype=torch.float32).reshape(3, 3).clone(), int(width), int(height))

    @staticmethod
    def from_focal(focal: float, width: int, height: int) -> "Camera":
        """A camera with square pixels and the principal point at the image centre."""
        K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
        return Camera(K, width, height)
