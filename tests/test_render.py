"""Tests of the differentiable Gaussian renderer (endogsim.gaussians.render)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from endogsim.errors import ModelError
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians, covariance_from_scale_rot
from endogsim.gaussians.render import rasterize, render_gaussians
from endogsim.gaussians.sh import SH_C1, eval_sh, sh_basis


def _scene(n=30, w=24, h=20, seed=0, dtype=torch.float64):
    """Random Gaussians in front of a camera at the origin, filling a small image."""
    g = torch.Generator().manual_seed(seed)
    z = 0.5 + 0.5 * torch.rand(n, generator=g, dtype=dtype)
    xy = (torch.rand(n, 2, generator=g, dtype=dtype) - 0.5) * 0.6 * z[:, None]
    means = torch.cat([xy, z[:, None]], 1)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = 0.01 + 0.04 * torch.rand(n, 3, generator=g, dtype=dtype)
    opac = 0.2 + 0.79 * torch.rand(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    cam = Camera(torch.tensor([[30.0, 0, w / 2 + 0.3], [0, 32.0, h / 2 - 0.2], [0, 0, 1]], dtype=dtype), w, h,
                 torch.eye(4, dtype=dtype))
    return means, quats, scales, opac, colors, cam


def _reference(means, covars, opac, colors, feats, cam, bg):
    """Brute force: every pixel, every Gaussian, in float64 numpy, straight from the definitions."""
    K = cam.K.double().numpy()
    R = cam.viewmat[:3, :3].double().numpy()
    t = cam.viewmat[:3, 3].double().numpy()
    mu = means.double().numpy() @ R.T + t
    S = R @ covars.double().numpy() @ R.T
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    n = len(mu)
    m2, conic = np.zeros((n, 2)), np.zeros((n, 2, 2))
    for i in range(n):
        x, y, z = mu[i]
        J = np.array([[fx / z, 0, -fx * x / z**2], [0, fy / z, -fy * y / z**2]])
        cov = J @ S[i] @ J.T + 0.3 * np.eye(2)
        conic[i] = np.linalg.inv(cov)
        m2[i] = [fx * x / z + cx, fy * y / z + cy]
    order = np.argsort(mu[:, 2], kind="stable")
    chans = np.concatenate([colors.double().numpy(), mu[:, 2:3], feats.double().numpy()], 1)
    out = np.zeros((cam.height, cam.width, chans.shape[1]))
    alpha_img = np.zeros((cam.height, cam.width))
    for py in range(cam.height):
        for px in range(cam.width):
            p = np.array([px + 0.5, py + 0.5])
            T, acc = 1.0, np.zeros(chans.shape[1])
            for i in order:
                d = p - m2[i]
                a = min(0.99, opac[i].item() * math.exp(-0.5 * d @ conic[i] @ d))
                if a < 1 / 255:
                    continue
                if T * (1 - a) <= 1e-4:
                    break
                acc += a * T * chans[i]
                T *= 1 - a
            acc[:3] += T * bg
            out[py, px], alpha_img[py, px] = acc, 1 - T
    return out, alpha_img


@pytest.mark.parametrize("backend", ["torch", "warp"])
def test_matches_brute_force_reference(backend):
    means, quats, scales, opac, colors, cam = _scene(dtype=torch.float32)
    feats = torch.randn(len(means), 2)
    bg = torch.tensor([0.1, 0.2, 0.3])
    out = rasterize(means, opac, colors, cam, quats=quats, scales=scales, features=feats, background=bg,
                    backend=backend)
    assert out.meta["backend"] == backend
    covars = covariance_from_scale_rot(scales.double(), quats.double())
    ref, ref_alpha = _reference(means, covars, opac, colors, feats, cam, bg.double().numpy())
    assert out.rgb.shape == (cam.height, cam.width, 3) and out.features.shape == (cam.height, cam.width, 2)
    assert np.abs(out.rgb.numpy() - ref[..., :3]).max() <= 1e-5
    assert np.abs(out.alpha.numpy() - ref_alpha).max() <= 1e-5
    assert np.abs(out.features.numpy() - ref[..., 4:]).max() <= 1e-5
    ref_depth = ref[..., 3] / np.maximum(ref_alpha, 1e-10)
    assert np.abs(out.depth.numpy() - ref_depth).max() <= 1e-5
    assert ref_alpha.max() > 0.9 and ref_alpha.min() < 0.5  # the scene is neither empty nor saturated


def test_gradcheck_all_parameters():
    """Gradients w.r.t. means, quats, scales, opacities, colours, features, background vs finite differences."""
    means, quats, scales, opac, colors, cam = _scene(n=6, w=10, h=8, seed=1)
    cam = Camera(cam.K * torch.tensor([[0.4], [0.4], [1.0]], dtype=torch.float64), 10, 8, cam.viewmat)
    cam.K[0, 2], cam.K[1, 2] = 5.1, 3.9
    feats = torch.randn(len(means), 2, dtype=torch.float64)
    bg = torch.tensor([0.3, 0.1, 0.2], dtype=torch.float64)
    wts = torch.randn(8, 10, 8, dtype=torch.float64)

    def f(means, quats, scales, opac, colors, feats, bg):
        o = rasterize(means, opac, colors, cam, quats=quats, scales=scales, features=feats, background=bg,
                      backend="torch")
        img = torch.cat([o.rgb, o.depth[..., None], o.alpha[..., None], o.features, (o.depth * o.alpha)[..., None]], -1)
        return (img * wts).sum()

    args = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors, feats, bg)]
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_gradcheck_covariances_and_sh():
    means, quats, scales, opac, colors, cam = _scene(n=5, w=10, h=8, seed=2)
    cam = Camera(cam.K * torch.tensor([[0.4], [0.4], [1.0]], dtype=torch.float64), 10, 8, cam.viewmat)
    cam.viewmat[:3, 3] = torch.tensor([0.01, -0.02, 0.05], dtype=torch.float64)
    covars = covariance_from_scale_rot(scales, quats)
    sh = 0.3 * torch.randn(len(means), 9, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    wts = torch.randn(8, 10, 4, dtype=torch.float64)

    def f(means, covars, opac, sh):
        o = rasterize(means, opac, sh, cam, covars=covars, backend="torch")
        return (torch.cat([o.rgb, o.depth[..., None]], -1) * wts).sum()

    args = [t.clone().requires_grad_(True) for t in (means, covars, opac, sh)]
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_sh_known_values():
    d = torch.tensor([[0.48, 0.6, 0.64]], dtype=torch.float64)  # unit length
    b = sh_basis(3, d)[0]
    x, y, z = 0.48, 0.6, 0.64
    expect = [
        0.28209479177387814, -SH_C1 * y, SH_C1 * z, -SH_C1 * x,
        1.0925484305920792 * x * y, -1.0925484305920792 * y * z, 0.31539156525252005 * (2 * z * z - x * x - y * y),
        -1.0925484305920792 * x * z, 0.5462742152960396 * (x * x - y * y),
        -0.5900435899266435 * y * (3 * x * x - y * y), 2.890611442640554 * x * y * z,
        -0.4570457994644658 * y * (4 * z * z - x * x - y * y), 0.3731763325901154 * z * (2 * z * z - 3 * x * x - 3 * y * y),
        -0.4570457994644658 * x * (4 * z * z - x * x - y * y), 1.445305721320277 * z * (x * x - y * y),
        -0.5900435899266435 * x * (x * x - 3 * y * y),
    ]
    assert torch.allclose(b, torch.tensor(expect, dtype=torch.float64), atol=1e-14)
    # Direction length does not matter; only the first (d+1)^2 coefficients are used at degree d.
    assert torch.allclose(sh_basis(3, 5 * d), sh_basis(3, d))
    coeffs = torch.randn(1, 16, 3, dtype=torch.float64)
    assert torch.allclose(eval_sh(coeffs, d, degree=1), (b[:4, None] * coeffs[0, :4]).sum(0)[None])


def test_sh_basis_is_orthonormal():
    """Gauss-Legendre x uniform-phi quadrature integrates degree <= 6 products exactly."""
    u, wu = np.polynomial.legendre.leggauss(8)
    phi = np.arange(16) * 2 * np.pi / 16
    ct, ph = np.meshgrid(u, phi, indexing="ij")
    st = np.sqrt(1 - ct**2)
    dirs = torch.tensor(np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 3))
    wts = torch.tensor((wu[:, None] * np.full_like(ph, 2 * np.pi / 16)).reshape(-1))
    B = sh_basis(3, dirs)
    gram = B.T @ (B * wts[:, None])
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=1e-12)


def test_render_gaussians_uses_sh_dc_colour_and_activations():
    pts = torch.tensor([[0.0, 0.0, 0.2]])
    g = Gaussians.from_points(pts, torch.tensor([[0.2, 0.5, 0.9]]), 0.02, opacity=0.9, sh_degree=2)
    cam = Camera.from_focal(100.0, 32, 32)
    out = render_gaussians(g, cam, backend="torch")
    # At the centre pixel the Gaussian peak is ~0.9 alpha (the centre sits on a pixel corner, so slightly less).
    assert out.alpha.max() > 0.85 and out.alpha.max() <= 0.9
    c = out.rgb[16, 16] / out.alpha[16, 16]
    assert torch.allclose(c, torch.tensor([0.2, 0.5, 0.9]), atol=1e-5)


@pytest.mark.parametrize("backend", ["torch", "warp"])
def test_depth_and_alpha_sanity(backend):
    # A dense opaque layer at z = 0.1 m in front of another at z = 0.3 m: depth 0.1, alpha ~1.
    ys, xs = torch.meshgrid(torch.linspace(-0.06, 0.06, 40), torch.linspace(-0.06, 0.06, 40), indexing="ij")
    front = torch.stack([xs.flatten(), ys.flatten(), torch.full((1600,), 0.1)], 1)
    back = front * torch.tensor([3.0, 3.0, 3.0])
    means = torch.cat([back, front])
    n = len(means)
    scales = torch.full((n, 3), 0.004)
    scales[:1600] *= 3
    quats = torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4)
    cam = Camera.from_focal(100.0, 40, 32)
    out = rasterize(means, torch.full((n,), 0.99), torch.rand(n, 3), cam, quats=quats, scales=scales,
                    background=torch.tensor([1.0, 0.0, 0.0]), backend=backend)
    assert (out.alpha > 0.99).all()
    assert torch.allclose(out.depth, torch.full_like(out.depth, 0.1), atol=1e-3)
    # Nothing in front of the camera: alpha 0, depth 0, the background everywhere.
    out = rasterize(-means, torch.full((n,), 0.99), torch.rand(n, 3), cam, quats=quats, scales=scales,
                    background=torch.tensor([1.0, 0.0, 0.0]), backend=backend)
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    assert torch.equal(out.rgb, torch.tensor([1.0, 0.0, 0.0]).expand(32, 40, 3))


@pytest.mark.parametrize("backend", ["torch", "warp"])
def test_depth_ordering_and_occlusion(backend):
    """An opaque near Gaussian hides a far one whatever their order in the input."""
    means = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, 0.2]])
    covars = torch.diag(torch.tensor([0.05, 0.05, 0.01]) ** 2).expand(2, 3, 3)
    colors = torch.tensor([[1.0, 0, 0], [0, 1.0, 0]])
    cam = Camera.from_focal(100.0, 16, 16)
    for perm in ([0, 1], [1, 0]):
        out = rasterize(means[perm], torch.full((2,), 0.99), colors[perm], cam, covars=covars[perm], backend=backend)
        c = out.rgb[8, 8]
        assert c[1] > 0.98 and c[0] < 0.011
        assert abs(out.depth[8, 8].item() - 0.2) < 0.01


def test_bad_inputs_raise_model_error():
    means, quats, scales, opac, colors, cam = _scene(dtype=torch.float32)
    with pytest.raises(ModelError, match="opacities"):
        rasterize(means, opac[:-1], colors, cam, quats=quats, scales=scales)
    with pytest.raises(ModelError, match="covars or both"):
        rasterize(means, opac, colors, cam)
    with pytest.raises(ModelError, match="backend"):
        rasterize(means, opac, colors, cam, quats=quats, scales=scales, backend="vulkan")
    with pytest.raises(ModelError, match="CUDA"):
        rasterize(means, opac, colors, cam, quats=quats, scales=scales, backend="gsplat")


def test_float32_matches_float64():
    means, quats, scales, opac, colors, cam = _scene(n=200, w=64, h=48, seed=4)
    cam = Camera(cam.K * torch.tensor([[2.6], [2.4], [1.0]], dtype=torch.float64), 64, 48, cam.viewmat)
    o64 = rasterize(means, opac, colors, cam, quats=quats, scales=scales, backend="torch")
    o32 = rasterize(means.float(), opac.float(), colors.float(), cam.to("cpu"), quats=quats.float(),
                    scales=scales.float(), backend="torch")
    assert (o32.rgb.double() - o64.rgb).abs().max() < 1e-4


def test_chunked_equals_unchunked():
    from endogsim.gaussians.rasterize_torch import RasterConfig

    means, quats, scales, opac, colors, cam = _scene(n=100, w=48, h=40, seed=5, dtype=torch.float32)
    cam = Camera(cam.K * torch.tensor([[2.0], [2.0], [1.0]]), 48, 40, cam.viewmat)
    p = [t.clone().requires_grad_(True) for t in (means, scales, opac, colors)]
    grads = []
    for cfg in (RasterConfig(), RasterConfig(max_pairs_per_chunk=300)):
        out = rasterize(p[0], p[2], p[3], cam, quats=quats, scales=p[1], backend="torch", config=cfg)
        loss = (out.rgb**2).sum() + out.depth.sum()
        grads.append((out.rgb.detach(), torch.autograd.grad(loss, p)))
    assert torch.allclose(grads[0][0], grads[1][0], atol=1e-6)
    for a, b in zip(grads[0][1], grads[1][1]):
        assert torch.allclose(a, b, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
@pytest.mark.parametrize("tile_size", [1, 4, 16])
def test_warp_backend_matches_torch_values_and_gradients(tile_size, device, monkeypatch):
    """The Warp tile compositor against the PyTorch reference (on the CPU): images and the gradients of
    every input, with features, a background, degenerate and off-screen Gaussians, at several tile sizes,
    with the Warp kernels on the CPU and on CUDA."""
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    import endogsim.gaussians.render as render_mod
    from endogsim.gaussians.rasterize_warp import bin_gaussians

    monkeypatch.setattr(render_mod, "bin_gaussians", lambda *a: bin_gaussians(*a, tile_size=tile_size))
    means, quats, scales, opac, colors, cam = _scene(n=400, w=61, h=45, seed=8, dtype=torch.float32)
    cam = Camera(cam.K * torch.tensor([[2.6], [2.4], [1.0]]), 61, 45, cam.viewmat)
    means[:5, :2] += 3.0  # off screen
    scales[5:8] = 1e-6  # sub-pixel: only the eps2d dilation
    opac[8:12] = 0.999  # above the alpha clamp
    feats = torch.randn(len(means), 3, generator=torch.Generator().manual_seed(9))
    bg = torch.tensor([0.2, 0.3, 0.4])
    wts = torch.randn(45, 61, 9, generator=torch.Generator().manual_seed(10))
    outs = {}
    for backend, dev in (("torch", "cpu"), ("warp", device)):
        args = [t.to(dev).requires_grad_(True) for t in (means, quats, scales, opac, colors, feats, bg)]
        o = rasterize(args[0], args[3], args[4], cam.to(dev), quats=args[1], scales=args[2], features=args[5],
                      background=args[6], backend=backend)
        img = torch.cat([o.rgb, o.depth[..., None], o.alpha[..., None], o.features, (o.depth * o.alpha)[..., None]], -1)
        grads = torch.autograd.grad((img * wts.to(dev)).sum(), args)
        outs[backend] = (img.detach().cpu(), [g.cpu() for g in grads])
    (ti, tg), (wi, wg) = outs["torch"], outs["warp"]
    assert (ti - wi).abs().max() < 2e-5
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors", "features", "background"), tg, wg):
        assert (a - b).abs().max() <= 1e-4 * a.abs().max() + 1e-7, name


def test_warp_renderer_is_compiled_once_whatever_the_channel_count():
    """Warp builds a module again (seconds on a CPU) whenever a generic kernel meets new argument types.
    Renders with 0 to 12 feature channels use the kernels instantiated at import, padded to their channel
    count, so no render adds an overload; and the padding changes no bit: colour, alpha and the gradients of
    a colour loss are the same whatever features are composited beside them."""
    import endogsim.gaussians.rasterize_warp as rw

    kernels = (rw.composite_forward, rw.composite_backward)
    declared = [set(k.overloads) for k in kernels]
    assert all(len(d) == len(rw.COMPILED_CHANNELS) for d in declared)
    means, quats, scales, opac, colors, cam = _scene(n=200, w=31, h=23, seed=3, dtype=torch.float32)
    feats = torch.rand(len(means), 12, generator=torch.Generator().manual_seed(4))
    wts = torch.randn(23, 31, 3, generator=torch.Generator().manual_seed(5))
    first = None
    for n_feat in range(13):
        args = [t.clone().requires_grad_(True) for t in (means, opac, colors)]
        o = rasterize(args[0], args[1], args[2], cam, quats=quats, scales=scales,
                      features=feats[:, :n_feat] if n_feat else None, backend="warp")
        got = (o.rgb.detach(), o.alpha.detach(), *torch.autograd.grad((o.rgb * wts).sum(), args))
        first = got if first is None else first
        assert all(torch.equal(a, b) for a, b in zip(first, got)), n_feat
    last_features = o.features.detach()
    for n_feat in (1, 5, 11):  # each feature channel is composited on its own, whatever the padding
        o = rasterize(means, opac, colors, cam, quats=quats, scales=scales, features=feats[:, :n_feat], backend="warp")
        assert torch.equal(o.features, last_features[..., :n_feat])
    assert [set(k.overloads) for k in kernels] == declared


def test_auto_backend_is_warp_for_float32_and_torch_for_float64_on_cpu():
    means, quats, scales, opac, colors, cam = _scene(n=20, seed=11)
    assert rasterize(means, opac, colors, cam, quats=quats, scales=scales).meta["backend"] == "torch"
    f32 = [t.float() for t in (means, quats, scales, opac, colors)]
    out = rasterize(f32[0], f32[3], f32[4], cam.to("cpu"), quats=f32[1], scales=f32[2])
    assert out.meta["backend"] == "warp"
    # nothing visible: the background everywhere, and gradients are zero rather than failing
    f32[0] = (-f32[0]).requires_grad_(True)
    out = rasterize(f32[0], f32[3], f32[4], cam.to("cpu"), quats=f32[1], scales=f32[2],
                    background=torch.tensor([0.5, 0.25, 1.0]), backend="warp")
    assert torch.equal(out.rgb, torch.tensor([0.5, 0.25, 1.0]).expand_as(out.rgb)) and (out.alpha == 0).all()
    out.rgb.sum().backward()
    assert (f32[0].grad == 0).all()


@pytest.mark.gpu
def test_gsplat_matches_torch_backend():
    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    from endogsim.gaussians.backend_gsplat import available

    if not available():
        pytest.skip("gsplat is not installed")
    # Opacities stay <= 0.99: gsplat clamps alpha at 0.999, this package at 0.99 (see backend_gsplat).
    means, quats, scales, opac, colors, cam = _scene(n=300, w=64, h=48, seed=6, dtype=torch.float32)
    cam = Camera(cam.K * torch.tensor([[2.6], [2.4], [1.0]]), 64, 48, cam.viewmat).to("cuda")
    feats = torch.randn(len(means), 4)
    args = [t.cuda().requires_grad_(True) for t in (means, quats, scales, opac, colors, feats)]
    outs = {}
    for backend in ("torch", "gsplat"):
        o = rasterize(args[0], args[3], args[4], cam, quats=args[1], scales=args[2], features=args[5],
                      background=torch.tensor([0.2, 0.3, 0.4], device="cuda"), backend=backend)
        assert o.meta["backend"] == backend
        loss = o.rgb.square().sum() + o.depth.sum() + o.alpha.sum() + o.features.sum()
        outs[backend] = (o, torch.autograd.grad(loss, args))
    (t, gt), (g, gg) = outs["torch"], outs["gsplat"]
    for name in ("rgb", "depth", "alpha", "features"):
        assert (getattr(t, name) - getattr(g, name)).abs().max() < 1e-4, name
    for a, b in zip(gt, gg):
        assert (a - b).abs().max() <= 1e-3 * b.abs().max() + 1e-6


@pytest.mark.parametrize("backend", ["torch", "warp"])
def test_opaque_stack_stops_at_min_transmittance(backend):
    """Many overlapping near-opaque Gaussians: the 1e-4 transmittance stop and the 0.99 clamp matter here."""
    g = torch.Generator().manual_seed(7)
    n, w, h = 40, 12, 10
    z = 0.4 + 0.4 * torch.rand(n, generator=g)
    means = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 0.05, z[:, None]], 1)
    covars = torch.diag(torch.tensor([0.3, 0.3, 0.05]) ** 2).expand(n, 3, 3).clone()
    opac = 0.9 + 0.1 * torch.rand(n, generator=g)  # some above the 0.99 clamp
    colors = torch.rand(n, 3, generator=g)
    feats = torch.randn(n, 1, generator=g)
    cam = Camera(torch.tensor([[20.0, 0, 6.1], [0, 20.0, 4.9], [0, 0, 1]]), w, h)
    out = rasterize(means, opac, colors, cam, covars=covars, features=feats, backend=backend)
    ref, ref_alpha = _reference(means, covars, opac, colors, feats, cam, np.zeros(3))
    assert np.abs(out.rgb.numpy() - ref[..., :3]).max() <= 1e-5
    assert np.abs(out.features.numpy() - ref[..., 4:]).max() <= 1e-5
    assert np.abs(out.alpha.numpy() - ref_alpha).max() <= 1e-5
    assert out.alpha.min() > 0.99  # every pixel is composited until the stop (a wrong stop shows as ~1e-4 errors)


def test_bench_cli_smallest_case(tmp_path):
    import json

    from typer.testing import CliRunner

    from endogsim.cli.main import app

    res = CliRunner().invoke(app, ["bench", "render", "--max-gaussians", "5000", "--repeats", "1",
                                   "--json", str(tmp_path / "b.json")])
    assert res.exit_code == 0, res.output
    case = json.loads((tmp_path / "b.json").read_text())["cases"][0]
    assert case["backend"] == "torch" and (case["gaussians"], case["width"], case["height"]) == (5000, 160, 128)
    assert 0 < case["forward_s"] <= case["forward_backward_s"] and case["peak_mem_mb"] > 0
