"""The ``Scene``: one endoscopic sequence in memory, whatever format it came from."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from endogsim.errors import DataError


@dataclass(frozen=True)
class ObjectLabel:
    """One entry of a scene's label table.

    Attributes:
        id: the integer stored in the object-id masks and on every Gaussian / particle.
        name: human-readable name ("liver", "grasper", ...).
        is_tool: True for rigid instruments, False for tissue.
        klass: the material-prior class key ("liver", "instrument", "unknown_tissue", ...).
    """

    id: int
    name: str
    is_tool: bool
    klass: str


@dataclass
class Scene:
    """An endoscopic sequence.

    Attributes:
        frames: [T, H, W, 3] float32 RGB in [0, 1].
        times: [T] float64 seconds from the first frame.
        K: [3, 3] float64 pinhole intrinsics for the (possibly downscaled) frames.
        depth: optional [T, H, W] float32 depth in metres; 0 where invalid.
        object_masks: optional [T, H, W] int32 object ids (see ``labels``); -1 where unlabelled.
        labels: label table, id -> ObjectLabel.
        downscale: factor by which the frames were reduced from the files (1 = as stored).
        source: folder or file the scene was read from.
        frame_names: [T] file name (or index) of each frame, for error messages and reports.
        poses: optional [T, 4, 4] camera-to-world transforms (identity for a fixed endoscope).
        notes: what the loader had to assume or repair (default intrinsics, saturated depth, a truncated
            video); :func:`endogsim.io.load_scene` warns with each, and outputs record them.
    """

    frames: np.ndarray
    times: np.ndarray
    K: np.ndarray
    depth: np.ndarray | None = None
    object_masks: np.ndarray | None = None
    labels: dict[int, ObjectLabel] = field(default_factory=dict)
    downscale: float = 1.0
    source: str = ""
    frame_names: list[str] = field(default_factory=list)
    poses: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.frames.ndim != 4 or self.frames.shape[-1] != 3:
            raise DataError(f"{self.source}: frames must be [T, H, W, 3], got {self.frames.shape}")
        t, h, w, _ = self.frames.shape
        if t == 0:
            raise DataError(f"{self.source}: empty sequence (no frames)")
        if self.times.shape != (t,):
            raise DataError(f"{self.source}: {self.times.shape[0]} times for {t} frames")
        for name in ("depth", "object_masks"):
            arr = getattr(self, name)
            if arr is not None and arr.shape != (t, h, w):
                raise DataError(f"{self.source}: {name} has shape {arr.shape}, frames are {(t, h, w)}")

    @property
    def num_frames(self) -> int:
        return self.frames.shape[0]

    @property
    def height(self) -> int:
        return self.frames.shape[1]

    @property
    def width(self) -> int:
        return self.frames.shape[2]

    @property
    def tool_mask(self) -> np.ndarray | None:
        """[T, H, W] bool, True on instrument pixels (None without masks)."""
        if self.object_masks is None:
            return None
        tool_ids = [i for i, lab in self.labels.items() if lab.is_tool]
        return np.isin(self.object_masks, tool_ids)

    def name_of(self, object_id: int) -> str:
        return self.labels[object_id].name if object_id in self.labels else f"object_{object_id}"

    @property
    def source_path(self) -> Path:
        return Path(self.source)
