"""The identification loss (DESIGN.md section 7) and the observations it compares against.

    L = sum_t ||I_t - I^_t||^2 + lambda sum_t ||U(I_t, I_t+1) - U^_t||^2        (lambda = 0.1)

Each squared norm is the mean over the frame's valid pixels (RGB in [0, 1] summed over channels; flow in
pixels summed over x and y), so the value does not depend on the image size. I_t are the observed frames,
I^_t the renders of the simulation; U the flow estimator on consecutive observed frames (computed once and
cached in the run folder); U^_t the Gaussian flow of the simulated Gaussians. Frame 0 is the rest state
shared by every simulation, so its render term is a constant and is left out. With a frame stride k
(:class:`~endogsim.identify.IdentifyConfig`) the sums run over t = 0, k, 2k, ... only: the simulation still
covers every frame, but rendering, the costliest part on a CPU, shrinks k-fold.

Valid pixels: those of deformable objects in the observed object masks (tools and background excluded;
the flow term needs the pixel on tissue at both t and t+1). Without masks: every pixel.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from endogsim.scene.forward import Rendered
from endogsim.io.atomic import save_npz_atomic
from endogsim.io.images import resize_frames

__all__ = ["Observations", "make_observations", "observed_flow", "identification_loss"]


@dataclass
class Observations:
    """What the loss compares against, at the rendering resolution.

    Attributes:
        frames: [T, H, W, 3] observed RGB in [0, 1].
        flow: [T-1, H, W, 2] estimated observed flow t -> t+1 (pixels at this resolution).
        valid_rgb: [T, H, W] bool pixels counted by the render term.
        valid_flow: [T-1, H, W] bool pixels counted by the flow term.
    """

    frames: torch.Tensor
    flow: torch.Tensor
    valid_rgb: torch.Tensor
    valid_flow: torch.Tensor


def _frames_key(frames: np.ndarray, estimator: str) -> str:
    h = hashlib.sha1()
    h.update(estimator.encode())
    h.update(str(frames.shape).encode())
    h.update(np.ascontiguousarray((frames * 255).round().astype(np.uint8)).tobytes())
    return h.hexdigest()[:16]


def _fine_dis():
    """DIS tuned for the sub-pixel motion of tissue between video frames (adapter over
    :class:`endogsim.priors.flow.DISFlow`): 8-pixel patches every 2 pixels, down to the finest scale, 20
    variational refinement iterations. On the procedural scenes its end-point error against the
    ground-truth tissue flow is about half that of the "medium" preset (0.07 vs 0.13 px on ``tiny``), and
    its bias is a third: the flow term's minimum then sits near the true material."""
    from endogsim.priors.flow import DISFlow, _to_uint8_gray

    class FineDIS(DISFlow):
        name = "dis_fine"

        def estimate(self, frame_a: np.ndarray, frame_b: np.ndarray) -> np.ndarray:
            import cv2

            dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
            dis.setPatchSize(8)
            dis.setPatchStride(2)
            dis.setFinestScale(0)
            dis.setVariationalRefinementIterations(20)
            return dis.calc(_to_uint8_gray(frame_a), _to_uint8_gray(frame_b), None).astype(np.float32)

    return FineDIS()


def observed_flow(frames: np.ndarray, estimator: str = "dis_fine", weights: str | None = None,
                  cache: str | Path | None = None) -> np.ndarray:
    """Flow of the observed video U(I_t, I_t+1): [T-1, H, W, 2] pixels, cached in ``cache`` (an .npz).

    Args:
        estimator: "dis_fine" (default, see :func:`_fine_dis`), "dis" (OpenCV DIS "medium" preset) or
            "raft" (needs ``weights``, a local file).
    The cache is keyed by the estimator and a hash of the frames, so a changed video is never served a
    stale flow. Written atomically.
    """
    from endogsim.priors.flow import get_flow_estimator

    key = _frames_key(frames, estimator)
    if cache is not None and Path(cache).is_file():
        with np.load(cache) as d:
            if str(d["key"]) == key:
                return d["flow"].astype(np.float32)
    if estimator == "dis_fine":
        est = _fine_dis()
    else:
        est = get_flow_estimator(estimator, **({} if estimator != "raft" else {"weights": weights}))
    flow = est.estimate_sequence(frames).astype(np.float32)
    if cache is not None:
        save_npz_atomic(cache, compressed=True, flow=flow, key=np.array(key),
                        meta=np.array(json.dumps({"estimator": estimator})))
    return flow


def make_observations(frames: np.ndarray, flow: np.ndarray, object_masks: np.ndarray | None,
                      deformable_ids: list[int], size: tuple[int, int]) -> Observations:
    """Observations at the rendering size ``size`` = (W, H).

    Args:
        frames: [T, H0, W0, 3] observed RGB in [0, 1]. flow: [T-1, H0, W0, 2] pixels (full resolution).
        object_masks: [T, H0, W0] object ids or None. deformable_ids: ids whose pixels count.
    """
    W, H = size
    scale = W / frames.shape[2]
    fr = resize_frames(frames.astype(np.float32), size)
    fl = resize_frames(flow.astype(np.float32), size) * scale
    if object_masks is not None:
        tissue = np.isin(object_masks, deformable_ids).astype(np.uint8)
        tissue = resize_frames(tissue, size, nearest=True).astype(bool)
    else:
        tissue = np.ones(fr.shape[:3], bool)
    return Observations(torch.from_numpy(fr), torch.from_numpy(fl), torch.from_numpy(tissue),
                        torch.from_numpy(tissue[:-1] & tissue[1:]))


def _masked_mean(err: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-frame mean of err [T, H, W] over mask [T, H, W] -> [T]."""
    m = mask.to(err.dtype)
    return (err * m).sum((1, 2)) / m.sum((1, 2)).clamp_min(1.0)


def identification_loss(rendered: Rendered, obs: Observations, kind: str = "joint",
                        flow_weight: float = 0.1) -> tuple[torch.Tensor, dict[str, float]]:
    """The loss and its parts.

    Args:
        rendered: renders of the simulation at ``rendered.frames`` (rgb [K,H,W,3], flow [K',H,W,2]).
        obs: the observations at the same size.
        kind: "joint" (render + flow_weight * flow), "render" or "flow" (flow_weight * flow).
    Returns:
        (loss, {"render": float, "flow": float, "total": float}); ``flow`` is the unweighted flow term.
    """
    idx = torch.as_tensor(rendered.frames, dtype=torch.long)
    rgb_sel = idx > 0  # frame 0 is the shared rest state: a constant
    flow_idx = idx[: rendered.flow.shape[0]]
    render_t = _masked_mean((rendered.rgb[rgb_sel] - obs.frames[idx[rgb_sel]]).square().sum(-1),
                            obs.valid_rgb[idx[rgb_sel]])
    flow_t = _masked_mean((rendered.flow - obs.flow[flow_idx]).square().sum(-1), obs.valid_flow[flow_idx])
    render, flow = render_t.sum(), flow_t.sum()
    if kind == "joint":
        total = render + flow_weight * flow
    elif kind == "render":
        total = render
    elif kind == "flow":
        total = flow_weight * flow
    else:
        raise ValueError(kind)
    return total, {"render": float(render.detach()), "flow": float(flow.detach()), "total": float(total.detach())}
