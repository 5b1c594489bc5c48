"""Everything reconstruction needs from a dataset, in one place: frames, object masks, depth, splits.

:func:`prepare_scene` loads a folder or video with :func:`endogsim.io.load_scene`, fills the missing
priors (depth: :mod:`endogsim.priors.depth`; masks: :mod:`endogsim.priors.segmentation`) and derives the
pixel classes the losses use:

* tissue pixels: ids whose label is not a tool and not ``background`` (CholecSeg8K's black border);
* tool pixels: ids whose label is a tool;
* neither: unlabelled (-1) and background pixels, left out of every loss and metric.

One object per instrument: masks that give one id per tool *class* (EndoNeRF's single tool id, the
fallback's, CholecSeg8K's grasper / L-hook) are split into instrument instances tracked through the clip
(:func:`~endogsim.priors.instances.split_tool_instances`, with the run's optical flow between consecutive
frames), so every later stage (tool motion, trajectories, objects) sees one rigid object per instrument;
``ReconConfig.tool_instances`` switches it (:func:`wants_tool_instances`).

The endoscope's field of view (:func:`field_of_view`): pixels labelled background in every training frame
lie outside the lens's image circle, and so do never-labelled pixels right beside them (CholecSeg8K's
unlabelled top row); renders are black there, as the camera's pictures are.

Scene folders written by ``endogsim synth`` are read with their own object ids and names (the
``endogsim_scene`` format of :mod:`endogsim.io.formats`), so reconstructed object ids match the generator's.

Train/test split (EndoNeRF protocol): frame i is a test frame when (i - 1) % 8 == 0; the rest train.

Frame times: videos converted to a higher frame rate repeat frames (CholecSeg8K's clip repeats every 6th
frame: 25 -> 30 fps). :func:`repeated_frames` finds the repeats among consecutive training frames and,
when they follow a regular cadence, extends it to the frames in between (a held-out frame is never
read); :func:`video_times` then gives a repeat the time of the frame it repeats, so the deformation
field and the interpolated poses of held-out frames follow the scene's time, not the frame index.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from endogsim.errors import DataError
from endogsim.io.scene import Scene
from endogsim.priors.instances import ToolInstances

__all__ = ["PreparedScene", "prepare_scene", "split_frames", "repeated_frames", "video_times",
           "field_of_view", "wants_tool_instances"]

#: mean absolute difference (RGB in [0, 1]) under which two consecutive frames are the same picture
REPEAT_THRESHOLD = 0.5 / 255
#: Smallest training image side (pixels): the optical flow of the point tracks and the SSIM window need it.
MIN_TRAINING_SIZE = 32


def split_frames(num_frames: int) -> tuple[list[int], list[int]]:
    """(train, test) frame indices: test when (i - 1) % 8 == 0 (frames 1, 9, 17, ...)."""
    test = [i for i in range(num_frames) if (i - 1) % 8 == 0]
    train = [i for i in range(num_frames) if (i - 1) % 8 != 0]
    if not train:
        raise DataError(f"{num_frames} frame(s) leave no training frame")
    return train, test


def repeated_frames(frames: np.ndarray, frames_used: list[int], threshold: float = REPEAT_THRESHOLD) -> np.ndarray:
    """Which frames repeat their predecessor, from the frames in ``frames_used`` only.

    A frame i repeats i - 1 when both are in ``frames_used`` and differ by less than ``threshold`` (mean
    absolute difference). When two or more repeats share a cadence (every P-th frame, same phase) and no
    pair of used frames contradicts it, the frames of that cadence whose pair includes an unused frame
    are marked too.

    Args:
        frames: [T, H, W, 3] RGB in [0, 1].
        frames_used: frame indices that may be read (the training frames).
    Returns:
        [T] bool, True where frame i shows the same instant as frame i - 1.
    """
    T = frames.shape[0]
    used = set(int(f) for f in frames_used)
    pairs = [i for i in range(1, T) if i in used and i - 1 in used]
    same = {i: float(np.abs(frames[i] - frames[i - 1]).mean()) < threshold for i in pairs}
    out = np.zeros(T, dtype=bool)
    found = [i for i, s in same.items() if s]
    out[found] = True
    if len(found) >= 2:
        period = int(np.gcd.reduce(np.diff(found)))
        cadence = [i for i in range(found[0] % period or period, T, period)] if period > 1 else []
        if cadence and all(same.get(i, True) for i in cadence):
            out[cadence] = True
    return out


def video_times(times: np.ndarray, repeated: np.ndarray) -> np.ndarray:
    """Frame times [T] (seconds) with every repeated frame at the time of the frame it repeats and the
    distinct frames evenly spaced over the same span as ``times`` [T]."""
    steps = np.concatenate([[0.0], (~repeated[1:]).astype(np.float64)])
    if steps.sum() == 0:
        return np.asarray(times, dtype=np.float64).copy()
    return times[0] + np.cumsum(steps) * (times[-1] - times[0]) / steps.sum()


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
        times: [T] float64 frame times (seconds) for the model, :func:`video_times` of the scene's
            (None: the scene's own).
        repeated: [T] bool, frames that repeat their predecessor (:func:`repeated_frames`).
        field_of_view: [H, W] bool, pixels inside the endoscope's field of view (:func:`field_of_view`;
            None: all of them).
        instances: the split of the tool classes into instruments (None: the masks' ids were kept).
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
    times: np.ndarray | None = None
    repeated: np.ndarray | None = None
    field_of_view: np.ndarray | None = None
    instances: ToolInstances | None = None

    @property
    def tool_ids(self) -> list[int]:
        return sorted(i for i, lab in self.scene.labels.items() if lab.is_tool)

    @property
    def tissue_ids(self) -> list[int]:
        return sorted(i for i, lab in self.scene.labels.items() if not lab.is_tool and lab.klass != "background")


#: How far (pixels) from the pixels labelled background in every frame an always-unlabelled pixel still counts as
#: outside the field of view (:func:`field_of_view`).
UNLABELLED_EDGE_PX = 2


def field_of_view(object_masks: np.ndarray, background_ids: list[int], frames_used: list[int]) -> np.ndarray | None:
    """[H, W] bool: pixels inside the endoscope's field of view, or None when it fills the image.

    The lens of an endoscope images a fixed circle (CholecSeg8K labels the black around it
    ``background``); a pixel is outside when it is background in every frame of ``frames_used``, or
    unlabelled (id < 0) or background in every frame and within ``UNLABELLED_EDGE_PX`` of such a pixel:
    CholecSeg8K leaves the image's top row unlabelled across its whole width, the black corners included,
    and those were taken for filmed pixels (a coloured line above the circle in every simulated frame and
    flow-error panel). Unlabelled pixels farther inside stay in view: the watershed masks' boundary lines
    between organs are unlabelled too, and on a still camera the same ones in every frame.

    Args:
        object_masks: [T, H, W] int object ids.
        background_ids: ids whose label is background.
        frames_used: frames to read (the training frames).
    """
    if not background_ids or not frames_used:
        return None
    from scipy.ndimage import binary_dilation

    masks = object_masks[frames_used]
    background = np.isin(masks, background_ids)
    outside = background.all(0)
    if not outside.any():
        return None
    never_filmed = (background | (masks < 0)).all(0)
    near = binary_dilation(outside, structure=np.ones((3, 3), bool), iterations=UNLABELLED_EDGE_PX)
    return ~(outside | (never_filmed & near))


def wants_tool_instances(mode: str, seg_source: str, data_format: str) -> bool:
    """Whether to split tool classes into instances: ``mode`` "on" / "off", or "auto": yes unless the
    masks already give one id per instrument (``seg_source`` "sam2": one track per prompt;
    ``data_format`` "endogsim_scene": the ids of the generator's objects)."""
    if mode == "auto":
        return seg_source != "sam2" and data_format != "endogsim_scene"
    return mode == "on"


def _split_instances(frames: np.ndarray, masks: np.ndarray, labels: dict, config, device: str) -> ToolInstances:
    """:func:`~endogsim.priors.instances.split_tool_instances` of ``masks`` [T, H, W], with the run's
    optical flow between consecutive frames of ``frames`` [T, H, W, 3] when there is any tool pixel."""
    from endogsim.priors.flow import flow_estimator
    from endogsim.priors.instances import split_tool_instances
    from endogsim.priors.tracks import consecutive_flows

    fwd = bwd = None
    if len(frames) > 1 and np.isin(masks, [i for i, lab in labels.items() if lab.is_tool]).any():
        fwd, bwd = consecutive_flows(frames, list(range(len(frames))), flow_estimator(config.flow, device))
    return split_tool_instances(masks, labels, fwd, bwd)


def prepare_scene(path: str | Path, config) -> PreparedScene:
    """Load ``path`` at ``config.resolution_scale`` and attach depth and segmentation priors.

    Args:
        path: dataset folder or video file.
        config: a :class:`~endogsim.recon.config.ReconConfig`.
    """
    from endogsim.io.formats import detect_format, load_scene
    from endogsim.priors.depth import estimate_depth
    from endogsim.priors.segmentation import segment_scene

    scene = load_scene(path, downscale=1.0 / config.resolution_scale, max_frames=config.max_frames)
    if scene.frames.shape[0] < 2:
        raise DataError(f"{path}: {scene.frames.shape[0]} frame; a 4D reconstruction needs at least 2 (motion, and "
                        "frames held out to evaluate it)")
    if min(scene.width, scene.height) < MIN_TRAINING_SIZE:
        raise DataError(f"{path}: the frames are {scene.width}x{scene.height} px at resolution scale "
                        f"{config.resolution_scale:g}; reconstruction needs at least {MIN_TRAINING_SIZE} px a side "
                        "(optical flow, SSIM windows): raise --resolution-scale or use larger frames")
    dev = "cuda" if config.device == "cuda" else "cpu"
    dp = estimate_depth(scene, config.depth_method, config.depth_weights, dev, config.working_distance)
    seg = segment_scene(scene, config.seg_method, config.seg_checkpoint, config.seg_config, dev)
    instances = None
    if wants_tool_instances(config.tool_instances, seg.source, detect_format(path)):
        instances = _split_instances(scene.frames, seg.masks, seg.labels, config, dev)
        seg = replace(seg, masks=instances.masks, labels=instances.labels)
    scene = replace(scene, object_masks=seg.masks, labels=seg.labels)
    tool_ids = [i for i, lab in seg.labels.items() if lab.is_tool]
    tissue_ids = [i for i, lab in seg.labels.items() if not lab.is_tool and lab.klass != "background"]
    tool = np.isin(seg.masks, tool_ids)
    tissue = np.isin(seg.masks, tissue_ids)
    train, test = split_frames(scene.num_frames)
    repeated = repeated_frames(scene.frames, train)
    background_ids = [i for i, lab in seg.labels.items() if lab.klass == "background"]
    return PreparedScene(scene, dp.depth, dp.source, dp.metric, seg.source, tissue, tool, train, test,
                         video_times(scene.times, repeated), repeated,
                         field_of_view(seg.masks, background_ids, train), instances)
