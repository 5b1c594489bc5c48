"""Observed optical flow U(I_t, I_t+1): the flow-estimator interface and its offline default.

Every estimator maps two RGB frames to the forward flow a -> b in pixels: ``flow[y, x] = (dx, dy)`` such
that the content at pixel (x, y) in ``frame_a`` is found at (x + dx, y + dy) in ``frame_b``.

Estimators are registered by name in :data:`FLOW_ESTIMATORS`; a :class:`FlowConfig` (method, weights)
names one, and :func:`flow_estimator` builds it:

* :class:`DISFlow` ("dis"): OpenCV's Dense Inverse Search, needs no weights (the offline default).
* :class:`FineDISFlow` ("dis_fine"): DIS tuned for sub-pixel tissue motion (identification's default).
* :class:`RAFTFlow` ("raft"): torchvision's RAFT architecture with a *local* weights file. Nothing is ever
  downloaded; a missing file or missing torchvision gives a :class:`~endogsim.errors.ModelError` that says
  what to supply.

Example::

    est = flow_estimator(FlowConfig("dis"))    # or FlowConfig("raft", weights="raft_large.pth")
    flow = est.estimate(frames[0], frames[1])  # [H, W, 2] pixels
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from endogsim.errors import ModelError
from endogsim.registry import Registry

__all__ = ["FlowEstimator", "DISFlow", "FineDISFlow", "RAFTFlow", "FlowConfig", "FLOW_ESTIMATORS", "flow_estimator",
           "to_uint8_gray"]


def to_uint8_gray(frame: np.ndarray) -> np.ndarray:
    """[H, W] uint8 grey of an [H, W, 3] RGB frame (float in [0, 1] or uint8)."""
    import cv2

    f = np.asarray(frame)
    if f.ndim != 3 or f.shape[-1] != 3:
        raise ModelError(f"flow estimator expects an [H, W, 3] RGB frame, got shape {f.shape}")
    if f.dtype != np.uint8:
        f = (np.clip(f, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return cv2.cvtColor(f, cv2.COLOR_RGB2GRAY)


class FlowEstimator:
    """Interface: ``estimate(frame_a, frame_b) -> flow`` [H, W, 2] float32, pixels, forward a -> b."""

    name = "base"

    def estimate(self, frame_a: np.ndarray, frame_b: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def estimate_sequence(self, frames: np.ndarray) -> np.ndarray:
        """Flow between consecutive frames of ``frames`` [T, H, W, 3] -> [T-1, H, W, 2] (pixels)."""
        return np.stack([self.estimate(frames[t], frames[t + 1]) for t in range(len(frames) - 1)])


class DISFlow(FlowEstimator):
    """OpenCV Dense Inverse Search optical flow (offline, CPU).

    Args:
        preset: "ultrafast", "fast" or "medium" (OpenCV's DISOPTICAL_FLOW_PRESET_*). "medium" is the
            most accurate and still runs in tens of milliseconds at 640x512.
    """

    name = "dis"
    _PRESETS = {"ultrafast": 0, "fast": 1, "medium": 2}

    def __init__(self, preset: str = "medium") -> None:
        if preset not in self._PRESETS:
            raise ModelError(f"unknown DIS preset {preset!r}; use one of {sorted(self._PRESETS)}")
        self.preset = preset

    def estimate(self, frame_a: np.ndarray, frame_b: np.ndarray) -> np.ndarray:
        """Forward flow [H, W, 2] (pixels) from ``frame_a`` to ``frame_b`` ([H, W, 3] float in [0, 1] or uint8)."""
        import cv2

        a, b = to_uint8_gray(frame_a), to_uint8_gray(frame_b)
        if a.shape != b.shape:
            raise ModelError(f"frames differ in size: {a.shape} vs {b.shape}")
        dis = cv2.DISOpticalFlow_create(self._PRESETS[self.preset])
        flow = dis.calc(a, b, None)
        return flow.astype(np.float32)


class FineDISFlow(FlowEstimator):
    """DIS tuned for the sub-pixel motion of tissue between video frames: 8-pixel patches every 2 pixels,
    down to the finest scale, 20 variational refinement iterations. On the procedural scenes its end-point
    error against the ground-truth tissue flow is about half that of the "medium" preset (0.07 vs 0.13 px
    on ``tiny``), and its bias a third: identification's flow term then has its minimum near the true
    material."""

    name = "dis_fine"

    def estimate(self, frame_a: np.ndarray, frame_b: np.ndarray) -> np.ndarray:
        import cv2

        a, b = to_uint8_gray(frame_a), to_uint8_gray(frame_b)
        if a.shape != b.shape:
            raise ModelError(f"frames differ in size: {a.shape} vs {b.shape}")
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        dis.setPatchSize(8)
        dis.setPatchStride(2)
        dis.setFinestScale(0)
        dis.setVariationalRefinementIterations(20)
        return dis.calc(a, b, None).astype(np.float32)


class RAFTFlow(FlowEstimator):
    """RAFT (Teed and Deng 2020) through torchvision's implementation, with a local weights file.

    Args:
        weights_path: a ``.pth`` state dict for ``torchvision.models.optical_flow.raft_large`` (or
            ``raft_small`` when ``small=True``), e.g. torchvision's ``raft_large_C_T_SKHT_V2`` file copied
            onto this machine. Never downloaded.
        small: use the small architecture.
        iters: refinement iterations (12 = torchvision's default).
        device: torch device ("cpu", "cuda").
    """

    name = "raft"

    def __init__(self, weights_path: str | Path | None, small: bool = False, iters: int = 12, device: str = "cpu") -> None:
        if weights_path is None:
            raise ModelError("RAFT needs a local weights file: pass --flow-weights PATH to a torchvision RAFT state "
                             "dict (e.g. raft_large_C_T_SKHT_V2-ff5fadd5.pth); nothing is downloaded")
        path = Path(weights_path).expanduser()
        if not path.is_file():
            raise ModelError(f"RAFT weights file {path} does not exist: supply a local torchvision RAFT state dict "
                             "(e.g. raft_large_C_T_SKHT_V2-ff5fadd5.pth); nothing is downloaded")
        try:
            from torchvision.models.optical_flow import raft_large, raft_small
        except ImportError as exc:
            raise ModelError("RAFT needs torchvision (pip install torchvision matching your torch), "
                             "or use the offline default flow estimator 'dis'") from exc
        import torch

        model = (raft_small if small else raft_large)(weights=None, progress=False)
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            if isinstance(state, dict) and "state_dict" in state:
                state = state["state_dict"]
            model.load_state_dict(state)
        except Exception as exc:  # noqa: BLE001 - any failure here means the file is not a RAFT state dict
            raise ModelError(f"{path} is not a torchvision RAFT {'small' if small else 'large'} state dict: {exc}") from exc
        self.model = model.eval().to(device)
        self.iters = iters
        self.device = device

    def estimate(self, frame_a: np.ndarray, frame_b: np.ndarray) -> np.ndarray:
        import torch
        import torch.nn.functional as tF

        def prep(f: np.ndarray) -> torch.Tensor:
            f = np.asarray(f, dtype=np.float32)
            if f.max() > 1.5:
                f = f / 255.0
            return torch.from_numpy(f).permute(2, 0, 1)[None].to(self.device) * 2.0 - 1.0

        a, b = prep(frame_a), prep(frame_b)
        H, W = a.shape[-2:]
        # RAFT needs sizes divisible by 8: pad, then crop the flow back.
        ph, pw = (-H) % 8, (-W) % 8
        a, b = tF.pad(a, (0, pw, 0, ph), mode="replicate"), tF.pad(b, (0, pw, 0, ph), mode="replicate")
        with torch.no_grad():
            flow = self.model(a, b, num_flow_updates=self.iters)[-1]
        return flow[0, :, :H, :W].permute(1, 2, 0).cpu().numpy().astype(np.float32)


@dataclass(frozen=True)
class FlowConfig:
    """Which optical-flow estimator to run (shared by reconstruction's point tracks and identification's
    observed flow).

    Attributes:
        method: a registered estimator (:data:`FLOW_ESTIMATORS`): "dis" (OpenCV DIS "medium"), "dis_fine"
            (DIS tuned for sub-pixel tissue motion) or "raft" (needs ``weights``).
        weights: local weights file of a model-backed estimator (never downloaded).
    """

    method: str = "dis"
    weights: str | None = None

    def __post_init__(self) -> None:
        FLOW_ESTIMATORS.get(self.method)  # unknown names are refused here, listing the known ones


#: name -> factory(weights, device) of an estimator.
FLOW_ESTIMATORS: Registry[Callable[..., FlowEstimator]] = Registry("optical-flow estimator", ModelError)


@FLOW_ESTIMATORS.register("dis")
def _dis(weights: str | Path | None = None, device: str = "cpu") -> FlowEstimator:
    return DISFlow("medium")


@FLOW_ESTIMATORS.register("dis_fine")
def _dis_fine(weights: str | Path | None = None, device: str = "cpu") -> FlowEstimator:
    return FineDISFlow()


@FLOW_ESTIMATORS.register("raft")
def _raft(weights: str | Path | None = None, device: str = "cpu") -> FlowEstimator:
    return RAFTFlow(weights, device=device)


def flow_estimator(config: FlowConfig = FlowConfig(), device: str = "cpu") -> FlowEstimator:
    """The estimator ``config`` names (its weights loaded on ``device`` for model-backed ones)."""
    return FLOW_ESTIMATORS.get(config.method)(weights=config.weights, device=device)
