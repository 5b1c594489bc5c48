"""Segmentation priors: which pixel belongs to which object (tissue ids, tool ids), per frame.

Entry point: :func:`segment_scene` returns a :class:`Segmentation` (object-id masks + label table).
Back-ends, registered by name in :data:`SEGMENTATION_BACKENDS`:

* ``"dataset"``: the scene's own masks (EndoNeRF tool masks, CholecSeg8K classes, procedural ids).
* ``"sam2"``: SAM 2 / Surgical-SAM-2 video propagation (``sam2`` package) with a *local* checkpoint and
  model config. It is prompted on the first frame with the boxes of the offline tool detector below and
  tracks every box through the video; each track becomes one tool object (``tool_1``, ``tool_2``, ...).
* ``"fallback"``: offline tool detection by colour and motion. Surgical instruments (da Vinci shafts,
  laparoscopic graspers and hooks) are grey or metallic: low saturation, mid-to-high value, unlike tissue
  (red, pink, yellow, all saturated). :func:`grey_tool_mask` thresholds HSV, drops small specular
  highlights with a morphological opening, keeps connected components above a minimum area, then grows
  them (hysteresis) into adjacent pixels with weaker tool evidence: darker or bluer colour (metal mirrors
  the reddish tissue around it), or, in a video, motion unlike the tissue's (:func:`motion_residual`:
  grasper jaws look like shadowed tissue but move with the instrument). Crude (white fat, glare and
  smoke are grey too): a warning says so.
* ``"auto"``: dataset masks when present, else the fallback.

Every object gets a stable integer id and a name; fallback/SAM 2 tables use id 0 ``tissue`` and tool ids
from 1, as the EndoNeRF table (:mod:`endogsim.io.labels`).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from endogsim.errors import DataError, ModelError
from endogsim.io.labels import endonerf_labels
from endogsim.io.scene import ObjectLabel
from endogsim.priors import resolve_auto
from endogsim.registry import Registry

__all__ = ["Segmentation", "segment_scene", "grey_tool_mask", "motion_residual", "GreyToolConfig",
           "sam2_segmentation", "SEGMENTATION_BACKENDS"]


@dataclass
class Segmentation:
    """Object-id masks for a sequence.

    Attributes:
        masks: [T, H, W] int32 object ids; -1 where unlabelled.
        labels: id -> :class:`ObjectLabel` (name, is_tool, klass).
        source: "dataset", "sam2" or "fallback".
    """

    masks: np.ndarray
    labels: dict[int, ObjectLabel]
    source: str


@dataclass(frozen=True)
class GreyToolConfig:
    """Thresholds of the colour-based tool detector (HSV with S, V in [0, 1]).

    A pixel is a tool candidate when it is bright enough and either grey (saturation below
    ``max_saturation``) or cool-coloured (hue in ``cool_hue_deg``, saturation below
    ``max_saturation_cool``): instruments under the endoscope's white light look grey or bluish-grey,
    tissue is red, pink, orange or yellow (pale, fatty or blanched tissue has a low saturation but a
    warm hue, so it fails both tests).

    Attributes:
        max_saturation: grey test: saturation below this.
        cool_hue_deg: (lo, hi) hue range in degrees of the cool-colour test (cyan to blue-violet).
        max_saturation_cool: cool-colour test: saturation below this.
        min_value: candidates must be brighter than this (dark shadows are not tools).
        open_frac: opening kernel size as a fraction of the image width (removes glints, thin vessels).
        close_frac: closing kernel size, same units (fills tool texture, text on the shaft).
        min_area_frac: components smaller than this fraction of the image are dropped.
        grow_frac: hysteresis: the detected tools then grow, by at most this fraction of the width, into
            connected pixels that pass a weaker test (metal mirrors the tissue around it, so jaws and
            shafts are often reddish, only darker or bluer than tissue of the same hue); 0 turns it off.
        weak_saturation, weak_value, weak_cool_value: the weaker test: saturation below
            ``weak_saturation``, or value below ``weak_value``, or a hue in ``weak_cool_hue_deg`` with
            value below ``weak_cool_value``.
        dilate_frac: the final mask is grown by this fraction of the width, so tool borders (dark
            edges, motion blur, shadows at the contact) stay out of the tissue loss.
        motion_threshold: weaker test in a video: :func:`motion_residual` above this (colour units in
            [0, 1]); None turns the motion cue off.
        motion_sigma_frac: width (fraction of the image width) of the Gaussian that averages the tissue
            flow into the smooth tissue motion the residual is measured against.
    """

    max_saturation: float = 0.15
    cool_hue_deg: tuple[float, float] = (170.0, 270.0)
    max_saturation_cool: float = 0.6
    min_value: float = 0.20
    open_frac: float = 0.012
    close_frac: float = 0.02
    min_area_frac: float = 0.004
    grow_frac: float = 0.25
    weak_saturation: float = 0.3
    weak_value: float = 0.4
    weak_cool_hue_deg: tuple[float, float] = (180.0, 345.0)
    weak_cool_value: float = 0.55
    dilate_frac: float = 0.01
    motion_threshold: float | None = 0.08
    motion_sigma_frac: float = 0.04


def motion_residual(frames: np.ndarray, t: int, exclude: np.ndarray, sigma_frac: float = 0.04,
                    estimator=None) -> np.ndarray:
    """How badly the smooth motion of the tissue explains frame ``t``: [H, W] float in [0, 1].

    For each neighbour s = t - 1, t + 1 the optical flow t -> s is averaged over the pixels not in
    ``exclude`` with a wide normalised Gaussian (the tissue's smooth motion), frame s is warped back with
    it and compared with frame t (max over channels); the result is the larger residual of the two
    neighbours. Tissue follows its own smooth motion (small residual, except at specular highlights and
    occlusion edges); an instrument moving over it does not.

    Args:
        frames: [T, H, W, 3] RGB in [0, 1].
        t: the frame.
        exclude: [H, W] bool pixels left out of the tissue motion (the confident tool cores).
        sigma_frac: Gaussian width as a fraction of the image width.
        estimator: a :class:`~endogsim.priors.flow.FlowEstimator` (default: DIS, offline).
    """
    import cv2

    from endogsim.evaluate.flow_metrics import warp_backward
    from endogsim.priors.flow import DISFlow

    est = estimator or DISFlow("medium")
    T, H, W, _ = frames.shape
    keep = (~cv2.dilate(exclude.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)).astype(np.float32)
    sigma = sigma_frac * W
    weight = cv2.GaussianBlur(keep, (0, 0), sigma) + 1e-6
    out = np.zeros((H, W), dtype=np.float32)
    for s in (t - 1, t + 1):
        if not 0 <= s < T:
            continue
        flow = est.estimate(frames[t], frames[s])
        smooth = np.stack([cv2.GaussianBlur(flow[..., c] * keep, (0, 0), sigma) / weight for c in range(2)], -1)
        out = np.maximum(out, np.abs(warp_backward(frames[s], smooth) - frames[t]).max(-1))
    return out


def grey_tool_mask(frame: np.ndarray, config: GreyToolConfig = GreyToolConfig(),
                   motion: np.ndarray | None = None) -> np.ndarray:
    """Offline instrument detector: [H, W] bool, True on grey, low-saturation regions.

    Args:
        frame: [H, W, 3] RGB, float in [0, 1] or uint8.
        config: thresholds (see :class:`GreyToolConfig`).
        motion: optional [H, W] :func:`motion_residual` of the frame (a video): pixels above
            ``config.motion_threshold`` count as weak tool evidence for the hysteresis growth.
    """
    import cv2

    f = np.asarray(frame)
    if f.ndim != 3 or f.shape[-1] != 3:
        raise DataError(f"grey_tool_mask expects an [H, W, 3] RGB frame, got shape {f.shape}")
    if f.dtype != np.uint8:
        f = (np.clip(f, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    hsv = cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2HSV).astype(np.float32)
    hue, s, v = hsv[..., 0] * 2.0, hsv[..., 1] / 255.0, hsv[..., 2] / 255.0  # OpenCV stores hue / 2
    lo, hi = config.cool_hue_deg
    cool = (hue >= lo) & (hue <= hi) & (s < config.max_saturation_cool)
    raw = ((s < config.max_saturation) | cool) & (v > config.min_value)
    h, w = raw.shape

    def kernel(frac: float) -> np.ndarray:
        k = max(1, int(round(frac * w)) | 1)
        return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))

    m = cv2.morphologyEx(raw.astype(np.uint8), cv2.MORPH_OPEN, kernel(config.open_frac))
    m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, kernel(config.close_frac))
    n, cc, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    keep = np.zeros(n, dtype=bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= config.min_area_frac * h * w
    m = keep[cc].astype(np.uint8)
    if config.grow_frac > 0 and m.any():
        wlo, whi = config.weak_cool_hue_deg
        weak = ((s < config.weak_saturation) | (v < config.weak_value)
                | ((hue >= wlo) & (hue <= whi) & (v < config.weak_cool_value)))
        if motion is not None and config.motion_threshold is not None:
            weak |= motion > config.motion_threshold
        weak = weak.astype(np.uint8)
        step = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
        for _ in range(max(1, int(round(config.grow_frac * w)))):  # geodesic dilation inside `weak`
            grown = cv2.dilate(m, step) & (weak | m)
            if np.array_equal(grown, m):
                break
            m = grown
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, kernel(config.close_frac))
    if config.dilate_frac > 0:
        m = cv2.dilate(m, kernel(config.dilate_frac))
    return m.astype(bool)


def _fallback(scene, config: GreyToolConfig) -> Segmentation:
    from dataclasses import replace

    frames = scene.frames
    if config.motion_threshold is None or len(frames) < 2:
        tool = np.stack([grey_tool_mask(f, config) for f in frames])
    else:
        # The motion cue: tissue motion measured away from the confident cores (colour alone, not grown).
        cores = np.stack([grey_tool_mask(f, replace(config, grow_frac=0.0, dilate_frac=0.0)) for f in frames])
        tool = np.stack([grey_tool_mask(f, config, motion_residual(frames, t, cores[t], config.motion_sigma_frac))
                         for t, f in enumerate(frames)])
    masks = np.where(tool, 1, 0).astype(np.int32)
    return Segmentation(masks, endonerf_labels(True), "fallback")


def sam2_segmentation(frames: np.ndarray, checkpoint: str | Path | None, model_config: str | None,
                      device: str = "cpu", prompt_config: GreyToolConfig = GreyToolConfig()) -> Segmentation:
    """Tool masks tracked by SAM 2 / Surgical-SAM-2 from a local checkpoint.

    Prompts: one box per connected component of :func:`grey_tool_mask` on the first frame.

    Args:
        frames: [T, H, W, 3] float RGB in [0, 1].
        checkpoint: local ``.pt`` checkpoint (SAM 2 or Surgical-SAM-2 weights).
        model_config: the matching Hydra config name of the ``sam2`` package, e.g.
            ``configs/sam2.1/sam2.1_hiera_s.yaml``.
    """
    if checkpoint is None or not Path(checkpoint).is_file():
        raise ModelError(f"SAM 2 segmentation needs a local checkpoint (--seg-checkpoint PATH to a SAM 2 / "
                         f"Surgical-SAM-2 .pt file) and --seg-config; got {checkpoint!r}. Nothing is downloaded.")
    if not model_config:
        raise ModelError("SAM 2 segmentation needs --seg-config (the sam2 model config matching the checkpoint, "
                         "e.g. configs/sam2.1/sam2.1_hiera_s.yaml)")
    try:
        import tempfile

        import cv2
        import torch
        from sam2.build_sam import build_sam2_video_predictor  # type: ignore[import-not-found]
    except ImportError as exc:
        raise ModelError(f"SAM 2 segmentation needs the `sam2` package (github.com/facebookresearch/sam2): {exc}") from None
    first = grey_tool_mask(frames[0], prompt_config).astype(np.uint8)
    n, cc, stats, _ = cv2.connectedComponentsWithStats(first, connectivity=8)
    if n <= 1:
        raise DataError("SAM 2 prompts come from the grey-tool detector, which found no instrument in frame 0")
    predictor = build_sam2_video_predictor(model_config, str(checkpoint), device=device)
    T, H, W, _ = frames.shape
    masks = np.zeros((T, H, W), dtype=np.int32)
    with tempfile.TemporaryDirectory() as tmp:
        for i, f in enumerate(frames):  # the video predictor reads a folder of JPEG frames
            cv2.imwrite(str(Path(tmp) / f"{i:05d}.jpg"), (np.clip(f[..., ::-1], 0, 1) * 255).astype(np.uint8))
        with torch.inference_mode():
            state = predictor.init_state(video_path=tmp)
            for k in range(1, n):
                x, y, w, h = stats[k, :4]
                predictor.add_new_points_or_box(state, frame_idx=0, obj_id=k, box=np.array([x, y, x + w, y + h]))
            for t, obj_ids, logits in predictor.propagate_in_video(state):
                for j, oid in enumerate(obj_ids):
                    masks[t][(logits[j, 0] > 0).cpu().numpy()] = int(oid)
    labels = {0: ObjectLabel(0, "tissue", False, "unknown_tissue")}
    labels.update({k: ObjectLabel(k, f"tool_{k}", True, "instrument") for k in range(1, n)})
    return Segmentation(masks, labels, "sam2")


#: name -> back-end(scene, checkpoint, model_config, device, fallback_config) -> Segmentation.
SEGMENTATION_BACKENDS: Registry[Callable[..., Segmentation]] = Registry("segmentation method", ModelError)


@SEGMENTATION_BACKENDS.register("dataset")
def _dataset_masks(scene, checkpoint=None, model_config=None, device="cpu",
                   fallback_config: GreyToolConfig = GreyToolConfig()) -> Segmentation:
    if scene.object_masks is None:
        raise DataError(f"{scene.source}: segmentation method 'dataset' but the scene has no masks")
    return Segmentation(scene.object_masks.astype(np.int32), dict(scene.labels), "dataset")


@SEGMENTATION_BACKENDS.register("sam2")
def _sam2(scene, checkpoint=None, model_config=None, device="cpu",
          fallback_config: GreyToolConfig = GreyToolConfig()) -> Segmentation:
    return sam2_segmentation(scene.frames, checkpoint, model_config, device, fallback_config)


@SEGMENTATION_BACKENDS.register("fallback")
def _fallback_masks(scene, checkpoint=None, model_config=None, device="cpu",
                    fallback_config: GreyToolConfig = GreyToolConfig()) -> Segmentation:
    warnings.warn(f"{scene.source}: no masks and no segmentation model given; detecting instruments by "
                  "colour (grey, low saturation). Expect errors on white fat, glare and smoke; supply masks/ "
                  "or --seg-method sam2 with --seg-checkpoint.", stacklevel=3)
    return _fallback(scene, fallback_config)


def segment_scene(scene, method: str = "auto", checkpoint: str | Path | None = None,
                  model_config: str | None = None, device: str = "cpu",
                  fallback_config: GreyToolConfig = GreyToolConfig()) -> Segmentation:
    """Object-id masks for every frame of ``scene``: "auto" or a registered back-end
    (:data:`SEGMENTATION_BACKENDS`; see the module docstring)."""
    backend = SEGMENTATION_BACKENDS.get(resolve_auto(method, scene.object_masks is not None))
    return backend(scene, checkpoint=checkpoint, model_config=model_config, device=device,
                   fallback_config=fallback_config)
