"""PSNR / SSIM against known values and a brute-force SSIM reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from endogsim.errors import DataError
from endogsim.evaluate.image_metrics import gaussian_window, mse, psnr, psnr_endonerf, ssim, ssim_map


def _img(h=20, w=24, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(h, w, 3, generator=g, dtype=torch.float64) * 0.8 + 0.1


def test_identical_images():
    a = _img()
    assert psnr(a, a) == math.inf
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert ssim(a, a, mask=torch.ones(20, 24)) == pytest.approx(1.0, abs=1e-12)


def test_constant_offset_gives_known_psnr():
    a = _img()
    assert psnr(a, a + 0.1) == pytest.approx(20.0, abs=1e-9)  # MSE 0.01
    assert psnr(a, a + 0.01) == pytest.approx(40.0, abs=1e-9)
    assert psnr(a.float(), (a + 0.1).float()) == pytest.approx(20.0, abs=1e-4)
    batch = torch.stack([a, a])
    assert psnr(batch, batch + 0.1) == pytest.approx(20.0, abs=1e-9)


def test_masked_psnr_ignores_pixels_outside_the_mask():
    a = _img()
    b = a.clone()
    mask = torch.zeros(20, 24, dtype=torch.bool)
    mask[:, :12] = True
    b[:, :12] += 0.1  # error 0.1 inside the mask
    b[:, 12:] = 0.0  # anything outside
    assert psnr(b, a, mask) == pytest.approx(20.0, abs=1e-9)
    assert float(mse(b, a, mask)) == pytest.approx(0.01, abs=1e-12)


def test_endonerf_protocol_zeroes_tools_and_averages_over_the_whole_image():
    a = _img()
    b = a + 0.1
    tool = torch.zeros(20, 24, dtype=torch.bool)
    tool[5:10, 3:15] = True  # 60 of 480 pixels
    b[tool] = 0.7  # tool pixels differ arbitrarily: they are zeroed in both images
    f = 1 - 60 / 480
    assert psnr_endonerf(b, a, tool) == pytest.approx(-10 * math.log10(f * 0.01), abs=1e-9)
    # the EndoNeRF value exceeds the masked one by 10 log10(#pixels / #tissue pixels)
    assert psnr_endonerf(b, a, tool) - psnr(b, a, ~tool) == pytest.approx(10 * math.log10(1 / f), abs=1e-9)


def _ssim_bruteforce(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM with explicit loops: Gaussian 11x11 window, sigma 1.5, zero padding, channel mean."""
    w = gaussian_window(11, 1.5).numpy()
    h, wd, c = x.shape
    c1, c2 = 0.01**2, 0.03**2
    xp = np.pad(x, ((5, 5), (5, 5), (0, 0)))
    yp = np.pad(y, ((5, 5), (5, 5), (0, 0)))
    out = np.zeros((h, wd))
    for i in range(h):
        for j in range(wd):
            vals = []
            for k in range(c):
                px, py = xp[i:i + 11, j:j + 11, k], yp[i:i + 11, j:j + 11, k]
                mx, my = (w * px).sum(), (w * py).sum()
                vx = (w * px * px).sum() - mx**2
                vy = (w * py * py).sum() - my**2
                cxy = (w * px * py).sum() - mx * my
                vals.append((2 * mx * my + c1) * (2 * cxy + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2)))
            out[i, j] = np.mean(vals)
    return out


def test_ssim_matches_bruteforce_reference():
    a = _img(12, 14, 1)
    b = (a + 0.05 * _img(12, 14, 2) - 0.03).clamp(0, 1)
    ref = _ssim_bruteforce(a.numpy(), b.numpy())
    got = ssim_map(a, b).numpy()
    assert np.allclose(got, ref, atol=1e-10)
    mask = torch.zeros(12, 14)
    mask[2:9, 3:11] = 1
    assert ssim(a, b, mask) == pytest.approx(ref[2:9, 3:11].mean(), abs=1e-10)


def test_ssim_of_constant_offset_on_flat_image_has_closed_form():
    a = torch.full((30, 30, 3), 0.4, dtype=torch.float64)
    b = a + 0.1
    s = ssim_map(a, b)
    mu_x, mu_y, c1 = 0.4, 0.5, 1e-4
    expect = (2 * mu_x * mu_y + c1) / (mu_x**2 + mu_y**2 + c1)  # variances and covariance are 0 inside
    assert float(s[15, 15]) == pytest.approx(expect, abs=1e-12)


def test_ssim_is_differentiable_and_shapes_are_checked():
    a = _img().float().requires_grad_()
    loss = 1 - ssim_map(a, _img(seed=3).float()).mean()
    loss.backward()
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0
    with pytest.raises(DataError, match="shapes differ"):
        psnr(_img(), _img(10, 10))
    with pytest.raises(DataError, match="mask"):
        psnr(_img(), _img(), torch.ones(3, 3))
