"""Image-quality metrics: PSNR (plain, masked, EndoNeRF protocol) and SSIM. Pure PyTorch.

Images are float tensors in [0, 1] with channels last: ``[H, W, C]`` or a batch ``[B, H, W, C]``.
Masks are ``[H, W]`` (or ``[B, H, W]``) bool/float, 1 on the pixels that count.

Two evaluation protocols for endoscopic video with instruments:

* **masked** (:func:`psnr` with ``mask``): mean squared error over the tissue pixels only;
  ``psnr_masked`` in the reconstruction's ``metrics.json``.
* **EndoNeRF** (:func:`psnr_endonerf`): tool pixels are set to 0 in both images and the error is
  averaged over the *whole* image (the protocol of EndoNeRF, EndoGaussian, Endo-4DGS, Deform3DGS). The
  zeroed pixels count as perfect, so this value is higher than the masked one by
  ``10 log10(#pixels / #tissue pixels)``.

SSIM is the standard Gaussian-window SSIM of Wang et al. 2004 as implemented in 3D Gaussian Splatting's
``ssim`` (11x11 window, sigma 1.5, K1 = 0.01, K2 = 0.03, zero padding of 5 so the map has the image size,
data range 1). With a mask, the SSIM map is averaged over the masked pixels.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from endogsim.errors import DataError

__all__ = ["mse", "masked_l1", "psnr", "psnr_endonerf", "ssim", "ssim_map", "gaussian_window"]


def masked_l1(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean absolute error of RGB images ``pred``, ``gt`` [H, W, 3] over the pixels of ``mask`` [H, W] (the
    reconstruction's photometric loss)."""
    return ((pred - gt).abs() * mask[..., None]).sum() / (mask.sum() * 3).clamp_min(1.0)


def _as_batch(img: torch.Tensor) -> torch.Tensor:
    if img.ndim == 3:
        return img[None]
    if img.ndim != 4:
        raise DataError(f"image must be [H, W, C] or [B, H, W, C], got shape {tuple(img.shape)}")
    return img


def _check(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    pred, gt = torch.as_tensor(pred), torch.as_tensor(gt)
    if pred.shape != gt.shape:
        raise DataError(f"image shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    p, g = _as_batch(pred).double(), _as_batch(gt).double()
    m = None
    if mask is not None:
        m = torch.as_tensor(mask).to(p.device)
        m = m[None] if m.ndim == 2 else m
        if tuple(m.shape) != tuple(p.shape[:3]):
            raise DataError(f"mask has shape {tuple(torch.as_tensor(mask).shape)}, images are {tuple(pred.shape)}")
        m = m.double()
    return p, g, m


def mse(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared error over all channels of the (masked) pixels; a 0-d float64 tensor.

    Args:
        pred, gt: [H, W, C] or [B, H, W, C] images.
        mask: optional [H, W] or [B, H, W]; pixels with weight 0 are left out.
    """
    p, g, m = _check(pred, gt, mask)
    err = (p - g).square()
    if m is None:
        return err.mean()
    return (err * m[..., None]).sum() / (m.sum() * p.shape[-1]).clamp_min(1e-12)


def psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB, 10 log10(range^2 / MSE) (masked MSE when ``mask`` is given).

    Identical images give ``inf``. Shapes as in :func:`mse`.
    """
    e = float(mse(pred, gt, mask))
    return math.inf if e == 0.0 else 10.0 * math.log10(data_range**2 / e)


def psnr_endonerf(pred: torch.Tensor, gt: torch.Tensor, tool_mask: torch.Tensor) -> float:
    """PSNR (dB) under the EndoNeRF protocol: tool pixels zeroed in both images, MSE over the whole image.

    Args:
        pred, gt: [H, W, C] or [B, H, W, C] images in [0, 1].
        tool_mask: [H, W] or [B, H, W], True (1) on instrument pixels.
    """
    p, g, m = _check(pred, gt, tool_mask)
    keep = (1.0 - m)[..., None]
    return psnr(p * keep, g * keep)


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """[size, size] normalised 2D Gaussian window (outer product of the 1D one)."""
    x = torch.arange(size, dtype=dtype) - size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return g[:, None] * g[None, :]


def ssim_map(pred: torch.Tensor, gt: torch.Tensor, window_size: int = 11, sigma: float = 1.5,
             data_range: float = 1.0) -> torch.Tensor:
    """Per-pixel SSIM, averaged over channels: [H, W] (or [B, H, W] for a batch). Differentiable.

    Local statistics use a Gaussian window with zero padding (the 3DGS / pytorch-ssim convention).
    Computed in the dtype of ``pred`` (use float64 for metrics, float32 inside a loss).
    """
    if pred.shape != gt.shape:
        raise DataError(f"image shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    batched = pred.ndim == 4
    s = _ssim_nchw(_as_batch(pred).permute(0, 3, 1, 2), _as_batch(gt).permute(0, 3, 1, 2).to(pred.dtype),
                   window_size, sigma, data_range)
    return s if batched else s[0]


def _ssim_nchw(p: torch.Tensor, g: torch.Tensor, window_size: int, sigma: float, data_range: float) -> torch.Tensor:
    """Per-pixel SSIM [B, H, W] of two [B, C, H, W] batches (of any memory layout), averaged over channels."""
    c = p.shape[1]
    # The window is separable: two 1-D passes (2 x 11 taps) equal the 11 x 11 one, zero padding included.
    g1 = gaussian_window(window_size, sigma, p.dtype).to(p.device)[window_size // 2]
    g1 = g1 / g1.sum()
    wx = g1.view(1, 1, 1, window_size).expand(c, 1, 1, window_size)
    wy = g1.view(1, 1, window_size, 1).expand(c, 1, window_size, 1)
    pad = window_size // 2

    def blur(x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(x, wx, padding=(0, pad), groups=c), wy, padding=(pad, 0), groups=c)

    mu_p, mu_g = blur(p), blur(g)
    var_p = blur(p * p) - mu_p**2
    var_g = blur(g * g) - mu_g**2
    cov = blur(p * g) - mu_p * mu_g
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * mu_p * mu_g + c1) * (2 * cov + c2)) / ((mu_p**2 + mu_g**2 + c1) * (var_p + var_g + c2))
    return s.mean(1)


def ssim(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None, window_size: int = 11,
         sigma: float = 1.5, data_range: float = 1.0) -> float:
    """Mean SSIM (float) of two images [H, W, C] / [B, H, W, C]; over ``mask`` pixels when given."""
    p, g, m = _check(pred, gt, mask)
    # One image at a time (the blurs' working set stays in cache), each copied to a contiguous [1, C, H, W]:
    # PyTorch's depthwise convolutions on CPU take 4x longer on the channels-last views ssim_map blurs (a
    # 63-frame clip at 640 x 512: 11 s instead of 35 on a laptop core; the same map up to rounding, 3e-15).
    # ssim_map, the reconstruction's loss, keeps the views: its numbers are part of every reconstruction.
    def nchw(x: torch.Tensor) -> torch.Tensor:
        return x.permute(0, 3, 1, 2).contiguous()

    s = torch.cat([_ssim_nchw(nchw(p[i:i + 1]), nchw(g[i:i + 1]), window_size, sigma, data_range)
                   for i in range(p.shape[0])])
    if m is None:
        return float(s.mean())
    return float((s * m).sum() / m.sum().clamp_min(1e-12))
