"""Procedural endoscopy-like geometry and textures, reusable by the benchmark scenes and the demo.

All functions are deterministic for a seed and return plain tensors (metres, colours in [0, 1]).

* :func:`endoscope_camera`: a fixed laparoscope (world = camera frame, OpenCV axes, ~70 deg field of view).
* :func:`mucosa_colors`: red-pink mucosa with vessels and specular highlights, from procedural noise.
* :func:`tissue_surface`: a textured height-field surface facing the camera -> surface points + colours.
* :func:`surface_gaussians`: flat Gaussians on the surface (the rendered tissue).
* :func:`tool_gaussians`: a metallic cylindrical instrument shaft with a tip, as Gaussians.
* :func:`bake_lighting`: endoscope light fall-off with distance and vignetting, baked into colours.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch

from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians, rgb_to_sh_dc, rotmat_to_quat

__all__ = [
    "endoscope_camera", "fractal_noise", "mucosa_colors", "tissue_surface", "surface_depth",
    "surface_gaussians", "tool_gaussians", "bake_lighting", "PALETTES",
]

# Base / dark / vessel colours per tissue look (linear RGB in [0, 1]).
PALETTES = {
    "mucosa": ((0.80, 0.38, 0.36), (0.55, 0.16, 0.16), (0.45, 0.05, 0.08)),
    "liver": ((0.55, 0.20, 0.16), (0.36, 0.10, 0.08), (0.30, 0.04, 0.06)),
    "gallbladder": ((0.55, 0.60, 0.38), (0.35, 0.45, 0.25), (0.40, 0.20, 0.25)),
    "stomach": ((0.86, 0.52, 0.48), (0.66, 0.28, 0.28), (0.50, 0.08, 0.12)),
    "fat": ((0.88, 0.76, 0.45), (0.72, 0.55, 0.30), (0.60, 0.20, 0.15)),
}


def endoscope_camera(width: int, height: int, fov_x_deg: float = 70.0) -> Camera:
    """A laparoscope-like pinhole camera: horizontal field of view ``fov_x_deg``, principal point centred."""
    focal = width / (2 * math.tan(math.radians(fov_x_deg) / 2))
    return Camera.from_focal(focal, width, height)


def fractal_noise(xy: np.ndarray, seed: int, base_freq: float, octaves: int = 4, waves: int = 12) -> np.ndarray:
    """Smooth pseudo-random noise at points ``xy`` [N, 2] (metres) -> [N] roughly in [-1, 1].

    A sum of random plane waves per octave (frequency ``base_freq`` cycles/metre, doubling per octave,
    amplitude halving): cheap, deterministic and isotropic enough for textures.
    """
    rng = np.random.default_rng(seed)
    out = np.zeros(len(xy))
    amp, freq, total = 1.0, base_freq, 0.0
    for _ in range(octaves):
        ang = rng.uniform(0, 2 * np.pi, waves)
        phase = rng.uniform(0, 2 * np.pi, waves)
        k = 2 * np.pi * freq * np.stack([np.cos(ang), np.sin(ang)], 1)
        out += amp * np.sin(xy @ k.T + phase).sum(1) / math.sqrt(waves / 2)
        total += amp
        amp *= 0.5
        freq *= 2.0
    return out / total


def mucosa_colors(xy: np.ndarray, seed: int, palette: str = "mucosa", vessel_density: float = 1.0,
                  highlights: float = 1.0) -> np.ndarray:
    """Texture colours [N, 3] in [0, 1] at surface coordinates ``xy`` [N, 2] (metres).

    Mottled base colour, branching dark-red vessels (zero crossings of two noise fields) and sparse
    specular highlights (peaks of a fine noise field), as seen under an endoscope's light.
    """
    base, dark, vessel = (np.array(c) for c in PALETTES[palette])
    mottle = fractal_noise(xy, seed, 60.0, octaves=4)
    col = base[None] + (dark - base)[None] * np.clip(0.45 + 0.35 * mottle, 0, 1)[:, None]
    for k, (freq, width) in enumerate(((70.0, 0.07), (160.0, 0.05))):
        n = fractal_noise(xy, seed + 101 + k, freq, octaves=3)
        strength = np.exp(-(n / width) ** 2) * vessel_density * (0.85 if k == 0 else 0.55)
        col = col * (1 - strength[:, None]) + vessel[None] * strength[:, None]
    spec = fractal_noise(xy, seed + 303, 150.0, octaves=2)
    hl = np.clip((spec - 1.55) / 0.3, 0, 1) ** 1.5 * highlights
    col = col * (1 - hl[:, None]) + np.array([1.0, 0.97, 0.95])[None] * hl[:, None]
    return np.clip(col, 0, 1)


def tissue_surface(
    center: tuple[float, float, float],
    size: tuple[float, float],
    spacing: float,
    seed: int,
    height_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    palette: str = "mucosa",
    bump: float = 0.002,
    mask_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A textured height-field surface facing the camera.

    Args:
        center: (x, y, z) of the surface centre (metres, camera frame; z = distance from the lens).
        size: (width, height) extent in x and y (metres).
        spacing: distance between surface samples (metres).
        seed: texture and bump seed.
        height_fn: optional extra depth offset (metres) as a function of local (u, v) [N] each (metres);
            positive = away from the camera. E.g. a dome: ``lambda u, v: -0.01 * np.exp(-(u*u+v*v)/r2)``.
        palette: key of :data:`PALETTES`.
        bump: amplitude (metres) of the random surface relief.
        mask_fn: optional keep-mask of (u, v) -> bool [N] (e.g. an elliptical organ outline).
    Returns:
        points [N, 3] (metres), colours [N, 3] in [0, 1], uv [N, 2] (metres, local surface coordinates).
    """
    nu_, nv_ = max(2, round(size[0] / spacing) + 1), max(2, round(size[1] / spacing) + 1)
    u, v = np.meshgrid(np.linspace(-size[0] / 2, size[0] / 2, nu_), np.linspace(-size[1] / 2, size[1] / 2, nv_))
    u, v = u.ravel(), v.ravel()
    if mask_fn is not None:
        keep = mask_fn(u, v)
        u, v = u[keep], v[keep]
    uv = np.stack([u, v], 1)
    z = surface_depth(uv, center[2], seed, height_fn, bump)
    pts = np.stack([center[0] + u, center[1] + v, z], 1)
    return pts, mucosa_colors(uv + np.array(center[:2])[None], seed, palette), uv


def surface_depth(uv: np.ndarray, distance: float, seed: int,
                  height_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                  bump: float = 0.002) -> np.ndarray:
    """Depth [N] (metres from the lens) of :func:`tissue_surface`'s surface at local coordinates ``uv`` [N, 2]
    (metres): ``distance`` (its centre's z), the seed's random relief of amplitude ``bump``, ``height_fn``."""
    uv = np.asarray(uv, float).reshape(-1, 2)
    z = distance + bump * fractal_noise(uv, seed + 7, 25.0, octaves=2)
    if height_fn is not None:
        z = z + height_fn(uv[:, 0], uv[:, 1])
    return z


def _normals_from_neighbours(points: np.ndarray) -> np.ndarray:
    # Surface normal facing the camera (-z) for flat Gaussians; local PCA over a few neighbours.
    from scipy.spatial import cKDTree

    k = min(8, len(points))
    _, nb = cKDTree(points).query(points, k=k)
    q = points[nb] - points[nb].mean(1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", q, q)
    _, vecs = np.linalg.eigh(cov)
    n = vecs[:, :, 0]
    n[n[:, 2] > 0] *= -1
    return n


def _frames_from_normals(n: np.ndarray) -> np.ndarray:
    """Rotation matrices [N, 3, 3] whose third column is the normal ``n`` [N, 3]."""
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    R = np.stack([t1, t2, n], 2)
    R[np.linalg.det(R) < 0, :, 0] *= -1
    return R


def surface_gaussians(points: np.ndarray, colors: np.ndarray, spacing: float, object_id: int,
                      opacity: float = 0.98, flatness: float = 0.15) -> Gaussians:
    """Flat Gaussians (discs tangent to the surface) at ``points`` [N, 3] with ``colors`` [N, 3].

    In-plane standard deviation 0.7 x ``spacing`` (metres) so neighbours overlap without holes; normal
    standard deviation ``flatness`` times that.
    """
    n = _normals_from_neighbours(points)
    R = _frames_from_normals(n)
    s = 0.7 * spacing
    scales = np.tile(np.array([[s, s, s * flatness]]), (len(points), 1))
    g = Gaussians.from_points(torch.tensor(points, dtype=torch.float32), torch.tensor(colors, dtype=torch.float32),
                              torch.tensor(scales, dtype=torch.float32), object_ids=object_id, opacity=opacity)
    return g.with_(quats=rotmat_to_quat(torch.tensor(R, dtype=torch.float32)))


def tool_gaussians(a: np.ndarray, b: np.ndarray, radius: float, spacing: float, object_id: int,
                   seed: int = 0, jaw: bool = False) -> Gaussians:
    """A metallic instrument: a cylinder of ``radius`` (metres) from tip ``a`` [3] to shaft end ``b`` [3].

    Grey steel with a brighter streak along the shaft (the specular line of a cylinder) and, with
    ``jaw``, a darker grasper head over the first 25 % of its length. Isotropic Gaussians of std
    0.6 x ``spacing`` cover the surface facing the camera.
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    axis = b - a
    length = float(np.linalg.norm(axis))
    d = axis / length
    R = _frames_from_normals(d[None])[0]
    e1, e2 = R[:, 0], R[:, 1]
    n_len = max(2, int(length / spacing) + 1)
    n_ang = max(6, int(2 * np.pi * radius / spacing) + 1)
    t, ang = np.meshgrid(np.linspace(0, length, n_len), np.linspace(0, 2 * np.pi, n_ang, endpoint=False))
    t, ang = t.ravel(), ang.ravel()
    radial = np.cos(ang)[:, None] * e1[None] + np.sin(ang)[:, None] * e2[None]
    pts = a[None] + t[:, None] * d[None] + radius * radial
    # Cap at the tip so the tool looks closed when pointing at the camera.
    cap_r = np.linspace(0, radius, max(2, int(radius / spacing) + 1))
    cr, ca = np.meshgrid(cap_r, np.linspace(0, 2 * np.pi, n_ang, endpoint=False))
    cap = a[None] + cr.ravel()[:, None] * (np.cos(ca.ravel())[:, None] * e1 + np.sin(ca.ravel())[:, None] * e2)
    pts = np.concatenate([pts, cap])
    to_cam = -pts / np.linalg.norm(pts, axis=1, keepdims=True)
    shade = np.concatenate([np.clip((radial * to_cam[: len(radial)]).sum(1), 0, 1), np.full(len(cap), 0.8)])
    rng = np.random.default_rng(seed)
    grey = 0.35 + 0.45 * shade + 0.03 * rng.standard_normal(len(pts))
    streak = np.exp(-((shade - 0.97) / 0.03) ** 2)
    col = np.clip(np.stack([grey, grey * 1.02, grey * 1.06], 1) + 0.4 * streak[:, None], 0, 1)
    if jaw:
        tt = np.concatenate([t, np.zeros(len(cap))])
        head = tt < 0.25 * length
        col[head] *= 0.45
    return Gaussians.from_points(torch.tensor(pts, dtype=torch.float32), torch.tensor(col, dtype=torch.float32),
                                 0.6 * spacing, object_ids=object_id, opacity=0.99)


def bake_lighting(g: Gaussians, camera: Camera, ref_distance: float, vignette: float = 0.45) -> Gaussians:
    """Endoscope lighting baked into the colours: inverse-square fall-off around ``ref_distance``
    (metres; the light sits at the lens) and radial vignetting of strength ``vignette`` at the corners."""
    means = g.means.detach().double()
    dist = means.norm(dim=1)
    fall = (ref_distance / dist).clamp(max=1.6) ** 2
    K = camera.K.double()
    uvw = means @ K.T
    px = uvw[:, :2] / uvw[:, 2:3]
    c = torch.tensor([camera.width / 2, camera.height / 2], dtype=torch.float64)
    r = ((px - c) / c.norm()).norm(dim=1)
    vig = 1 - vignette * r.clamp(max=1.2) ** 2
    rgb = (g.colors_dc.double() * (fall * vig).clamp(0.05, 1.3)[:, None]).clamp(0, 1)
    sh = g.sh.clone()
    sh[:, 0] = rgb_to_sh_dc(rgb.to(sh.dtype))
    return g.with_(sh=sh)
