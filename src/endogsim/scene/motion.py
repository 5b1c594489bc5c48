"""Tool motion as a scene describes it: keyframed translations and the per-frame rigid transforms they give.

Keyframes are ``[[fraction of the clip in [0, 1], dx, dy, dz], ...]`` (metres, world), the first at 0;
:func:`tool_offsets` eases between them so a tool starts and stops smoothly.
"""

from __future__ import annotations

import numpy as np

from endogsim.errors import DataError
from endogsim.scene.schema import ToolCapsule

__all__ = ["tool_offsets", "translations", "tool_capsule", "tool_speed"]


def translations(offsets: np.ndarray) -> np.ndarray:
    """[T, 4, 4] rigid transforms that translate by ``offsets`` [T, 3] (metres)."""
    offsets = np.asarray(offsets, dtype=np.float64)
    tf = np.tile(np.eye(4), (len(offsets), 1, 1))
    tf[:, :3, 3] = offsets
    return tf


def _smoothstep(s: np.ndarray) -> np.ndarray:
    return s * s * (3 - 2 * s)


def tool_offsets(keyframes: list[list[float]], frames: int) -> np.ndarray:
    """Tool translation [frames, 3] (metres) from keyframes [[fraction of the sequence, dx, dy, dz], ...],
    eased in and out between keyframes so the tool starts and stops smoothly."""
    kf = np.asarray(keyframes, dtype=np.float64)
    if kf.ndim != 2 or kf.shape[1] != 4 or kf[0, 0] != 0.0 or np.any(np.diff(kf[:, 0]) <= 0):
        raise DataError(f"tool keyframes must be [[0, dx, dy, dz], [f1, ...], ...] with increasing fractions, got {keyframes}")
    s = np.linspace(0, 1, frames) if frames > 1 else np.zeros(1)
    out = np.zeros((frames, 3))
    for i, si in enumerate(s):
        j = min(np.searchsorted(kf[:, 0], si, side="right") - 1, len(kf) - 1)
        if j == len(kf) - 1:
            out[i] = kf[-1, 1:]
            continue
        a = (si - kf[j, 0]) / (kf[j + 1, 0] - kf[j, 0])
        out[i] = kf[j, 1:] + _smoothstep(a) * (kf[j + 1, 1:] - kf[j, 1:])
    return out


def tool_capsule(object_id: int, tip, end, radius: float, offsets: np.ndarray, contact: str = "sticky") -> ToolCapsule:
    """A capsule tool (``tip``/``end`` [3] metres at frame 0, ``radius`` metres) translated by ``offsets`` [T, 3];
    ``contact`` "sticky" or "grasp" (:class:`ToolCapsule`)."""
    return ToolCapsule(object_id=int(object_id), tip=[float(v) for v in tip], end=[float(v) for v in end],
                       radius=float(radius), transforms=translations(offsets).tolist(), contact=contact)


def tool_speed(tools: list[ToolCapsule], frame_dt: float) -> float:
    """Largest speed (m/s) of any capsule end point between two frames (the CFL rule needs it)."""
    speed = 0.0
    for tool in tools:
        tf = tool.matrices()
        ends = np.array([tool.tip, tool.end], float)
        pos = np.einsum("tij,pj->tpi", tf[:, :3, :3], ends) + tf[:, None, :3, 3]
        if len(pos) > 1:
            speed = max(speed, float(np.linalg.norm(np.diff(pos, axis=0), axis=-1).max()) / frame_dt)
    return speed
