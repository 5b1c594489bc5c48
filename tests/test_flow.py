"""Tests of Gaussian flow (endogsim.gaussians.flow) against analytic answers."""

from __future__ import annotations

import torch

from endogsim.gaussians.camera import Camera
from endogsim.gaussians.flow import render_flow, render_with_flow, sqrtm_2x2
from endogsim.gaussians.render import rasterize

F, W, H = 60.0, 40, 32


def _camera(dtype=torch.float64):
    K = torch.tensor([[F, 0, W / 2 + 0.25], [0, F * 1.1, H / 2 - 0.4], [0, 0, 1]], dtype=dtype)
    return Camera(K, W, H, torch.eye(4, dtype=dtype))


def _flat_gaussians(n, z, seed=0, dtype=torch.float64):
    """Gaussians in the plane at depth z, flat along z: their footprint then does not depend on x/z."""
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n, 2, generator=g, dtype=dtype) - 0.5) * torch.tensor([W / F, H / F], dtype=dtype) * z * 0.8
    means = torch.cat([xy, torch.full((n, 1), z, dtype=dtype)], 1)
    L = torch.zeros(n, 3, 3, dtype=dtype)
    L[:, :2, :2] = torch.randn(n, 2, 2, generator=g, dtype=dtype) * 0.02 * z
    covars = L @ L.transpose(1, 2)
    covars[:, :2, :2] += torch.eye(2, dtype=dtype) * (0.01 * z) ** 2
    opac = 0.3 + 0.6 * torch.rand(n, generator=g, dtype=dtype)
    return means, covars, opac


def _pixel_grid(cam, dtype=torch.float64):
    ys, xs = torch.meshgrid(torch.arange(H, dtype=dtype) + 0.5, torch.arange(W, dtype=dtype) + 0.5, indexing="ij")
    return torch.stack([xs, ys], -1)


def test_pure_translation_is_alpha_times_displacement():
    cam = _camera()
    z = 0.2
    means, covars, opac = _flat_gaussians(12, z)
    shift = torch.tensor([0.004, -0.003, 0.0], dtype=torch.float64)  # metres, parallel to the image plane
    out = render_with_flow(means, opac, torch.rand(12, 3, dtype=torch.float64), cam, means + shift, covars=covars,
                           backend="torch")
    d = torch.tensor([F * shift[0] / z, 1.1 * F * shift[1] / z], dtype=torch.float64)  # pixels
    expect = out.alpha[..., None] * d
    assert out.alpha.max() > 0.5
    assert (out.flow - expect).abs().max() < 1e-9


def test_scaling_and_translation_match_analytic_flow():
    """Each Gaussian scales its footprint by s_i about its centre and moves by d_i: flow = sum w_i [(s_i-1)(x-mu_i)+d_i]."""
    cam = _camera()
    n, z = 8, 0.15
    means, covars, opac = _flat_gaussians(n, z, seed=1)
    s = 0.7 + 0.6 * torch.rand(n, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    shift = torch.randn(n, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(6)) * 0.002
    shift[:, 2] = 0
    covars_next = covars * (s**2)[:, None, None]
    out = render_with_flow(means, opac, torch.rand(n, 3, dtype=torch.float64), cam, means + shift, covars=covars,
                           covars_next=covars_next, backend="torch")
    # The compositing weights w_i(x): render one-hot features.
    w = rasterize(means, opac, torch.zeros(n, 3, dtype=torch.float64), cam, covars=covars,
                  features=torch.eye(n, dtype=torch.float64), backend="torch").features  # [H, W, n]
    mu = means[:, :2] / z * torch.tensor([F, 1.1 * F], dtype=torch.float64) + cam.K[:2, 2]
    d = shift[:, :2] / z * torch.tensor([F, 1.1 * F], dtype=torch.float64)
    x = _pixel_grid(cam)
    per = (s - 1)[:, None] * (x[:, :, None, :] - mu) + d  # [H, W, n, 2]
    expect = (w[..., None] * per).sum(2)
    assert w.sum(-1).max() > 0.5
    assert (out.flow - expect).abs().max() < 1e-6  # flows are O(1) px; 1e-6 px^2 regulariser


def test_single_gaussian_pure_scaling():
    cam = _camera()
    means = torch.tensor([[0.0, 0.0, 0.1]], dtype=torch.float64)
    covars = torch.diag(torch.tensor([0.006, 0.004, 0.0], dtype=torch.float64) ** 2)[None]
    opac = torch.tensor([0.9], dtype=torch.float64)
    flow = render_flow(means, opac, cam, means, covars=covars, covars_next=covars * 1.5**2, backend="torch")
    alpha = rasterize(means, opac, torch.ones(1, 3, dtype=torch.float64), cam, covars=covars, backend="torch").alpha
    mu = cam.K[:2, 2]
    expect = alpha[..., None] * 0.5 * (_pixel_grid(cam) - mu)
    assert (flow - expect).abs().max() < 1e-6


def test_flow_gradcheck():
    cam = Camera(torch.tensor([[8.0, 0, 4.1], [0, 8.5, 3.2], [0, 0, 1]], dtype=torch.float64), 8, 6,
                 torch.eye(4, dtype=torch.float64))
    g = torch.Generator().manual_seed(3)
    n = 4
    means = torch.cat([(torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 0.8,
                       0.8 + 0.4 * torch.rand(n, 1, generator=g, dtype=torch.float64)], 1)
    L = torch.randn(n, 3, 3, generator=g, dtype=torch.float64) * 0.08
    covars = L @ L.transpose(1, 2) + 0.002 * torch.eye(3, dtype=torch.float64)
    opac = 0.4 + 0.5 * torch.rand(n, generator=g, dtype=torch.float64)
    wts = torch.randn(6, 8, 2, generator=g, dtype=torch.float64)

    def f(means, covars, means_next, covars_next, opac):
        return (render_flow(means, opac, cam, means_next, covars=covars, covars_next=covars_next,
                            backend="torch") * wts).sum()

    means_next = means + 0.02 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    covars_next = covars * 1.2
    args = [t.clone().requires_grad_(True) for t in (means, covars, means_next, covars_next, opac)]
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_rgb_unchanged_by_flow_pass():
    cam = _camera(torch.float32)
    means, covars, opac = _flat_gaussians(10, 0.2, dtype=torch.float32)
    colors = torch.rand(10, 3)
    a = render_with_flow(means, opac, colors, cam, means * 1.01, covars=covars, backend="torch")
    b = rasterize(means, opac, colors, cam, covars=covars, backend="torch")
    assert torch.allclose(a.rgb, b.rgb) and torch.allclose(a.depth, b.depth) and a.flow.shape == (H, W, 2)


def test_sqrtm_2x2():
    m = torch.tensor([[[4.0, 1.0], [1.0, 3.0]]], dtype=torch.float64)
    r = sqrtm_2x2(m)
    assert torch.allclose(r @ r, m, atol=1e-12) and torch.allclose(r, r.transpose(1, 2))
