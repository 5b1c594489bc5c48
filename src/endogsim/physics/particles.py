"""Particles from Gaussians, and Gaussians that follow the particles.

- :func:`particles_from_gaussians`: choose the simulated Gaussians (by object id), give a surface seen
  from one side a volume by extruding it along the viewing rays by a thickness, and resample on a
  regular lattice of ``spacing`` so that each particle carries the volume spacing^3 (mass = rho * volume
  inside the simulator).
- :func:`bind_gaussians` / :func:`drive_gaussians`: move every Gaussian with its k nearest particles of
  the same object: mean_t = mean_0 + sum_k w_k (x_k,t - x_k,0), F_g = sum_k w_k F_k,t,
  Sigma_t = F_g Sigma_0 F_g^T, and SH colour rotated by the polar rotation of F_g.

Units: metres, world coordinates. All tensors on CPU or any torch device; driving is differentiable in
the particle positions and deformation gradients (the SH rotation is treated as a constant).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from endogsim.errors import ModelError, SimulationError
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians, sh_degree_from_count
from endogsim.gaussians.sh import sh_basis
from endogsim.physics.polar import polar_rotation_torch


@dataclass
class Particles:
    """Material points of the simulation.

    Attributes:
        x: [P, 3] rest positions (metres, world).
        volume: [P] volume each particle stands for (m^3); mass = density * volume.
        object_ids: [P] int64 object id (indexes the per-object material arrays).
        v: [P, 3] initial velocities (m/s) or None for rest.
    """

    x: torch.Tensor
    volume: torch.Tensor
    object_ids: torch.Tensor
    v: torch.Tensor | None = None

    def __post_init__(self) -> None:
        P = self.x.shape[0]
        if self.x.ndim != 2 or self.x.shape[1] != 3:
            raise SimulationError(f"Particles.x has shape {tuple(self.x.shape)}, expected (P, 3)")
        if tuple(self.volume.shape) != (P,) or tuple(self.object_ids.shape) != (P,):
            raise SimulationError("Particles.volume and object_ids must have shape (P,)")
        if self.v is not None and tuple(self.v.shape) != (P, 3):
            raise SimulationError(f"Particles.v has shape {tuple(self.v.shape)}, expected ({P}, 3)")
        if P and not torch.isfinite(self.x).all():
            raise SimulationError("Particles.x holds NaN/inf")
        if P and not (self.volume > 0).all():
            raise SimulationError("Particles.volume must be > 0")

    def __len__(self) -> int:
        return self.x.shape[0]

    def subset(self, index: torch.Tensor) -> "Particles":
        return Particles(self.x[index], self.volume[index], self.object_ids[index],
                         None if self.v is None else self.v[index])

    @staticmethod
    def concat(parts: list["Particles"]) -> "Particles":
        v = None
        if any(p.v is not None for p in parts):
            v = torch.cat([p.v if p.v is not None else torch.zeros_like(p.x) for p in parts])
        return Particles(torch.cat([p.x for p in parts]), torch.cat([p.volume for p in parts]),
                         torch.cat([p.object_ids for p in parts]), v)

    @staticmethod
    def box(lo, hi, spacing: float, object_id: int = 0, dtype=torch.float32) -> "Particles":
        """A solid box [lo, hi] (metres) filled on a lattice of ``spacing`` (cell-centred)."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        counts = np.maximum(np.round((hi - lo) / spacing).astype(int), 1)
        axes = [lo[i] + (np.arange(counts[i]) + 0.5) * (hi[i] - lo[i]) / counts[i] for i in range(3)]
        g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        cell = np.prod((hi - lo) / counts)
        P = g.shape[0]
        return Particles(torch.as_tensor(g, dtype=dtype), torch.full((P,), float(cell), dtype=dtype),
                         torch.full((P,), int(object_id), dtype=torch.int64))


def extrude_along_rays(points: torch.Tensor, center: torch.Tensor, thickness: float, spacing: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Give a one-sided surface a volume: copies of ``points`` pushed away from the camera along the rays.

    Args:
        points: [N, 3] visible surface points (metres, world).
        center: [3] camera centre (metres, world).
        thickness: how far behind the surface the solid extends (metres).
        spacing: distance between layers (metres).
    Returns:
        extruded points [N * L, 3] (layer 0 = the surface) and the index [N * L] of their surface point.
    """
    rays = points - center.to(points)
    rays = rays / rays.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    layers = max(1, int(round(thickness / spacing)) + 1)
    depths = torch.linspace(0.0, thickness, layers, dtype=points.dtype)
    out = (points[None] + depths[:, None, None] * rays[None]).reshape(-1, 3)
    src = torch.arange(points.shape[0]).repeat(layers)
    return out, src


def voxel_downsample(points: torch.Tensor, spacing: float) -> torch.Tensor:
    """One point per occupied voxel of edge ``spacing`` (the mean of the points in it): [M, 3]."""
    key = torch.floor(points / spacing).to(torch.int64)
    _, inv = torch.unique(key, dim=0, return_inverse=True)
    M = int(inv.max()) + 1
    sums = torch.zeros(M, 3, dtype=points.dtype).index_add_(0, inv, points)
    counts = torch.zeros(M, dtype=points.dtype).index_add_(0, inv, torch.ones_like(points[:, 0]))
    return sums / counts[:, None]


def particles_from_gaussians(
    gaussians: Gaussians,
    spacing: float,
    object_ids: list[int] | None = None,
    thickness: float = 0.0,
    camera: Camera | None = None,
    min_opacity: float = 0.05,
) -> Particles:
    """Particles for the selected Gaussians.

    Args:
        gaussians: the scene's Gaussians (world metres).
        spacing: particle lattice spacing (metres); each particle's volume is spacing^3. Half a grid cell
            (8 particles per cell) is the usual MPM choice.
        object_ids: ids of the objects to simulate (default: every id present).
        thickness: extrusion depth behind the visible surface (metres); 0 keeps the Gaussian centres as a
            solid sample (e.g. a volumetric reconstruction).
        camera: the camera the surface was seen from (needed when thickness > 0).
        min_opacity: Gaussians less opaque than this are ignored.
    Returns:
        :class:`Particles` (rest positions, volumes, object ids), objects resampled separately.
    """
    if spacing <= 0:
        raise SimulationError(f"particle spacing {spacing} m must be > 0")
    if thickness > 0 and camera is None:
        raise SimulationError("extruding by a thickness needs the camera the surface was seen from")
    ids = gaussians.object_ids.cpu()
    keep_ids = torch.unique(ids).tolist() if object_ids is None else list(object_ids)
    parts = []
    for oid in keep_ids:
        sel = (ids == oid) & (gaussians.opacities.detach().cpu() >= min_opacity)
        pts = gaussians.means.detach().cpu().to(torch.float64)[sel]
        if pts.shape[0] == 0:
            continue
        if thickness > 0:
            pts, _ = extrude_along_rays(pts, camera.center().double(), thickness, spacing)
        x = voxel_downsample(pts, spacing)
        parts.append(Particles(x.float(), torch.full((x.shape[0],), spacing**3, dtype=torch.float32),
                               torch.full((x.shape[0],), int(oid), dtype=torch.int64)))
    if not parts:
        raise SimulationError(f"no Gaussians of objects {keep_ids} (opacity >= {min_opacity}) to make particles from")
    return Particles.concat(parts)


@dataclass
class GaussianBinding:
    """How each Gaussian follows particles (see :func:`bind_gaussians`).

    Attributes:
        index: [G, k] particle indices (of the same object); a Gaussian without particles has weights 0.
        weights: [G, k] inverse-square-distance weights summing to 1 (or 0 for a static Gaussian).
        particle_rest: [P, 3] particle rest positions (metres).
    """

    index: torch.Tensor
    weights: torch.Tensor
    particle_rest: torch.Tensor


def bind_gaussians(gaussian_means: torch.Tensor, gaussian_object_ids: torch.Tensor, particles: Particles, k: int = 8) -> GaussianBinding:
    """k nearest particles of the same object for every Gaussian (rest configuration).

    Args:
        gaussian_means: [G, 3] rest centres (metres); gaussian_object_ids: [G] int64.
        particles: the simulated particles.
        k: neighbours per Gaussian.
    """
    from scipy.spatial import cKDTree

    gm = gaussian_means.detach().cpu().double().numpy()
    gid = gaussian_object_ids.cpu().numpy()
    px = particles.x.detach().cpu().double().numpy()
    pid = particles.object_ids.cpu().numpy()
    G = gm.shape[0]
    index = np.zeros((G, k), dtype=np.int64)
    weights = np.zeros((G, k), dtype=np.float64)
    for oid in np.unique(gid):
        gsel = np.nonzero(gid == oid)[0]
        psel = np.nonzero(pid == oid)[0]
        if len(psel) == 0:
            continue  # an object without particles (static or a tool) stays where it is
        kk = min(k, len(psel))
        dist, nb = cKDTree(px[psel]).query(gm[gsel], k=kk)
        dist, nb = dist.reshape(len(gsel), kk), psel[nb.reshape(len(gsel), kk)]
        w = 1.0 / (dist + 1e-6) ** 2
        index[gsel, :kk] = nb
        weights[gsel, :kk] = w / w.sum(1, keepdims=True)
    return GaussianBinding(torch.as_tensor(index), torch.as_tensor(weights, dtype=torch.float32),
                           particles.x.detach().clone())


_SH_DIRS_CACHE: dict[int, torch.Tensor] = {}


def _fibonacci_dirs(n: int) -> torch.Tensor:
    if n not in _SH_DIRS_CACHE:
        i = torch.arange(n, dtype=torch.float64) + 0.5
        phi = torch.acos(1 - 2 * i / n)
        theta = torch.pi * (1 + 5**0.5) * i
        _SH_DIRS_CACHE[n] = torch.stack([torch.cos(theta) * torch.sin(phi), torch.sin(theta) * torch.sin(phi), torch.cos(phi)], -1)
    return _SH_DIRS_CACHE[n]


def rotate_sh(sh: torch.Tensor, R: torch.Tensor, chunk: int = 16384) -> torch.Tensor:
    """SH coefficients of a colour field rotated by R: new(d) = old(R^T d), every band (degrees 1..3).

    Each band of degree l spans a rotation-invariant space, so the rotated coefficients are exact: solve
    Y_l(D) c' = Y_l(D R) c in least squares over 32 well-spread directions D (uses the tree's SH basis,
    so conventions match the renderer).

    Args:
        sh: [N, K, 3] coefficients (K = (degree + 1)^2); R: [N, 3, 3] rotations.
    Returns:
        [N, K, 3] rotated coefficients (the DC term is unchanged).
    """
    degree = sh_degree_from_count(sh.shape[1])
    if degree == 0:
        return sh
    D = _fibonacci_dirs(32).to(sh.device)
    YD = sh_basis(degree, D)  # [32, K]
    out = sh.clone()
    for a in range(0, sh.shape[0], chunk):
        b = min(a + chunk, sh.shape[0])
        Rc = R[a:b].to(torch.float64)
        rotated_dirs = torch.einsum("dj,nji->ndi", D, Rc)  # rows d^T R = (R^T d)^T
        YR = sh_basis(degree, rotated_dirs.reshape(-1, 3)).reshape(b - a, D.shape[0], -1)  # [n, 32, K]
        for l in range(1, degree + 1):
            s0, s1 = l * l, (l + 1) * (l + 1)
            pinv = torch.linalg.pinv(YD[:, s0:s1])  # [2l+1, 32]
            M = torch.einsum("md,ndk->nmk", pinv, YR[:, :, s0:s1])  # [n, 2l+1, 2l+1]
            out[a:b, s0:s1] = torch.einsum("nmk,nkc->nmc", M, sh[a:b, s0:s1].to(torch.float64)).to(sh.dtype)
    return out


def drive_gaussians(
    gaussians: Gaussians,
    binding: GaussianBinding,
    positions: torch.Tensor,
    F: torch.Tensor,
    rotate_colors: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gaussians moved by the particles of one frame.

    Args:
        gaussians: the rest Gaussians (G of them, those used in :func:`bind_gaussians`).
        binding: from :func:`bind_gaussians`.
        positions: [P, 3] particle positions at this frame (metres); differentiable.
        F: [P, 3, 3] particle deformation gradients at this frame; differentiable.
        rotate_colors: rotate the view-dependent SH bands by the polar rotation of F (no gradient).
    Returns:
        means [G, 3] (metres), covariances [G, 3, 3] (metres^2) = F_g Sigma_0 F_g^T, SH [G, K, 3].
    """
    if positions.shape[0] != binding.particle_rest.shape[0]:
        raise ModelError(f"positions have {positions.shape[0]} particles, the binding {binding.particle_rest.shape[0]}")
    idx, w = binding.index.to(positions.device), binding.weights.to(positions.device, positions.dtype)
    G, k = idx.shape
    flat = idx.reshape(-1)
    # index_select, not positions[idx]: outside PyTorch's deterministic mode (endogsim.determinism) the
    # backward of advanced indexing adds a particle's shares on a CPU with atomics in whatever order the
    # threads come, a gradient differing run to run in its last bits; index_select's backward adds them in
    # order, to the same bits as the deterministic mode's, so callers need not switch the mode on.
    disp = (positions - binding.particle_rest.to(positions)).index_select(0, flat).reshape(G, k, 3)
    means = gaussians.means.to(positions) + (w[..., None] * disp).sum(1)
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    wsum = w.sum(1)
    Fg = (w.to(F.dtype)[..., None, None] * F.index_select(0, flat).reshape(G, k, 3, 3)).sum(1) \
        + (1 - wsum.to(F.dtype))[:, None, None] * eye
    cov0 = gaussians.covariances().to(F)
    covs = Fg @ cov0 @ Fg.transpose(-1, -2)
    sh = gaussians.sh
    if rotate_colors and gaussians.sh_degree > 0:
        with torch.no_grad():
            sh = rotate_sh(gaussians.sh, polar_rotation_torch(Fg.detach().double()).to(gaussians.sh.dtype))
    return means, covs, sh


def capsule_collider_points(tip, end, radius: float, dx: float) -> tuple[np.ndarray, float]:
    """Points filling a capsule (segment tip-end, ``radius`` metres) for a point-based kinematic collider.

    The simulator marks grid nodes within a small contact radius of each collider point, so a capsule is
    sampled on a lattice of spacing dx / 2 inside the capsule shrunk by that contact radius
    (0.45 dx >= half the lattice diagonal), plus the nearby lattice points projected onto the shrunk
    surface: the union of the little spheres then covers the capsule and stays inside it.

    Returns:
        points [Pc, 3] (metres, world, frame 0) and the contact radius (metres).
    """
    a, b = np.asarray(tip, float), np.asarray(end, float)
    rho = 0.45 * dx
    inner = max(radius - rho, 0.0)
    h = dx / 2
    lo = np.minimum(a, b) - inner
    hi = np.maximum(a, b) + inner
    axes = [np.arange(lo[i], hi[i] + h / 2, h) for i in range(3)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    ab = b - a
    t = np.clip(((g - a) @ ab) / max(ab @ ab, 1e-18), 0, 1)
    d = np.linalg.norm(g - (a + t[:, None] * ab), axis=1)
    # Lattice points just outside the shrunk capsule are projected onto its surface: projection onto a
    # convex set is non-expansive, so every point of the shrunk capsule stays within half a lattice
    # diagonal (< rho) of some collider point, and no contact sphere pokes out of the capsule.
    keep = d <= inner + 0.5 * math.sqrt(3.0) * h + 1e-12
    g, t, d = g[keep], t[keep], d[keep]
    axis_pt = a + t[:, None] * ab
    outside = d > inner
    g[outside] = axis_pt[outside] + (g[outside] - axis_pt[outside]) * (inner / d[outside])[:, None]
    pts = np.unique(np.round(g, 12), axis=0) if inner > 0 else g[:0]
    if len(pts) == 0:  # a capsule thinner than the lattice: its axis alone
        n = max(2, int(math.ceil(np.linalg.norm(ab) / h)) + 1)
        pts = a + np.linspace(0, 1, n)[:, None] * ab
        rho = max(radius, rho)
    return pts, float(rho)


#: A grasping instrument's jaws hold the tissue within this distance of its tip sphere (metres): the
#: bite of a closed grasper, a physical size, so the held tissue is the same at every discretisation. 3 mm
#: makes the suite's bites 12-13 mm across, about a grasper jaw's length. At 1 mm (an 8-mm bite, 3 cells of
#: the default grid) the bite's edge carried the lifted tissue's weight on too small a ring, and the bite
#: tore out of the sheet by numerical fracture, by how much depending on the grid: in the suite's
#: `lift_real` the tissue 1-2 mm outside the bite moved 1-3 mm while the bite moved 9 mm; on a slab lifted
#: 8 mm under gravity the ring around the bite rose 2.8 / 4.7 mm on grids 50 / 100, and 6.7 / 7.1 mm at 3 mm
#: (tests/test_physics.py::test_a_grasped_sheet_lifted_under_its_weight_comes_with_the_bite).
GRASP_MARGIN = 3.0e-3


def grasped_particles(x, tip, radius: float, free=None, margin: float = GRASP_MARGIN) -> np.ndarray:
    """Indices of the particles a grasper holds: within ``radius + margin`` of its ``tip`` (the jaws).

    Args:
        x: [P, 3] particle rest positions (metres, world).
        tip: [3] the instrument's tip at frame 0 (metres); radius: its capsule radius (metres).
        free: [P] bool, particles that may be held (not anchored); default all.
    Returns:
        [Ph] int64 indices, ascending (empty when the jaws touch no tissue).
    """
    x = np.asarray(torch.as_tensor(x).detach().cpu().numpy(), float)
    near = np.linalg.norm(x - np.asarray(tip, float), axis=1) <= radius + margin
    if free is not None:
        near &= np.asarray(torch.as_tensor(free).cpu().numpy(), bool).reshape(-1)
    return np.flatnonzero(near)


#: How far (grid cells, median) the free tissue around a grasper's bite may end up from the bite before the
#: bite counts as torn out: beyond 1.5 cells the quadratic B-spline stencils of the two sides barely share a
#: node, and MPM lets them separate (numerical fracture, by an amount the grid sets). Measured on the suite's
#: ground truths (grid 2x identification's): `pull` and `lift_real` stay within 1.1 cells at every frame;
#: `stomach`, lifted 16 mm at revision 8, passed 1.5 cells at frame 15 and ended 9 cells away.
BITE_TEAR_CELLS = 1.5


def bite_ring_distance(rest, positions, held, spacing: float, dx: float) -> np.ndarray:
    """How far the tissue around a grasper's bite has come from it, frame by frame.

    The ring is the free particles within one particle ``spacing`` of a held one at rest; per frame, the
    median over the ring of the distance to the nearest held particle, in grid cells. It starts at about
    spacing / dx and grows past :data:`BITE_TEAR_CELLS` when the bite tears out of the tissue.

    Args:
        rest: [P, 3] particle rest positions (metres, world).
        positions: [T, P, 3] simulated positions (metres, world).
        held: [Ph] indices of the particles the grasper holds.
        spacing: particle spacing (metres); dx: grid cell (metres).
    Returns:
        [T] median ring distance (cells); zeros when nothing is held or the bite has no free neighbours.
    """
    from scipy.spatial import cKDTree

    rest = np.asarray(torch.as_tensor(rest).detach().cpu().numpy(), float)
    pos = torch.as_tensor(positions).detach().cpu().double().numpy()
    held = np.asarray(held, np.int64).reshape(-1)
    out = np.zeros(pos.shape[0])
    if len(held) == 0:
        return out
    free = np.setdiff1d(np.arange(len(rest)), held)
    d0, _ = cKDTree(rest[held]).query(rest[free])
    ring = free[d0 <= 1.01 * spacing]
    if len(ring) == 0:
        return out
    for t in range(pos.shape[0]):
        d, _ = cKDTree(pos[t, held]).query(pos[t, ring])
        out[t] = np.median(d) / dx
    return out


def bite_records(rest, positions, colliders, spacing: float, dx: float) -> list[dict]:
    """Whether each grasp's bite stayed in its tissue over a simulation: per collider of ``colliders`` that
    holds particles (``RigidCollider.holds``), {"held_particles", "ring_cells_max" (the largest
    :func:`bite_ring_distance`, grid cells), "frame_of_max", "torn_from" (the first frame past
    :data:`BITE_TEAR_CELLS`, or None), "torn", "tolerance_cells"}. ``rest`` [P, 3] and ``positions``
    [T, P, 3] metres; ``spacing`` the particle spacing and ``dx`` the grid cell (metres)."""
    out = []
    for c in colliders:
        if c.holds is None or not len(c.holds):
            continue
        ring = bite_ring_distance(rest, positions, c.holds.numpy(), spacing, dx)
        torn = np.flatnonzero(ring > BITE_TEAR_CELLS)
        out.append({"held_particles": int(len(c.holds)), "ring_cells_max": float(ring.max()),
                    "frame_of_max": int(ring.argmax()), "torn_from": int(torn[0]) if len(torn) else None,
                    "torn": bool(len(torn)), "tolerance_cells": BITE_TEAR_CELLS})
    return out


#: How far beyond its radius a pushing instrument marks grid nodes (cells); 0: the nodes inside its capsule.
#: Those stop short of the surface by a fraction of a cell that depends on where the grid falls, so a probe
#: acts smaller than it is, the more so the coarser the grid (a 3-mm probe is about one cell). Grown by a
#: quarter cell, a probe presses alike on every grid (tests/test_physics.py::_probe_press: centre deflection
#: 0.76 / 0.96 mm on grids 50 / 100 marking the capsule alone, 1.15 / 1.17 / 1.16 mm on grids 50 / 100 / 200
#: grown by 0.25) and the benchmark's probe scenes change less under refinement (press 0.272 -> 0.170,
#: gallbladder 0.199 -> 0.145). It stays 0 because the bigger probe drags more tissue: sliding sideways 4-5
#: mm deep, the demo's sticky probe tears its tissue behind it past the coverage check (seeds 2 and 3: 1.1%
#: of the footprint; 0.96% at most with 0). docs/IDENTIFICATION.md section 3. Graspers are never grown: the
#: tissue their jaws hold is their contact, a bite of physical size.
PUSH_CONTACT_CELLS = 0.0


def capsule_collider(tip, end, radius: float, transforms, dx: float, holds=None):
    """A :class:`~endogsim.physics.config.RigidCollider` for a capsule instrument (``tip``-``end``, ``radius``
    metres, frame 0) moved by ``transforms`` [T, 4, 4] on a grid of cell ``dx`` metres; ``holds``: the
    particle indices it grasps (:func:`grasped_particles`), or None for a tool that only pushes (its nodes
    are marked :data:`PUSH_CONTACT_CELLS` beyond its surface)."""
    from endogsim.physics.config import RigidCollider

    reach = radius if holds is not None else radius + PUSH_CONTACT_CELLS * dx
    pts, rho = capsule_collider_points(tip, end, reach, dx)
    return RigidCollider(points=torch.as_tensor(pts), transforms=torch.as_tensor(transforms), radius=rho,
                         holds=None if holds is None else torch.as_tensor(holds))
