"""Camera-motion prior: per-frame endoscope rotation from tracked tissue features (offline, OpenCV).

A hand-held or robot-held laparoscope mostly pans and tilts about its own centre between video frames.
Between consecutive frames we track corners on tissue pixels (Shi-Tomasi + pyramidal Lucas-Kanade) and
fit a similarity transform with RANSAC (tools and deforming tissue are outliers). The shift it gives the
principal point is the pan/tilt, its rotation angle the roll:

    pan  r_y = atan(du / fx),   tilt  r_x = -atan(dv / fy),   roll  r_z = angle of the similarity

(OpenCV camera axes: x right, y down, z forward; r is the axis-angle of the world->camera rotation of
frame t relative to frame 0, so a world point ahead of the camera moves by +du when r_y grows). Relative
rotations are chained by adding axis-angle vectors, which is exact to second order in the small
frame-to-frame angles of endoscopic video. Zoom and translation are left to the optimisation (they
depend on depth). The result only initialises :class:`~endogsim.recon.camera_motion.CameraMotion`.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["estimate_camera_rotations"]


def _grey(frame: np.ndarray) -> np.ndarray:
    import cv2

    f = frame if frame.dtype == np.uint8 else (np.clip(frame, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2GRAY)


def _relative_rotation(a: np.ndarray, b: np.ndarray, mask: np.ndarray, K: np.ndarray) -> np.ndarray | None:
    """Axis-angle [3] of frame b's camera relative to frame a's, or None when too few features track."""
    import cv2

    h, w = a.shape
    pts = cv2.goodFeaturesToTrack(a, maxCorners=400, qualityLevel=0.01, minDistance=max(3, w // 80),
                                  mask=mask.astype(np.uint8) * 255, blockSize=7)
    if pts is None or len(pts) < 12:
        return None
    nxt, status, _ = cv2.calcOpticalFlowPyrLK(a, b, pts, None, winSize=(21, 21), maxLevel=3)
    ok = status[:, 0] == 1
    if ok.sum() < 12:
        return None
    A, inliers = cv2.estimateAffinePartial2D(pts[ok], nxt[ok], method=cv2.RANSAC,
                                             ransacReprojThreshold=max(1.0, w / 320))
    if A is None or inliers is None or inliers.sum() < 8:
        return None
    cx, cy = K[0, 2], K[1, 2]
    du, dv = A @ np.array([cx, cy, 1.0]) - np.array([cx, cy])
    roll = math.atan2(A[1, 0], A[0, 0])
    return np.array([-math.atan(dv / K[1, 1]), math.atan(du / K[0, 0]), roll])


def estimate_camera_rotations(frames: np.ndarray, tissue: np.ndarray, K: np.ndarray,
                              frames_used: list[int] | None = None) -> np.ndarray:
    """World->camera rotation of every frame relative to frame 0, as axis-angle vectors.

    Args:
        frames: [T, H, W, 3] RGB, float in [0, 1] or uint8.
        tissue: [T, H, W] bool, pixels where features may be tracked (tissue, not tools or border).
        K: [3, 3] intrinsics (pixels).
        frames_used: increasing frame indices to read (the training frames; default all). Rotations are
            chained between consecutive entries; the other frames are interpolated linearly between
            their neighbours (constant beyond the ends), so held-out frames are never read.
    Returns:
        [T, 3] float32 axis-angle (radians); frame ``frames_used[0]`` is zero. A pair of frames where
        tracking fails (too few features) is taken as no motion.
    """
    T = frames.shape[0]
    used = list(range(T)) if frames_used is None else [int(f) for f in frames_used]
    chained = np.zeros((len(used), 3), dtype=np.float64)
    prev = _grey(frames[used[0]])
    for i in range(1, len(used)):
        cur = _grey(frames[used[i]])
        rel = _relative_rotation(prev, cur, tissue[used[i - 1]], np.asarray(K, dtype=np.float64))
        chained[i] = chained[i - 1] + (rel if rel is not None else 0.0)
        prev = cur
    out = np.stack([np.interp(np.arange(T), used, chained[:, k]) for k in range(3)], 1)
    return out.astype(np.float32)
