"""Tile-based Gaussian compositing in NVIDIA Warp: the fast CPU backend (the kernels also run on CUDA).

The projection (EWA splatting) stays in PyTorch (:func:`~endogsim.gaussians.rasterize_torch.project_gaussians`,
plain autograd); this module replaces the pair-list compositing of the PyTorch reference with the
scheme of the reference 3DGS CUDA rasteriser, compiled by Warp:

1. :func:`bin_gaussians` (PyTorch, no gradient): every visible Gaussian is listed in each
   ``tile_size`` x ``tile_size`` pixel tile its opacity-aware screen box touches; one stable sort by tile
   of the depth-ordered list gives each tile its Gaussians front to back.
2. :func:`composite_forward` (one thread per pixel): walks its tile's list front to back with the
   conventions of the reference (alpha clamp 0.99, skip below 1/255, stop before the transmittance falls
   to 1e-4) and, when gradients are wanted, records which Gaussians contributed to the pixel. A pair
   whose exponent exceeds its Gaussian's ln(opacity / alpha_min) is left before the exponential.
3. :func:`composite_backward` (one thread per pixel): walks the recorded contributors back to front,
   recovering the transmittance in front of each by division and carrying the scalar
   ``S = sum_{j>k} w_j c_j . g + T_final bg . g``, so any number of channels needs no per-channel state;
   gradients reach the Gaussians by atomic adds.

On CPU Warp runs a launch serially as native code and releases the GIL meanwhile, so each launch is
split into interleaved pixel bands, one per torch thread, launched from a small thread pool (every band
accumulates gradients in its own buffer). Pixels are visited tile by tile, so a thread finds the
Gaussians of a tile's list in its cache. The per-pair work costs nanoseconds instead of the dozen tensor
passes per pair of the PyTorch path; ``endogsim bench render`` compares the two. Kernels are float32 (a
per-pixel running product needs no float64, unlike the PyTorch path's long cumulative sums).
"""

from __future__ import annotations

from typing import Any

import torch
import warp as wp

from endogsim.gaussians.types import RasterConfig
from endogsim.warp_runtime import float_vector, launch_split, n_bands, warp_array as _wp, warp_device

__all__ = ["TILE_SIZE", "CHANNEL_QUANTUM", "COMPILED_CHANNELS", "TileBins", "bin_gaussians", "padded_channels",
           "rasterize_warp"]

#: Default tile edge (pixels). Smaller tiles list a Gaussian in more tiles but make every pixel test
#: fewer Gaussians that miss it; on a serial CPU the tests dominate (see ``endogsim bench render``).
TILE_SIZE = 4

#: Renders composite their channels (RGB, depth, then any features) zero-padded to a multiple of this.
CHANNEL_QUANTUM = 4
#: Padded channel counts the kernels are instantiated for at import (colour and depth with up to 12 features).
COMPILED_CHANNELS = (4, 8, 12, 16)

# The gradients are written by hand (composite_backward): Warp need not generate adjoint code, which halves
# the module's build.
wp.set_module_options({"enable_backward": False})


@wp.func
def gaussian_sigma(px: float, py: float, mean: wp.vec2, conic: wp.vec3):
    """The exponent 0.5 d^T Sigma2D^-1 d at pixel centre (px, py); d = pixel - mean."""
    dx = px - mean[0]
    dy = py - mean[1]
    return 0.5 * (conic[0] * dx * dx + conic[2] * dy * dy) + conic[1] * dx * dy


@wp.func
def pixel_tile_list(item: int, width: int, height: int, tiles_x: int, tile_size: int,
                    tile_offsets: wp.array(dtype=wp.int32)):
    """The pixel of launch item ``item``: items run tile by tile (the pixels of a tile in a row, so a
    thread reuses the tile's Gaussians from its cache instead of fetching them once per image row).

    Returns the pixel's index p (row-major, -1 for the items of an edge tile beyond the image), its
    centre (px, py), its tile's list ``[begin, end)`` in ``gaussian_ids``, and the first slot of its
    contributor list in ``contrib``: every pixel of a tile gets as many slots as the tile's list is long,
    which bounds its contributors (the forward pass writes there, the backward pass reads)."""
    area = tile_size * tile_size
    tile = item / area
    local = item % area
    x = (tile % tiles_x) * tile_size + local % tile_size
    y = (tile / tiles_x) * tile_size + local / tile_size
    begin = tile_offsets[tile]
    end = tile_offsets[tile + 1]
    slot = begin * area + local * (end - begin)
    p = wp.where((x < width) and (y < height), y * width + x, -1)
    return p, float(x) + 0.5, float(y) + 0.5, begin, end, slot


@wp.kernel
def composite_forward(
    tile_offsets: wp.array(dtype=wp.int32),  # [n_tiles + 1] start of each tile's list in gaussian_ids
    gaussian_ids: wp.array(dtype=wp.int32),  # [M] per tile, front to back
    means2d: wp.array(dtype=wp.vec2),  # [N] pixels
    conics: wp.array(dtype=wp.vec3),  # [N] (a, b, c) of the inverse 2D covariance
    opacities: wp.array(dtype=float),  # [N]
    sigma_cut: wp.array(dtype=float),  # [N] ln(opacity / alpha_min): the pair's alpha < alpha_min beyond it
    colors: wp.array(dtype=Any),  # [N] vectors of C channels
    background: Any,  # C channels
    width: int,
    height: int,
    n_items: int,  # tiles * tile_size^2
    tiles_x: int,
    tile_size: int,
    alpha_min: float,
    alpha_max: float,
    transmittance_min: float,
    band: int,
    n_bands: int,
    record: int,
    image: wp.array(dtype=Any),  # [P] out: C channels per pixel
    final_transmittance: wp.array(dtype=float),  # [P] out
    n_contrib: wp.array(dtype=wp.int32),  # [P] out: pairs recorded for the backward pass
    contrib: wp.array(dtype=wp.int32),  # [M * tile_size^2] out (when record): each pixel's contributors
):
    item = wp.tid() * n_bands + band  # bands interleave pixels so that every band gets the same mix of work
    if item >= n_items:
        return
    p, px, py, begin, end, slot = pixel_tile_list(item, width, height, tiles_x, tile_size, tile_offsets)
    if p < 0:
        return
    acc = background * 0.0
    T = float(1.0)
    n = int(0)
    for k in range(begin, end):
        g = gaussian_ids[k]
        sigma = gaussian_sigma(px, py, means2d[g], conics[g])
        # Most pairs of a tile's list miss the pixel (the tissue never becomes opaque enough to stop the
        # walk early): leave them before the exponential, which is most of a pair's cost.
        if sigma > sigma_cut[g]:
            continue
        alpha = wp.min(alpha_max, opacities[g] * wp.exp(-sigma))
        # The remaining skipped pairs (alpha < 1/255 by rounding, or sigma < 0 from a degenerate conic) get
        # alpha 0, which changes nothing.
        alpha = wp.where(sigma >= 0.0, wp.where(alpha >= alpha_min, alpha, 0.0), 0.0)
        next_T = T * (1.0 - alpha)
        if next_T <= transmittance_min:
            break
        acc = acc + (alpha * T) * colors[g]
        T = next_T
        if record != 0:
            contrib[slot + n] = g  # overwritten by the next pair unless this one counts
            n = n + wp.where(alpha > 0.0, 1, 0)
    image[p] = acc + T * background
    final_transmittance[p] = T
    n_contrib[p] = n


@wp.kernel
def composite_backward(
    tile_offsets: wp.array(dtype=wp.int32),
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=float),
    colors: wp.array(dtype=Any),
    background: Any,
    width: int,
    height: int,
    n_items: int,
    tiles_x: int,
    tile_size: int,
    alpha_max: float,
    band: int,
    n_bands: int,
    final_transmittance: wp.array(dtype=float),
    n_contrib: wp.array(dtype=wp.int32),
    contrib: wp.array(dtype=wp.int32),
    grad_image: wp.array(dtype=Any),  # [P] d loss / d image (C channels)
    grad_alpha: wp.array(dtype=float),  # [P] d loss / d (1 - T_final)
    grad_means2d: wp.array(dtype=wp.vec2),  # [N] out (accumulated, this band's buffer)
    grad_conics: wp.array(dtype=wp.vec3),  # [N] out
    grad_opacities: wp.array(dtype=float),  # [N] out
    grad_colors: wp.array(dtype=Any),  # [N] out
):
    item = wp.tid() * n_bands + band
    if item >= n_items:
        return
    p, px, py, begin, end, slot = pixel_tile_list(item, width, height, tiles_x, tile_size, tile_offsets)
    if p < 0:
        return
    T = final_transmittance[p]
    g_img = grad_image[p]
    g_alpha_px = grad_alpha[p]
    # S: what the pairs behind the current one (and the background) contribute to d loss.
    S = T * wp.dot(background, g_img)
    for i in range(n_contrib[p] - 1, -1, -1):  # back to front over the pairs that contributed
        g = contrib[slot + i]
        mean = means2d[g]
        conic = conics[g]
        sigma = gaussian_sigma(px, py, mean, conic)
        o = opacities[g]
        raw = o * wp.exp(-sigma)
        alpha = wp.min(alpha_max, raw)
        T = T / (1.0 - alpha)  # transmittance in front of this pair
        w = alpha * T
        wp.atomic_add(grad_colors, g, w * g_img)
        cg = wp.dot(colors[g], g_img) + g_alpha_px  # the alpha channel composites a colour of 1
        d_alpha = T * cg - S / (1.0 - alpha)
        S = S + w * cg
        if raw < alpha_max:  # a clamped alpha does not depend on the Gaussian
            d_sigma = -alpha * d_alpha
            dx = px - mean[0]
            dy = py - mean[1]
            wp.atomic_add(grad_means2d, g, wp.vec2(-d_sigma * (conic[0] * dx + conic[1] * dy),
                                                   -d_sigma * (conic[1] * dx + conic[2] * dy)))
            wp.atomic_add(grad_conics, g, wp.vec3(0.5 * d_sigma * dx * dx, d_sigma * dx * dy, 0.5 * d_sigma * dy * dy))
            wp.atomic_add(grad_opacities, g, d_alpha * alpha / o)


# Warp builds a module again, all its kernels, whenever a generic kernel meets new argument types: a
# renderer instantiated for each channel count as it was met was built 7 times by a first demo (seconds
# each on a CPU), and again by every process that met the counts in another order. With the channel counts
# padded to a few and those declared here, the module is the same in every process and built once per machine.
for _c in COMPILED_CHANNELS:
    _vec = float_vector(_c)
    wp.overload(composite_forward, {"colors": wp.array(dtype=_vec), "background": _vec, "image": wp.array(dtype=_vec)})
    wp.overload(composite_backward, {"colors": wp.array(dtype=_vec), "background": _vec,
                                     "grad_image": wp.array(dtype=_vec), "grad_colors": wp.array(dtype=_vec)})


def padded_channels(channels: int) -> int:
    """The channel count a render of ``channels`` channels composites (zero-padded; see :data:`CHANNEL_QUANTUM`).
    Padding changes no bit of the real channels: every channel is composited on its own, and the padded
    ones add exact zeros to the backward pass's dot products."""
    return -(-channels // CHANNEL_QUANTUM) * CHANNEL_QUANTUM


class TileBins:
    """Per-tile, depth-ordered Gaussian lists of one render (no gradients).

    Attributes:
        offsets: [n_tiles + 1] int32, tile t owns ``gaussian_ids[offsets[t]:offsets[t + 1]]``.
        gaussian_ids: [M] int32 Gaussian indices, front to back within each tile.
        tiles_x: tiles per image row.  tile_size: tile edge (pixels).
    """

    def __init__(self, offsets: torch.Tensor, gaussian_ids: torch.Tensor, tiles_x: int, tile_size: int) -> None:
        self.offsets, self.gaussian_ids, self.tiles_x, self.tile_size = offsets, gaussian_ids, tiles_x, tile_size

    @property
    def n_pairs(self) -> int:
        return int(self.gaussian_ids.numel())

    @property
    def n_items(self) -> int:
        """Launch items of the compositing kernels: every pixel slot of every tile (edge tiles included)."""
        return (len(self.offsets) - 1) * self.tile_size**2


def bin_gaussians(means2d: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor, valid: torch.Tensor,
                  width: int, height: int, tile_size: int = TILE_SIZE) -> TileBins:
    """List every visible Gaussian in the tiles its screen box touches, front to back per tile.

    Args:
        means2d: [N, 2] projected centres (pixels).
        radii: [N, 2] int half-extents of the screen boxes (pixels; alpha < 1/255 outside).
        depths: [N] camera z (sort key).
        valid: [N] bool, drawn at all.
        width, height: image size (pixels).
        tile_size: tile edge (pixels).
    """
    with torch.no_grad():
        dev = means2d.device
        tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
        vis = torch.nonzero(valid).squeeze(1)
        order = vis[torch.argsort(depths.detach()[vis], stable=True)]
        m = means2d.detach()[order]
        r = radii[order].to(m.dtype)
        # pixel j has its centre at j + 0.5: the box covers centres within the radius of the mean
        x0 = torch.ceil(m[:, 0] - r[:, 0] - 0.5).clamp(0, width - 1).long() // tile_size
        x1 = torch.floor(m[:, 0] + r[:, 0] - 0.5).clamp(0, width - 1).long() // tile_size
        y0 = torch.ceil(m[:, 1] - r[:, 1] - 0.5).clamp(0, height - 1).long() // tile_size
        y1 = torch.floor(m[:, 1] + r[:, 1] - 0.5).clamp(0, height - 1).long() // tile_size
        nx, ny = (x1 - x0 + 1).clamp_min(0), (y1 - y0 + 1).clamp_min(0)
        counts = nx * ny
        total = int(counts.sum())
        rank = torch.repeat_interleave(torch.arange(len(order), device=dev), counts, output_size=total)
        local = torch.arange(total, device=dev) - (torch.cumsum(counts, 0) - counts)[rank]
        nxr = nx[rank]
        tile = (y0[rank] + local // nxr) * tiles_x + x0[rank] + local % nxr
        # Entries are depth-major, so a stable sort by tile keeps each tile's list front to back.
        tile, perm = torch.sort(tile.to(torch.int32), stable=True)
        ids = order[rank[perm]].to(torch.int32)
        per_tile = torch.bincount(tile, minlength=tiles_x * tiles_y)
        offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int32, device=dev)
        offsets[1:] = torch.cumsum(per_tile, 0)
    return TileBins(offsets, ids.contiguous(), tiles_x, tile_size)


class _TileComposite(torch.autograd.Function):
    """Alpha compositing of binned Gaussians (Warp kernels) with the reference's closed-form backward."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, background, bins: TileBins, width: int, height: int,
                config: RasterConfig):
        f32 = torch.float32
        dev = means2d.device
        inputs = [t.detach().to(f32).contiguous() for t in (means2d, conics, opacities, colors, background)]
        m2, co, op, col, bg = inputs
        P, C = width * height, col.shape[1]
        Cp = padded_channels(C)
        col, bg = torch.nn.functional.pad(col, (0, Cp - C)), torch.nn.functional.pad(bg, (0, Cp - C))
        vec = float_vector(Cp)
        record = any(ctx.needs_input_grad[:5])
        image = torch.empty(P, Cp, dtype=f32, device=dev)
        t_final = torch.empty(P, dtype=f32, device=dev)
        n_contrib = torch.zeros(P, dtype=torch.int32, device=dev)
        capacity = bins.n_pairs * bins.tile_size**2 if record else 1
        contrib = torch.empty(max(capacity, 1), dtype=torch.int32, device=dev)
        if P > 0:
            sigma_cut = torch.log(op.clamp_min(1e-30) / config.alpha_min)
            common = [_wp(bins.offsets), _wp(bins.gaussian_ids), _wp(m2, wp.vec2), _wp(co, wp.vec3), _wp(op),
                      _wp(sigma_cut), _wp(col, vec), vec(*bg.tolist()), width, height, bins.n_items, bins.tiles_x,
                      bins.tile_size, config.alpha_min, config.alpha_max, config.transmittance_min]
            outs = [_wp(image, vec), _wp(t_final), _wp(n_contrib), _wp(contrib)]
            device = warp_device(m2)
            launch_split(composite_forward, bins.n_items, device, n_bands(device, P),
                         lambda b, n: common + [b, n, int(record)] + outs)
        ctx.bins, ctx.width, ctx.height, ctx.config = bins, width, height, config
        ctx.dtypes = [t.dtype for t in (means2d, conics, opacities, colors, background)]
        ctx.save_for_backward(m2, co, op, col, bg, t_final, n_contrib, contrib)
        out = torch.cat([image[:, :C], (1.0 - t_final)[:, None]], 1)
        return out.to(colors.dtype)

    @staticmethod
    def backward(ctx, grad_out):
        m2, co, op, col, bg, t_final, n_contrib, contrib = ctx.saved_tensors
        bins, cfg = ctx.bins, ctx.config
        g = grad_out.to(torch.float32)
        P, Cp = len(t_final), col.shape[1]  # col and bg are padded to Cp channels, grad_out has C + 1
        C = g.shape[1] - 1
        vec = float_vector(Cp)
        g_img, g_alpha = g[:, :C].contiguous(), g[:, C].contiguous()
        g_img_padded = torch.nn.functional.pad(g_img, (0, Cp - C))
        device = warp_device(m2)
        nb = n_bands(device, P)
        # one gradient buffer per band: CPU atomics are plain adds, so bands must not share one
        g_m2, g_co = m2.new_zeros(nb, *m2.shape), co.new_zeros(nb, *co.shape)
        g_op, g_col = op.new_zeros(nb, *op.shape), col.new_zeros(nb, *col.shape)
        if P > 0:
            common = [_wp(bins.offsets), _wp(m2, wp.vec2), _wp(co, wp.vec3), _wp(op), _wp(col, vec),
                      vec(*bg.tolist()), ctx.width, ctx.height, bins.n_items, bins.tiles_x, bins.tile_size,
                      cfg.alpha_max]
            rest = [_wp(t_final), _wp(n_contrib), _wp(contrib), _wp(g_img_padded, vec), _wp(g_alpha)]

            def inputs(b, n):
                return common + [b, n] + rest + [_wp(g_m2[b], wp.vec2), _wp(g_co[b], wp.vec3), _wp(g_op[b]),
                                                 _wp(g_col[b], vec)]

            launch_split(composite_backward, bins.n_items, device, nb, inputs)
        g_bg = g_img.T @ t_final
        grads = (g_m2.sum(0), g_co.sum(0), g_op.sum(0), g_col.sum(0)[:, :C], g_bg)
        return (*(gr.to(dt) for gr, dt in zip(grads, ctx.dtypes)), None, None, None, None)


def rasterize_warp(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    background: torch.Tensor,
    bins: TileBins,
    width: int,
    height: int,
    config: RasterConfig = RasterConfig(),
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite projected Gaussians into an image (differentiable w.r.t. every tensor argument); the
    same contract as :func:`~endogsim.gaussians.rasterize_torch.rasterize_torch`.

    Args:
        means2d: [N, 2] projected centres (pixels).
        conics: [N, 3] inverse 2D covariance (a, b, c), pixels^-2.
        opacities: [N] in [0, 1].
        colors: [N, C] any per-Gaussian channels (RGB, depth, features).
        background: [C] value composited behind the Gaussians with the final transmittance.
        bins: from :func:`bin_gaussians`.
    Returns:
        image [H, W, C] and alpha [H, W].
    """
    out = _TileComposite.apply(means2d, conics, opacities, colors, background, bins, width, height, config)
    out = out.view(height, width, -1)
    return out[..., :-1], out[..., -1]
