"""Gaussian flow: the 2D optical flow that moving Gaussians induce between two time steps.

A Gaussian whose 2D footprint goes from (mu_t, Sigma_t) to (mu_t+1, Sigma_t+1) carries the point x of
its footprint to mu_t+1 + A (x - mu_t) with A = Sigma_t+1^(1/2) Sigma_t^(-1/2). Blending with the
compositing weights w_i of time t gives the rendered flow at pixel x (DESIGN.md section 5):

    flow(x) = sum_i w_i [ (A_i - I)(x - mu_i,t) + (mu_i,t+1 - mu_i,t) ].

Each term is affine in x, so with x' = x - c (c the principal point, for float32 precision),
flow(x) = (sum_i w_i M_i) x' + sum_i w_i b_i with M_i = A_i - I and b_i = (mu_i,t+1 - mu_i,t) - M_i (mu_i,t - c).
The six numbers (M_i, b_i) are composited as ordinary feature channels by the same ``rasterize`` call
that renders colour, so one pass gives RGB, depth, alpha and flow, on either backend, differentiably.

Sigma here is the projected 2D covariance *without* the eps2d anti-aliasing dilation: the dilation is a
screen-space filter, not motion, and with it a pure scaling would not map to A = s I. Like the formula,
the flow is not normalised by alpha (at a half-covered pixel it is weighted by the coverage).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from endogsim.errors import ModelError
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import covariance_from_scale_rot
from endogsim.gaussians.rasterize_torch import project_gaussians
from endogsim.gaussians.render import Backend, rasterize
from endogsim.gaussians.types import RasterConfig, RenderOutput

FLOW_CHANNELS = 6  # M00 M01 M10 M11 b0 b1
_FLOW_EPS = 1e-6  # pixels^2 added to both 2D covariances so the inverse square root of a needle stays finite


@dataclass
class FlowRenderOutput(RenderOutput):
    """:class:`RenderOutput` plus ``flow`` [H, W, 2]: pixel displacement (dx, dy) from t to t+1 (pixels)."""

    flow: torch.Tensor | None = None


def sqrtm_2x2(m: torch.Tensor) -> torch.Tensor:
    """Square root of symmetric positive-definite 2x2 matrices [N, 2, 2] (closed form, differentiable).

    sqrt(M) = (M + s I) / sqrt(tr M + 2 s) with s = sqrt(det M).
    """
    det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
    s = torch.sqrt(det.clamp_min(1e-30))
    t = torch.sqrt(m[:, 0, 0] + m[:, 1, 1] + 2 * s)
    eye = torch.eye(2, dtype=m.dtype, device=m.device)
    return (m + s[:, None, None] * eye) / t[:, None, None]


def _inv_2x2(m: torch.Tensor) -> torch.Tensor:
    det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
    adj = torch.stack([torch.stack([m[:, 1, 1], -m[:, 0, 1]], -1), torch.stack([-m[:, 1, 0], m[:, 0, 0]], -1)], -2)
    return adj / det[:, None, None]


def gaussian_flow_coefficients(
    means: torch.Tensor,
    covars: torch.Tensor,
    means_next: torch.Tensor,
    covars_next: torch.Tensor,
    opacities: torch.Tensor,
    camera: Camera,
    config: RasterConfig = RasterConfig(),
) -> torch.Tensor:
    """Per-Gaussian affine flow coefficients, to composite as features.

    Args:
        means, means_next: [N, 3] world centres at t and t+1 (metres).
        covars, covars_next: [N, 3, 3] world covariances at t and t+1 (metres^2).
        opacities: [N] in [0, 1] (only for culling in the projection).
        camera: the camera (the same at both times).
    Returns:
        [N, 6] (M00, M01, M10, M11, b0, b1); see the module docstring. Culled Gaussians get zeros.
    """
    dtype, device = means.dtype, means.device
    K = camera.K.to(device=device, dtype=dtype)
    V = camera.viewmat.to(device=device, dtype=dtype)
    p0 = project_gaussians(means, covars, opacities, K, V, camera.width, camera.height, config)
    p1 = project_gaussians(means_next, covars_next, opacities, K, V, camera.width, camera.height, config)
    eye = torch.eye(2, dtype=dtype, device=device)
    ok = p0.valid & p1.valid
    # Culled Gaussians never reach the image; give them identity footprints so nothing is NaN.
    c0 = torch.where(ok[:, None, None], p0.cov2d, eye) + _FLOW_EPS * eye
    c1 = torch.where(ok[:, None, None], p1.cov2d, eye) + _FLOW_EPS * eye
    A = sqrtm_2x2(c1) @ _inv_2x2(sqrtm_2x2(c0))
    M = A - eye
    centre = K[:2, 2]
    b = (p1.means2d - p0.means2d) - (M @ (p0.means2d - centre)[:, :, None])[:, :, 0]
    coeffs = torch.cat([M.reshape(-1, 4), b], 1)
    return torch.where(ok[:, None], coeffs, torch.zeros_like(coeffs))


def flow_from_channels(channels: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Evaluate composited affine coefficients [H, W, 6] at the pixel centres -> flow [H, W, 2] (pixels)."""
    H, W = channels.shape[:2]
    dtype, device = channels.dtype, channels.device
    cx, cy = float(camera.K[0, 2]), float(camera.K[1, 2])
    xs = torch.arange(W, dtype=dtype, device=device) + 0.5 - cx
    ys = torch.arange(H, dtype=dtype, device=device) + 0.5 - cy
    X, Y = xs[None, :].expand(H, W), ys[:, None].expand(H, W)
    fx = channels[..., 0] * X + channels[..., 1] * Y + channels[..., 4]
    fy = channels[..., 2] * X + channels[..., 3] * Y + channels[..., 5]
    return torch.stack([fx, fy], -1)


def render_with_flow(
    means: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    camera: Camera,
    means_next: torch.Tensor,
    *,
    quats: torch.Tensor | None = None,
    scales: torch.Tensor | None = None,
    covars: torch.Tensor | None = None,
    covars_next: torch.Tensor | None = None,
    features: torch.Tensor | None = None,
    background: torch.Tensor | None = None,
    backend: Backend = "auto",
    config: RasterConfig = RasterConfig(),
) -> FlowRenderOutput:
    """Render the scene at time t and the Gaussian flow t -> t+1 in one rasterisation pass.

    Args:
        means: [N, 3] world centres at t (metres).
        opacities: [N] in [0, 1].
        colors: [N, 3] RGB or [N, K, 3] SH coefficients.
        camera: the camera (fixed between t and t+1).
        means_next: [N, 3] world centres at t+1 (metres).
        quats, scales: [N, 4], [N, 3] (metres) giving the covariance at t when ``covars`` is None.
        covars: [N, 3, 3] world covariances at t (metres^2).
        covars_next: [N, 3, 3] at t+1; default: the covariance at t (pure translation).
        features: [N, F] extra channels; background: [3] RGB; backend, config: as :func:`rasterize`.
    Returns:
        :class:`FlowRenderOutput`: rgb, depth, alpha, features at t, flow [H, W, 2] in pixels.
    """
    if covars is None:
        if quats is None or scales is None:
            raise ModelError("render_with_flow needs either covars or both quats and scales")
        covars = covariance_from_scale_rot(scales, quats)
    if covars_next is None:
        covars_next = covars
    if means_next.shape != means.shape or covars_next.shape != covars.shape:
        raise ModelError(f"means_next {tuple(means_next.shape)} / covars_next {tuple(covars_next.shape)} must match "
                         f"means {tuple(means.shape)} / covars {tuple(covars.shape)}")
    coeffs = gaussian_flow_coefficients(means, covars, means_next, covars_next, opacities, camera, config)
    n_user = 0 if features is None else features.shape[1]
    feats = coeffs if features is None else torch.cat([features.to(coeffs.dtype), coeffs], 1)
    out = rasterize(means, opacities, colors, camera, covars=covars, features=feats, background=background,
                    backend=backend, config=config)
    flow = flow_from_channels(out.features[..., n_user:], camera)
    return FlowRenderOutput(
        rgb=out.rgb, depth=out.depth, alpha=out.alpha,
        features=out.features[..., :n_user] if n_user else None, meta=out.meta, flow=flow,
    )


def render_flow(means, opacities, camera, means_next, **kwargs) -> torch.Tensor:
    """Only the flow [H, W, 2] (pixels); same arguments as :func:`render_with_flow` minus colours."""
    colors = torch.zeros_like(means)
    return render_with_flow(means, opacities, colors, camera, means_next, **kwargs).flow
