"""Instrument instances: one object per instrument, from masks that give one id per tool *class*.

Segmentation labels a pixel with a class: EndoNeRF masks and the offline fallback have one "tool" id for
every instrument in view, CholecSeg8K one id per instrument type (grasper 31, L-hook 32). Reconstruction
and simulation need one rigid object per instrument. :func:`split_tool_instances` splits each tool class
into instances (connected components tracked through time) and returns new object-id masks and an
extended label table.

Tracking (:func:`track_instances`, one tool class at a time, so classes never mix):

1. **Tracklets, frame to frame.** Components are the 8-connected blobs of the class's mask, after
   dropping those under ``min_area_frac`` of the image (glints, label noise). Tracking starts at the
   *seed* frame, the first frame with the most components (so instruments that touch at the start of the
   clip are still told apart), and runs forward to the end and backward to frame 0. Frame t is labelled
   from its neighbour s (t - 1 going forward, t + 1 going backward):

   a. prediction: the tracklet map of s moved into t by the optical flow t -> s (nearest neighbour;
      without flow, the map of s itself);
   b. merged blobs: a component holding at least ``merge_share`` of each of two or more predicted
      tracklets is instruments touching; its pixels go to the nearest predicted tracklet;
   c. matching: the other components are matched one-to-one to predicted tracklets by IoU (Hungarian,
      IoU >= ``min_iou``); a leftover component overlapping a predicted tracklet is a fragment of it
      (the segmentation broke one instrument in two); any other component starts a new tracklet.
2. **Spurious tracklets**, seen in fewer than ``min_track_frames`` frames, are dropped (false detections).
3. **Re-identification.** In order of start, a tracklet continues the instance whose last tracklet ended
   before it starts (the instrument left the view or was occluded) and whose last mask is nearest its
   first mask, if within ``reid_dist_frac`` of the image diagonal; else it is a new instance.

Object ids (:func:`split_tool_instances`): tissue ids are unchanged. The first instance of a tool class
(in order of appearance) keeps the class's id, so a scene with one instrument per class reads as before;
further instances take fresh ids above every id in use. With several instances a class's name gets the
instance number ("tool_1", "tool_2", "grasper_2"); the prior class (``klass``) is the class's, so the
material priors stay right. Tool pixels of no instance (dropped specks, spurious blobs) become
:data:`~endogsim.io.labels.UNLABELLED` (-1): neither tissue nor tool, they are left out of every loss.

Limits: instruments merged in every frame stay one instance (use dataset classes or per-instrument
prompts); an instrument crossing in front of another would need depth order; re-identification is by
distance only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from endogsim.errors import DataError
from endogsim.io.labels import UNLABELLED
from endogsim.io.scene import ObjectLabel

__all__ = ["InstanceConfig", "InstanceEvent", "ToolInstances", "track_instances", "split_tool_instances"]


@dataclass(frozen=True)
class InstanceConfig:
    """Thresholds of the instance tracker (fractions of the image area or diagonal, so they hold at any
    resolution).

    Attributes:
        min_area_frac: components smaller than this fraction of the image area are ignored.
        min_iou: smallest IoU between a component and a predicted tracklet that counts as a match.
        merge_share: a component holding at least this share of each of >= 2 predicted tracklets is split.
        reid_dist_frac: an instrument that reappears within this fraction of the image diagonal of its
            last mask keeps its instance.
        min_track_frames: tracklets visible in fewer frames are dropped as spurious.
    """

    min_area_frac: float = 0.002
    min_iou: float = 0.1
    merge_share: float = 0.2
    reid_dist_frac: float = 0.25
    min_track_frames: int = 3

    def __post_init__(self) -> None:
        for name in ("min_area_frac", "min_iou", "merge_share", "reid_dist_frac"):
            if not 0 <= getattr(self, name) <= 1:
                raise DataError(f"InstanceConfig.{name} {getattr(self, name)} must be in [0, 1]")
        if self.min_track_frames < 1:
            raise DataError(f"InstanceConfig.min_track_frames {self.min_track_frames} must be >= 1")


@dataclass(frozen=True)
class InstanceEvent:
    """One line of the tracker's log: at ``frame``, ``kind`` ("seed", "merged", "fragment", "spurious",
    "new", "lost", "reappeared") with a readable ``detail``."""

    frame: int
    kind: str
    detail: str


@dataclass
class ToolInstances:
    """Result of :func:`split_tool_instances`.

    Attributes:
        masks: [T, H, W] int32 object ids: tissue ids as given, one id per instrument instance, -1
            (unlabelled) on tool pixels of no instance and where the input was unlabelled.
        labels: id -> :class:`ObjectLabel`: the tissue entries as given, one tool entry per instance.
        class_of: instance id -> the tool class id it came from.
        frames: instance id -> sorted frames where it is visible.
        events: the tracker's log, in frame order.
    """

    masks: np.ndarray
    labels: dict[int, ObjectLabel]
    class_of: dict[int, int] = field(default_factory=dict)
    frames: dict[int, list[int]] = field(default_factory=dict)
    events: list[InstanceEvent] = field(default_factory=list)

    def summary(self) -> dict:
        """JSON-ready: per instance its name, class, visible-frame count and the gaps (first, last frame)
        where it is not seen; and the log."""
        out = {}
        for oid, fr in self.frames.items():
            gaps = [[a + 1, b - 1] for a, b in zip(fr, fr[1:]) if b > a + 1]
            out[str(oid)] = {"name": self.labels[oid].name, "class_id": self.class_of[oid],
                             "frames_visible": len(fr), "first": fr[0], "last": fr[-1], "gaps": gaps}
        return {"instances": out, "events": [[e.frame, e.kind, e.detail] for e in self.events]}


# ----------------------------------------------------------------------------------------------- helpers
def _components(mask: np.ndarray, min_area: int) -> list[np.ndarray]:
    """The 8-connected components of ``mask`` [H, W] bool with at least ``min_area`` pixels, in raster
    order of their first pixel; each an [H, W] bool mask."""
    import cv2

    n, cc, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    return [cc == k for k in range(1, n) if stats[k, cv2.CC_STAT_AREA] >= min_area]


def _warp_ids(ids: np.ndarray, flow: np.ndarray | None) -> np.ndarray:
    """An id map [H, W] of a neighbour frame moved into this frame: out(x) = ids(x + flow(x)), nearest
    neighbour, 0 outside the image; ``flow`` [H, W, 2] (pixels) goes from this frame to the neighbour."""
    import cv2

    if flow is None:
        return ids
    H, W = ids.shape
    xs, ys = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    warped = cv2.remap(ids.astype(np.float32), xs + flow[..., 0].astype(np.float32),
                       ys + flow[..., 1].astype(np.float32), cv2.INTER_NEAREST,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return warped.astype(np.int32)


def _distance_map(mask: np.ndarray) -> np.ndarray:
    """[H, W] float32 Euclidean distance (pixels) from every pixel to the nearest pixel of ``mask``."""
    import cv2

    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)


def _label_frame(out: np.ndarray, comps: list[np.ndarray], predicted: np.ndarray, next_id: int,
                 config: InstanceConfig, frame: int, events: list[InstanceEvent]) -> int:
    """Write tracklet ids into ``out`` [H, W] for the components ``comps`` of one frame, given the
    neighbour frame's ``predicted`` tracklet map [H, W] (steps 1b and 1c of the module docstring);
    returns the next free tracklet id."""
    from scipy.optimize import linear_sum_assignment

    predicted_ids = [int(k) for k in np.unique(predicted) if k > 0]
    area = {k: int((predicted == k).sum()) for k in predicted_ids}
    active = list(predicted_ids)  # not yet given a component
    rest = []
    for m in comps:  # merged blobs: pixels go to the nearest predicted tracklet
        held = [k for k in active if (m & (predicted == k)).sum() >= config.merge_share * area[k]]
        if len(held) < 2:
            rest.append(m)
            continue
        owner = np.argmin(np.stack([_distance_map(predicted == k) for k in held]), axis=0)
        for j, k in enumerate(held):
            out[m & (owner == j)] = k
        events.append(InstanceEvent(frame, "merged", f"one blob split between {len(held)} instruments"))
        active = [k for k in active if k not in held]
    matched = set()
    if rest and active:
        iou = np.array([[(m & (predicted == k)).sum() / max(1, (m | (predicted == k)).sum()) for k in active]
                        for m in rest])
        for i, j in zip(*linear_sum_assignment(-iou)):
            if iou[i, j] >= config.min_iou:
                out[rest[i]] = active[j]
                matched.add(i)
    for i, m in enumerate(rest):
        if i in matched:
            continue
        overlap = [int((m & (predicted == k)).sum()) for k in predicted_ids]
        if overlap and max(overlap) > 0:
            out[m] = predicted_ids[int(np.argmax(overlap))]
            events.append(InstanceEvent(frame, "fragment", f"a {int(m.sum())} px piece joined its instrument"))
        else:
            out[m] = next_id
            next_id += 1
    return next_id


def _tracklets(mask: np.ndarray, flows_fwd, flows_bwd, config: InstanceConfig,
               events: list[InstanceEvent]) -> np.ndarray:
    """Pass 1: [T, H, W] int32 tracklet ids (0: none) of the class mask ``mask`` [T, H, W] bool."""
    T, H, W = mask.shape
    min_area = max(1, int(round(config.min_area_frac * H * W)))
    comps = [_components(mask[t], min_area) for t in range(T)]
    seed = int(np.argmax([len(c) for c in comps]))
    if seed > 0:
        events.append(InstanceEvent(seed, "seed", f"tracking starts at frame {seed} ({len(comps[seed])} "
                                                  f"blobs; frame 0 has {len(comps[0])})"))
    ids = np.zeros((T, H, W), dtype=np.int32)
    for k, m in enumerate(comps[seed], 1):
        ids[seed][m] = k
    next_id = len(comps[seed]) + 1
    steps = ([(t, t - 1, None if flows_bwd is None else flows_bwd[t - 1]) for t in range(seed + 1, T)]
             + [(t, t + 1, None if flows_fwd is None else flows_fwd[t]) for t in range(seed - 1, -1, -1)])
    for t, s, flow in steps:
        next_id = _label_frame(ids[t], comps[t], _warp_ids(ids[s], flow), next_id, config, t, events)
    return ids


def track_instances(mask: np.ndarray, flows_fwd: Sequence[np.ndarray] | None = None,
                    flows_bwd: Sequence[np.ndarray] | None = None, config: InstanceConfig = InstanceConfig()
                    ) -> tuple[np.ndarray, dict[int, list[int]], list[InstanceEvent]]:
    """The instruments of one tool class, tracked through the clip (see the module docstring).

    Args:
        mask: [T, H, W] bool pixels of the class.
        flows_fwd: optional T - 1 flows [H, W, 2] (pixels): ``flows_fwd[t]`` moves a pixel of frame t to
            frame t + 1 (:func:`~endogsim.priors.tracks.consecutive_flows` over every frame).
        flows_bwd: optional T - 1 flows [H, W, 2]: ``flows_bwd[t]`` moves a pixel of frame t + 1 to frame t.
        config: thresholds.
    Returns:
        (ids [T, H, W] int32 with 0 = no instrument and 1..K the instances in order of appearance,
        instance -> sorted frames where it is visible, the log).
    """
    mask = np.asarray(mask, dtype=bool)
    T, H, W = mask.shape
    for name, flows in (("flows_fwd", flows_fwd), ("flows_bwd", flows_bwd)):
        if flows is not None and len(flows) != T - 1:
            raise DataError(f"track_instances: {name} holds {len(flows)} flows for {T} frames (needs {T - 1})")
    events: list[InstanceEvent] = []
    ids = _tracklets(mask, flows_fwd, flows_bwd, config, events)

    present = {int(k): np.nonzero((ids == k).any((1, 2)))[0].tolist() for k in np.unique(ids) if k > 0}
    for k, fr in list(present.items()):  # pass 2: spurious tracklets
        if len(fr) < config.min_track_frames:
            area = int((ids == k).sum()) // len(fr)
            events.append(InstanceEvent(fr[0], "spurious", f"a {area} px blob seen in frame(s) {fr} only, dropped"))
            ids[ids == k] = 0
            del present[k]

    # pass 3: re-identification; chains[i] = the tracklets of instance i, in time order
    reid_dist = config.reid_dist_frac * float(np.hypot(H, W))
    chains: list[list[int]] = []
    for k in sorted(present, key=lambda k: (present[k][0], k)):
        first = present[k][0]
        best, best_d = None, np.inf
        for i, chain in enumerate(chains):
            last = present[chain[-1]][-1]
            if last < first:
                d = float(_distance_map(ids[last] == chain[-1])[ids[first] == k].min())
                if d < best_d:
                    best, best_d = i, d
        if best is not None and best_d <= reid_dist:
            gap = first - present[chains[best][-1]][-1] - 1
            events.append(InstanceEvent(first, "reappeared", f"instance {best + 1} after {gap} frame(s) unseen, "
                                                             f"{best_d:.0f} px from where it was last seen"))
            events.append(InstanceEvent(first - gap, "lost", f"instance {best + 1} not seen (left the view or "
                                                             "occluded)"))
            chains[best].append(k)
        else:
            chains.append([k])
            events.append(InstanceEvent(first, "new", f"instance {len(chains)} ({int((ids[first] == k).sum())} px)"))
    remap = np.zeros(int(ids.max()) + 1, dtype=np.int32)
    for i, chain in enumerate(chains, 1):
        remap[chain] = i
    frames = {i: sorted(f for k in chain for f in present[k]) for i, chain in enumerate(chains, 1)}
    return remap[ids], frames, sorted(events, key=lambda e: e.frame)


def split_tool_instances(masks: np.ndarray, labels: dict[int, ObjectLabel],
                         flows_fwd: Sequence[np.ndarray] | None = None,
                         flows_bwd: Sequence[np.ndarray] | None = None,
                         config: InstanceConfig = InstanceConfig()) -> ToolInstances:
    """One object per instrument: every tool class of ``labels`` split into tracked instances.

    Args:
        masks: [T, H, W] int object ids (class ids for tools), -1 where unlabelled.
        labels: id -> :class:`ObjectLabel`; the entries with ``is_tool`` are the tool classes.
        flows_fwd, flows_bwd: optional optical flow between consecutive frames (see :func:`track_instances`).
        config: thresholds.
    Returns:
        :class:`ToolInstances` (ids as described in the module docstring).
    """
    masks = np.asarray(masks)
    out = masks.astype(np.int32, copy=True)
    new_labels = {i: lab for i, lab in labels.items() if not lab.is_tool}
    result = ToolInstances(out, new_labels)
    next_free = max([*labels, int(masks.max(initial=0))]) + 1
    for cls in sorted(i for i, lab in labels.items() if lab.is_tool):
        lab = labels[cls]
        of_class = masks == cls
        ids, frames, events = track_instances(of_class, flows_fwd, flows_bwd, config)
        out[of_class] = UNLABELLED
        result.events += [InstanceEvent(e.frame, e.kind, f"{lab.name}: {e.detail}") for e in events]
        for k in sorted(frames):
            if k == 1:
                oid = cls
            else:
                oid, next_free = next_free, next_free + 1
            out[ids == k] = oid
            name = lab.name if len(frames) == 1 else f"{lab.name}_{k}"
            new_labels[oid] = ObjectLabel(oid, name, True, lab.klass)
            result.class_of[oid] = cls
            result.frames[oid] = frames[k]
    result.events.sort(key=lambda e: e.frame)
    return result
