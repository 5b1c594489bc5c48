"""Dataset formats: a registry of the layouts the package reads, detection, and one loading entry point.

Each :class:`DatasetFormat` says how to recognise a path (``detect``) and how to read it into a
:class:`~endogsim.io.scene.Scene` (``load``), and which format-specific options ``load`` takes. Formats are
tried in registration order, the most specific first. Add one with :func:`register_format`::

    register_format(DatasetFormat("my_layout", "what it is", detect=my_detect, load=my_loader,
                                  options=("hfov_deg",)))

Every command that takes ``DATA`` reads it with :func:`load_scene`.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from endogsim.errors import DataError, DataWarning
from endogsim.io import loaders
from endogsim.io.scene import Scene

__all__ = ["DatasetFormat", "FORMATS", "register_format", "detect_format", "load_scene"]


@dataclass(frozen=True)
class DatasetFormat:
    """One dataset layout.

    Attributes:
        name: the format's key ("endonerf", ...).
        description: what the layout holds, for help texts and error messages.
        detect: path -> True when the path is in this layout (cheap: file names, not contents).
        load: ``load(path, *, downscale, max_frames, fps, [mask_dir,] **options) -> Scene``.
        options: the format-specific keyword options ``load`` accepts.
        mask_dir: whether ``load`` takes a separate tool-mask folder.
    """

    name: str
    description: str
    detect: Callable[[Path], bool]
    load: Callable[..., Scene]
    options: tuple[str, ...] = ()
    mask_dir: bool = False


FORMATS: dict[str, DatasetFormat] = {}


def register_format(fmt: DatasetFormat) -> DatasetFormat:
    """Add (or replace) a dataset format; returns it."""
    FORMATS[fmt.name] = fmt
    return fmt


register_format(DatasetFormat(
    "endogsim_scene", "EndoGSim scene folder (EndoNeRF layout + scene.json: `endogsim synth`, a run's scene/)",
    detect=lambda p: p.is_dir() and (p / "scene.json").is_file() and (p / "images").is_dir(),
    load=loaders.load_scene_folder, options=("depth_scale",), mask_dir=True))
register_format(DatasetFormat(
    "endonerf", "EndoNeRF folder (images/, optional depth/, masks/, poses_bounds.npy)",
    detect=lambda p: p.is_dir() and ((p / "images").is_dir() or (p / "poses_bounds.npy").is_file()),
    load=loaders.load_endonerf, options=("depth_scale",), mask_dir=True))
register_format(DatasetFormat(
    "cholecseg8k", "CholecSeg8K clip (frame_N_endo.png + frame_N_endo_watershed_mask.png)",
    detect=lambda p: p.is_dir() and loaders.cholecseg8k_frame_dir(p) is not None,
    load=loaders.load_cholecseg8k, options=("hfov_deg",)))
register_format(DatasetFormat(
    "video", f"video file ({', '.join(loaders.VIDEO_EXTS)}), optional tool-mask folder",
    detect=lambda p: p.is_file() and p.suffix.lower() in loaders.VIDEO_EXTS,
    load=loaders.load_video, options=("hfov_deg",), mask_dir=True))


def detect_format(path: str | Path) -> str:
    """The name of the first registered format that recognises ``path``; DataError if missing or unknown."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    for fmt in FORMATS.values():
        if fmt.detect(path):
            return fmt.name
    kinds = "; ".join(f.description for f in FORMATS.values())
    raise DataError(f"{path}: unknown format (expected one of: {kinds})")


def load_scene(path: str | Path, *, downscale: float = 1.0, max_frames: int | None = None,
               mask_dir: str | Path | None = None, fps: float | None = None, **options) -> Scene:
    """Load any supported dataset into a :class:`Scene` (format detected from the path).

    Args:
        path: a folder or video file in a registered format (:data:`FORMATS`).
        downscale: factor >= 1 applied to frames, depth, masks and K.
        max_frames: keep only the first ``max_frames`` frames.
        mask_dir: tool masks (255 = tool) for the formats that take them (EndoNeRF folders, videos).
        fps: override the frame rate used for ``times`` (seconds).
        options: format-specific options (``depth_scale`` for EndoNeRF, ``hfov_deg`` for CholecSeg8K and
            videos).

    Every assumption the loader made (``Scene.notes``: default intrinsics, saturated depth, a truncated
    video) is also issued as a :class:`~endogsim.errors.DataWarning`.
    """
    if max_frames is not None and max_frames < 1:
        raise DataError(f"max_frames must be >= 1, got {max_frames}")
    fmt = FORMATS[detect_format(path)]
    extra = sorted(set(options) - set(fmt.options))
    if extra:
        raise DataError(f"{path}: option(s) {extra} not supported for {fmt.name} data (allowed: {sorted(fmt.options)})")
    if mask_dir is not None:
        if not fmt.mask_dir:
            raise DataError(f"{path}: {fmt.name} data carries its own masks; mask_dir is not used")
        options["mask_dir"] = mask_dir
    scene = fmt.load(path, downscale=downscale, max_frames=max_frames, fps=fps, **options)
    for note in scene.notes:
        warnings.warn(f"{path}: {note}", DataWarning, stacklevel=2)
    return scene
