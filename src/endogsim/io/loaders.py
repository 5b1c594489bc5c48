"""Loaders that turn an EndoNeRF folder, a CholecSeg8K clip or a video file into one :class:`Scene`.

One function per dataset layout; :mod:`endogsim.io.formats` registers them, detects a path's format and
dispatches (:func:`endogsim.io.load_scene`). All bad input raises :class:`~endogsim.errors.DataError`
naming the file and the problem.

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
  ``1e-3`` (millimetres). 0 means invalid and stays 0; so does 65535 in a 16-bit PNG (saturated: noted). Depth may also be float ``.npy`` or ``.tiff``
  files (also multiplied by ``depth_scale``); NaN, inf or negative values are refused.
- EndoGSim scene folders (``endogsim synth`` output, a run's ``scene/``) are EndoNeRF folders with a
  ``scene.json``: its ``depth_scale`` (stored units per metre), ``scenario.frame_dt`` (seconds), camera
  and objects (with ``object_masks/``) replace the EndoNeRF defaults; explicit arguments still win.
- EndoNeRF times: the LLFF file holds no frame rate; the sequences are ~30 fps stereo videos, so the
  default is ``ENDONERF_FPS = 30``.
- CholecSeg8K: no intrinsics are published. We assume a pinhole with a horizontal field of view of
  ``CHOLEC_HFOV_DEG = 75`` degrees (typical 0/30-degree laparoscopes: 70-80 degrees), principal point
  at the image centre; 25 fps (the Cholec80 rate).
- Plain video: the same default field of view; fps from the container (or ``fps=``).
- Assumptions and repairs (default intrinsics of an EndoNeRF folder without ``poses_bounds.npy``, saturated
  depth, a video that decodes to fewer frames than its container announces) are recorded in ``Scene.notes``;
  :func:`endogsim.io.load_scene` warns with them.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np

from endogsim.errors import DataError
from endogsim.io import labels as L
from endogsim.io.images import read_grey, read_rgb, resize
from endogsim.io.scene import Scene

ENDONERF_FPS = 30.0
CHOLEC_FPS = 25.0
CHOLEC_HFOV_DEG = 75.0
VIDEO_HFOV_DEG = 75.0
DEFAULT_DEPTH_SCALE = 1e-3  # metres per stored depth unit (EndoNeRF stores ~mm)
NO_POSES_NOTE = "no poses_bounds.npy"  # the start of the note of an EndoNeRF folder's assumed intrinsics

IMAGE_EXTS = (".png", ".jpg", ".jpeg")
DEPTH_EXTS = (".png", ".npy", ".tif", ".tiff")  # png: 8/16-bit; npy/tiff: may be float
VIDEO_EXTS = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")


# ----------------------------------------------------------------------------------------------- helpers
def _natural_key(p: Path) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


def _list_images(folder: Path, exts=IMAGE_EXTS) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in exts and p.is_file()), key=_natural_key)


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
        img = read_rgb(p)
        if size0 is None:
            size0, first = img.shape[:2], p
            target = _target_size(img.shape[1], img.shape[0], downscale)
        elif img.shape[:2] != size0:
            raise DataError(f"{p}: {what} is {img.shape[1]}x{img.shape[0]}, but {first.name} is "
                            f"{size0[1]}x{size0[0]} (all frames must have the same size)")
        out.append(resize(img, target, nearest=False))
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
        m = read_grey(p)
        _check_mask_size(m, p, w0, h0)
        out.append(resize((m > 127).astype(np.uint8), size, nearest=True))
    return np.stack(out).astype(np.int32)


def _load_npy(path: Path, what: str) -> np.ndarray:
    """``np.load`` of a ``.npy`` file holding ``what`` (no pickles); DataError when it is not one."""
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
    except OSError as exc:
        raise DataError(f"{path}: cannot read file ({exc.strerror})") from None
    if magic != b"\x93NUMPY":
        raise DataError(f"{path}: not a NumPy .npy file (no NUMPY header: a text or other file under that name?); "
                        f"expected {what} saved with numpy.save")
    try:
        return np.load(str(path), allow_pickle=False)
    except Exception as exc:  # numpy raises ValueError/OSError/EOFError on truncated or pickled files
        raise DataError(f"{path}: unreadable .npy file ({type(exc).__name__}: {exc}); expected {what}") from None


# ----------------------------------------------------------------------------------------------- EndoNeRF
def _read_poses_bounds(path: Path, n_images: int) -> tuple[np.ndarray, float, float, float, np.ndarray]:
    """LLFF poses_bounds.npy -> (poses [N,4,4] camera-to-world, H, W, focal, bounds [N,2])."""
    arr = _load_npy(path, "the LLFF poses array (N, 17)")
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise DataError(f"{path}: poses have shape {arr.shape}, expected (N, 17) in LLFF layout")
    if not np.issubdtype(arr.dtype, np.integer) and not np.issubdtype(arr.dtype, np.floating):
        raise DataError(f"{path}: poses are stored as {arr.dtype}, not numbers (expected a float array)")
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
                depth_scale: float, notes: list[str]) -> np.ndarray:
    """Depth maps (png 8/16-bit, float .npy or .tiff; 0 = invalid) -> [n, h, w] float32 metres.

    16-bit pixels at 65535 are saturated (farther than the format holds, or no measurement), not a depth:
    they become invalid (0) and ``notes`` says how many there were.
    """
    paths = sorted((p for p in depth_dir.iterdir() if p.suffix.lower() in DEPTH_EXTS),
                   key=_natural_key)
    _match_count(paths, n_all, depth_dir, "depth maps")
    paths = paths[:n]
    out, saturated, total = [], 0, 0
    for p in paths:
        if p.suffix.lower() == ".npy":
            d = _load_npy(p, "a depth map")
            if d.ndim == 3 and d.shape[-1] == 1:
                d = d[..., 0]
            if d.ndim != 2 or not np.issubdtype(d.dtype, np.number):
                raise DataError(f"{p}: depth must be a 2-D numeric array, got {d.dtype} {d.shape}")
            d = d.astype(np.float64)
        else:
            d = read_grey(p)
            if d.dtype == np.uint16:
                sat = d == np.iinfo(np.uint16).max
                saturated += int(sat.sum())
                d = np.where(sat, 0, d)
            d = d.astype(np.float64)
        if not np.isfinite(d).all():
            raise DataError(f"{p}: depth contains NaN or inf")
        if (d < 0).any():
            raise DataError(f"{p}: depth contains negative values (min {d.min():.4g})")
        if d.shape != (h0, w0):
            raise DataError(f"{p}: depth is {d.shape[1]}x{d.shape[0]}, frames are {w0}x{h0}")
        total += d.size
        out.append(resize((d * depth_scale).astype(np.float32), size, nearest=True))
    if saturated:
        notes.append(f"{saturated / total:.1%} of the depth pixels in {depth_dir.name}/ are saturated at 65535 "
                     f"(would read as {65535 * depth_scale:.4g} m); they are treated as invalid (no depth)")
    depth = np.stack(out)
    if not (depth > 0).any():
        raise DataError(f"{depth_dir}: every depth pixel of the {len(paths)} maps is 0 or saturated (no "
                        "measurement); remove the folder to use a depth model or the fallback")
    return depth


def load_endonerf(folder: str | Path, *, downscale: float = 1.0, max_frames: int | None = None,
                  fps: float | None = None, depth_scale: float | None = None,
                  mask_dir: str | Path | None = None) -> Scene:
    """Load an EndoNeRF folder: ``images/``, optional ``depth/`` and ``masks/``, ``poses_bounds.npy``.

    Args:
        folder: the dataset folder.
        downscale: factor >= 1 by which images, depth, masks and K are reduced.
        max_frames: keep only the first frames.
        fps: frame rate for ``times`` (default ``ENDONERF_FPS`` = 30; the LLFF file holds none).
        depth_scale: metres per stored depth unit (default 1e-3: EndoNeRF depth is ~millimetres).
        mask_dir: tool-mask folder to use instead of ``folder/masks``.
    Returns:
        a Scene with K from the LLFF focal (cx, cy at the image centre; without ``poses_bounds.npy``
        a default 75-degree horizontal FOV, noted in ``notes``), object ids 0 tissue / 1 tool.
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
    notes = []
    if focal is not None:
        if (round(H), round(W)) != (h0, w0):
            raise DataError(f"{pb}: poses say {round(W)}x{round(H)} but images are {w0}x{h0}")
        K0 = np.array([[focal, 0, w0 / 2], [0, focal, h0 / 2], [0, 0, 1]], dtype=np.float64)
        hfov = math.degrees(2 * math.atan(w0 / (2 * focal)))
        if not 20.0 <= hfov <= 160.0:  # endoscopes see 60-120 degrees; this is a wrong file, not a lens
            notes.append(f"{pb.name}: focal length {focal:.4g} px at {w0} px width is a {hfov:.3g}-degree horizontal "
                         "field of view, outside the 20-160 degrees of any endoscope: check the file (sizes and "
                         "depths follow from it)")
    else:
        K0 = default_K(w0, h0, VIDEO_HFOV_DEG)
        notes.append(f"{NO_POSES_NOTE}: intrinsics assumed (a {VIDEO_HFOV_DEG:g}-degree horizontal field of view, "
                     f"fx = fy = {K0[0, 0]:.0f} px at {w0}x{h0})")
    K = _scale_K(K0, w0, h0, w, h)

    if depth_scale is None:
        depth_scale = DEFAULT_DEPTH_SCALE
    depth = None
    if (folder / "depth").is_dir():
        depth = _load_depth(folder / "depth", n_all, n, w0, h0, (w, h), depth_scale, notes)
    mdir = Path(mask_dir) if mask_dir is not None else folder / "masks"
    masks = None
    if mask_dir is not None or mdir.is_dir():
        masks = _load_endonerf_style_masks(mdir, n_all, n, w0, h0, (w, h))
    rate = fps or ENDONERF_FPS
    return Scene(
        frames=frames, times=np.arange(n, dtype=np.float64) / rate, K=K, depth=depth,
        object_masks=masks,
        labels=L.endonerf_labels(masks is not None), downscale=float(downscale), source=str(folder),
        frame_names=[p.name for p in paths], poses=poses, notes=notes,
    )


# ----------------------------------------------------------------------------------------------- CholecSeg8K
_CHOLEC_RE = re.compile(r"^frame_(\d+)_endo\.png$")


def cholecseg8k_frame_dir(folder: Path) -> Path | None:
    """The folder holding a CholecSeg8K clip's ``frame_N_endo.png`` files (``folder`` or ``folder/frames``)."""
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
    d = cholecseg8k_frame_dir(folder)
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
        m = read_grey(mp)
        _check_mask_size(m, mp, w0, h0)
        ids = m.astype(np.int32)
        ids[m == L.CHOLECSEG8K_UNLABELLED_VALUE] = L.UNLABELLED
        unknown = set(np.unique(ids).tolist()) - set(L.CHOLECSEG8K_LABELS) - {L.UNLABELLED}
        if unknown:
            raise DataError(f"{mp}: unknown CholecSeg8K class ids {sorted(unknown)}")
        masks.append(resize(ids, (w, h), nearest=True))
    K = _scale_K(default_K(w0, h0, hfov_deg), w0, h0, w, h)
    rate = fps or CHOLEC_FPS
    # Times from the frame numbers in the names: a clip with frames left out is not evenly sampled.
    numbers = np.array([int(_CHOLEC_RE.match(p.name)[1]) for p in paths], dtype=np.float64)
    notes = []
    gaps = [(int(a), int(b)) for a, b in zip(numbers[:-1], numbers[1:]) if b - a != 1]
    if gaps:
        notes.append(f"{d}: frame numbers jump {', '.join(f'{a} -> {b}' for a, b in gaps[:5])}"
                     f"{' ...' if len(gaps) > 5 else ''}: times follow the numbers, so the frames are not evenly "
                     "spaced (simulations take the median frame interval)")
    return Scene(
        frames=frames, times=(numbers - numbers[0]) / rate, K=K, depth=None,
        object_masks=np.stack(masks).astype(np.int32), labels=dict(L.CHOLECSEG8K_LABELS),
        downscale=float(downscale), source=str(folder), frame_names=[p.name for p in paths], poses=None,
        notes=notes,
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
    notes = []
    expected = float(meta.get("duration") or 0) * float(meta.get("fps") or 0)
    if (max_frames is None or len(raw) < max_frames) and len(raw) < 0.9 * expected - 1:
        notes.append(f"only {len(raw)} frames could be decoded, but the container says {meta['duration']:g} s at "
                     f"{meta['fps']:g} fps (about {expected:.0f} frames): the file is probably truncated")
    size = _target_size(w0, h0, downscale)
    frames = np.stack([resize(f, size, nearest=False).astype(np.float32) / 255.0 for f in raw])
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
        frame_names=[f"{path.name}#{i}" for i in range(n)], notes=notes,
    )


# ----------------------------------------------------------------------------------------------- scene folder
def _read_scene_json(path: Path) -> dict:
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: unreadable scene.json ({exc})") from None
    if not isinstance(meta, dict):
        raise DataError(f"{path}: scene.json must hold a JSON object")
    return meta


def _positive(meta: dict, path: Path, *keys: str) -> float | None:
    """meta[keys[0]][keys[1]]... as a positive float, None when absent; DataError naming the key otherwise."""
    v = meta
    for k in keys:
        v = v.get(k) if isinstance(v, dict) else None
    if v is None:
        return None
    try:
        v = float(v)
    except (TypeError, ValueError):
        v = float("nan")
    if not (math.isfinite(v) and v > 0):
        raise DataError(f"{path}: {'.'.join(keys)} must be a positive number")
    return v


def load_scene_folder(folder: str | Path, *, downscale: float = 1.0, max_frames: int | None = None,
                      fps: float | None = None, depth_scale: float | None = None,
                      mask_dir: str | Path | None = None) -> Scene:
    """Load an EndoGSim scene folder: the EndoNeRF layout plus ``scene.json`` (``endogsim synth`` output, or
    the scene folder of a run).

    ``scene.json`` supplies what EndoNeRF lacks, where it says it: ``depth_scale`` (stored units per metre),
    ``scenario.frame_dt`` (seconds), ``camera`` (K, width, height) and ``objects`` (id, name, class, rigid)
    with their ``object_masks/`` (object id per pixel, 0 = empty background). Explicit arguments win.
    """
    folder = Path(folder)
    path = folder / "scene.json"
    meta = _read_scene_json(path)
    units_per_m = _positive(meta, path, "depth_scale")
    frame_dt = _positive(meta, path, "scenario", "frame_dt")
    if depth_scale is None and units_per_m is not None:
        depth_scale = 1.0 / units_per_m
    if fps is None and frame_dt is not None:
        fps = 1.0 / frame_dt
    scene = load_endonerf(folder, downscale=downscale, max_frames=max_frames, fps=fps, depth_scale=depth_scale,
                          mask_dir=mask_dir)
    cam = meta.get("camera")
    if isinstance(cam, dict) and "K" in cam and not (folder / "poses_bounds.npy").is_file():
        try:
            K0, w0, h0 = np.asarray(cam["K"], np.float64).reshape(3, 3), int(cam["width"]), int(cam["height"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"{path}: malformed camera ({exc})") from None
        scene = replace(scene, K=_scale_K(K0, w0, h0, scene.width, scene.height),
                        notes=[n for n in scene.notes if not n.startswith(NO_POSES_NOTE)])
    objects = meta.get("objects")
    mdir = folder / "object_masks"
    if objects and mdir.is_dir():
        labels = L.label_table({"objects": objects}, str(path))
        files = _list_images(mdir)[: scene.num_frames]
        if len(files) != scene.num_frames:
            raise DataError(f"{mdir}: {len(files)} object masks for {scene.num_frames} frames")
        ids = np.stack([resize(read_grey(f).astype(np.int32), (scene.width, scene.height), nearest=True)
                        for f in files])
        # id 0 in a scene folder's masks is empty space behind everything
        ids = np.where(np.isin(ids, list(labels)), ids, L.UNLABELLED).astype(np.int32)
        scene = replace(scene, object_masks=ids, labels=labels)
    return scene
