"""Loaders that turn an EndoNeRF folder, a CholecSeg8K clip or a video file into one :class:`Scene`.

Entry point: :func:`load_scene` detects the format and dispatches. All bad input raises
:class:`~endogsim.errors.DataError` naming the file and the problem.

Conventions
-----------
- Frames: float32 RGB in [0, 1]. Downscaling uses ``cv2.INTER_AREA`` for images and depth-free
  nearest-neighbour for masks and depth (so invalid-depth zeros and ids are never blended); K is
  scaled by the same factor (``fx, fy, cx, cy`` times ``1 / downscale``).
- EndoNeRF depth (``depth/``): the stereo depth maps of the EndoNeRF release are stored as 8- or 16-bit
  PNG in the units of the LLFF near/far bounds (roughly millimetres; the pulling sequence's bounds are
  0..105). The EndoNeRF/EndoGaussian loaders use the raw values as scene units (clipped to the 3rd/99.8th
  percentiles); SurgicalGaussian divides them by ``depth_scale=100`` for its own units. None converts to
  metres, so the mm reading is our assumption (it matches the bounds and a ~5-10 cm working distance). We convert to metres with ``depth_scale`` metres per stored unit, default
  ``1e-3`` (millimetres). 0 means invalid and stays 0. Depth may also be float ``.npy`` or ``.tiff``
  files (also multiplied by ``depth_scale``); NaN, inf or negative values are refused.
- Folders written by ``endogsim synth`` carry a ``scene.json``: its ``depth_scale`` (stored units per
  metre) and ``scenario.frame_dt`` (seconds) replace the EndoNeRF defaults; explicit arguments still win.
- EndoNeRF times: the LLFF file holds no frame rate; the sequences are ~30 fps stereo videos, so the
  default is ``ENDONERF_FPS = 30``.
- CholecSeg8K: no intrinsics are published. We assume a pinhole with a horizontal field of view of
  ``CHOLEC_HFOV_DEG = 75`` degrees (typical 0/30-degree laparoscopes: 70-80 degrees), principal point
  at the image centre; 25 fps (the Cholec80 rate).
- Plain video: the same default field of view; fps from the container (or ``fps=``).
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import cv2
import numpy as np

from endogsim.errors import DataError
from endogsim.io import labels as L
from endogsim.io.scene import Scene

ENDONERF_FPS = 30.0
CHOLEC_FPS = 25.0
CHOLEC_HFOV_DEG = 75.0
VIDEO_HFOV_DEG = 75.0
DEFAULT_DEPTH_SCALE = 1e-3  # metres per stored depth unit (EndoNeRF stores ~mm)

IMAGE_EXTS = (".png", ".jpg", ".jpeg")
DEPTH_EXTS = (".png", ".npy", ".tif", ".tiff")  # png: 8/16-bit; npy/tiff: may be float
VIDEO_EXTS = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")


# ----------------------------------------------------------------------------------------------- helpers
def _natural_key(p: Path) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


def _list_images(folder: Path, exts=IMAGE_EXTS) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in exts and p.is_file()), key=_natural_key)


def _read_raw(path: Path) -> np.ndarray:
    """Read an image as stored (8/16 bit, any channels); DataError if unreadable or truncated."""
    try:
        data = np.fromfile(str(path), dtype=np.uint8)
    except OSError as exc:
        raise DataError(f"{path}: cannot read file ({exc.strerror})") from None
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


def _read_rgb(path: Path) -> np.ndarray:
    """[H, W, 3] float32 RGB in [0, 1]."""
    img = _read_raw(path)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    elif img.shape[2] == 4:
        img = img[..., :3]
    img = img[..., ::-1]  # OpenCV is BGR
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    return np.ascontiguousarray(img, dtype=np.float32) / np.float32(scale)


def _read_grey(path: Path) -> np.ndarray:
    """[H, W] single channel as stored (first channel of a colour file)."""
    img = _read_raw(path)
    return img if img.ndim == 2 else img[..., 0]


def _resize(img: np.ndarray, size: tuple[int, int], nearest: bool) -> np.ndarray:
    w, h = size
    if img.shape[1] == w and img.shape[0] == h:
        return img
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


def _target_size(w: int, h: int, downscale: float) -> tuple[int, int]:
    if not downscale >= 1.0 or not math.isfinite(downscale):
        raise DataError(f"downscale must be a finite number >= 1, got {downscale}")
    return max(1, round(w / downscale)), max(1, round(h / downscale))


def _scale_K(K: np.ndarray, w0: int, h0: int, w: int, h: int) -> np.ndarray:
    K = K.astype(np.float64).copy()
    K[0] *= w / w0
    K[1] *= h / h0
    K[2] = [0.0, 0.0, 1.0]
    return K


def default_K(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """[3, 3] pinhole intrinsics with square pixels, horizontal FOV ``hfov_deg`` and centred principal point."""
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=np.float64)


def _load_frames(paths: list[Path], downscale: float, what: str = "frame") -> tuple[np.ndarray, int, int]:
    """Stack RGB frames, refusing different sizes. Returns (frames [T,h,w,3], W0, H0)."""
    out, size0, first = [], None, None
    for p in paths:
        img = _read_rgb(p)
        if size0 is None:
            size0, first = img.shape[:2], p
            target = _target_size(img.shape[1], img.shape[0], downscale)
        elif img.shape[:2] != size0:
            raise DataError(f"{p}: {what} is {img.shape[1]}x{img.shape[0]}, but {first.name} is "
                            f"{size0[1]}x{size0[0]} (all frames must have the same size)")
        out.append(_resize(img, target, nearest=False))
    return np.stack(out), size0[1], size0[0]


def _check_mask_size(mask: np.ndarray, path: Path, w0: int, h0: int) -> None:
    if mask.shape[:2] != (h0, w0):
        raise DataError(f"{path}: mask is {mask.shape[1]}x{mask.shape[0]}, frames are {w0}x{h0}")


def _match_count(items: list[Path], n: int, folder: Path, what: str) -> None:
    if len(items) != n:
        raise DataError(f"{folder}: {len(items)} {what} for {n} frames (counts must match)")


def _load_endonerf_style_masks(mask_dir: Path, n_all: int, n: int, w0: int, h0: int,
                               size: tuple[int, int]) -> np.ndarray:
    """Tool masks (>127 = tool, 255 in the files) -> [n, h, w] int32 ids (0 tissue, 1 tool).

    ``n_all`` is the sequence length the folder must match; only the first ``n`` are read.
    """
    if not mask_dir.is_dir():
        raise DataError(f"{mask_dir}: mask folder does not exist")
    paths = _list_images(mask_dir)
    if n_all >= 0:
        _match_count(paths, n_all, mask_dir, "masks")
    elif len(paths) < n:
        _match_count(paths, n, mask_dir, "masks")
    paths = paths[:n]
    out = []
    for p in paths:
        m = _read_grey(p)
        _check_mask_size(m, p, w0, h0)
        out.append(_resize((m > 127).astype(np.uint8), size, nearest=True))
    return np.stack(out).astype(np.int32)


# ----------------------------------------------------------------------------------------------- EndoNeRF
def _read_poses_bounds(path: Path, n_images: int) -> tuple[np.ndarray, float, float, float, np.ndarray]:
    """LLFF poses_bounds.npy -> (poses [N,4,4] camera-to-world, H, W, focal, bounds [N,2])."""
    try:
        arr = np.load(str(path), allow_pickle=False)
    except Exception as exc:  # numpy raises ValueError/OSError/EOFError/UnpicklingError on bad files
        raise DataError(f"{path}: not a readable .npy file ({type(exc).__name__}: {exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise DataError(f"{path}: poses have shape {arr.shape}, expected (N, 17) in LLFF layout")
    if not np.isfinite(arr).all():
        raise DataError(f"{path}: poses contain NaN or inf")
    if arr.shape[0] != n_images:
        raise DataError(f"{path}: {arr.shape[0]} poses for {n_images} images (counts must match)")
    m = arr[:, :15].reshape(-1, 3, 5)
    h, w, focal = float(m[0, 0, 4]), float(m[0, 1, 4]), float(m[0, 2, 4])
    if not (h > 0 and w > 0 and focal > 0):
        raise DataError(f"{path}: H, W, focal in column 4 must be positive, got {h}, {w}, {focal}")
    # Kept as stored: EndoNeRF poses are all identity (a fixed endoscope), which we read as "world =
    # camera frame, OpenCV axes"; the LLFF axis swap of NeRF loaders would only rotate that frame.
    poses = np.tile(np.eye(4), (arr.shape[0], 1, 1))
    poses[:, :3, :4] = m[:, :, :4]
    return poses, h, w, focal, arr[:, 15:17].copy()


def _load_depth(depth_dir: Path, n_all: int, n: int, w0: int, h0: int, size: tuple[int, int],
                depth_scale: float) -> np.ndarray:
    """Depth maps (png 8/16-bit, float .npy or .tiff; 0 = invalid) -> [n, h, w] float32 metres."""
    paths = sorted((p for p in depth_dir.iterdir() if p.suffix.lower() in DEPTH_EXTS),
                   key=_natural_key)
    _match_count(paths, n_all, depth_dir, "depth maps")
    paths = paths[:n]
    out = []
    for p in paths:
        if p.suffix.lower() == ".npy":
            try:
                d = np.load(str(p), allow_pickle=False)
            except Exception as exc:
                raise DataError(f"{p}: not a readable .npy depth map ({type(exc).__name__})") from None
            if d.ndim == 3 and d.shape[-1] == 1:
                d = d[..., 0]
            if d.ndim != 2 or not np.issubdtype(d.dtype, np.number):
                raise DataError(f"{p}: depth must be a 2-D numeric array, got {d.dtype} {d.shape}")
            d = d.astype(np.float64)
        else:
            d = _read_grey(p).astype(np.float64)
        if not np.isfinite(d).all():
            raise DataError(f"{p}: depth contains NaN or inf")
        if (d < 0).any():
            raise DataError(f"{p}: depth contains negative values (min {d.min():.4g})")
        if d.shape != (h0, w0):
            raise DataError(f"{p}: depth is {d.shape[1]}x{d.shape[0]}, frames are {w0}x{h0}")
        out.append(_resize((d * depth_scale).astype(np.float32), size, nearest=True))
    return np.stack(out)


def _synth_meta(folder: Path) -> tuple[float | None, float | None]:
    """(metres per stored depth unit, frame rate in Hz) from an ``endogsim synth`` folder's ``scene.json``,
    None for what it does not say (or when there is no ``scene.json``)."""
    path = folder / "scene.json"
    if not path.is_file():
        return None, None
    try:
        meta = json.loads(path.read_text())
        units_per_m = meta.get("depth_scale")
        frame_dt = (meta.get("scenario") or {}).get("frame_dt")
        depth_scale = None if units_per_m is None else 1.0 / float(units_per_m)
        fps = None if frame_dt is None else 1.0 / float(frame_dt)
    except (ValueError, TypeError, AttributeError, ZeroDivisionError) as exc:
        raise DataError(f"{path}: malformed scene.json ({exc})") from None
    for name, v in (("depth_scale", depth_scale), ("scenario.frame_dt", fps)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise DataError(f"{path}: {name} must be a positive number")
    return depth_scale, fps


def load_endonerf(folder: str | Path, *, downscale: float = 1.0, max_frames: int | None = None,
                  fps: float | None = None, depth_scale: float | None = None,
                  mask_dir: str | Path | None = None) -> Scene:
    """Load an EndoNeRF folder: ``images/``, optional ``depth/`` and ``masks/``, ``poses_bounds.npy``.

    Args:
        folder: the dataset folder.
        downscale: factor >= 1 by which images, depth, masks and K are reduced.
        max_frames: keep only the first frames.
        fps: frame rate for ``times`` (default: 1 / ``scenario.frame_dt`` of a ``scene.json`` in the folder,
            else ``ENDONERF_FPS`` = 30; the LLFF file holds none).
        depth_scale: metres per stored depth unit (default: 1 / ``depth_scale`` of a ``scene.json`` in the
            folder, else 1e-3: EndoNeRF depth is ~millimetres).
        mask_dir: tool-mask folder to use instead of ``folder/masks``.
    Returns:
        a Scene with K from the LLFF focal (cx, cy at the image centre; without ``poses_bounds.npy``
        a default 75-degree horizontal FOV), object ids 0 tissue / 1 tool.
    """
    folder = Path(folder)
    img_dir = folder / "images"
    if not img_dir.is_dir():
        raise DataError(f"{img_dir}: EndoNeRF images folder does not exist")
    paths = _list_images(img_dir)
    if not paths:
        raise DataError(f"{img_dir}: empty sequence (no .png or .jpg frames)")
    n_all = len(paths)
    pb = folder / "poses_bounds.npy"
    if pb.is_file():
        poses, H, W, focal, _ = _read_poses_bounds(pb, n_all)
    else:
        poses, H, W, focal = None, None, None, None
    if max_frames is not None:
        paths = paths[:max_frames]
        poses = poses[:max_frames] if poses is not None else None
    frames, w0, h0 = _load_frames(paths, downscale)
    n, h, w = frames.shape[:3]
    if focal is not None:
        if (round(H), round(W)) != (h0, w0):
            raise DataError(f"{pb}: poses say {round(W)}x{round(H)} but images are {w0}x{h0}")
        K0 = np.array([[focal, 0, w0 / 2], [0, focal, h0 / 2], [0, 0, 1]], dtype=np.float64)
    else:
        K0 = default_K(w0, h0, VIDEO_HFOV_DEG)
    K = _scale_K(K0, w0, h0, w, h)

    meta_depth_scale, meta_fps = _synth_meta(folder)
    if depth_scale is None:
        depth_scale = meta_depth_scale or DEFAULT_DEPTH_SCALE
    depth = None
    if (folder / "depth").is_dir():
        depth = _load_depth(folder / "depth", n_all, n, w0, h0, (w, h), depth_scale)
    mdir = Path(mask_dir) if mask_dir is not None else folder / "masks"
    masks = None
    if mask_dir is not None or mdir.is_dir():
        masks = _load_endonerf_style_masks(mdir, n_all, n, w0, h0, (w, h))
    rate = fps or meta_fps or ENDONERF_FPS
    return Scene(
        frames=frames, times=np.arange(n, dtype=np.float64) / rate, K=K, depth=depth,
        object_masks=masks,
        labels=L.endonerf_labels(masks is not None), downscale=float(downscale), source=str(folder),
        frame_names=[p.name for p in paths], poses=poses,
    )


# ----------------------------------------------------------------------------------------------- CholecSeg8K
_CHOLEC_RE = re.compile(r"^frame_(\d+)_endo\.png$")


def _cholec_dir(folder: Path) -> Path | None:
    for d in (folder, folder / "frames"):
        if d.is_dir() and any(_CHOLEC_RE.match(p.name) for p in d.iterdir()):
            return d
    return None


def load_cholecseg8k(folder: str | Path, *, downscale: float = 1.0, max_frames: int | None = None,
                     fps: float | None = None, hfov_deg: float = CHOLEC_HFOV_DEG) -> Scene:
    """Load a CholecSeg8K clip: ``frame_N_endo.png`` + ``frame_N_endo_watershed_mask.png`` (grey = class id).

    The frames may sit in ``folder`` or ``folder/frames``. Mask value 255 (unlabelled) becomes -1.
    K is a default pinhole with horizontal FOV ``hfov_deg`` (the data has no intrinsics); 25 fps.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder}: folder does not exist")
    d = _cholec_dir(folder)
    if d is None:
        raise DataError(f"{folder}: no frame_N_endo.png files (empty CholecSeg8K sequence)")
    paths = sorted((p for p in d.iterdir() if _CHOLEC_RE.match(p.name)), key=lambda p: int(_CHOLEC_RE.match(p.name)[1]))
    if max_frames is not None:
        paths = paths[:max_frames]
    frames, w0, h0 = _load_frames(paths, downscale)
    n, h, w = frames.shape[:3]
    masks = []
    for p in paths:
        mp = p.with_name(p.stem + "_watershed_mask.png")
        if not mp.is_file():
            raise DataError(f"{mp}: watershed mask missing for frame {p.name}")
        m = _read_grey(mp)
        _check_mask_size(m, mp, w0, h0)
        ids = m.astype(np.int32)
        ids[m == L.CHOLECSEG8K_UNLABELLED_VALUE] = L.UNLABELLED
        unknown = set(np.unique(ids).tolist()) - set(L.CHOLECSEG8K_LABELS) - {L.UNLABELLED}
        if unknown:
            raise DataError(f"{mp}: unknown CholecSeg8K class ids {sorted(unknown)}")
        masks.append(_resize(ids, (w, h), nearest=True))
    K = _scale_K(default_K(w0, h0, hfov_deg), w0, h0, w, h)
    rate = fps or CHOLEC_FPS
    return Scene(
        frames=frames, times=np.arange(n, dtype=np.float64) / rate, K=K, depth=None,
        object_masks=np.stack(masks).astype(np.int32), labels=dict(L.CHOLECSEG8K_LABELS),
        downscale=float(downscale), source=str(folder), frame_names=[p.name for p in paths], poses=None,
    )


# ----------------------------------------------------------------------------------------------- video
def load_video(path: str | Path, *, mask_dir: str | Path | None = None, downscale: float = 1.0,
               max_frames: int | None = None, fps: float | None = None,
               hfov_deg: float = VIDEO_HFOV_DEG) -> Scene:
    """Load a video file (decoded with imageio-ffmpeg); optional tool masks (255 = tool), one per frame.

    K is a default pinhole with horizontal FOV ``hfov_deg``; fps from the container unless given.
    """
    import imageio_ffmpeg

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: video file does not exist")
    raw = []
    try:
        reader = imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24")
        meta = next(reader)
        w0, h0 = meta["size"]
        for buf in reader:
            raw.append(np.frombuffer(buf, dtype=np.uint8).reshape(h0, w0, 3))
            if max_frames is not None and len(raw) >= max_frames:
                break
        reader.close()
    except Exception as exc:  # ffmpeg failures surface as RuntimeError/OSError/StopIteration
        msg = str(exc).strip().splitlines()
        raise DataError(f"{path}: cannot decode video ({msg[-1] if msg else type(exc).__name__})") from None
    if not raw:
        raise DataError(f"{path}: empty sequence (no decodable frames)")
    size = _target_size(w0, h0, downscale)
    frames = np.stack([_resize(f, size, nearest=False).astype(np.float32) / 255.0 for f in raw])
    n, h, w = frames.shape[:3]
    masks = None
    if mask_dir is not None:
        n_all = n if max_frames is None or n < max_frames else -1  # -1: the video may hold more frames
        masks = _load_endonerf_style_masks(Path(mask_dir), n_all, n, w0, h0, (w, h))
    rate = fps or float(meta.get("fps") or 0) or 30.0
    return Scene(
        frames=frames, times=np.arange(n, dtype=np.float64) / rate,
        K=_scale_K(default_K(w0, h0, hfov_deg), w0, h0, w, h), object_masks=masks,
        labels=L.endonerf_labels(masks is not None), downscale=float(downscale), source=str(path),
        frame_names=[f"{path.name}#{i}" for i in range(n)],
    )


# ----------------------------------------------------------------------------------------------- dispatch
def detect_format(path: str | Path) -> str:
    """'endonerf', 'cholecseg8k' or 'video'; DataError if missing or unknown."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if path.is_file():
        if path.suffix.lower() in VIDEO_EXTS:
            return "video"
        raise DataError(f"{path}: unknown format (expected a folder or a video file {', '.join(VIDEO_EXTS)})")
    if (path / "images").is_dir() or (path / "poses_bounds.npy").is_file():
        return "endonerf"
    if _cholec_dir(path) is not None:
        return "cholecseg8k"
    raise DataError(f"{path}: unknown format (not an EndoNeRF folder with images/, a CholecSeg8K clip "
                    "with frame_N_endo.png, or a video file)")


def load_scene(path: str | Path, *, downscale: float = 1.0, max_frames: int | None = None,
               mask_dir: str | Path | None = None, fps: float | None = None, **kwargs) -> Scene:
    """Load any supported dataset into a :class:`Scene` (format detected from the path).

    Args:
        path: EndoNeRF folder, CholecSeg8K clip folder, or video file.
        downscale: factor >= 1 applied to frames, depth, masks and K.
        max_frames: keep only the first ``max_frames`` frames.
        mask_dir: tool masks (255 = tool) for EndoNeRF folders or videos.
        fps: override the frame rate used for ``times`` (seconds).
        kwargs: format-specific options (``depth_scale`` for EndoNeRF, ``hfov_deg`` otherwise).
    """
    if max_frames is not None and max_frames < 1:
        raise DataError(f"max_frames must be >= 1, got {max_frames}")
    fmt = detect_format(path)
    allowed = {"endonerf": {"depth_scale"}, "cholecseg8k": {"hfov_deg"}, "video": {"hfov_deg"}}[fmt]
    extra = sorted(set(kwargs) - allowed)
    if extra:
        raise DataError(f"{path}: option(s) {extra} not supported for {fmt} data (allowed: {sorted(allowed)})")
    common = dict(downscale=downscale, max_frames=max_frames, fps=fps, **kwargs)
    if fmt == "endonerf":
        return load_endonerf(path, mask_dir=mask_dir, **common)
    if fmt == "cholecseg8k":
        if mask_dir is not None:
            raise DataError(f"{path}: CholecSeg8K clips carry their own masks; mask_dir is not used")
        return load_cholecseg8k(path, **common)
    return load_video(path, mask_dir=mask_dir, **common)
