"""Optical-flow metrics and visualisation.

* :func:`epe`: mean end-point error (pixels) on valid pixels (DESIGN.md section 7).
* :func:`flow_to_color`: the Middlebury/Baker colour wheel (hue = direction, saturation = magnitude), for
  videos and figures.
"""

from __future__ import annotations

import numpy as np

from endogsim.errors import DataError

__all__ = ["epe", "flow_to_color", "warp_backward"]


def epe(flow_est: np.ndarray, flow_gt: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Mean end-point error in pixels.

    Args:
        flow_est: [..., H, W, 2] estimated flow (pixels).
        flow_gt: [..., H, W, 2] ground-truth flow (pixels), same shape.
        valid: optional [..., H, W] bool mask of pixels to average over (default: all finite ones).
    Returns:
        mean over valid pixels of ||flow_est - flow_gt||_2; NaN when no pixel is valid.
    """
    a, b = np.asarray(flow_est, dtype=np.float64), np.asarray(flow_gt, dtype=np.float64)
    if a.shape != b.shape or a.shape[-1] != 2:
        raise DataError(f"flow shapes differ or are not [..., 2]: {a.shape} vs {b.shape}")
    err = np.linalg.norm(a - b, axis=-1)
    mask = np.isfinite(err)
    if valid is not None:
        if valid.shape != err.shape:
            raise DataError(f"valid mask shape {valid.shape} does not match flow {err.shape}")
        mask &= valid.astype(bool)
    return float(err[mask].mean()) if mask.any() else float("nan")


def warp_backward(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """Sample ``image`` [H, W, C] at x + flow(x): with the forward flow t -> t+1 and image = frame t+1,
    this reconstructs frame t. Bilinear, border replicated. Returns [H, W, C] float32."""
    import cv2

    H, W = flow.shape[:2]
    xs, ys = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    return cv2.remap(np.asarray(image, dtype=np.float32), xs + flow[..., 0].astype(np.float32),
                     ys + flow[..., 1].astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _color_wheel() -> np.ndarray:
    # Baker et al. (Middlebury) wheel: RY, YG, GC, CB, BM, MR segments.
    segs = [(15, (255, 0, 0), (255, 255, 0)), (6, (255, 255, 0), (0, 255, 0)), (4, (0, 255, 0), (0, 255, 255)),
            (11, (0, 255, 255), (0, 0, 255)), (13, (0, 0, 255), (255, 0, 255)), (6, (255, 0, 255), (255, 0, 0))]
    rows = []
    for n, c0, c1 in segs:
        t = np.arange(n)[:, None] / n
        rows.append(np.array(c0)[None] * (1 - t) + np.array(c1)[None] * t)
    return np.concatenate(rows) / 255.0


def flow_to_color(flow: np.ndarray, max_norm: float | None = None) -> np.ndarray:
    """Colour-code a flow field [H, W, 2] (pixels) -> RGB [H, W, 3] float32 in [0, 1].

    Hue gives the direction, saturation the magnitude relative to ``max_norm`` (default: the largest finite
    magnitude in this field, so pass a fixed value to compare frames of a video). Zero flow is white.
    """
    f = np.nan_to_num(np.asarray(flow, dtype=np.float64))
    u, v = f[..., 0], f[..., 1]
    mag = np.sqrt(u * u + v * v)
    norm = max_norm if max_norm is not None else max(float(mag.max()), 1e-9)
    r = np.clip(mag / max(norm, 1e-9), 0, 1)
    wheel = _color_wheel()
    ncols = len(wheel)
    ang = np.arctan2(-v, -u) / np.pi  # in [-1, 1]
    fk = (ang + 1) / 2 * (ncols - 1)
    k0 = np.floor(fk).astype(int)
    k1 = (k0 + 1) % ncols
    a = (fk - k0)[..., None]
    col = (1 - a) * wheel[k0] + a * wheel[k1]
    col = 1 - r[..., None] * (1 - col)
    return col.astype(np.float32)
