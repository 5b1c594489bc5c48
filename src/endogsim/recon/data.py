"""Everything reconstruction needs from a dataset, in one place: frames, object masks, depth, splits.

:func:`prepare_scene` loads a folder or video with :func:`endogsim.io.load_scene`, fills the missing
priors (depth: :mod:`endogsim.priors.depth`; masks: :mod:`endogsim.priors.segmentation`) and derives the
pixel classes the losses use:

* tissue pixels: ids whose label is not a tool and not ``background`` (CholecSeg8K's black border);
* tool pixels: ids whose label is a tool;
* neither: unlabelled (-1) and background pixels, left out of every loss and metric.

Procedural scenes written by ``endogsim synth`` carry ``scene.json``: its ``depth_scale`` (stored units
per metre) and its ``object_masks/`` (the scene's own ids and names) are used when present, so
reconstructed object ids match the generator's.

Train/test split (EndoNeRF protocol): frame i is a test frame when (i - 1) % 8 == 0; the rest train.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from endogsim.errors import DataError
from endogsim.io.scene import ObjectLabel, Scene

__all__ = ["PreparedScene", "prepare_scene", "split_frames", "load_recon_scene"]


def split_frames(num_frames: int) -> tuple[list[int], list[int]]:
    """(train, test) frame indices: test when (i - 1) % 8 == 0 (frames 1, 9, 17, ...)."""
    test = [i for i in range(num_frames) if (i - 1) % 8 == 0]
    train = [i for i in range(num_frames) if (i - 1) % 8 != 0]
    if not train:
        raise DataError(f"{num_frames} frame(s) leave no training frame")
    return train, test


@dataclass
class PreparedScene:
    """A scene ready for training.

    Attributes:
        scene: the loaded :class:`Scene` with ``object_masks`` and ``labels`` filled by the priors.
        depth: [T, H, W] float32 depth (metres) from the depth prior; 0 = unknown.
        depth_source, depth_metric: where the depth came from; metric depth also supervises.
        seg_source: where the masks came from ("dataset", "sam2", "fallback").
        tissue: [T, H, W] bool tissue pixels.  tool: [T, H, W] bool instrument pixels.
        train, test: frame indices.
    """

    scene: Scene
    depth: np.ndarray
    depth_source: str
    depth_metric: bool
    seg_source: str
    tissue: np.ndarray
    tool: np.ndarray
    train: list[int]
    test: list[int]

    @property
    def tool_ids(self) -> list[int]:
        return sorted(i for i, lab in self.scene.labels.items() if lab.is_tool)

    @property
    def tissue_ids(self) -> list[int]:
        return sorted(i for i, lab in self.scene.labels.items() if not lab.is_tool and lab.klass != "background")


def load_recon_scene(path: str | Path, downscale: float, max_frames: int | None = None) -> Scene:
    """:func:`load_scene` plus the extras of procedural scenes (``scene.json``: depth scale, object ids)."""
    from endogsim.io import load_scene
    from endogsim.io.loaders import _resize  # the loaders' nearest-neighbour convention for id masks

    path = Path(path)
    meta = None
    if path.is_dir() and (path / "scene.json").is_file():
        try:
            meta = json.loads((path / "scene.json").read_text())
        except json.JSONDecodeError as exc:
            raise DataError(f"{path / 'scene.json'}: not valid JSON ({exc})") from None
    kwargs = {}
    if meta and "depth_scale" in meta and (path / "depth").is_dir():
        kwargs["depth_scale"] = 1.0 / float(meta["depth_scale"])  # file: stored units per metre
    scene = load_scene(path, downscale=downscale, max_frames=max_frames, **kwargs)
    if meta and (path / "object_masks").is_dir() and meta.get("objects"):
        import cv2

        files = sorted((path / "object_masks").glob("*.png"))[: scene.num_frames]
        if len(files) != scene.num_frames:
            raise DataError(f"{path / 'object_masks'}: {len(files)} masks for {scene.num_frames} frames")
        masks = []
        for f in files:
            m = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            if m is None:
                raise DataError(f"{f}: cannot read object mask")
            masks.append(_resize(m.astype(np.int32), (scene.width, scene.height), nearest=True))
        ids = np.stack(masks).astype(np.int32)
        labels = {}
        for o in meta["objects"]:
            klass = str(o.get("class", "unknown_tissue"))
            is_tool = bool(o.get("is_tool", klass == "instrument"))
            labels[int(o["id"])] = ObjectLabel(int(o["id"]), str(o["name"]), is_tool, klass)
        # id 0 in procedural masks is empty space behind everything
        ids = np.where(np.isin(ids, list(labels)), ids, -1).astype(np.int32)
        scene = replace(scene, object_masks=ids, labels=labels)
    return scene


def prepare_scene(path: str | Path, config) -> PreparedScene:
    """Load ``path`` at ``config.resolution_scale`` and attach depth and segmentation priors.

    Args:
        path: dataset folder or video file.
        config: a :class:`~endogsim.recon.config.ReconConfig`.
    """
    from endogsim.priors.depth import estimate_depth
    from endogsim.priors.segmentation import segment_scene

    scene = load_recon_scene(path, 1.0 / config.resolution_scale, config.max_frames)
    dev = "cuda" if config.device == "cuda" else "cpu"
    dp = estimate_depth(scene, config.depth_method, config.depth_weights, dev, config.working_distance)
    seg = segment_scene(scene, config.seg_method, config.seg_checkpoint, config.seg_config, dev)
    scene = replace(scene, object_masks=seg.masks, labels=seg.labels)
    tool_ids = [i for i, lab in seg.labels.items() if lab.is_tool]
    tissue_ids = [i for i, lab in seg.labels.items() if not lab.is_tool and lab.klass != "background"]
    tool = np.isin(seg.masks, tool_ids)
    tissue = np.isin(seg.masks, tissue_ids)
    train, test = split_frames(scene.num_frames)
    return PreparedScene(scene, dp.depth, dp.source, dp.metric, seg.source, tissue, tool, train, test)
