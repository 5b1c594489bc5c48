"""Pure-PyTorch differentiable Gaussian rasteriser (the CPU backend and the reference for any other).

The pipeline, in four small steps:

1. :func:`project_gaussians` -- EWA splatting: camera-space means and covariances, the Jacobian of the
   pinhole projection, 2D covariance + ``eps2d`` dilation, conic (inverse 2D covariance). Plain autograd.
2. :func:`_row_spans` / :func:`_expand_pairs` -- the (pixel, Gaussian) pairs. Instead of a square
   3-sigma box we take, for every image row a Gaussian touches, the exact x-interval where its alpha
   reaches ``alpha_min`` (1/255). That region is the opacity-aware bounding ellipse gsplat 1.5 uses for
   its tiles (``extend = sqrt(2 ln(255 opacity)) <= 3.33`` sigmas), so both backends composite the same
   pairs, and hardly any generated pair is thrown away.
3. Sort by pixel then depth: Gaussians are ranked by camera depth first, pairs are generated rank-major,
   so one stable sort on the pixel index gives (pixel, depth) order.
4. :class:`_Composite` -- front-to-back alpha compositing as a segmented cumulative sum of
   log(1 - alpha) in float64 (float32 gave colour errors up to 0.15 at 640x512), with the alpha clamp
   0.99, the skip below 1/255 and the stop at transmittance 1e-4 of the reference 3DGS kernel. Its
   backward is written in closed form (suffix sums over each pixel's list), which is much faster and
   lighter than autograd through cumsum/gather chains.

Steps 2-4 run over bands of image rows: transient memory is bounded by
``RasterConfig.max_pairs_per_chunk`` whatever the image size, and the backward keeps ~25 bytes per pair
(pixel, Gaussian id, alpha, transmittance, offsets). Everything runs on any torch device; per-pair work
uses 1-D tensors and int32 indices (see :func:`_composite_band`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from endogsim.gaussians.types import RasterConfig


@dataclass
class Projection:
    """2D footprints of N Gaussians seen by one camera.

    Attributes:
        means2d: [N, 2] projected centres (pixels; pixel (i, j) has its centre at (j + 0.5, i + 0.5)).
        cov2d: [N, 2, 2] projected covariances before the ``eps2d`` dilation (pixels^2).
        conics: [N, 3] (a, b, c) of the inverse of the dilated 2D covariance.
        depths: [N] camera-space z (metres).
        radii: [N, 2] int32 half-extent of the screen box where alpha >= alpha_min (pixels); 0 = culled.
        valid: [N] bool, the Gaussian is in front of the camera, on screen and not degenerate.
    """

    means2d: torch.Tensor
    cov2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor
    valid: torch.Tensor


def world_to_camera(means: torch.Tensor, covars: torch.Tensor | None,
                    viewmat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Camera-space means [N, 3] and covariances [N, 3, 3] (None stays None) from world ones and a [4, 4]
    world->camera."""
    R = viewmat[:3, :3].to(means.dtype)
    t = viewmat[:3, 3].to(means.dtype)
    return means @ R.T + t, None if covars is None else R @ covars @ R.T


def project_gaussians(
    means: torch.Tensor,
    covars: torch.Tensor,
    opacities: torch.Tensor,
    K: torch.Tensor,
    viewmat: torch.Tensor,
    width: int,
    height: int,
    config: RasterConfig = RasterConfig(),
) -> Projection:
    """EWA projection of 3D Gaussians to the image plane (differentiable).

    Args:
        means: [N, 3] world centres (metres).
        covars: [N, 3, 3] world covariances (metres^2).
        opacities: [N] opacities in [0, 1] (only used for the opacity-aware screen extent and culling).
        K: [3, 3] pinhole intrinsics (pixels).
        viewmat: [4, 4] world->camera transform.
        width, height: image size (pixels).
    """
    mc, cc = world_to_camera(means, covars, viewmat)
    x, y, z = mc.unbind(-1)
    in_depth = (z > config.near_plane) & (z < config.far_plane)
    # Culled Gaussians still flow through the maths below; give them a harmless depth so no inf/NaN
    # reaches the gradients of the others.
    zs = torch.where(in_depth, z, torch.ones_like(z))
    fx, fy, cx, cy = (K[0, 0].item(), K[1, 1].item(), K[0, 2].item(), K[1, 2].item())
    # Clamp the Jacobian's x/z, y/z slightly outside the frustum, like gsplat's persp_proj: splats far
    # off-screen would otherwise get huge, unstable footprints.
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    rz = 1.0 / zs
    tx = zs * torch.clamp(x * rz, -lim_x_neg, lim_x_pos)
    ty = zs * torch.clamp(y * rz, -lim_y_neg, lim_y_pos)
    zero = torch.zeros_like(zs)
    J = torch.stack(
        [torch.stack([fx * rz, zero, -fx * tx * rz * rz], -1), torch.stack([zero, fy * rz, -fy * ty * rz * rz], -1)],
        dim=-2,
    )  # [N, 2, 3]
    cov2d = J @ cc @ J.transpose(-1, -2)
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)

    a = cov2d[:, 0, 0] + config.eps2d
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + config.eps2d
    det = a * c - b * b
    ok = in_depth & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)

    with torch.no_grad():
        # Opacity-aware extent: alpha = o exp(-r^2 / 2) reaches alpha_min at r = sqrt(2 ln(o / alpha_min)).
        o = opacities.detach().clamp(max=1.0)
        ok = ok & (o >= config.alpha_min)  # a new tensor: the one above is saved by torch.where
        extend = torch.sqrt(2.0 * torch.log(o.clamp_min(config.alpha_min) / config.alpha_min)).clamp(max=3.33)
        rx = torch.ceil(extend * torch.sqrt(a.detach().clamp_min(0)))
        ry = torch.ceil(extend * torch.sqrt(c.detach().clamp_min(0)))
        ok &= (rx > config.radius_clip) | (ry > config.radius_clip)
        m = means2d.detach()
        ok &= (m[:, 0] + rx > 0) & (m[:, 0] - rx < width) & (m[:, 1] + ry > 0) & (m[:, 1] - ry < height)
        radii = torch.stack([rx, ry], -1).nan_to_num(0).to(torch.int32) * ok[:, None]
    return Projection(means2d, cov2d, conics, z, radii, ok)


# ---------------------------------------------------------------------------------------------------
# (pixel, Gaussian) pairs
# ---------------------------------------------------------------------------------------------------

_SPAN_MARGIN = 1e-3  # pixels: widen each row span a little; the exact alpha test decides at the edges


def _row_spans(means2d, conics, opacities, order, width, height, config):
    """One entry per (Gaussian, image row) the Gaussian's alpha >= alpha_min region touches.

    Gaussians are visited in ``order`` (front to back), so the spans come out front to back.
    Returns gid [R] (int32 Gaussian index), row [R], x0 [R], span width [R] (int64).
    """
    m = means2d[order]
    a, b, c = conics[order].unbind(-1)
    tau = torch.log(opacities[order] / config.alpha_min)  # sigma threshold: o exp(-sigma) = alpha_min
    det = a * c - b * b
    # y half-extent of the ellipse 0.5 a dx^2 + b dx dy + 0.5 c dy^2 <= tau.
    ry = torch.sqrt((2.0 * tau * a / det).clamp_min(0))
    y0 = torch.ceil(m[:, 1] - ry - 0.5 - _SPAN_MARGIN).clamp(0, height).long()
    y1 = (torch.floor(m[:, 1] + ry - 0.5 + _SPAN_MARGIN) + 1).clamp(0, height).long()
    h = (y1 - y0).clamp_min(0)
    n_rows = int(h.sum())
    rank = torch.repeat_interleave(torch.arange(len(order), device=m.device), h, output_size=n_rows)
    first = torch.cumsum(h, 0) - h
    row = y0[rank] + torch.arange(n_rows, device=m.device) - first[rank]
    # x-interval of the ellipse on this row's centre line.
    dy = (row + 0.5) - m[rank, 1]
    ar, br = a[rank], b[rank]
    half = torch.sqrt((2.0 * ar * tau[rank] - det[rank] * dy * dy).clamp_min(0)) / ar
    xc = m[rank, 0] - br * dy / ar
    x0 = torch.ceil(xc - half - 0.5 - _SPAN_MARGIN).clamp(0, width).long()
    x1 = (torch.floor(xc + half - 0.5 + _SPAN_MARGIN) + 1).clamp(0, width).long()
    span = (x1 - x0).clamp_min(0)
    keep = torch.nonzero(span > 0).squeeze(1)
    return order[rank[keep]].to(torch.int32), row[keep], x0[keep], span[keep]


def _expand_pairs(gid, row, x0, span, row_offset, width):
    """Expand row spans into (local pixel index, Gaussian id) pairs sorted by pixel, then depth.

    Returns pix [M] and gid [M], both int32.
    """
    dev = span.device
    total = int(span.sum())
    first = torch.cumsum(span, 0) - span
    # Span index of every pair: a cumulative count of span starts (cheaper than repeat_interleave).
    marks = torch.zeros(total, dtype=torch.int32, device=dev)
    marks[first[1:]] = 1
    idx = torch.cumsum(marks, 0, dtype=torch.int32)
    # pixel = (row - row_offset) * width + x0 + (position inside the span)
    base = ((row - row_offset) * width + x0 - first).to(torch.int32)
    pix = torch.arange(total, dtype=torch.int32, device=dev) + base.index_select(0, idx)
    # Pairs are front to back, so a stable sort by pixel keeps depth order within each pixel.
    pix, perm = torch.sort(pix, stable=True)
    return pix, gid.index_select(0, idx.index_select(0, perm))


def _band_bounds(row, span, height, max_pairs):
    """Split image rows into bands holding at most ~max_pairs pairs each: list of (r0, r1)."""
    per_row = torch.zeros(height, dtype=torch.float64, device=row.device)
    per_row.index_add_(0, row, span.to(torch.float64))
    cum = torch.cumsum(per_row, 0).cpu()
    bounds, r0 = [], 0
    while r0 < height:
        base = float(cum[r0 - 1]) if r0 > 0 else 0.0
        r1 = int(torch.searchsorted(cum, torch.tensor(base + max_pairs, dtype=torch.float64), right=True))
        r1 = min(max(r1, r0 + 1), height)
        bounds.append((r0, r1))
        r0 = r1
    return bounds


@dataclass
class PairList:
    """Sorted (pixel, Gaussian) pairs of every row band, plus their count (no gradients)."""

    bands: list[tuple[int, int, torch.Tensor, torch.Tensor]]  # (r0, r1, pix [M] local int32, gid [M] int32)
    n_pairs: int


def build_pairs(proj: Projection, opacities: torch.Tensor, width: int, height: int, config: RasterConfig) -> PairList:
    """All candidate (pixel, Gaussian) pairs in (pixel, depth) order, split into row bands."""
    with torch.no_grad():
        vis = torch.nonzero(proj.valid).squeeze(1)
        order = vis[torch.argsort(proj.depths.detach()[vis], stable=True)]
        gid, row, x0, span = _row_spans(
            proj.means2d.detach(), proj.conics.detach(), opacities.detach(), order, width, height, config
        )
        bounds = _band_bounds(row, span, height, config.max_pairs_per_chunk)
        bands = []
        n = 0
        for r0, r1 in bounds:
            if len(bounds) == 1:
                pix, g = _expand_pairs(gid, row, x0, span, r0, width)
            else:
                sel = torch.nonzero((row >= r0) & (row < r1)).squeeze(1)
                pix, g = _expand_pairs(gid[sel], row[sel], x0[sel], span[sel], r0, width)
            bands.append((r0, r1, pix, g))
            n += len(pix)
    return PairList(bands, n)


# ---------------------------------------------------------------------------------------------------
# Compositing
# ---------------------------------------------------------------------------------------------------
# Per-pair work is done on 1-D tensors, one channel at a time: on CPU, gathers/scatters of [M, k]
# blocks and broadcasts like w[:, None] * x[M, k] are several times slower than k 1-D passes.


def _segment_sum(values: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """Sum of ``values`` over consecutive runs of lengths ``counts`` (pixel-sorted pairs -> pixels)."""
    return torch.segment_reduce(values, "sum", lengths=counts)


def _gather(columns: torch.Tensor, index: torch.Tensor) -> list[torch.Tensor]:
    """[k, N] per-Gaussian columns -> k tensors [M] of the rows ``index`` selects."""
    return [col.index_select(0, index) for col in columns]


def _composite_band(pix, gid, r0, r1, width, geom, colors_t, config):
    """Forward compositing of one band of rows.

    Args:
        pix, gid: [M] pixel-sorted pairs (int32; pix is local to the band).
        geom: [6, N] per-Gaussian (mean x, mean y, conic a, b, c, opacity).
        colors_t: [C, N] per-Gaussian channels.
    Returns:
        out [C, P] composited channels, t_final [P] final transmittance, saved tensors for backward.
    """
    n_pix = (r1 - r0) * width
    dtype = geom.dtype
    mx, my, ca, cb, cc, op = _gather(geom, gid)
    dx = (pix % width).to(dtype) + 0.5 - mx
    dy = (pix // width + r0).to(dtype) + 0.5 - my
    sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
    raw = op * torch.exp(-sigma)
    alpha = torch.clamp_max(raw, config.alpha_max)
    # Skipped pairs get alpha 0: log(1 - 0) = 0 leaves every transmittance unchanged.
    alpha = torch.where((sigma >= 0) & (alpha >= config.alpha_min), alpha, 0.0)
    # Each log(1 - alpha) is fine in float32; their running sum is not (see the module docstring).
    logq = torch.log1p(-alpha).to(torch.float64)
    counts = torch.bincount(pix, minlength=n_pix)
    first = torch.cumsum(counts, 0) - counts
    excl = torch.cumsum(logq, 0) - logq
    log_t = excl - excl.index_select(0, first.index_select(0, pix))  # log transmittance in front of the pair
    # Stop before the transmittance would fall to transmittance_min (the pair that would do it is skipped).
    # Pairs that do not contribute keep their place with alpha = 0, which makes them inert in the
    # backward pass too (w = 0, d sigma = -alpha (...) = 0): cheaper than compacting the arrays.
    live = (alpha > 0) & (log_t + logq > math.log(config.transmittance_min))
    alpha = torch.where(live, alpha, 0.0)
    clamped = raw >= config.alpha_max
    t_final = torch.exp(_segment_sum(torch.where(live, logq, 0.0), counts)).to(dtype)
    trans = torch.exp(log_t).to(dtype)
    w = alpha * trans
    out = torch.stack([_segment_sum(w * col.index_select(0, gid), counts) for col in colors_t])
    return out, t_final, (pix, gid, alpha, trans, dx, dy, clamped, t_final, counts)


class _Composite(torch.autograd.Function):
    """Alpha compositing of pre-built pairs with a closed-form backward.

    Forward (per pixel p with its pairs k = 1..n front to back, transmittance T_k = prod_{j<k} (1 - a_j)):
        out_p = sum_k a_k T_k c_k + T_final bg,   alpha_p = 1 - T_final.
    Backward: d out / d a_k = T_k c_k - (sum_{j>k} a_j T_j c_j + T_final bg) / (1 - a_k), and the
    suffix sums come from one cumulative sum per band.
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, background, pairs: PairList, width: int, height: int, config):
        C = colors.shape[1]
        geom = torch.cat([means2d.T, conics.T, opacities[None]]).contiguous()  # [6, N]
        colors_t = colors.T.contiguous()  # [C, N]
        out = torch.empty(height * width, C + 1, dtype=colors.dtype, device=colors.device)
        saved = []
        for r0, r1, pix, gid in pairs.bands:
            band, t_final, s = _composite_band(pix, gid, r0, r1, width, geom, colors_t, config)
            rows = slice(r0 * width, r1 * width)
            out[rows, :C] = (band + t_final[None] * background[:, None]).T
            out[rows, C] = 1.0 - t_final
            saved.append((r0, r1, *s))
        ctx.saved_bands = saved
        ctx.width = width
        ctx.save_for_backward(geom, colors_t, background)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        geom, colors_t, background = ctx.saved_tensors
        width = ctx.width
        C, N = colors_t.shape
        dtype = colors_t.dtype
        g_colors = torch.zeros(C, N, dtype=dtype, device=colors_t.device)
        moments = torch.zeros(6, N, dtype=dtype, device=geom.device)
        g_bg = torch.zeros_like(background)
        for r0, r1, pix, gid, alpha, trans, dx, dy, clamped, t_final, counts in ctx.saved_bands:
            g = grad_out[r0 * width : r1 * width].to(dtype).T.contiguous()  # [C+1, P]
            g_bg += g[:C] @ t_final
            if len(pix) == 0:
                continue
            gid64 = gid.long()
            w = alpha * trans
            # c_k . g_p over every channel; the alpha channel composites a colour of 1.
            gp_alpha = g[C].index_select(0, pix)
            cg = gp_alpha.clone()
            for c in range(C):
                gp = g[c].index_select(0, pix)
                g_colors[c].index_add_(0, gid64, w * gp)
                cg += colors_t[c].index_select(0, gid) * gp
            # Suffix sums sum_{j>k} w_j c_j . g_p within each pixel's run, in float64.
            incl = torch.cumsum((w * cg).to(torch.float64), 0)
            last = torch.cumsum(counts, 0) - 1
            suffix = (incl.index_select(0, last.index_select(0, pix)) - incl).to(dtype)
            bg_term = t_final * (background @ g[:C])  # [P]
            g_alpha = trans * cg - (suffix + bg_term.index_select(0, pix)) / (1.0 - alpha)
            g_sigma = torch.where(clamped, 0.0, -alpha * g_alpha)  # alpha = o exp(-sigma) where not clamped
            # sigma = 0.5 a dx^2 + b dx dy + 0.5 c dy^2: scatter the moments of g_sigma per Gaussian and apply
            # the (per-Gaussian constant) conic afterwards, instead of gathering the conic for every pair.
            gdx, gdy = g_sigma * dx, g_sigma * dy
            for i, v in enumerate((gdx, gdy, gdx * dx, gdx * dy, gdy * dy, g_sigma)):
                moments[i].index_add_(0, gid64, v)
        a, b, c, o = geom[2:]
        s_x, s_y, s_xx, s_xy, s_yy, s_1 = moments
        g_geom = torch.stack([-(a * s_x + b * s_y), -(b * s_x + c * s_y), 0.5 * s_xx, s_xy, 0.5 * s_yy, -s_1 / o.clamp_min(1e-30)])  # s_1 = 0 where o = 0 (no pairs)
        return g_geom[:2].T, g_geom[2:5].T, g_geom[5], g_colors.T, g_bg, None, None, None, None


def rasterize_torch(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    background: torch.Tensor,
    pairs: PairList,
    width: int,
    height: int,
    config: RasterConfig = RasterConfig(),
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite projected Gaussians into an image (differentiable w.r.t. every tensor argument).

    Args:
        means2d: [N, 2] projected centres (pixels).
        conics: [N, 3] inverse 2D covariance (a, b, c), pixels^-2.
        opacities: [N] in [0, 1].
        colors: [N, C] any per-Gaussian channels (RGB, depth, features).
        background: [C] value composited behind the Gaussians with the final transmittance.
        pairs: from :func:`build_pairs`.
    Returns:
        image [H, W, C] and alpha [H, W].
    """
    out = _Composite.apply(means2d, conics, opacities, colors, background, pairs, width, height, config)
    out = out.view(height, width, -1)
    return out[..., :-1], out[..., -1]
