"""The identification loss (DESIGN.md section 7) and the observations it compares against.

    L = sum_t ||I_t - I^_t||^2 + lambda sum_t ||U(I_t, I_t+1) - U^_t||^2        (lambda = 0.1)
        [+ mu sum_t mean_n |x^_tn - x_tn|^2]                                       (scenes with tracks)

Each term is registered by name in :data:`LOSS_TERMS` ("render", "flow", "track"); the configuration gives the
weights (:meth:`endogsim.identify.IdentifyConfig.term_weights`), and the parts come back by name, so the
history, plots and tables list whatever terms a run used.

Each squared norm is the mean over the frame's valid pixels (RGB in [0, 1] summed over channels; flow in
pixels summed over x and y), so the value does not depend on the image size. I_t are the observed frames,
I^_t the renders of the simulation; U the flow estimator on consecutive observed frames (computed once and
cached in the run folder); U^_t the Gaussian flow of the simulated Gaussians. Frame 0 is the rest state
shared by every simulation, so its render term is a constant and is left out. With a frame stride k
(:class:`~endogsim.identify.IdentifyConfig`) the sums run over t = 0, k, 2k, ... only: the simulation still
covers every frame, but rendering, the costliest part on a CPU, shrinks k-fold.

The track term compares the projections x^_tn of tracked tissue Gaussians moved by the simulation with
the projections x_tn of the same Gaussians moved by the 4D reconstruction (:mod:`endogsim.scene.tracks`):
the reconstruction's estimate of the tissue motion, fitted to every frame, which carries the motion signal
that the render term buries under the reconstruction's own render residual.

Valid pixels: those of deformable objects in the observed object masks (tools and background excluded;
the flow term needs the pixel on tissue at both t and t+1). Without masks: every pixel.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from endogsim.errors import IdentificationError, MaterialError
from endogsim.io.atomic import save_npz_atomic
from endogsim.io.images import resize_frames
from endogsim.priors.flow import FlowConfig, flow_estimator
from endogsim.registry import Registry
from endogsim.scene.forward import Rendered

__all__ = ["Observations", "make_observations", "observed_flow", "LOSS_TERMS", "LOSS_RESIDUALS", "LossValue",
           "identification_loss", "loss_residuals"]


@dataclass
class Observations:
    """What the loss compares against, at the rendering resolution.

    Attributes:
        frames: [T, H, W, 3] observed RGB in [0, 1].
        flow: [T-1, H, W, 2] estimated observed flow t -> t+1 (pixels at this resolution).
        valid_rgb: [T, H, W] bool pixels counted by the render term.
        valid_flow: [T-1, H, W] bool pixels counted by the flow term.
        tracks: [T, N, 2] pixel positions (this resolution) of the reconstruction's tracked tissue Gaussians
            (:mod:`endogsim.scene.tracks`) or None.
        valid_tracks: [T, N] bool: the track lies on a tissue pixel of that frame (in view, not behind a tool).
    """

    frames: torch.Tensor
    flow: torch.Tensor
    valid_rgb: torch.Tensor
    valid_flow: torch.Tensor
    tracks: torch.Tensor | None = None
    valid_tracks: torch.Tensor | None = None


def _frames_key(frames: np.ndarray, estimator: str) -> str:
    h = hashlib.sha1()
    h.update(estimator.encode())
    h.update(str(frames.shape).encode())
    h.update(np.ascontiguousarray((frames * 255).round().astype(np.uint8)).tobytes())
    return h.hexdigest()[:16]


def observed_flow(frames: np.ndarray, flow: FlowConfig = FlowConfig("dis_fine"),
                  cache: str | Path | None = None) -> np.ndarray:
    """Flow of the observed video U(I_t, I_t+1): [T-1, H, W, 2] pixels, cached in ``cache`` (an .npz).

    Args:
        frames: [T, H, W, 3] RGB in [0, 1].
        flow: the estimator (:class:`~endogsim.priors.flow.FlowConfig`; default "dis_fine").
        cache: .npz file keyed by the estimator and a hash of the frames, so a changed video is never
            served a stale flow. Written atomically.
    """
    key = _frames_key(frames, flow.method)
    if cache is not None and Path(cache).is_file():
        with np.load(cache) as d:
            if str(d["key"]) == key:
                return d["flow"].astype(np.float32)
    U = flow_estimator(flow).estimate_sequence(frames).astype(np.float32)
    if cache is not None:
        save_npz_atomic(cache, compressed=True, flow=U, key=np.array(key),
                        meta=np.array(json.dumps({"estimator": flow.method})))
    return U


def make_observations(frames: np.ndarray, flow: np.ndarray, object_masks: np.ndarray | None,
                      deformable_ids: list[int], size: tuple[int, int],
                      tracks: np.ndarray | torch.Tensor | None = None) -> Observations:
    """Observations at the rendering size ``size`` = (W, H).

    Args:
        frames: [T, H0, W0, 3] observed RGB in [0, 1]. flow: [T-1, H0, W0, 2] pixels (full resolution).
        object_masks: [T, H0, W0] object ids or None. deformable_ids: ids whose pixels count.
        tracks: [T, N, 2] pixel positions at the rendering size of the tracked tissue Gaussians, or None.
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
    tr = valid_tr = None
    if tracks is not None:
        tr = torch.as_tensor(tracks, dtype=torch.float32).detach()
        ij = tr.floor().long()
        inside = (ij[..., 0] >= 0) & (ij[..., 0] < W) & (ij[..., 1] >= 0) & (ij[..., 1] < H)
        t_idx = torch.arange(tr.shape[0])[:, None].expand(ij.shape[:2])
        on = torch.from_numpy(tissue)[t_idx, ij[..., 1].clamp(0, H - 1), ij[..., 0].clamp(0, W - 1)]
        valid_tr = inside & on
    return Observations(torch.from_numpy(fr), torch.from_numpy(fl), torch.from_numpy(tissue),
                        torch.from_numpy(tissue[:-1] & tissue[1:]), tr, valid_tr)


def _masked_mean(err: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-frame mean of err [T, H, W] over mask [T, H, W] -> [T]."""
    m = mask.to(err.dtype)
    return (err * m).sum((1, 2)) / m.sum((1, 2)).clamp_min(1.0)


#: name -> term(rendered, observations) -> (frame indices [K], per-frame values [K]) (unweighted, each a mean
#: over the frame's valid pixels); the loss is the weighted sum over terms and frames.
LOSS_TERMS: Registry[Callable[[Rendered, Observations], tuple[list[int], torch.Tensor]]] = Registry(
    "loss term", MaterialError)


@LOSS_TERMS.register("render")
def render_term(rendered: Rendered, obs: Observations) -> tuple[list[int], torch.Tensor]:
    """||I_t - I^_t||^2 per rendered frame t > 0 (frame 0 is the shared rest state: a constant)."""
    idx = torch.as_tensor(rendered.frames, dtype=torch.long)
    sel = idx > 0
    return idx[sel].tolist(), _masked_mean((rendered.rgb[sel] - obs.frames[idx[sel]]).square().sum(-1),
                                           obs.valid_rgb[idx[sel]])


@LOSS_TERMS.register("flow")
def flow_term(rendered: Rendered, obs: Observations) -> tuple[list[int], torch.Tensor]:
    """||U(I_t, I_t+1) - U^_t||^2 per rendered frame t < T - 1 (pixels^2)."""
    idx = torch.as_tensor(rendered.frames, dtype=torch.long)[: rendered.flow.shape[0]]
    return idx.tolist(), _masked_mean((rendered.flow - obs.flow[idx]).square().sum(-1), obs.valid_flow[idx])


@LOSS_TERMS.register("track")
def track_term(rendered: Rendered, obs: Observations) -> tuple[list[int], torch.Tensor]:
    """|x^_t - x_t|^2 per rendered frame t > 0 (pixels^2), mean over the tracks valid at t: the simulated
    Gaussians' projections against the reconstruction's trajectories of the same Gaussians. No frames when
    the scene has no tracks."""
    if rendered.tracks is None or obs.tracks is None:
        return [], torch.zeros(0, dtype=torch.float64)
    idx = torch.as_tensor(rendered.frames, dtype=torch.long)
    sel = idx > 0
    err = (rendered.tracks[sel] - obs.tracks[idx[sel]]).square().sum(-1)  # [K, N]
    m = obs.valid_tracks[idx[sel]].to(err.dtype)
    return idx[sel].tolist(), (err * m).sum(1) / m.sum(1).clamp_min(1.0)


#: name -> residuals(rendered, observations) -> [n] (float64): each term's residuals, scaled so that their squares
#: sum to the term's unweighted value over its frames (the term's pixels of frame t divided by the root of their
#: count). Levenberg-Marquardt (:mod:`endogsim.identify.levenberg_marquardt`) fits them; every term of
#: :data:`LOSS_TERMS` has one.
LOSS_RESIDUALS: Registry[Callable[[Rendered, Observations], torch.Tensor]] = Registry("loss residual", MaterialError)


def _scaled(err: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The entries of err [H, W, C] (or [N, C]) where mask [H, W] (or [N]) holds, over the root of the mask's count."""
    return err[mask].double().flatten() / math.sqrt(max(int(mask.sum()), 1))


@LOSS_RESIDUALS.register("render")
def render_residuals(rendered: Rendered, obs: Observations) -> torch.Tensor:
    """RGB residuals I^_t - I_t of the rendered frames t > 0 (see :func:`render_term`)."""
    parts = [_scaled(rendered.rgb[k] - obs.frames[t], obs.valid_rgb[t])
             for k, t in enumerate(rendered.frames) if t > 0]
    return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.float64)


@LOSS_RESIDUALS.register("flow")
def flow_residuals(rendered: Rendered, obs: Observations) -> torch.Tensor:
    """Flow residuals U^_t - U_t (pixels; see :func:`flow_term`)."""
    parts = [_scaled(rendered.flow[k] - obs.flow[t], obs.valid_flow[t])
             for k, t in enumerate(rendered.frames[: rendered.flow.shape[0]])]
    return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.float64)


@LOSS_RESIDUALS.register("track")
def track_residuals(rendered: Rendered, obs: Observations) -> torch.Tensor:
    """Track residuals x^_tn - x_tn (pixels; see :func:`track_term`)."""
    if rendered.tracks is None or obs.tracks is None:
        return torch.zeros(0, dtype=torch.float64)
    parts = [_scaled(rendered.tracks[k] - obs.tracks[t], obs.valid_tracks[t])
             for k, t in enumerate(rendered.frames) if t > 0]
    return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.float64)


def loss_residuals(rendered: Rendered, obs: Observations, weights: Mapping[str, float]) -> torch.Tensor:
    """[n] float64: every term's residuals times the root of its weight, so that their squares sum to
    :func:`identification_loss`'s total (to rounding: the two sum in another order)."""
    parts = [math.sqrt(w) * LOSS_RESIDUALS.get(name)(rendered, obs) for name, w in weights.items()]
    return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.float64)


@dataclass
class LossValue:
    """The loss of one simulation and where it comes from.

    Attributes:
        total: the weighted sum (differentiable).
        parts: {term: its unweighted sum over frames, ..., "total": total} (floats).
        per_frame: {frame: weighted sum of the terms at that frame} (floats): the loss frame by frame, for
            its noise and for naming the frame of a NaN.
    """

    total: torch.Tensor
    parts: dict[str, float]
    per_frame: dict[int, float]


def identification_loss(rendered: Rendered, obs: Observations, weights: Mapping[str, float]) -> LossValue:
    """The loss, its terms and its frames.

    Args:
        rendered: renders of the simulation at ``rendered.frames`` (rgb [K,H,W,3], flow [K',H,W,2]).
        obs: the observations at the same size.
        weights: {term name: weight} over :data:`LOSS_TERMS` (e.g. the paper's {"render": 1, "flow": 0.1}).
    Raises:
        IdentificationError: a term is NaN/inf; the message names the term and the first such frame.
    """
    total = torch.zeros((), dtype=torch.float64)
    parts: dict[str, float] = {}
    per_frame: dict[int, float] = {}
    for name, w in weights.items():
        frames, values = LOSS_TERMS.get(name)(rendered, obs)
        bad = [t for t, v in zip(frames, values.detach().tolist()) if not math.isfinite(v)]
        if bad:
            raise IdentificationError(f"the {name} term of the loss is NaN/inf at frame {bad[0]} "
                                      f"(frames {bad}); the simulation or its render failed there")
        for t, v in zip(frames, values.detach().tolist()):
            per_frame[t] = per_frame.get(t, 0.0) + w * v
        value = values.sum()
        parts[name] = float(value.detach())
        total = total + w * value
    parts["total"] = float(total.detach())
    return LossValue(total, parts, per_frame)
