"""Typed configuration of a simulation: numerics (:class:`MPMConfig`) and the world (:class:`Scenario`).

Every quantity here is in physical units (metres, seconds, kg, Pa) and world coordinates; the simulator
converts them to sim-box units in :mod:`endogsim.physics.units`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Literal, get_args

import numpy as np
import torch

from endogsim.errors import SimulationError
from endogsim.physics.units import SimBox

#: Settling before frame 0 whose last frame still moves a particle by more than this share of a grid cell
#: has not reached the equilibrium frame 0 stands for: the rest of it moves in the clip, where a fit reads
#: it as the tissue's response to the instruments (docs/REAL_VIDEO.md section 3).
SETTLING_TOLERANCE = 0.01


@dataclass
class MPMConfig:
    """Numerics of the MLS-MPM solver (the materials, constitutive models included, are per object:
    :class:`~endogsim.physics.materials.ObjectMaterials`).

    Attributes:
        grid_res: grid cells per axis over the sim box (paper: 50).
        frame_dt: time between two output (rendered) frames, seconds (paper: 25 x 2e-4 = 5e-3).
        substeps_per_frame: the least number of substeps per frame (paper: 25). More are taken when the
            CFL condition asks for them (dt = None) .
        dt: explicit substep in seconds, or None to choose it from the CFL condition. An explicit dt above
            the stable limit is refused with :class:`SimulationError` giving the limit.
        max_substeps_per_frame: refuse materials that would need more substeps than this (e.g. E = 1e12 Pa).
        cfl_number: C in dt <= C dx / c_p (0.3 to 1 is stable for explicit MPM).
        damping: grid velocity damping rate (1/s); v *= exp(-damping dt) each substep.
        wall: grid domain walls: "slip" (separating: outward normal velocity removed) or "sticky" (v = 0).
        wall_padding: wall thickness in grid cells (3 keeps every quadratic stencil inside the grid).
        device: Warp device, "cpu" or "cuda" / "cuda:0".
    """

    grid_res: int = 50
    frame_dt: float = 25 * 2e-4
    substeps_per_frame: int = 25
    dt: float | None = None
    max_substeps_per_frame: int = 4000
    cfl_number: float = 0.5
    damping: float = 0.0
    wall: Literal["slip", "sticky"] = "slip"
    wall_padding: int = 3
    device: str = "cpu"

    def __post_init__(self) -> None:
        if not (8 <= int(self.grid_res) <= 1024):
            raise SimulationError(f"MPMConfig.grid_res = {self.grid_res} must lie in [8, 1024]")
        if not (self.frame_dt > 0 and np.isfinite(self.frame_dt)):
            raise SimulationError(f"MPMConfig.frame_dt = {self.frame_dt} s must be > 0")
        if self.substeps_per_frame < 1:
            raise SimulationError(f"MPMConfig.substeps_per_frame = {self.substeps_per_frame} must be >= 1")
        if self.dt is not None and not (self.dt > 0 and np.isfinite(self.dt)):
            raise SimulationError(f"MPMConfig.dt = {self.dt} s must be > 0")
        if not (0 < self.cfl_number <= 1.0):
            raise SimulationError(f"MPMConfig.cfl_number = {self.cfl_number} must lie in (0, 1]")
        if self.damping < 0:
            raise SimulationError(f"MPMConfig.damping = {self.damping} 1/s must be >= 0")
        if self.wall not in ("slip", "sticky"):
            raise SimulationError(f"MPMConfig.wall {self.wall!r} is not slip|sticky")
        if not (2 <= self.wall_padding <= self.grid_res // 4):
            raise SimulationError(f"MPMConfig.wall_padding = {self.wall_padding} cells must lie in [2, grid_res/4]")


#: An indicator of world points: points [N, 3] (metres) -> bool [N].
Region = Callable[[np.ndarray], np.ndarray]
#: Unit normals at world points: points [N, 3] (metres) -> [N, 3].
NormalField = Callable[[np.ndarray], np.ndarray]


#: What an :class:`Anchor` does to the grid nodes (and particles) in its region.
AnchorKind = Literal["fixed", "sticky", "slip", "support", "slip_support"]
#: The kinds that act along a normal (a wall or support stops the velocity component into it).
NORMAL_KINDS = ("slip", "support", "slip_support")


@dataclass
class Anchor:
    """A boundary condition on a region of the world (an axis-aligned box, or any indicator of world
    points) and/or on a set of particles.

    Kinds:
      - "fixed": particles that start in the region (or are in ``particle_mask``) are held at their initial
        position and carry no mass (their inertia is the fixed anatomy's); grid nodes in the region, and the
        nodes those particles dominate at rest, get v = 0.
      - "sticky": grid nodes in the region get v = 0 (particles there stop, but are not pinned exactly).
      - "slip": grid nodes in the region lose the velocity component along ``normal`` (a frictionless wall).
      - "support": grid nodes in the region that move into the support (along -``normal``) stop, those that
        move away from it are free: a support that pushes but never pulls, with friction while pressed
        (tissue lying on the anatomy behind it does not slide under its weight, but can be lifted off).
        Give the region as the space behind the tissue's back face: conditions set on nodes by geometry
        converge with the grid, those inferred from particle layers do not.
      - "slip_support": the same separable support without friction: a node moving into it loses only that
        component of its velocity and slides along it (wet tissue on wet anatomy).
      A "support" with a ``friction`` coefficient mu is a Coulomb support instead: a node pressed into it loses
      its normal velocity and its tangential speed shrinks by mu times the normal speed (to rest when that
      is more). Its velocity is continuous where "support"'s stick-or-free switch jumps (a last-bit change
      of a material can flip a node and move the tissue by microns; docs/REAL_VIDEO.md section 10).

    Attributes:
        lo, hi: world box corners (metres), or None.
        region: indicator of world points (instead of a box), or None.
        kind: "fixed" | "sticky" | "slip" | "support" | "slip_support".
        normal: unit normal (world) for "slip" and the supports (for a support: pointing out of it, into the
            tissue), or a field of normals at world points.
        particle_mask: [P] bool, particles to pin ("fixed" only).
        friction: Coulomb coefficient of a "support" (>= 0), or None: the support sticks while pressed.
    """

    lo: tuple[float, float, float] | None = None
    hi: tuple[float, float, float] | None = None
    kind: AnchorKind = "fixed"
    normal: tuple[float, float, float] | NormalField = (0.0, 0.0, 1.0)
    particle_mask: torch.Tensor | np.ndarray | None = None
    region: Region | None = None
    friction: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in get_args(AnchorKind):
            raise SimulationError(f"Anchor.kind {self.kind!r} is not {'|'.join(get_args(AnchorKind))}")
        if self.friction is not None:
            if self.kind != "support":
                raise SimulationError(f"Anchor.friction is a support's Coulomb coefficient, not a {self.kind} anchor's")
            if not (math.isfinite(self.friction) and self.friction >= 0):
                raise SimulationError(f"Anchor.friction = {self.friction} must be a finite number >= 0")
        if (self.lo is None) != (self.hi is None):
            raise SimulationError("Anchor needs both lo and hi (or neither)")
        if self.lo is not None and self.region is not None:
            raise SimulationError("Anchor takes a box (lo, hi) or a region, not both")
        if self.lo is None and self.region is None and self.particle_mask is None:
            raise SimulationError("Anchor needs a box (lo, hi), a region or a particle_mask")
        if self.particle_mask is not None and self.kind != "fixed":
            raise SimulationError("Anchor.particle_mask is only meaningful for kind 'fixed'")
        if self.kind in NORMAL_KINDS and not callable(self.normal) and float(np.linalg.norm(self.normal)) < 1e-9:
            raise SimulationError(f"Anchor.normal must be non-zero for a {self.kind} anchor")

    def contains(self, points: np.ndarray) -> np.ndarray:
        """[N] bool: which world points [N, 3] (metres) lie in the anchor's box or region (none without one)."""
        if self.region is not None:
            return np.asarray(self.region(points), dtype=bool).reshape(-1)
        if self.lo is None:
            return np.zeros(len(points), bool)
        return ((points >= np.asarray(self.lo, float)) & (points <= np.asarray(self.hi, float))).all(1)

    def normals(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] unit normals at world points [N, 3]."""
        n = self.normal(points) if callable(self.normal) else np.broadcast_to(np.asarray(self.normal, float), points.shape)
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


@dataclass
class ExternalForce:
    """A body acceleration on a region over a time window, or an impulse.

    Attributes:
        acceleration: world vector (m/s^2) added to the particles of the region while t_start <= t < t_end;
            for an impulse (``impulse=True``) it is the velocity change (m/s) applied once at t_start.
        lo, hi: world box (metres) selecting the particles by their initial position, or None with a mask.
        particle_mask: [P] bool particles the force acts on.
        t_start, t_end: time window (s) from the start of the rollout.
        impulse: see ``acceleration``.
    """

    acceleration: tuple[float, float, float]
    lo: tuple[float, float, float] | None = None
    hi: tuple[float, float, float] | None = None
    particle_mask: torch.Tensor | np.ndarray | None = None
    t_start: float = 0.0
    t_end: float = float("inf")
    impulse: bool = False

    def __post_init__(self) -> None:
        if self.lo is None and self.particle_mask is None:
            raise SimulationError("ExternalForce needs a box (lo, hi) or a particle_mask")
        if not self.t_end > self.t_start and not self.impulse:
            raise SimulationError(f"ExternalForce window [{self.t_start}, {self.t_end}) s is empty")


@dataclass
class RigidCollider:
    """A kinematic rigid instrument: a set of points that follows a prescribed trajectory and pushes tissue.

    Give either per-frame rigid transforms of rest points, or per-frame positions of every point. Between
    two frames the points move at constant velocity. Grid nodes within ``radius`` of a collider point take
    the collider velocity (sticky contact). The collider is not moved by the tissue (it is kinematic).

    A grasping instrument also ``holds`` particles: the tissue its jaws close on moves rigidly with it
    (a Dirichlet condition on those particles, like an anchor that moves). Sticky grid contact alone cannot
    lift tissue: a particle follows the tool only while most of its B-spline stencil lies in marked nodes,
    so a lifted bite slips out of a coarse grid and stays held on a fine one (measured by ``endogsim bench
    convergence``); a held particle follows the tool at every resolution.

    Attributes:
        points: [Pc, 3] rest points (metres, world) -- with ``transforms``.
        transforms: [T, 4, 4] world rigid transforms per output frame applied to ``points``
            (transforms[0] is usually the identity).
        positions: [T, Pc, 3] world positions per output frame (instead of points + transforms).
        radius: contact radius around each point (metres); default: one grid cell.
        holds: [Ph] indices of the particles the instrument holds (a grasp; needs ``transforms``): each
            moves rigidly with the instrument from its rest position (``Particles.x``, where it is at frame 0),
            and the grid nodes within ``radius`` of it take the instrument's velocity, as around its own points.
    """

    points: torch.Tensor | np.ndarray | None = None
    transforms: torch.Tensor | np.ndarray | None = None
    positions: torch.Tensor | np.ndarray | None = None
    radius: float | None = None
    holds: torch.Tensor | np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.holds is not None:
            self.holds = torch.as_tensor(self.holds, dtype=torch.long).reshape(-1)
            if self.transforms is None:
                raise SimulationError("RigidCollider.holds needs transforms [T, 4, 4]: a held particle moves "
                                      "rigidly with the instrument")

    def moved(self, rest: torch.Tensor, from_first: bool = False) -> torch.Tensor:
        """[T, N, 3] world positions per frame of points ``rest`` [N, 3] (metres) carried by the transforms;
        ``from_first``: by the motion since frame 0 (T_t T_0^-1), for points given where they are at frame 0."""
        T = torch.as_tensor(self.transforms, dtype=torch.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise SimulationError(f"RigidCollider.transforms has shape {tuple(T.shape)}, expected (T, 4, 4)")
        if from_first:
            T = T @ torch.linalg.inv(T[0])
        return torch.einsum("tij,pj->tpi", T[:, :3, :3], rest.to(torch.float64)) + T[:, None, :3, 3]

    def trajectory(self) -> torch.Tensor:
        """[T, Pc, 3] world positions per frame (float64)."""
        if self.positions is not None:
            pos = torch.as_tensor(self.positions, dtype=torch.float64)
        elif self.points is not None and self.transforms is not None:
            pos = self.moved(torch.as_tensor(self.points, dtype=torch.float64))
        else:
            raise SimulationError("RigidCollider needs positions [T, Pc, 3] or points [Pc, 3] + transforms [T, 4, 4]")
        if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[1] == 0:
            raise SimulationError(f"RigidCollider positions have shape {tuple(pos.shape)}, expected (T, Pc>0, 3)")
        if not torch.isfinite(pos).all():
            raise SimulationError("RigidCollider trajectory holds NaN/inf")
        return pos


@dataclass
class MovingAnchor:
    """Particles held on a prescribed path: a boundary that moves as observed (the outline of a tissue in view
    follows the reconstruction's tracks of the tissue there, because the tissue goes on beyond the image and
    is moved by what the camera does not see).

    Like a grasper's bite (:attr:`RigidCollider.holds`) but not rigid: each particle goes to its own position
    every frame (a Dirichlet condition on the particle, constant velocity between frames), and the grid nodes
    within ``radius`` of the held particles take their velocity, as around a collider's points.

    Attributes:
        particles: [N] indices of the held particles (they start at their rest positions, ``positions[0]``).
        positions: [T, N, 3] world positions per output frame (metres).
        radius: contact radius of the nodes around them (metres).
    """

    particles: torch.Tensor | np.ndarray
    positions: torch.Tensor | np.ndarray
    radius: float

    def __post_init__(self) -> None:
        self.particles = torch.as_tensor(self.particles, dtype=torch.long).reshape(-1)
        self.positions = torch.as_tensor(self.positions, dtype=torch.float64)
        if self.positions.ndim != 3 or self.positions.shape[1:] != (len(self.particles), 3):
            raise SimulationError(f"MovingAnchor.positions has shape {tuple(self.positions.shape)}, expected "
                                  f"(T, {len(self.particles)}, 3)")
        if not torch.isfinite(self.positions).all():
            raise SimulationError("MovingAnchor.positions holds NaN/inf")
        if not self.radius > 0:
            raise SimulationError(f"MovingAnchor.radius = {self.radius} m must be > 0")

    def still(self, frames: int) -> "MovingAnchor":
        """The same particles held where they are at frame 0 for ``frames`` frames."""
        return replace(self, positions=self.positions[:1].expand(frames, -1, -1).clone())


@dataclass
class Scenario:
    """Everything about the world a simulation needs besides particles and materials.

    Attributes:
        box: the sim box (world cube covered by the grid).
        gravity: world gravity vector (m/s^2); (0, 9.81, 0) points down the image for an OpenCV camera.
        anchors: boundary conditions on regions (see :class:`Anchor`).
        forces: external accelerations / impulses (see :class:`ExternalForce`).
        colliders: kinematic rigid instruments (see :class:`RigidCollider`).
        moving_anchors: particles held on prescribed paths (see :class:`MovingAnchor`).
        settle_frames: frames simulated before frame 0 with the colliders at their frame-0 pose and no
            external force but gravity, so that frame 0 is the equilibrium under gravity (a tissue seen at
            rest in a video is not stress-free: it carries its weight). 0: frame 0 is stress-free.
        settle: what frame 0 is after settling: "keep" (the settled state: a ground truth whose observed
            frame 0 is its equilibrium) or "subtract" (the given positions: the static sag is subtracted
            from every later frame and its deformation gradient divided out, so a rollout from an observed,
            already-loaded frame 0 does not sag twice).
        settle_damping: grid velocity damping (1/s) while settling, or None for ``MPMConfig.damping``. The
            equilibrium does not depend on it; a strong one reaches it in fewer frames.
        mass_scaling: k >= 1, quasi-static mass scaling (as in explicit FEM codes): the simulator multiplies
            every density by k and divides gravity, body accelerations and the grid damping by k, so weight,
            body forces and damping forces are unchanged and only inertia grows k-fold. The wave speed, and
            with it the CFL substep count, drops by sqrt(k). Valid when the motion is quasi-static (strongly
            damped tissue driven slowly by tools); check with a rollout at k = 1. Impulses (a dynamic drive)
            refuse it.
    """

    box: SimBox
    gravity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    anchors: list[Anchor] = field(default_factory=list)
    forces: list[ExternalForce] = field(default_factory=list)
    colliders: list[RigidCollider] = field(default_factory=list)
    moving_anchors: list[MovingAnchor] = field(default_factory=list)
    settle_frames: int = 0
    settle: Literal["keep", "subtract"] = "subtract"
    settle_damping: float | None = None
    mass_scaling: float = 1.0

    def __post_init__(self) -> None:
        if not self.mass_scaling >= 1.0:
            raise SimulationError(f"Scenario.mass_scaling = {self.mass_scaling} must be >= 1")
        if self.mass_scaling != 1.0 and any(f.impulse for f in self.forces):
            raise SimulationError("mass scaling changes what an impulse does: a scenario with impulses needs "
                                  "mass_scaling = 1")
        if self.settle_frames < 0:
            raise SimulationError(f"Scenario.settle_frames = {self.settle_frames} must be >= 0")
        if self.settle_damping is not None and not self.settle_damping >= 0:
            raise SimulationError(f"Scenario.settle_damping = {self.settle_damping} 1/s must be >= 0")
        if self.settle not in ("keep", "subtract"):
            raise SimulationError(f"Scenario.settle {self.settle!r} is not keep|subtract")

    def pinned(self, x: np.ndarray) -> np.ndarray:
        """[P] bool: particles (rest positions ``x`` [P, 3], metres) that a "fixed" anchor pins (in its
        particle mask, or starting in its box or region)."""
        pinned = np.zeros(len(x), dtype=bool)
        for a in self.anchors:
            if a.kind == "fixed":
                if a.particle_mask is not None:
                    m = np.asarray(torch.as_tensor(a.particle_mask).cpu().numpy(), dtype=bool).reshape(-1)
                    if m.shape[0] != len(x):
                        raise SimulationError(f"Anchor.particle_mask has {m.shape[0]} entries for {len(x)} particles")
                    pinned |= m
                pinned |= a.contains(x)
        return pinned

    def held(self, x: np.ndarray) -> np.ndarray:
        """[P] bool: particles (rest positions ``x`` [P, 3]) a boundary condition holds, still (:meth:`pinned`)
        or on a path (``moving_anchors``): no instrument may also hold them."""
        out = self.pinned(x)
        for a in self.moving_anchors:
            out[a.particles.numpy()] = True
        return out

    def boundary_still(self, frames: int) -> "Scenario":
        """This scenario with every moving anchor held at its frame-0 place for ``frames`` frames (an
        interaction that is not the filmed clip has no observed boundary motion)."""
        return replace(self, moving_anchors=[a.still(frames) for a in self.moving_anchors])

    def with_settling(self, frame_dt: float) -> "Scenario":
        """The scenario over settle_frames + T frames: colliders and moving anchors held at their frame-0 pose,
        forces shifted in time by the settling (the same world, seen from the start of the settling)."""
        if self.settle_frames == 0:
            return self
        S, shift = self.settle_frames, self.settle_frames * frame_dt
        colliders = []
        for c in self.colliders:
            if c.transforms is not None and c.points is not None:
                tf = torch.as_tensor(c.transforms, dtype=torch.float64)
                colliders.append(replace(c, transforms=torch.cat([tf[:1].expand(S, -1, -1), tf])))
            else:
                traj = c.trajectory()
                colliders.append(RigidCollider(positions=torch.cat([traj[:1].expand(S, -1, -1), traj]),
                                               radius=c.radius))
        forces = [replace(f, t_start=f.t_start + shift, t_end=f.t_end + shift) for f in self.forces]
        moving = [replace(a, positions=torch.cat([a.positions[:1].expand(S, -1, -1), a.positions]))
                  for a in self.moving_anchors]
        return replace(self, colliders=colliders, forces=forces, moving_anchors=moving, settle_frames=0,
                       settle_damping=None)

    def mass_scaled(self) -> "Scenario":
        """The world the simulator runs with ``mass_scaling`` = k applied: gravity, body accelerations and
        settling damping divided by k (densities and ``MPMConfig.damping`` are scaled by the simulator)."""
        k = self.mass_scaling
        if k == 1.0:
            return self
        return replace(self, gravity=tuple(g / k for g in self.gravity),
                       forces=[replace(f, acceleration=tuple(a / k for a in f.acceleration)) for f in self.forces],
                       settle_damping=None if self.settle_damping is None else self.settle_damping / k,
                       mass_scaling=1.0)

    def settling_cells(self, settling_left: float, grid_res: int) -> float:
        """What the settling left (:attr:`~endogsim.physics.SimResult.settling_left`, metres) in cells of a
        ``grid_res`` grid over the sim box; settled is at most :data:`SETTLING_TOLERANCE`."""
        return settling_left / (self.box.size / grid_res)

    def damping_of_frame(self, frame: int, damping: float) -> float:
        """The grid damping (1/s) of output frame ``frame`` of the settled rollout (settle frames first)."""
        if frame < self.settle_frames and self.settle_damping is not None:
            return self.settle_damping
        return damping
