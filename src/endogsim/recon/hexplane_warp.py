"""HexPlane feature sampling in NVIDIA Warp: the fast CPU path of :class:`~endogsim.recon.hexplane.HexPlane`.

Per point and resolution level, the six planes are sampled bilinearly (``grid_sample`` with
``align_corners=True`` and border padding, exactly as the PyTorch reference) and multiplied channel-wise;
levels are concatenated. One thread handles one point; the backward pass recomputes the six samples, forms
the gradient of each as the upstream gradient times the product of the other five, scatters it to the
four plane cells (atomic adds) and to the point's coordinates.

On CPU PyTorch's ``grid_sampler_2d_backward`` plus the per-plane products cost more than the deformation
MLP at tens of thousands of Gaussians; these kernels do the same work in one pass per point, split over
the torch threads (:func:`endogsim.warp_runtime.launch_split`, one plane-gradient buffer per band).
Planes are read channel-last ([cells, C]) so that a cell's channels are one vector load.
"""

from __future__ import annotations

from typing import Any

import torch
import warp as wp

from endogsim.warp_runtime import float_vector, launch_split, n_bands, warp_array, warp_device

__all__ = ["hexplane_features_warp"]

#: Channels per plane the kernels are instantiated for at import (DeformationConfig's feature_dim: the
#: default and the quality preset's); another count instantiates them on first use (and rebuilds the module).
COMPILED_CHANNELS = (16, 32)

# The gradients are written by hand (hexplane_backward): Warp need not generate adjoint code.
wp.set_module_options({"enable_backward": False})


@wp.func
def _cell_coordinate(u: float, size: int):
    """Pixel coordinate of normalised ``u`` in [-1, 1] (align_corners=True), clamped to the border, and its
    derivative (0 at or beyond the border, as PyTorch's border padding)."""
    x = (u + 1.0) * 0.5 * float(size - 1)
    hi = float(size - 1)
    d = wp.where(x > 0.0, wp.where(x < hi, 0.5 * float(size - 1), 0.0), 0.0)
    return wp.clamp(x, 0.0, hi), d


@wp.func
def _corner_index(x: float, size: int):
    """Lower corner index of a clamped coordinate and the weight of the upper corner."""
    i0 = wp.min(int(wp.floor(x)), wp.max(size - 2, 0))
    return i0, x - float(i0)


@wp.func
def _bilinear_cells(offset: int, ra: int, rb: int, u: float, v: float):
    """The four cells around (u, v) on a plane ``ra`` wide and ``rb`` high whose first cell is ``offset``:
    indices i00, i01 (next along a), i10 (next along b), i11; the weights wx, wy of the upper corners; and
    du/dv, the derivatives of the cell coordinates w.r.t. u and v."""
    x, dxu = _cell_coordinate(u, ra)
    y, dyv = _cell_coordinate(v, rb)
    ix, wx = _corner_index(x, ra)
    iy, wy = _corner_index(y, rb)
    ix1 = wp.min(ix + 1, ra - 1)
    iy1 = wp.min(iy + 1, rb - 1)
    return (offset + iy * ra + ix, offset + iy * ra + ix1, offset + iy1 * ra + ix, offset + iy1 * ra + ix1,
            wx, wy, dxu, dyv)


@wp.func
def _sample(planes: wp.array(dtype=Any), offset: int, ra: int, rb: int, u: float, v: float):
    i00, i01, i10, i11, wx, wy, dxu, dyv = _bilinear_cells(offset, ra, rb, u, v)
    return (1.0 - wy) * ((1.0 - wx) * planes[i00] + wx * planes[i01]) + wy * ((1.0 - wx) * planes[i10] + wx * planes[i11])


@wp.kernel
def hexplane_forward(
    coords: wp.array2d(dtype=float),  # [N, 4] normalised (x, y, z, t) in [-1, 1]
    planes: wp.array(dtype=Any),  # [cells] C-channel vectors, all planes of all levels, channel-last
    plane_offset: wp.array(dtype=wp.int32),  # [L * 6] first cell of each plane
    plane_ra: wp.array(dtype=wp.int32),  # [L * 6] plane width (along its first axis)
    plane_rb: wp.array(dtype=wp.int32),  # [L * 6] plane height (along its second axis)
    axis_a: wp.array(dtype=wp.int32),  # [6] first coordinate of each plane
    axis_b: wp.array(dtype=wp.int32),  # [6] second coordinate
    n_points: int,
    n_levels: int,
    ones: Any,  # a C-channel vector of ones
    band: int,
    n_bands: int,
    features: wp.array(dtype=Any),  # [N * L] out: product of the six samples per level
):
    n = wp.tid() * n_bands + band
    if n >= n_points:
        return
    for level in range(n_levels):
        f = ones
        for j in range(6):
            p = level * 6 + j
            f = wp.cw_mul(f, _sample(planes, plane_offset[p], plane_ra[p], plane_rb[p],
                                     coords[n, axis_a[j]], coords[n, axis_b[j]]))
        features[n * n_levels + level] = f


@wp.kernel
def hexplane_backward(
    coords: wp.array2d(dtype=float),
    planes: wp.array(dtype=Any),
    plane_offset: wp.array(dtype=wp.int32),
    plane_ra: wp.array(dtype=wp.int32),
    plane_rb: wp.array(dtype=wp.int32),
    axis_a: wp.array(dtype=wp.int32),
    axis_b: wp.array(dtype=wp.int32),
    n_points: int,
    n_levels: int,
    band: int,
    n_bands: int,
    grad_features: wp.array(dtype=Any),  # [N * L]
    grad_planes: wp.array(dtype=Any),  # [cells] out (this band's buffer)
    grad_coords: wp.array2d(dtype=float),  # [N, 4] out (each point is written by one band only)
):
    n = wp.tid() * n_bands + band
    if n >= n_points:
        return
    for level in range(n_levels):
        g = grad_features[n * n_levels + level]
        base = level * 6
        s0 = _sample(planes, plane_offset[base], plane_ra[base], plane_rb[base], coords[n, axis_a[0]], coords[n, axis_b[0]])
        s1 = _sample(planes, plane_offset[base + 1], plane_ra[base + 1], plane_rb[base + 1], coords[n, axis_a[1]], coords[n, axis_b[1]])
        s2 = _sample(planes, plane_offset[base + 2], plane_ra[base + 2], plane_rb[base + 2], coords[n, axis_a[2]], coords[n, axis_b[2]])
        s3 = _sample(planes, plane_offset[base + 3], plane_ra[base + 3], plane_rb[base + 3], coords[n, axis_a[3]], coords[n, axis_b[3]])
        s4 = _sample(planes, plane_offset[base + 4], plane_ra[base + 4], plane_rb[base + 4], coords[n, axis_a[4]], coords[n, axis_b[4]])
        s5 = _sample(planes, plane_offset[base + 5], plane_ra[base + 5], plane_rb[base + 5], coords[n, axis_a[5]], coords[n, axis_b[5]])
        # d f / d s_j = product of the other five samples (prefix x suffix: no division by a zero sample)
        p01 = wp.cw_mul(s0, s1)
        p45 = wp.cw_mul(s4, s5)
        p012 = wp.cw_mul(p01, s2)
        p345 = wp.cw_mul(s3, p45)
        for j in range(6):
            others = wp.cw_mul(wp.cw_mul(s1, s2), p345)
            if j == 1:
                others = wp.cw_mul(wp.cw_mul(s0, s2), p345)
            elif j == 2:
                others = wp.cw_mul(p01, p345)
            elif j == 3:
                others = wp.cw_mul(p012, p45)
            elif j == 4:
                others = wp.cw_mul(p012, wp.cw_mul(s3, s5))
            elif j == 5:
                others = wp.cw_mul(p012, wp.cw_mul(s3, s4))
            gs = wp.cw_mul(g, others)
            p = base + j
            i00, i01, i10, i11, wx, wy, dxu, dyv = _bilinear_cells(plane_offset[p], plane_ra[p], plane_rb[p],
                                                                   coords[n, axis_a[j]], coords[n, axis_b[j]])
            wp.atomic_add(grad_planes, i00, ((1.0 - wy) * (1.0 - wx)) * gs)
            wp.atomic_add(grad_planes, i01, ((1.0 - wy) * wx) * gs)
            wp.atomic_add(grad_planes, i10, (wy * (1.0 - wx)) * gs)
            wp.atomic_add(grad_planes, i11, (wy * wx) * gs)
            c00 = planes[i00]
            c01 = planes[i01]
            c10 = planes[i10]
            c11 = planes[i11]
            ds_dx = (1.0 - wy) * (c01 - c00) + wy * (c11 - c10)
            ds_dy = (1.0 - wx) * (c10 - c00) + wx * (c11 - c01)
            grad_coords[n, axis_a[j]] = grad_coords[n, axis_a[j]] + wp.dot(gs, ds_dx) * dxu
            grad_coords[n, axis_b[j]] = grad_coords[n, axis_b[j]] + wp.dot(gs, ds_dy) * dyv


# Declared here so that the module is the same in every process (built once per machine): Warp builds a
# module again whenever a generic kernel meets new argument types (see rasterize_warp).
for _c in COMPILED_CHANNELS:
    _vec = float_vector(_c)
    wp.overload(hexplane_forward, {"planes": wp.array(dtype=_vec), "ones": _vec, "features": wp.array(dtype=_vec)})
    wp.overload(hexplane_backward, {"planes": wp.array(dtype=_vec), "grad_features": wp.array(dtype=_vec),
                                    "grad_planes": wp.array(dtype=_vec)})


class _HexPlaneSample(torch.autograd.Function):
    @staticmethod
    def forward(ctx, coords, axes, *planes):
        C = planes[0].shape[1]
        vec = float_vector(C)
        dev = coords.device
        # channel-last cells of every plane, in order; plane p = level * 6 + j
        cells = torch.cat([p.detach()[0].permute(1, 2, 0).reshape(-1, C) for p in planes]).float().contiguous()
        sizes = torch.tensor([[p.shape[3], p.shape[2]] for p in planes], dtype=torch.int32)
        offsets = torch.cumsum(sizes[:, 0] * sizes[:, 1], 0, dtype=torch.int32) - sizes[:, 0] * sizes[:, 1]
        meta = [offsets.to(dev), sizes[:, 0].contiguous().to(dev), sizes[:, 1].contiguous().to(dev),
                axes[0].to(dev), axes[1].to(dev)]
        N, L = coords.shape[0], len(planes) // 6
        xyzt = coords.detach().float().contiguous()
        feats = torch.empty(N * L, C, dtype=torch.float32, device=dev)
        device = warp_device(xyzt)
        common = [warp_array(xyzt), warp_array(cells, vec)] + [warp_array(m) for m in meta] + [N, L]
        if N > 0:
            launch_split(hexplane_forward, N, device, n_bands(device, N, 1024),
                         lambda b, nb: common + [vec(*([1.0] * C)), b, nb, warp_array(feats, vec)])
        ctx.save_for_backward(xyzt, cells, *meta)
        ctx.shapes = [tuple(p.shape) for p in planes]
        ctx.dtype = coords.dtype
        return feats.view(N, L * C).to(coords.dtype)

    @staticmethod
    def backward(ctx, grad):
        xyzt, cells, *meta = ctx.saved_tensors
        N, C = xyzt.shape[0], cells.shape[1]
        L = len(ctx.shapes) // 6
        vec = float_vector(C)
        device = warp_device(xyzt)
        bands = n_bands(device, N, 1024)
        g = grad.float().contiguous().view(N * L, C)
        g_cells = cells.new_zeros(bands, *cells.shape)
        g_coords = torch.zeros_like(xyzt)
        common = [warp_array(xyzt), warp_array(cells, vec)] + [warp_array(m) for m in meta] + [N, L]
        if N > 0:
            launch_split(hexplane_backward, N, device, bands,
                         lambda b, nb: common + [b, nb, warp_array(g, vec), warp_array(g_cells[b], vec),
                                                 warp_array(g_coords)])
        g_cells = g_cells.sum(0)
        grads, start = [], 0
        for shape in ctx.shapes:
            _, _, rb, ra = shape
            grads.append(g_cells[start:start + rb * ra].view(rb, ra, C).permute(2, 0, 1)[None].contiguous())
            start += rb * ra
        return (g_coords.to(ctx.dtype), None, *grads)


def hexplane_features_warp(coords: torch.Tensor, planes: list[torch.Tensor], axes: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """Features [N, L * C] of normalised points (differentiable w.r.t. the coordinates and every plane).

    Args:
        coords: [N, 4] (x, y, z, t) in [-1, 1].
        planes: L * 6 planes [1, C, R_b, R_a], level-major, in the order of ``axes``.
        axes: ([6], [6]) int32 coordinate index of each plane's first and second axis.
    """
    return _HexPlaneSample.apply(coords, axes, *planes)
