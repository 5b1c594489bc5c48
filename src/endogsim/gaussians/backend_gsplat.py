"""gsplat backend of :func:`endogsim.gaussians.render.rasterize` (CUDA only, optional).

Calls ``gsplat.rasterization`` (gsplat 1.5.3, ``pip install gsplat==1.5.3``) with the conventions of the
PyTorch rasteriser: classic mode, eps2d 0.3, same near/far planes and radius clip, unpacked
intermediates, colours already evaluated (SH is done by :mod:`endogsim.gaussians.sh` for both backends),
"RGB+ED" so the last channel is gsplat's alpha-normalised expected depth. The import is guarded: nothing
here is needed on a CPU machine.

Known difference: gsplat's kernels clamp alpha at 0.999 (a constant in its CUDA code), the PyTorch
backend at ``RasterConfig.alpha_max`` = 0.99 as in the reference 3DGS kernel. The two agree to float
precision wherever opacity * G(x) <= 0.99, i.e. everywhere for opacities up to 0.99; above that the
cores of near-opaque splats differ by up to 0.009 in alpha.
"""

from __future__ import annotations

import functools

import torch

from endogsim.gaussians.types import RasterConfig, RenderOutput


@functools.lru_cache(maxsize=1)
def available() -> bool:
    """True when CUDA is usable and ``gsplat`` imports (its kernels compile or are prebuilt)."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:  # ImportError, or a failed JIT build of the CUDA extension
        return False
    return True


def rasterize_gsplat(
    means: torch.Tensor,
    opacities: torch.Tensor,
    rgb: torch.Tensor,
    covars: torch.Tensor,
    K: torch.Tensor,
    viewmat: torch.Tensor,
    width: int,
    height: int,
    *,
    features: torch.Tensor | None,
    background: torch.Tensor,
    config: RasterConfig = RasterConfig(),
):
    """Render with ``gsplat.rasterization``.

    Args:
        means: [N, 3] world centres (metres), CUDA.
        opacities: [N] in [0, 1].
        rgb: [N, 3] colours (SH already evaluated).
        covars: [N, 3, 3] world covariances (metres^2).
        K: [3, 3] intrinsics (pixels).  viewmat: [4, 4] world->camera.
        features: [N, F] extra channels or None.
        background: [3] RGB.
    Returns:
        :class:`endogsim.gaussians.types.RenderOutput`.
    """
    from gsplat import rasterization

    n_feat = 0 if features is None else features.shape[1]
    colors = rgb if features is None else torch.cat([rgb, features.to(rgb.dtype)], 1)
    bg = torch.cat([background, background.new_zeros(n_feat)]) if n_feat else background
    # gsplat's kernels are float32.
    f32 = torch.float32
    render, alphas, meta = rasterization(
        means=means.to(f32),
        quats=None,
        scales=None,
        opacities=opacities.to(f32),
        colors=colors.to(f32),
        viewmats=viewmat[None].to(f32),
        Ks=K[None].to(f32),
        width=width,
        height=height,
        near_plane=config.near_plane,
        far_plane=config.far_plane,
        radius_clip=config.radius_clip,
        eps2d=config.eps2d,
        sh_degree=None,
        packed=False,
        tile_size=16,
        backgrounds=bg[None].to(f32),
        render_mode="RGB+ED",
        rasterize_mode="classic",
        covars=covars.to(f32),
    )
    dtype = means.dtype
    render, alpha = render[0].to(dtype), alphas[0, ..., 0].to(dtype)
    return RenderOutput(
        rgb=render[..., :3],
        depth=render[..., -1],
        alpha=alpha,
        features=render[..., 3 : 3 + n_feat] if n_feat else None,
        meta={"backend": "gsplat", "means2d": meta["means2d"][0], "radii": meta["radii"][0],
              "depths": meta["depths"][0], "n_pairs": int(meta["flatten_ids"].numel())},
    )
