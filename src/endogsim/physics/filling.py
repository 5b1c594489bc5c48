"""A solid behind a surface seen from one side: the volume an endoscope's view of tissue stands for.

A video shows the tissue's front surface only. :func:`fill_behind_surface` turns samples of that surface
(Gaussian centres of a reconstruction, or a procedural surface) into material points filling the slab
between the surface and ``thickness`` behind it along the viewing rays, on a regular lattice (PhysGaussian's
interior filling, for a one-sided view):

1. the surface samples are binned on a grid in the image plane (u = x / z, v = y / z in the camera frame)
   and each cell keeps the nearest sample's range (distance from the camera): the front surface;
   small holes in the footprint are closed and filled from the nearest cell, spikes removed by a 3x3 median;
   where instruments in front hide the surface (``hidden_by``), the notch they cut into the footprint is
   closed too (:func:`hidden_part`), and the holes that closing encloses filled: the tissue goes on under
   the instrument;
2. every point of a lattice of spacing ``spacing`` (offset ``origin``, e.g. at the quarter points of the
   simulation grid's cells for two particles per cell per axis) whose ray hits the footprint is kept when
   its range lies within [front, front + thickness): the slab, filled evenly;
3. each kept point carries its depth behind the surface and its distance to the footprint's outline in the
   image-parallel plane; the :class:`SurfaceMap` locates any point the same way, so boundary conditions can
   be set on grid nodes by geometry (behind the back face; within a band of the outline), independent of
   how finely the particles sample the slab. Where several objects are seen side by side,
   :func:`outline_beside` measures that distance to the part of the outline that borders none of them.

Units: metres; world coordinates; the camera gives the rays.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from endogsim.errors import SimulationError
from endogsim.gaussians.camera import Camera

__all__ = ["FilledSolid", "SurfaceMap", "surface_map", "hidden_part", "fill_behind_surface", "outline_beside"]


@dataclass
class FilledSolid:
    """Material points filling a slab behind a surface.

    Attributes:
        x: [P, 3] positions (metres, world), on the lattice.
        depth_behind: [P] range behind the front surface along the viewing ray (metres, in [0, thickness)).
        edge_distance: [P] distance to the outline of the surface's footprint, measured in the
            image-parallel plane at the point's depth (metres).
        spacing: lattice spacing (metres); each point stands for spacing^3 of material.
    """

    x: np.ndarray
    depth_behind: np.ndarray
    edge_distance: np.ndarray
    spacing: float

    def __len__(self) -> int:
        return len(self.x)


def _to_camera(points: np.ndarray, camera: Camera) -> np.ndarray:
    V = camera.viewmat.detach().double().cpu().numpy()
    return points @ V[:3, :3].T + V[:3, 3]


@dataclass
class SurfaceMap:
    """A surface seen from one side, as a map over the image plane of its range from the camera.

    Attributes:
        camera: the camera (its viewmat maps world to camera coordinates).
        lo: [2] image-plane coordinates (u = x / z, v = y / z) of cell (0, 0)'s corner.
        du: cell size in the image plane (radians, about).
        front: [Nu, Nv] range (metres) of the surface per cell; inf outside the footprint.
        edge: [Nu, Nv] distance to the footprint's outline (cells).
    """

    camera: Camera
    lo: np.ndarray
    du: float
    front: np.ndarray
    edge: np.ndarray

    def _cells(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The map cell (i [N], j [N]; 0 where off the map) of image-plane points ``uv`` [N, 2], and [N] bool
        whether it lies on the map."""
        cij = np.floor((uv - self.lo) / self.du).astype(np.int64)
        ok = (cij >= 0).all(1) & (cij[:, 0] < self.front.shape[0]) & (cij[:, 1] < self.front.shape[1])
        return np.where(ok, cij[:, 0], 0), np.where(ok, cij[:, 1], 0), ok

    def locate(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depth behind the surface along the viewing ray [N] (metres; inf off the footprint) and distance to
        the footprint's outline in the image-parallel plane [N] (metres; 0 off it) of world points [N, 3]."""
        pc = _to_camera(np.asarray(points, np.float64), self.camera)
        z = pc[:, 2]
        ahead = z > 1e-6
        i, j, ok = self._cells(pc[:, :2] / np.where(ahead, z, 1.0)[:, None])
        ok &= ahead
        depth = np.where(ok, np.linalg.norm(pc, axis=1) - self.front[i, j], np.inf)
        edge = np.where(ok & np.isfinite(depth), self.edge[i, j] * self.du * np.abs(z), 0.0)
        return depth, edge

    def covers(self, uv: np.ndarray) -> np.ndarray:
        """[N] bool: image-plane points ``uv`` [N, 2] (u = x / z, v = y / z) that lie on the footprint."""
        i, j, ok = self._cells(np.asarray(uv, np.float64))
        return ok & np.isfinite(self.front[i, j])


def hidden_part(footprint: np.ndarray, hiding: np.ndarray) -> np.ndarray:
    """[Nu, Nv] bool: the cells of ``hiding`` (an instrument's image footprint, bool [Nu, Nv]) that the surface
    whose footprint is ``footprint`` (bool [Nu, Nv]) goes on under.

    An instrument in front of the tissue cuts a notch into the tissue's footprint, open to the outside where
    its shaft leaves the tissue, so hole filling does not close it; seen as the footprint's outline, the
    notch would make the tissue around the instrument a border band, held still (the instrument then holds
    and moves nothing). A closing of the footprint as wide as the instrument closes the notch: only cells of
    the instrument's footprint are added, and none beyond the tissue's outline, where the closing of a
    straight or convex outline adds nothing (of a ragged one, a cell here and there: `two_tissues`' probe
    shaft adds 3 particles where it crosses the outline).
    """
    from scipy import ndimage

    if not hiding.any():
        return np.zeros_like(footprint)
    r = int(np.ceil(ndimage.distance_transform_edt(hiding).max())) + 2  # the instrument's half-width, cells
    disk = np.hypot(*np.mgrid[-r:r + 1, -r:r + 1]) <= r
    closed = ndimage.binary_closing(np.pad(footprint, r + 1), structure=disk)[r + 1:-r - 1, r + 1:-r - 1]
    return closed & hiding & ~footprint


def surface_map(points: np.ndarray | torch.Tensor, camera: Camera, spacing: float, closing_cells: int = 2,
                hidden_by: np.ndarray | None = None) -> SurfaceMap:
    """The :class:`SurfaceMap` of surface samples ``points`` [N, 3] (metres, world), on image-plane cells a
    little finer than ``spacing`` at the surface's depth, but never finer than half the samples' own spacing;
    holes up to about ``closing_cells`` are closed, and so are notches that instruments in front cut into the
    footprint (``hidden_by``: [M, 3] world samples of the instruments' surfaces, e.g. their Gaussian centres;
    :func:`hidden_part`)."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    pts = np.asarray(points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise SimulationError(f"a surface needs at least 3 samples [N, 3], got shape {pts.shape}")
    pc = _to_camera(pts, camera)
    if (pc[:, 2] <= 1e-6).any():
        raise SimulationError("surface points behind the camera cannot be seen along viewing rays")
    uv = pc[:, :2] / pc[:, 2:3]
    rng = np.linalg.norm(pc, axis=1)
    # A map finer than the samples is a map of dots: with samples more than two cells apart the closing below
    # no longer joins them, and the footprint falls apart into holes whose edges make every lattice point a
    # "border" point (seen filling `tiny`, Gaussians 0.8 mm apart, at 4x its grid: every particle pinned).
    sample_spacing = float(np.median(cKDTree(uv).query(uv, k=2)[0][:, 1]))
    du = max(0.7 * spacing / float(np.median(pc[:, 2])), sample_spacing / 2)
    lo = uv.min(0) - 2 * du
    shape = tuple((np.ceil((uv.max(0) + 2 * du - lo) / du)).astype(int) + 1)
    ij = np.floor((uv - lo) / du).astype(int)
    front = np.full(shape, np.inf)
    np.minimum.at(front, (ij[:, 0], ij[:, 1]), rng)
    seen = np.isfinite(front)
    footprint = ndimage.binary_closing(seen, iterations=closing_cells) | seen
    footprint = ndimage.binary_fill_holes(footprint)
    if hidden_by is not None and len(hidden_by):
        hiding = np.zeros(shape, bool)
        hc = _to_camera(np.asarray(hidden_by, np.float64).reshape(-1, 3), camera)
        hc = hc[hc[:, 2] > 1e-6]  # an instrument point at or behind the camera hides nothing
        hij = np.floor((hc[:, :2] / hc[:, 2:3] - lo) / du).astype(int)
        on = (hij >= 0).all(1) & (hij < np.asarray(shape)).all(1)
        hiding[hij[on, 0], hij[on, 1]] = True
        # The instrument's samples lie apart, and its outline and the tissue's need not meet: grown by the
        # holes the footprint closes, with its own holes filled, it covers the gap between them.
        hiding = ndimage.binary_fill_holes(ndimage.binary_dilation(hiding, iterations=closing_cells))
        # Closing the notch can enclose what is left of it beside the instrument's footprint: the reconstruction's
        # gap is wider than the instrument, and the closing above (a few map cells) narrows it less on the finer
        # map of a finer discretisation. Enclosed by tissue, it is tissue, as the holes filled above; left open,
        # its outline made a held band around the jaws at 1.5x the demo's grid (240 of the 553 particles a
        # grasper lifting `tiny`'s patch bit on, none at 1x), so the refined correction lifted another tissue.
        footprint = ndimage.binary_fill_holes(footprint | hidden_part(footprint, hiding))
    # Cells of the footprint without a sample take the nearest sampled cell's range; a 3x3 median removes spikes.
    _, (ni, nj) = ndimage.distance_transform_edt(~seen, return_indices=True)
    front = np.where(footprint, front[ni, nj], 0.0)
    front = np.where(footprint, ndimage.median_filter(front, size=3), np.inf)
    front = np.where(front <= 0, np.inf, front)
    edge = ndimage.distance_transform_edt(np.pad(np.isfinite(front), 1))[1:-1, 1:-1]
    return SurfaceMap(camera, lo, du, front, edge)


def fill_behind_surface(points: np.ndarray | torch.Tensor, camera: Camera, thickness: float, spacing: float,
                        origin: np.ndarray | None = None, closing_cells: int = 2,
                        hidden_by: np.ndarray | None = None,
                        map_spacing: float | None = None) -> tuple[FilledSolid, SurfaceMap]:
    """Fill the slab of ``thickness`` behind the surface sampled by ``points`` with a lattice of ``spacing``.

    Args:
        points: [N, 3] samples of the visible surface (metres, world), e.g. Gaussian centres of one object.
        camera: the camera the surface is seen from (its viewmat and the rays through its centre).
        thickness: slab thickness along the viewing rays (metres, > 0): the material occupies depths
            [0, thickness) behind the surface.
        spacing: lattice spacing (metres).
        origin: [3] a lattice point (metres, world); default: the lattice through (spacing / 2, ...), i.e.
            cell-centred on a grid of spacing through the world origin.
        closing_cells: holes in the footprint up to about this many image-plane cells are closed.
        hidden_by: [M, 3] world samples of instruments in front of the surface (:func:`surface_map`).
        map_spacing: the spacing (metres) the surface map's cells follow (:func:`surface_map`); default
            ``spacing``. Discretisations of one scene at several spacings pass one value, so that a finer one
            refines the lattice inside the same solid: the map's hole closing and every band measured on it
            are counted in its cells, and a map that followed the lattice would make a finer discretisation
            see a more ragged outline.
    Returns:
        the :class:`FilledSolid` (empty when no lattice point lies in the slab: a surface smaller than about
        the spacing) and the :class:`SurfaceMap` it was filled behind.
    """
    if not (thickness > 0 and spacing > 0 and (map_spacing is None or map_spacing > 0)):
        raise SimulationError(f"thickness {thickness} m, spacing {spacing} m and map spacing {map_spacing} m must "
                              "be > 0")
    smap = surface_map(points, camera, spacing if map_spacing is None else map_spacing, closing_cells, hidden_by)
    pts = np.asarray(points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else points, np.float64)
    rng = np.linalg.norm(_to_camera(pts, camera), axis=1)
    # Lattice points in the box the slab can occupy (camera frame -> world via the inverse viewmat).
    V = camera.viewmat.detach().double().cpu().numpy()
    Rinv, cam = V[:3, :3].T, -V[:3, :3].T @ V[:3, 3]
    nu_, nv_ = smap.front.shape
    lo, du = smap.lo, smap.du
    hi = lo + du * np.array([nu_, nv_])
    # The slab's bounding box: the footprint's corner rays, and its ray nearest the optical axis (the
    # deepest point of a range lies on the most central ray), between the nearest and farthest range.
    rays_uv = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [lo[0], hi[1]], [hi[0], hi[1]], np.clip(0.0, lo, hi)])
    r_lo, r_hi = float(rng.min()) - spacing, float(rng.max()) + thickness + spacing
    dirs = np.concatenate([rays_uv, np.ones((len(rays_uv), 1))], 1)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ext = np.concatenate([dirs * r_lo, dirs * r_hi]) @ Rinv.T + cam
    org = np.full(3, spacing / 2) if origin is None else np.asarray(origin, np.float64)
    axes = [org[a] + spacing * np.arange(np.floor((ext[:, a].min() - org[a]) / spacing),
                                         np.ceil((ext[:, a].max() - org[a]) / spacing) + 1) for a in range(3)]
    out_x, out_d, out_e = [], [], []
    # One slab of lattice planes at a time keeps the memory bounded whatever the resolution.
    for x0 in axes[0]:
        g = np.stack(np.meshgrid([x0], axes[1], axes[2], indexing="ij"), -1).reshape(-1, 3)
        depth, edge = smap.locate(g)
        keep = (depth >= 0) & (depth < thickness)
        if keep.any():
            out_x.append(g[keep])
            out_d.append(depth[keep])
            out_e.append(edge[keep])
    if not out_x:  # a surface smaller than the lattice spacing
        return FilledSolid(np.zeros((0, 3)), np.zeros(0), np.zeros(0), float(spacing)), smap
    return FilledSolid(np.concatenate(out_x), np.concatenate(out_d), np.concatenate(out_e), float(spacing)), smap


def outline_beside(smap: SurfaceMap, neighbours: list[SurfaceMap], gap_cells: int = 4) -> SurfaceMap:
    """``smap`` with its distance to the outline measured to the part of the outline that borders none of
    ``neighbours`` (surfaces seen from the same camera).

    A band along an object's outline is held because the tissue goes on beyond what is seen of it; where
    the outline borders another simulated object (an organ attached to it, or one in front of it) the tissue
    goes on into that object, which the simulation couples to it on the shared grid, so nothing there is
    held. Footprints up to ``gap_cells`` map cells apart count as bordering: adjacent organs' samples lie
    about a sample apart, and each footprint's outline is ragged by a cell. The distance is Euclidean in
    the image plane, so it may cross a neighbour narrower than the band to the view's outline beyond it.

    Args:
        smap: the object's map. neighbours: the maps of the other objects it may border.
        gap_cells: the widest gap (cells of ``smap``, >= 1) between footprints that still counts as bordering.
    """
    from scipy import ndimage

    if not neighbours:
        return smap
    nu, nv = smap.front.shape
    # Neighbours are looked for gap_cells beyond the map too: it reaches only 2 cells past the object's
    # outermost samples, and a neighbour up to gap_cells beyond them borders it as well.
    g = gap_cells
    ij = np.stack(np.meshgrid(np.arange(-g, nu + g), np.arange(-g, nv + g), indexing="ij"), -1).reshape(-1, 2)
    centres = smap.lo + (ij + 0.5) * smap.du
    beside = np.zeros(len(centres), bool)
    for other in neighbours:
        beside |= other.covers(centres)
    beside = ndimage.binary_dilation(beside.reshape(nu + 2 * g, nv + 2 * g), iterations=g)[g:g + nu, g:g + nv]
    inside = np.isfinite(smap.front) | beside
    # Padding repeats the map's border cells: a neighbour that goes on beyond this map's extent goes on.
    edge = ndimage.distance_transform_edt(np.pad(inside, 1, mode="edge"))[1:-1, 1:-1]
    return replace(smap, edge=edge)
