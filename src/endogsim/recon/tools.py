"""Rigid per-frame motion of the instruments.

Each tool object k has canonical Gaussians (in the pose of its reference frame) and, per frame t, a
rotation r_kt (axis-angle, radians) about the tool's canonical centroid c_k and a translation T_kt
(metres). A canonical point x moves to

    x_t = R(r_kt) (x - c_k) + c_k + T_kt,

i.e. the world-frame rigid transform M_kt = [R | c_k + T_kt - R c_k]. Those [T, 4, 4] transforms (world
metres, canonical -> frame t) are what the simulator's kinematic colliders follow.
"""

from __future__ import annotations

import torch
import torch.nn as nn

from endogsim.gaussians.model import Gaussians, quat_to_rotmat

__all__ = ["ToolMotion", "axis_angle_to_quat", "quat_to_axis_angle", "quat_multiply", "fill_untrained_frames"]


def axis_angle_to_quat(r: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (w, x, y, z) [..., 4] from axis-angle vectors [..., 3] (radians); smooth at 0."""
    theta2 = (r * r).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2 + 1e-20)
    half = 0.5 * theta
    # sin(theta/2)/theta, with its Taylor series near 0 so the gradient stays finite
    k = torch.where(theta2 > 1e-12, torch.sin(half) / theta, 0.5 - theta2 / 48.0)
    return torch.cat([torch.cos(half), r * k], -1)


def quat_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors [..., 3] (radians, angle <= pi) from quaternions (w, x, y, z) [..., 4], any norm;
    the inverse of :func:`axis_angle_to_quat`."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    q = q * torch.where(q[..., :1] < 0, -1.0, 1.0)  # q and -q are the same rotation; take the short way
    v = q[..., 1:]
    s = v.norm(dim=-1, keepdim=True)
    # angle / sin(angle/2), with its limit 2 / w near 0
    k = torch.where(s > 1e-12, 2 * torch.atan2(s, q[..., :1]) / s.clamp_min(1e-12), 2 / q[..., :1])
    return v * k


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of quaternions (w, x, y, z), broadcasting over leading dims."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


class ToolMotion(nn.Module):
    """Per-frame rigid transforms of K tool objects over T frames.

    Args:
        tool_ids: the K object ids (as in the masks).
        centers: [K, 3] canonical centroid of each tool (metres): the rotation pivot.
        num_frames: T.
        init_translation: optional [K, T, 3] initial translations (metres).
    """

    def __init__(self, tool_ids: list[int], centers: torch.Tensor, num_frames: int,
                 init_translation: torch.Tensor | None = None) -> None:
        super().__init__()
        k = len(tool_ids)
        self.tool_ids = [int(i) for i in tool_ids]
        self.register_buffer("centers", torch.as_tensor(centers, dtype=torch.float32).reshape(k, 3).clone())
        self.rotation = nn.Parameter(torch.zeros(k, num_frames, 3))
        t0 = torch.zeros(k, num_frames, 3) if init_translation is None else init_translation.float().clone()
        self.translation = nn.Parameter(t0)

    @property
    def num_frames(self) -> int:
        return self.rotation.shape[1]

    def transforms(self) -> torch.Tensor:
        """[K, T, 4, 4] canonical -> frame-t rigid transforms (world metres)."""
        R = quat_to_rotmat(axis_angle_to_quat(self.rotation))  # [K, T, 3, 3]
        c = self.centers[:, None, :, None]
        t = c[..., 0] + self.translation - (R @ c)[..., 0]
        M = torch.zeros(*R.shape[:2], 4, 4, dtype=R.dtype, device=R.device)
        M[..., :3, :3] = R
        M[..., :3, 3] = t
        M[..., 3, 3] = 1
        return M

    def apply(self, g: Gaussians, frame: int) -> Gaussians:
        """Tool Gaussians ``g`` (canonical) moved to ``frame``; Gaussians whose id is not a tool stay put."""
        means, quats = g.means, g.quats
        for k, oid in enumerate(self.tool_ids):
            sel = g.object_ids == oid
            if not bool(sel.any()):
                continue
            q = axis_angle_to_quat(self.rotation[k, frame])
            R = quat_to_rotmat(q[None])[0]
            c = self.centers[k]
            moved = (means[sel] - c) @ R.T + c + self.translation[k, frame]
            means = means.index_put((sel.nonzero()[:, 0],), moved)
            quats = quats.index_put((sel.nonzero()[:, 0],), quat_multiply(q[None], quats[sel]))
        return g.with_(means=means, quats=quats)

    def smoothness(self, length_scale: float = 1.0) -> torch.Tensor:
        """Mean squared frame-to-frame change of rotation (rad^2) plus that of translation divided by
        ``length_scale`` (metres; the scene extent makes both terms unitless)."""
        if self.num_frames < 2:
            return self.rotation.sum() * 0
        return (self.rotation.diff(dim=1).square().mean()
                + (self.translation.diff(dim=1) / length_scale).square().mean())

    @torch.no_grad()
    def interpolate_missing(self, trained: torch.Tensor, times: torch.Tensor | None = None) -> None:
        """Fill frames never supervised (test frames, frames without the tool) by linear interpolation
        of the trained neighbours (constant beyond the ends).

        Args:
            trained: [T] or [K, T] bool, True where a frame's pose was optimised.
            times: [T] frame times to interpolate in (default: the frame index).
        """
        K, T = self.rotation.shape[:2]
        fill_untrained_frames([self.rotation, self.translation], trained.expand(K, T) if trained.ndim == 1 else trained,
                              times)


@torch.no_grad()
def fill_untrained_frames(values: list[torch.Tensor], trained: torch.Tensor, times: torch.Tensor | None = None) -> None:
    """In place: every frame of ``values`` (each [K, T, C]) where ``trained`` [K, T] is False becomes the
    linear interpolation, in ``times`` [T] (default: the frame index), of the nearest trained frames
    before and after it, or the nearest one beyond the ends; rows without any trained frame are left alone."""
    K, T = trained.shape
    times = torch.arange(T, dtype=torch.float64) if times is None else torch.as_tensor(times, dtype=torch.float64).cpu()
    for k in range(K):
        idx = trained[k].nonzero()[:, 0]
        if len(idx) == 0:
            continue
        for t in range(T):
            if trained[k, t]:
                continue
            before, after = idx[idx < t], idx[idx > t]
            if len(before) and len(after):
                a, b = int(before[-1]), int(after[0])
                span = float(times[b] - times[a])
                w = float(times[t] - times[a]) / span if span > 0 else 0.5
                for p in values:
                    p[k, t] = (1 - w) * p[k, a] + w * p[k, b]
            else:
                src = int(before[-1]) if len(before) else int(after[0])
                for p in values:
                    p[k, t] = p[k, src]
