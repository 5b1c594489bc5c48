"""Observed optical flow U(I_t, I_t+1): the flow-estimator interface and its offline default.

Every estimator maps two RGB frames to the forward flow a -> b in pixels: ``flow[y, x] = (dx, dy)`` such
that the content at pixel (x, y) in ``frame_a`` is found at (x + dx, y + dy) in ``frame_b``.

* :class:`DISFlow`: OpenCV's Dense Inverse Search, needs no weights (the offline default).
* :class:`RAFTFlow`: torchvision's RAFT architecture with a *local* weights file. Nothing is ever
  downloaded; a missing file or missing torchvision gives a :class:`~endogsim.errors.ModelError` that says
  what to supply.

Example::

    est = get_flow_estimator("dis")            # or get_flow_estimator("raft", weights="raft_large.pth")
    flow = est.estimate(frames[0], frames[1])  # [H, W, 2] pixels
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from endogsim.errors import ModelError

__all__ = ["FlowEstimator", "DISFlow", "RAFTFlow", "get_flow_estimator", "FLOW_ESTIMATORS"]


def _to_uint8_gray(frame: np.ndarray) -> np.ndarray:
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

        a, b = _to_uint8_gray(frame_a), _to_uint8_gray(frame_b)
        if a.shape != b.shape:
            raise ModelError(f"frames differ in size: {a.shape} vs {b.shape}")
        dis = cv2.DISOpticalFlow_create(self._PRESETS[self.preset])
        flow = dis.calc(a, b, None)
        return flow.astype(np.float32)


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


FLOW_ESTIMATORS = ("dis", "raft")


def get_flow_estimator(name: str = "dis", weights: str | Path | None = None, **kwargs) -> FlowEstimator:
    """Factory: ``"dis"`` (offline default; kwargs: preset) or ``"raft"`` (needs ``weights``; kwargs: small, iters, device)."""
    key = name.lower()
    if key == "dis":
        return DISFlow(**kwargs)
    if key == "raft":
        return RAFTFlow(weights, **kwargs)
    raise ModelError(f"unknown flow estimator {name!r}; use one of {', '.join(FLOW_ESTIMATORS)}")
