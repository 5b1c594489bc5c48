"""The simulated material of a scene: particles filling each deformable object, and their boundary conditions.

Built the same way from any sampling of the objects' visible surfaces: the Gaussians of frame 0 (a real
video's reconstruction, and identification on a benchmark scene, which never sees its ground truth's
particles) or a procedural scene's true surface (the benchmark's ground truth, at a finer spacing):

1. each object's slab of ``scenario.thickness(name)`` behind its surface is filled with a lattice of the
   discretisation's particle spacing, aligned with the simulation grid (two particles per cell and axis at
   half-cell spacing: :func:`endogsim.physics.filling.fill_behind_surface`);
2. where objects meet, each place holds one material: a lattice point inside several slabs (an organ
   filled behind one in front of it) belongs to the object seen in front along its ray;
3. its boundary conditions (``scenario.boundary(name)``) are set by geometry on the grid nodes (the space
   behind the back face, unless another object's slab is there, is a fixed wall or a support, with or
   without friction, outside an optional release disc; a band along the outline holds still, except where
   the outline borders another object: the tissue goes on into it), and on the particles they contain
   (pinned: the band along the outline, and the deepest layer of a "fixed" back face).

Units: metres, world coordinates.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from endogsim.errors import DataError, DataWarning
from endogsim.gaussians.camera import Camera
from endogsim.gaussians.model import Gaussians
from endogsim.physics import Anchor, ExternalForce, MovingAnchor, Particles, RigidCollider
from endogsim.physics.filling import FilledSolid, SurfaceMap, fill_behind_surface, outline_beside
from endogsim.physics.particles import capsule_collider, grasped_particles
from endogsim.scene.schema import ObjectBoundary, ScenarioSpec, SceneSpec, SimSettings, ToolCapsule
from endogsim.scene.tracks import TissueTracks

__all__ = ["SlabConditions", "SceneParticles", "build_particles", "particles_from_scene_gaussians", "gaussian_surfaces",
           "one_object_per_place", "scenario_forces", "tool_colliders"]


@dataclass
class SlabConditions:
    """The boundary conditions of one object's slab, as geometry: its surface map locates any world point
    (depth behind the surface, distance to the outline), so grid nodes get their conditions by position.

    Attributes:
        surface: the object's :class:`~endogsim.physics.filling.SurfaceMap` (its distance to the outline
            measured to the part that borders no other object: :func:`~endogsim.physics.filling.outline_beside`).
        thickness: slab thickness (metres).
        boundary: the scene's description of its conditions.
        neighbours: the other objects' slabs; the space behind this back face is not held where they are.
    """

    surface: SurfaceMap
    thickness: float
    boundary: ObjectBoundary
    neighbours: list["SlabConditions"] = field(default_factory=list)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """[N] bool: world points inside the slab (depth behind its surface in [0, thickness))."""
        depth, _ = self.surface.locate(points)
        return (depth >= 0) & (depth < self.thickness)

    def released(self, points: np.ndarray) -> np.ndarray:
        """[N] bool: world points over the release disc, where the back face is free."""
        if self.boundary.release is None:
            return np.zeros(len(points), bool)
        (cx, cy), r = self.boundary.release
        return np.hypot(points[:, 0] - cx, points[:, 1] - cy) <= r

    def behind(self, points: np.ndarray) -> np.ndarray:
        """[N] bool: world points behind the slab's back face (inside its footprint, off the release disc)."""
        depth, _ = self.surface.locate(points)
        out = np.isfinite(depth) & (depth >= self.thickness) & ~self.released(points)
        for other in self.neighbours:  # an organ behind this one's back face is tissue, not the anatomy's wall
            out[out] &= ~other.contains(points[out])
        return out

    def border(self, points: np.ndarray) -> np.ndarray:
        """[N] bool: world points of the slab within ``boundary.border`` of the outline."""
        depth, edge = self.surface.locate(points)
        return np.isfinite(depth) & (depth >= 0) & (depth < self.thickness) & (edge < self.boundary.border)

    def towards_camera(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] unit vectors from world points towards the camera (the support's normal: out of it)."""
        d = self.surface.camera.center().double().numpy()[None] - points
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def anchors(self) -> list[Anchor]:
        out = []
        if self.boundary.back_face == "fixed":
            out.append(Anchor(kind="sticky", region=self.behind))
        elif self.boundary.back_face in ("support", "slip_support"):
            out.append(Anchor(kind=self.boundary.back_face, region=self.behind, normal=self.towards_camera,
                              friction=self.boundary.support_friction))
        if self.boundary.border > 0 and self.boundary.border_motion == "still":
            out.append(Anchor(kind="sticky", region=self.border))
        return out


@dataclass
class SceneParticles:
    """Particles of the deformable objects and their boundary conditions.

    Attributes:
        particles: the particles (positions, volumes spacing^3, object ids).
        pinned: [P] bool, held by a boundary condition (back face "fixed", border band, still or tracked).
        slabs: {object id: its :class:`SlabConditions`}.
        border: [P] bool, the particles of the border bands (part of ``pinned``).
    """

    particles: Particles
    pinned: np.ndarray
    slabs: dict[int, SlabConditions]
    border: np.ndarray

    def tracked_border(self) -> np.ndarray:
        """[P] bool: the border particles of the objects whose band follows the tracks (``border_motion``)."""
        ids = self.particles.object_ids.numpy()
        tracked = [oid for oid, slab in self.slabs.items() if slab.boundary.border_motion == "tracked"]
        return self.border & np.isin(ids, tracked)

    def anchors(self) -> list[Anchor]:
        """The :class:`~endogsim.physics.Anchor` list of these boundary conditions: pinned particles held at
        rest, and every slab's node conditions (behind its back face; along a still outline)."""
        still = self.pinned & ~self.tracked_border()
        out = [Anchor(kind="fixed", particle_mask=torch.as_tensor(still))] if still.any() else []
        for slab in self.slabs.values():
            out += slab.anchors()
        return out

    def moving_anchors(self, tracks: TissueTracks, track_objects: np.ndarray, dx: float) -> list[MovingAnchor]:
        """One :class:`~endogsim.physics.MovingAnchor` per object whose border follows the tracks: its band's
        particles carried by the object's own tracks (:meth:`TissueTracks.carry`; all tracks, warned, for an
        object without any), the nodes within 0.45 dx of them (a collider's contact radius) moving with them.

        Args:
            tracks: the reconstruction's tissue tracks; track_objects: [N_tracks] object id of each.
            dx: grid cell (metres).
        """
        ids = self.particles.object_ids.numpy()
        x = self.particles.x.double().numpy()
        tracked = self.tracked_border()
        out = []
        for oid in np.unique(ids[tracked]):
            idx = np.nonzero(tracked & (ids == oid))[0]
            use = np.asarray(track_objects) == oid
            if not use.any():  # a sliver without opaque Gaussians: carried by its neighbours' tracks
                warnings.warn(f"object {int(oid)} has no tissue track of its own; its border follows the nearest "
                              "tracks of the other objects", DataWarning, stacklevel=2)
                use = None
            out.append(MovingAnchor(idx, tracks.carry(x[idx], use), radius=0.45 * dx))
        return out


def gaussian_surfaces(g: Gaussians, object_ids: list[int], min_opacity: float = 0.05) -> dict[int, np.ndarray]:
    """{object id: [N, 3] centres (metres) of its Gaussians at least ``min_opacity`` opaque}: the visible
    surfaces a reconstruction gives."""
    ids = g.object_ids.cpu().numpy()
    keep = g.opacities.detach().cpu().numpy() >= min_opacity
    means = g.means.detach().cpu().double().numpy()
    return {oid: means[(ids == oid) & keep] for oid in object_ids}


def build_particles(surfaces: dict[int, np.ndarray], spec: SceneSpec, camera: Camera,
                    settings: SimSettings, instruments: dict[int, np.ndarray] | None = None,
                    map_settings: SimSettings | None = None) -> SceneParticles:
    """Fill every deformable object of ``surfaces`` and apply its boundary conditions.

    Args:
        surfaces: {object id: [N, 3] samples of its visible surface (metres, world)}.
        spec: the scene (objects' names, the scenario's thicknesses and boundary conditions, the sim box).
        camera: the camera the surfaces are seen from.
        settings: the discretisation (its particle spacing and grid set the lattice).
        instruments: {object id: [M, 3] samples of an instrument's surface} in the same frame (metres, world).
            A reconstruction has no tissue where an instrument hid it in every frame (a grasper's bite moves
            with the jaws); the tissue is filled on under them (:func:`~endogsim.physics.filling.hidden_part`)
            instead of ending, and being held, around them. A ground truth's whole surfaces need none.
        map_settings: the discretisation whose particle spacing the objects' surface maps follow (their cells,
            the holes they close, the gap that counts as two objects bordering; default ``settings``). A
            refined or coarsened discretisation of identification's passes identification's, so that it
            refines the particles inside the same solids, held along the same outlines
            (:func:`particles_from_scene_gaussians`).
    """
    sc: ScenarioSpec = spec.scenario
    spacing = sc.spacing(settings)
    map_spacing = sc.spacing(map_settings or settings)
    # Lattice points at the particle spacing through box_lo + spacing / 2: with spacing = dx / 2 these are
    # the quarter points of every grid cell, the usual two particles per cell and axis.
    origin = np.asarray(sc.box_lo, float) + spacing / 2
    hiding = np.concatenate([np.zeros((0, 3)), *(instruments or {}).values()])
    solids, maps = {}, {}
    for oid, pts in surfaces.items():
        name = spec.object(oid).name
        thickness = sc.thickness(name)
        if thickness <= 0:
            raise DataError(f"scene {spec.name!r}: object {name!r} has no thickness behind its surface "
                            "(scenario.extrusion.thickness)")
        if len(pts) >= 3:
            solids[oid], maps[oid] = fill_behind_surface(pts, camera, thickness, spacing, origin=origin,
                                                         hidden_by=hiding, map_spacing=map_spacing)
    kept = one_object_per_place(solids, origin, spacing)
    parts, pinned, borders, slabs = [], [], [], {}
    for oid, pts in surfaces.items():
        name = spec.object(oid).name
        solid = solids.get(oid)
        x = solid.x[kept[oid]] if solid is not None else np.zeros((0, 3))
        if len(x) == 0:  # a sliver of segmentation: nothing to simulate
            warnings.warn(f"scene {spec.name!r}: object {name!r} ({len(pts)} surface samples) is smaller than "
                          f"one particle at {spacing * 1e3:.2f} mm spacing; it is not simulated (its Gaussians "
                          "stay in place)", DataWarning, stacklevel=2)
            continue
        others = [m for o, m in maps.items() if o != oid and kept[o].any()]
        slab = SlabConditions(outline_beside(maps[oid], others), sc.thickness(name), sc.boundary(name))
        pin = slab.border(x)
        borders.append(pin.copy())
        if slab.boundary.back_face == "fixed":  # the deepest lattice layer is glued to the anatomy behind
            pin |= (solid.depth_behind[kept[oid]] >= slab.thickness - spacing) & ~slab.released(x)
        P = len(x)
        parts.append(Particles(torch.as_tensor(x, dtype=torch.float32),
                               torch.full((P,), spacing ** 3, dtype=torch.float32),
                               torch.full((P,), int(oid), dtype=torch.int64)))
        pinned.append(pin)
        slabs[int(oid)] = slab
    if not parts:
        raise DataError(f"scene {spec.name!r}: no deformable object large enough to fill with particles "
                        f"(spacing {spacing * 1e3:.2f} mm)")
    for oid, slab in slabs.items():
        slab.neighbours = [s for o, s in slabs.items() if o != oid]
    return SceneParticles(Particles.concat(parts), np.concatenate(pinned), slabs, np.concatenate(borders))


def particles_from_scene_gaussians(g: Gaussians, spec: SceneSpec, camera: Camera,
                                   settings: SimSettings) -> SceneParticles:
    """:func:`build_particles` of a scene's frame-0 Gaussians ``g``, as identification builds them on a real video
    and on a benchmark alike: the deformable objects' Gaussians are the surfaces filled, the rigid objects'
    (the instruments) what hides them. The surface maps follow the scenario's identification discretisation
    whatever ``settings`` is: its refinements and coarsenings (the refined correction, the discretisation-error
    walk, ``--refine``) fill the same solids, held along the same outlines."""
    return build_particles(gaussian_surfaces(g, [o.id for o in spec.deformable]), spec, camera, settings,
                           instruments=gaussian_surfaces(g, [o.id for o in spec.rigid]),
                           map_settings=spec.scenario.identification)


def one_object_per_place(solids: dict[int, FilledSolid], origin: np.ndarray, spacing: float) -> dict[int, np.ndarray]:
    """{object id: [P] bool, the points of its solid it keeps}: a lattice point inside several objects' slabs
    (an organ whose footprint was filled behind another one seen in front of it) belongs to the object seen
    in front along its ray, the one it lies deepest behind the surface of.

    Args:
        solids: {object id: its :class:`~endogsim.physics.filling.FilledSolid`}, all on one lattice.
        origin: [3] a lattice point (metres); spacing: the lattice spacing (metres).
    """
    if not solids:
        return {}
    keys = np.concatenate([np.rint((s.x - origin) / spacing).astype(np.int64) for s in solids.values()])
    depth = np.concatenate([s.depth_behind for s in solids.values()])
    order = np.lexsort((-depth, keys[:, 2], keys[:, 1], keys[:, 0]))  # each point's deepest claim first
    k = keys[order]
    first = np.ones(len(k), bool)
    first[1:] = (k[1:] != k[:-1]).any(1)
    keep = np.zeros(len(k), bool)
    keep[order[first]] = True
    sizes = np.cumsum([0] + [len(s) for s in solids.values()])
    return {oid: keep[a:b] for oid, a, b in zip(solids, sizes[:-1], sizes[1:])}


def scenario_forces(spec: SceneSpec, particles: Particles) -> list[ExternalForce]:
    """The :class:`~endogsim.physics.ExternalForce` list of ``spec.scenario.forces`` over these particles
    (regions are geometric, so the ground truth's particles and identification's get the same drive)."""
    out = []
    x = particles.x.double().numpy()
    ids = particles.object_ids.numpy()
    for f in spec.scenario.forces:
        if f.get("type") != "impulse":
            raise DataError(f"scene {spec.name!r}: unknown force type {f.get('type')!r} (expected 'impulse')")
        oid = spec.object(f["object"]).id
        mask = (ids == oid) & (np.linalg.norm(x - np.asarray(f["center"], float), axis=1) <= float(f["radius"]))
        if not mask.any():
            raise DataError(f"scene {spec.name!r}: the impulse on {f['object']!r} reaches no particle "
                            f"within {f['radius']} m of {f['center']}")
        out.append(ExternalForce(acceleration=tuple(float(v) for v in f["velocity"]), particle_mask=torch.as_tensor(mask),
                                 t_start=float(f.get("t_start", 0.0)), impulse=True))
    return out


def tool_colliders(tools: list[ToolCapsule], particles: Particles, free: np.ndarray, dx: float,
                   transforms: dict[int, torch.Tensor | np.ndarray] | None = None) -> list[RigidCollider]:
    """One :class:`~endogsim.physics.RigidCollider` per capsule tool on a grid of cell ``dx`` metres; a
    "grasp" tool holds the ``free`` particles its jaws close on at frame 0
    (:func:`~endogsim.physics.particles.grasped_particles`), the same tissue at any particle spacing.

    Args:
        tools: the scene's tools. particles: the simulated particles; free: [P] bool, those not pinned.
        transforms: {tool id: [T, 4, 4]} to use instead of the tools' own (frame 0 places the tool).
    """
    out, taken = [], np.zeros(len(particles), bool)
    for tool in tools:
        tf = np.asarray(tool.matrices() if transforms is None else transforms[tool.object_id], dtype=np.float64)
        holds = None
        if tool.contact == "grasp":
            tip = tf[0, :3, :3] @ np.asarray(tool.tip, float) + tf[0, :3, 3]
            holds = grasped_particles(particles.x, tip, tool.radius, free=np.asarray(free, bool) & ~taken)
            taken[holds] = True
        out.append(capsule_collider(tool.tip, tool.end, tool.radius, tf, dx, holds))
    return out
