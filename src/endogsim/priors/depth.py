"""Depth priors for reconstruction: the dataset's depth, model adapters, and an offline fallback.

Entry point: :func:`estimate_depth` returns a :class:`DepthPrior` (depth in metres for every frame and
where it came from). Back-ends, registered by name in :data:`DEPTH_BACKENDS`:

* ``"dataset"``: the scene's own depth (EndoNeRF stereo depth, procedural ground truth).
* ``"pi3"``: the pi3 feed-forward geometry model (Wang et al. 2025; ``pi3`` package) with a *local*
  weights file. Its depth is up to scale; it is rescaled so the median depth equals the working distance.
* ``"depth_anything"``: Depth-Anything V2 (``depth_anything_v2`` package) with a local ``.pth``
  checkpoint. It predicts relative inverse depth; converted to depth and rescaled the same way.
* ``"fallback"``: no model, no data: a smooth bowl at a nominal endoscopic working distance (default
  7 cm), deeper at the image centre, built from the intrinsics only. It is a *placeholder* that lets
  reconstruction start; the photometric loss then moves the Gaussians. A monocular fixed camera cannot
  observe absolute depth, so geometry from this prior is plausible, not measured: a warning says so.
* ``"auto"``: dataset depth when present, else the fallback (never a model: weights are never implied).

Nothing here downloads anything. Missing packages or weights raise :class:`~endogsim.errors.ModelError`
naming what to supply.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from endogsim.errors import DataError, ModelError
from endogsim.priors import resolve_auto
from endogsim.registry import Registry

__all__ = ["DepthPrior", "estimate_depth", "fallback_depth", "pi3_depth", "depth_anything_depth",
           "DEPTH_BACKENDS", "DEFAULT_WORKING_DISTANCE"]
#: Nominal camera-to-tissue distance of laparoscopy / robotic endoscopy (metres): 5-10 cm.
DEFAULT_WORKING_DISTANCE = 0.07


@dataclass
class DepthPrior:
    """Per-frame depth used to initialise (and optionally supervise) the reconstruction.

    Attributes:
        depth: [T, H, W] float32 camera z in metres; 0 where unknown.
        source: "dataset", "pi3", "depth_anything" or "fallback".
        metric: True when the values are measurements (dataset), False for up-to-scale or placeholder
            depth; the reconstruction supervises only with metric depth by default.
    """

    depth: np.ndarray
    source: str
    metric: bool


def fallback_depth(K: np.ndarray, width: int, height: int, num_frames: int = 1,
                   working_distance: float = DEFAULT_WORKING_DISTANCE, bowl: float = 0.15) -> np.ndarray:
    """A smooth bowl-shaped depth map from the intrinsics alone (no image content).

    The endoscope looks into a cavity: the centre of view is farthest, the periphery closer. Depth is
    ``z = d * (1 - bowl * r^2)`` with ``r`` the angle off the optical axis, tan(theta), normalised by
    its value at the image corner (so the corners sit ``bowl`` closer than the centre).

    Args:
        K: [3, 3] intrinsics (pixels).
        width, height: image size (pixels).
        num_frames: T, the number of copies stacked.
        working_distance: d, depth on the optical axis (metres), 0.05-0.10 for endoscopy.
        bowl: relative depth change from centre to corner (0 gives a fronto-parallel plane).
    Returns:
        [T, H, W] float32 depth in metres.
    """
    if not 0.0 < working_distance < 10.0:
        raise DataError(f"working_distance {working_distance} m is not a plausible camera distance")
    if not 0.0 <= bowl < 1.0:
        raise DataError(f"bowl {bowl} must be in [0, 1)")
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = (np.arange(width) + 0.5 - cx) / fx
    v = (np.arange(height) + 0.5 - cy) / fy
    r2 = u[None, :] ** 2 + v[:, None] ** 2
    r2_corner = max(((0 - cx) / fx) ** 2 + ((0 - cy) / fy) ** 2, ((width - cx) / fx) ** 2 + ((height - cy) / fy) ** 2)
    z = working_distance * (1.0 - bowl * r2 / r2_corner)
    return np.broadcast_to(z.astype(np.float32), (num_frames, height, width)).copy()


def _rescale_to_working_distance(depth: np.ndarray, working_distance: float) -> np.ndarray:
    valid = depth > 0
    if not valid.any():
        raise ModelError("depth model returned no positive depth")
    return (depth * (working_distance / np.median(depth[valid]))).astype(np.float32)


def pi3_depth(frames: np.ndarray, weights: str | Path | None, device: str = "cpu",
              working_distance: float = DEFAULT_WORKING_DISTANCE) -> np.ndarray:
    """Depth [T, H, W] (metres, rescaled) from pi3 with a local weights file.

    Args:
        frames: [T, H, W, 3] float RGB in [0, 1].
        weights: path to the pi3 checkpoint (``model.safetensors`` or ``.pt``/``.pth``).
    """
    if weights is None or not Path(weights).is_file():
        raise ModelError(f"pi3 depth needs a local weights file (--depth-weights PATH to the pi3 "
                         f"model.safetensors); got {weights!r}. Nothing is downloaded.")
    try:
        import torch
        from pi3.models.pi3 import Pi3  # type: ignore[import-not-found]
    except ImportError as exc:
        raise ModelError(f"pi3 depth needs the `pi3` package (github.com/yyfz/Pi3, pip install -e .): {exc}") from None
    model = Pi3()
    w = str(weights)
    if w.endswith(".safetensors"):
        from safetensors.torch import load_file  # type: ignore[import-not-found]

        state = load_file(w)
    else:
        state = torch.load(w, map_location="cpu")
    model.load_state_dict(state)
    model = model.to(device).eval()
    T, H, W, _ = frames.shape
    # pi3 wants sizes that are multiples of its 14-pixel patch.
    h14, w14 = max(14, H // 14 * 14), max(14, W // 14 * 14)
    x = torch.as_tensor(frames, dtype=torch.float32).permute(0, 3, 1, 2)
    x = torch.nn.functional.interpolate(x, size=(h14, w14), mode="bilinear", align_corners=False)
    with torch.no_grad():
        out = model(x[None].to(device))
    z = out["local_points"][0, ..., 2]  # [T, h14, w14] camera-frame z, up to scale
    z = torch.nn.functional.interpolate(z[:, None], size=(H, W), mode="bilinear", align_corners=False)[:, 0]
    return _rescale_to_working_distance(z.clamp_min(0).cpu().numpy(), working_distance)


def depth_anything_depth(frames: np.ndarray, weights: str | Path | None, device: str = "cpu",
                         encoder: str = "vits", working_distance: float = DEFAULT_WORKING_DISTANCE) -> np.ndarray:
    """Depth [T, H, W] (metres, rescaled) from Depth-Anything V2 with a local checkpoint.

    Depth-Anything predicts relative inverse depth (disparity); depth = 1 / disparity, then the median is
    set to the working distance. Not metric: use it for initialisation, not as supervision.

    Args:
        frames: [T, H, W, 3] float RGB in [0, 1].
        weights: path to ``depth_anything_v2_{encoder}.pth``.
        encoder: "vits", "vitb" or "vitl" (must match the checkpoint).
    """
    if weights is None or not Path(weights).is_file():
        raise ModelError(f"Depth-Anything depth needs a local checkpoint (--depth-weights PATH to "
                         f"depth_anything_v2_{encoder}.pth); got {weights!r}. Nothing is downloaded.")
    try:
        import torch
        from depth_anything_v2.dpt import DepthAnythingV2  # type: ignore[import-not-found]
    except ImportError as exc:
        raise ModelError("Depth-Anything depth needs the `depth_anything_v2` package "
                         f"(github.com/DepthAnything/Depth-Anything-V2): {exc}") from None
    cfgs = {"vits": dict(features=64, out_channels=[48, 96, 192, 384]),
            "vitb": dict(features=128, out_channels=[96, 192, 384, 768]),
            "vitl": dict(features=256, out_channels=[256, 512, 1024, 1024])}
    if encoder not in cfgs:
        raise ModelError(f"unknown Depth-Anything encoder {encoder!r}; use one of {sorted(cfgs)}")
    model = DepthAnythingV2(encoder=encoder, **cfgs[encoder])
    model.load_state_dict(torch.load(str(weights), map_location="cpu"))
    model = model.to(device).eval()
    out = []
    for f in frames:
        bgr = (np.clip(f[..., ::-1], 0, 1) * 255).astype(np.uint8)
        disp = model.infer_image(bgr)  # [H, W] relative inverse depth
        out.append(1.0 / np.maximum(disp, np.percentile(disp, 1) * 0.5 + 1e-6))
    return _rescale_to_working_distance(np.stack(out), working_distance)


#: name -> back-end(scene, weights, device, working_distance) -> DepthPrior.
DEPTH_BACKENDS: Registry[Callable[..., DepthPrior]] = Registry("depth method", ModelError)


@DEPTH_BACKENDS.register("dataset")
def _dataset_depth(scene, weights=None, device="cpu", working_distance=DEFAULT_WORKING_DISTANCE) -> DepthPrior:
    if scene.depth is None:
        raise DataError(f"{scene.source}: depth method 'dataset' but the scene has no depth maps")
    return DepthPrior(scene.depth.astype(np.float32), "dataset", True)


@DEPTH_BACKENDS.register("pi3")
def _pi3(scene, weights=None, device="cpu", working_distance=DEFAULT_WORKING_DISTANCE) -> DepthPrior:
    return DepthPrior(pi3_depth(scene.frames, weights, device, working_distance), "pi3", False)


@DEPTH_BACKENDS.register("depth_anything")
def _depth_anything(scene, weights=None, device="cpu", working_distance=DEFAULT_WORKING_DISTANCE) -> DepthPrior:
    return DepthPrior(depth_anything_depth(scene.frames, weights, device, working_distance=working_distance),
                      "depth_anything", False)


@DEPTH_BACKENDS.register("fallback")
def _fallback_depth(scene, weights=None, device="cpu", working_distance=DEFAULT_WORKING_DISTANCE) -> DepthPrior:
    warnings.warn(f"{scene.source}: no depth maps and no depth model given; using the offline fallback "
                  f"(a smooth bowl at {working_distance * 100:.0f} cm). Geometry will be plausible, not "
                  "measured; supply depth/ or --depth-method pi3|depth_anything with --depth-weights.",
                  stacklevel=3)
    return DepthPrior(fallback_depth(scene.K, scene.width, scene.height, scene.num_frames, working_distance),
                      "fallback", False)


def estimate_depth(scene, method: str = "auto", weights: str | Path | None = None, device: str = "cpu",
                   working_distance: float = DEFAULT_WORKING_DISTANCE) -> DepthPrior:
    """Depth for every frame of ``scene`` (a :class:`~endogsim.io.scene.Scene`).

    Args:
        scene: the sequence (frames [T, H, W, 3], K, optional depth).
        method: "auto" or a registered back-end (:data:`DEPTH_BACKENDS`; see the module docstring).
        weights: local weights file for "pi3" / "depth_anything".
        device: torch device for the model adapters.
        working_distance: metres; centre depth of the fallback and median depth of model outputs.
    """
    backend = DEPTH_BACKENDS.get(resolve_auto(method, scene.depth is not None))
    return backend(scene, weights=weights, device=device, working_distance=working_distance)
