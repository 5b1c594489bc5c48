"""The differentiable Gaussian renderer: one functional entry point, three backends.

``rasterize`` takes activated Gaussian parameters (opacities in [0, 1], scales in metres or full 3x3
covariances) and a :class:`~endogsim.gaussians.camera.Camera`, and returns RGB, expected depth, alpha
and any extra per-Gaussian feature channels, all differentiable w.r.t. every input tensor.

Backends (same conventions, see :class:`RasterConfig`):
  * ``"torch"``: the pure-PyTorch pair-list rasteriser (:mod:`endogsim.gaussians.rasterize_torch`);
    runs on any device and dtype (float64 for gradcheck) and is the reference.
  * ``"warp"``: the same projection, then tile-based compositing in NVIDIA Warp kernels
    (:mod:`endogsim.gaussians.rasterize_warp`); float32, the fast path on CPU.
  * ``"gsplat"``: ``gsplat.rasterization`` on CUDA (:mod:`endogsim.gaussians.backend_gsplat`).
  * ``"auto"``: gsplat when the tensors are on CUDA and gsplat imports; else warp for float32 and
    torch for float64.

Depth convention: ``depth`` is the alpha-normalised expected camera z, sum_i w_i z_i / sum_i w_i
(gsplat's "ED"), 0 where nothing was drawn; ``alpha`` = sum_i w_i = 1 - final transmittance. Multiply
the two to get the unnormalised sum_i w_i z_i.

Example::

    cam = Camera.from_focal(300.0, 320, 256)
    out = rasterize(means, opacities, rgb, cam, quats=quats, scales=scales)   # or covars=F @ S @ F.mT
    loss = (out.rgb - target).square().mean()
    loss.backward()
    # Flow between two time steps (and RGB at t) in one pass: endogsim.gaussians.flow.render_with_flow
"""

from __future__ import annotations

from typing import Literal

import torch

from endogsim.errors import ModelError
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians, covariance_from_scale_rot
from endogsim.gaussians.rasterize_torch import (
    build_pairs,
    project_gaussians,
    rasterize_torch,
)
from endogsim.gaussians.rasterize_warp import bin_gaussians, rasterize_warp
from endogsim.gaussians.sh import sh_to_rgb
from endogsim.gaussians.types import RasterConfig, RenderOutput

Backend = Literal["auto", "torch", "warp", "gsplat"]

__all__ = ["RasterConfig", "RenderOutput", "rasterize", "render_gaussians", "resolve_backend"]


def gsplat_available() -> bool:
    from endogsim.gaussians import backend_gsplat

    return backend_gsplat.available()


def resolve_backend(backend: str, device: torch.device, dtype: torch.dtype = torch.float32) -> str:
    """The backend ``rasterize`` will use for tensors of ``dtype`` on ``device``."""
    if backend not in ("auto", "torch", "warp", "gsplat"):
        raise ModelError(f"unknown render backend {backend!r}; use 'auto', 'torch', 'warp' or 'gsplat'")
    if backend == "auto":
        if device.type == "cuda" and gsplat_available():
            return "gsplat"
        return "warp" if dtype == torch.float32 else "torch"
    if backend == "gsplat":
        if device.type != "cuda":
            raise ModelError("render backend 'gsplat' needs the Gaussians on a CUDA device")
        if not gsplat_available():
            raise ModelError("render backend 'gsplat' requested but gsplat (1.5.3) does not import; "
                             "install it with `pip install gsplat==1.5.3` or use backend='torch'")
    return backend


def _check_shapes(means, opacities, colors, quats, scales, covars, features, background) -> None:
    n = means.shape[0] if means.ndim == 2 else -1
    if means.ndim != 2 or means.shape[1] != 3:
        raise ModelError(f"means has shape {tuple(means.shape)}, expected (N, 3)")
    if tuple(opacities.shape) != (n,):
        raise ModelError(f"opacities has shape {tuple(opacities.shape)}, expected ({n},)")
    if not ((colors.ndim == 2 and tuple(colors.shape) == (n, 3)) or (colors.ndim == 3 and colors.shape[0] == n and colors.shape[2] == 3)):
        raise ModelError(f"colors has shape {tuple(colors.shape)}, expected ({n}, 3) RGB or ({n}, K, 3) SH coefficients")
    if covars is not None:
        if tuple(covars.shape) != (n, 3, 3):
            raise ModelError(f"covars has shape {tuple(covars.shape)}, expected ({n}, 3, 3)")
    else:
        if quats is None or scales is None:
            raise ModelError("rasterize needs either covars or both quats and scales")
        if tuple(quats.shape) != (n, 4) or tuple(scales.shape) != (n, 3):
            raise ModelError(f"quats/scales have shapes {tuple(quats.shape)}/{tuple(scales.shape)}, expected ({n}, 4)/({n}, 3)")
    if features is not None and (features.ndim != 2 or features.shape[0] != n):
        raise ModelError(f"features has shape {tuple(features.shape)}, expected ({n}, F)")
    if background is not None and tuple(background.shape) != (3,):
        raise ModelError(f"background has shape {tuple(background.shape)}, expected (3,)")


def rasterize(
    means: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    camera: Camera,
    *,
    quats: torch.Tensor | None = None,
    scales: torch.Tensor | None = None,
    covars: torch.Tensor | None = None,
    features: torch.Tensor | None = None,
    background: torch.Tensor | None = None,
    backend: Backend = "auto",
    config: RasterConfig = RasterConfig(),
) -> RenderOutput:
    """Render N Gaussians seen by a pinhole camera (differentiable w.r.t. every tensor argument).

    Args:
        means: [N, 3] centres in world coordinates (metres).
        opacities: [N] opacities in [0, 1] (already activated).
        colors: [N, 3] RGB in [0, 1], or [N, K, 3] SH coefficients (K = 1, 4, 9, 16) evaluated along the
            direction camera centre -> Gaussian, colour = max(SH + 0.5, 0).
        camera: the :class:`Camera` (intrinsics, image size, world->camera ``viewmat``).
        quats: [N, 4] rotations (w, x, y, z), any norm. Needed unless ``covars`` is given.
        scales: [N, 3] axis standard deviations (metres, activated). Needed unless ``covars`` is given.
        covars: [N, 3, 3] world covariances (metres^2); replaces quats/scales (e.g. F Sigma F^T).
        features: [N, F] extra per-Gaussian channels composited like colour (no background).
        background: [3] RGB behind the Gaussians; default black.
        backend: "auto", "torch", "warp" or "gsplat" (see the module docstring).
        config: numerical conventions (eps2d, near plane, alpha thresholds); defaults match gsplat.
    Returns:
        :class:`RenderOutput` (rgb [H, W, 3], depth [H, W], alpha [H, W], features [H, W, F] or None, meta).
    """
    _check_shapes(means, opacities, colors, quats, scales, covars, features, background)
    device, dtype = means.device, means.dtype
    which = resolve_backend(backend, device, dtype)
    if covars is None:
        covars = covariance_from_scale_rot(scales, quats)
    viewmat = camera.viewmat.to(device=device, dtype=dtype)
    K = camera.K.to(device=device, dtype=dtype)
    if colors.ndim == 3:
        rgb = sh_to_rgb(colors, means - camera.center().to(device=device, dtype=dtype))
    else:
        rgb = colors
    bg = torch.zeros(3, device=device, dtype=dtype) if background is None else background.to(device=device, dtype=dtype)
    n_feat = 0 if features is None else features.shape[1]

    if which == "gsplat":
        from endogsim.gaussians.backend_gsplat import rasterize_gsplat

        return rasterize_gsplat(means, opacities, rgb, covars, K, viewmat, camera.width, camera.height,
                                features=features, background=bg, config=config)

    proj = project_gaussians(means, covars, opacities, K, viewmat, camera.width, camera.height, config)
    channels = torch.cat([rgb, proj.depths[:, None]] + ([features.to(dtype)] if features is not None else []), 1)
    bg_all = torch.cat([bg, torch.zeros(1 + n_feat, device=device, dtype=dtype)])
    if which == "warp":
        bins = bin_gaussians(proj.means2d, proj.radii, proj.depths, proj.valid, camera.width, camera.height)
        image, alpha = rasterize_warp(proj.means2d, proj.conics, opacities, channels, bg_all,
                                      bins, camera.width, camera.height, config)
        n_pairs = bins.n_pairs
    else:
        pairs = build_pairs(proj, opacities, camera.width, camera.height, config)
        image, alpha = rasterize_torch(proj.means2d, proj.conics, opacities, channels, bg_all,
                                       pairs, camera.width, camera.height, config)
        n_pairs = pairs.n_pairs
    depth = image[..., 3] / alpha.clamp_min(1e-10)
    return RenderOutput(
        rgb=image[..., :3],
        depth=depth,
        alpha=alpha,
        features=image[..., 4:] if features is not None else None,
        meta={"backend": which, "means2d": proj.means2d, "radii": proj.radii, "depths": proj.depths,
              "n_pairs": n_pairs},
    )


def render_gaussians(
    gaussians: Gaussians,
    camera: Camera,
    *,
    covars: torch.Tensor | None = None,
    features: torch.Tensor | None = None,
    background: torch.Tensor | None = None,
    backend: Backend = "auto",
    sh_degree: int | None = None,
    config: RasterConfig = RasterConfig(),
) -> RenderOutput:
    """Render a :class:`Gaussians` model: applies the activations (sigmoid opacity, exp scales, SH).

    Args:
        gaussians: the model (unconstrained parameters).
        camera: the camera.
        covars: [N, 3, 3] world covariances (metres^2) to use instead of the model's rotation and scale
            (the simulator passes F Sigma F^T).
        features: [N, F] extra channels to composite.
        background: [3] RGB behind the Gaussians.
        backend: "auto", "torch", "warp" or "gsplat".
        sh_degree: evaluate SH only up to this degree (default: all stored coefficients).
    """
    sh = gaussians.sh
    if sh_degree is not None:
        sh = sh[:, : (sh_degree + 1) ** 2]
    return rasterize(
        gaussians.means, gaussians.opacities, sh, camera,
        quats=None if covars is not None else gaussians.quats,
        scales=None if covars is not None else gaussians.scales,
        covars=covars, features=features, background=background, backend=backend, config=config,
    )
