"""Reading and resizing images, the one way the package does it.

- :func:`read_image` reads a file as stored (8/16 bit, any channels) and refuses unreadable, empty or
  truncated files with a :class:`~endogsim.errors.DataError` naming the file;
  :func:`read_rgb` gives float32 RGB in [0, 1], :func:`read_grey` the first channel as stored.
- :func:`resize` / :func:`resize_frames`: ``cv2.INTER_AREA`` for images (anti-aliased downscaling) and
  nearest-neighbour for ids, masks and depth (``nearest=True``) so labels and invalid-depth zeros are
  never blended.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from endogsim.errors import DataError

__all__ = ["read_image", "read_rgb", "read_grey", "resize", "resize_frames"]


def read_image(path: str | Path) -> np.ndarray:
    """Read an image as stored (8/16 bit, any channels); DataError if unreadable or truncated."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as exc:
        raise DataError(f"{path}: cannot read file ({exc.strerror})") from None
    path = Path(path)
    if data.size == 0:
        raise DataError(f"{path}: empty file")
    # Silence OpenCV's own warning on truncated files: the DataError below says it better.
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    finally:
        cv2.utils.logging.setLogLevel(level)
    if img is None:
        raise DataError(f"{path}: not a readable image (corrupt or unsupported)")
    if path.suffix.lower() in (".jpg", ".jpeg") and not data[-2:].tobytes() == b"\xff\xd9":
        # OpenCV decodes a truncated JPEG to a grey-filled image with only a warning.
        raise DataError(f"{path}: truncated JPEG (no end-of-image marker)")
    return img


def read_rgb(path: str | Path) -> np.ndarray:
    """[H, W, 3] float32 RGB in [0, 1] (8- or 16-bit files; grey is repeated, alpha dropped)."""
    img = read_image(path)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    elif img.shape[2] == 4:
        img = img[..., :3]
    img = img[..., ::-1]  # OpenCV is BGR
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    return np.ascontiguousarray(img, dtype=np.float32) / np.float32(scale)


def read_grey(path: str | Path) -> np.ndarray:
    """[H, W] single channel as stored (first channel of a colour file)."""
    img = read_image(path)
    return img if img.ndim == 2 else img[..., 0]


def resize(img: np.ndarray, size: tuple[int, int], nearest: bool = False) -> np.ndarray:
    """``img`` [H, W, ...] resized to ``size`` = (width, height): area averaging, or nearest neighbour."""
    w, h = size
    if img.shape[1] == w and img.shape[0] == h:
        return img
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


def resize_frames(frames: np.ndarray, size: tuple[int, int], nearest: bool = False) -> np.ndarray:
    """:func:`resize` of every frame of ``frames`` [T, H, W, ...] to ``size`` = (width, height)."""
    w, h = size
    if frames.shape[1] == h and frames.shape[2] == w:
        return frames
    return np.stack([resize(f, size, nearest) for f in frames])
