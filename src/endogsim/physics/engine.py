"""The MPM engine: the static arrays of a simulation set-up, the substep launches, and taped segments.

:class:`MPMEngine` is built once per (particles, scenario, numerics, frame count) and then runs any number
of rollouts, each with its own materials and its own :class:`Timestep` (the substep count follows the
materials' CFL number). It owns the buffers of the taped segments (:meth:`MPMEngine.segment_buffers`),
kept between calls of the same size: an optimisation loop back-propagates through the same engine many
times.

Why segments are taped during backward only (never across the whole forward): Warp replays adjoints with
arrays' *current* contents, so every substep inside a taped segment writes fresh buffers (``substeps + 1``
particle states, ``substeps`` grids and particle-grid transfer buffers).

A segment is recorded on a tape of its own (:meth:`MPMEngine.record_segment`; never Warp's global tape,
which every thread's launches would join), so the next segment back can be recomputed on a second core
while the adjoints of this one run (:meth:`MPMEngine.pull_back`; :mod:`endogsim.physics.rollout`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

from endogsim.errors import SimulationError
from endogsim.physics import kernels as K
from endogsim.physics import transfer_adjoints as A
from endogsim.physics.config import NORMAL_KINDS, MPMConfig, Scenario
from endogsim.physics.constitutive import MODELS
from endogsim.physics.particles import Particles
from endogsim.warp_runtime import init_warp

__all__ = ["MPMEngine", "Timestep", "resolve_device"]


def resolve_device(device: str) -> str:
    """A Warp device name that exists here ("cuda" without a GPU is refused with a clear error)."""
    init_warp()
    if not isinstance(device, str) or not (device == "cpu" or device == "cuda" or
                                           (device.startswith("cuda:") and device[5:].isdigit())):
        raise SimulationError(f"device {device!r} is not cpu, cuda or cuda:N")
    if device.startswith("cuda") and not wp.is_cuda_available():
        raise SimulationError(f"device {device!r} requested but CUDA is not available to Warp on this machine")
    return device


def _torch_device(device) -> torch.device:
    return torch.device("cpu") if device.is_cpu else torch.device(f"cuda:{device.ordinal}")


def as_torch(a: wp.array) -> torch.Tensor:
    """A torch view of a Warp array (numpy route on CPU: it avoids torch's thread pool, slow on busy CPUs)."""
    return torch.from_numpy(a.numpy()) if a.device.is_cpu else wp.to_torch(a)


def stack_arrays(arrays: list[wp.array]) -> torch.Tensor:
    """[N, ...] torch tensor of N Warp arrays of one shape."""
    if arrays[0].device.is_cpu:
        return torch.from_numpy(np.stack([a.numpy() for a in arrays]))
    return torch.stack([wp.to_torch(a) for a in arrays])


def _from_torch(t: torch.Tensor, like: wp.array) -> wp.array:
    return wp.from_torch(t.detach().float().contiguous().to(_torch_device(like.device)), dtype=like.dtype)


# ---------------------------------------------------------------------------------------------------
# Buffers
# ---------------------------------------------------------------------------------------------------

STATE_FIELDS = ("x", "v", "C", "F")


def alloc_state(P: int, device: str, grad: bool) -> K.ParticleState:
    s = K.ParticleState()
    s.x = wp.zeros(P, dtype=wp.vec3, device=device, requires_grad=grad)
    s.v = wp.zeros(P, dtype=wp.vec3, device=device, requires_grad=grad)
    s.C = wp.zeros(P, dtype=wp.mat33, device=device, requires_grad=grad)
    s.F = wp.zeros(P, dtype=wp.mat33, device=device, requires_grad=grad)
    return s


def state_arrays(s: K.ParticleState) -> tuple[wp.array, ...]:
    return tuple(getattr(s, f) for f in STATE_FIELDS)


def load_state(s: K.ParticleState, src) -> None:
    """Copy a saved state (Warp arrays) or torch tensors (x, v, C, F) into ``s``."""
    for a, t in zip(state_arrays(s), src):
        wp.copy(a, _from_torch(t, a) if isinstance(t, torch.Tensor) else t)


def save_state(s: K.ParticleState) -> tuple[wp.array, ...]:
    return tuple(wp.clone(a, requires_grad=False) for a in state_arrays(s))


def state_grads(s: K.ParticleState) -> tuple[torch.Tensor, ...]:
    return tuple(as_torch(a.grad).cpu().clone() for a in state_arrays(s))


def set_state_grads(s: K.ParticleState, tensors) -> None:
    for a, t in zip(state_arrays(s), tensors):
        wp.copy(a.grad, _from_torch(t, a))


def adjoints_of(s, struct):
    """A ``struct`` (a Warp struct of arrays, e.g. :class:`~endogsim.physics.kernels.ParticleState`) of the
    adjoints of the arrays of ``s`` (one of its instances), for the hand-written adjoint kernels."""
    adj = struct()
    for name in struct.vars:
        setattr(adj, name, getattr(s, name).grad)
    return adj


def alloc_transfer(P: int, device: str, grad: bool) -> K.ParticleTransfer:
    t = K.ParticleTransfer()
    t.mass = wp.zeros(P, dtype=float, device=device, requires_grad=grad)
    t.momentum = wp.zeros(P, dtype=wp.vec3, device=device, requires_grad=grad)
    t.affine = wp.zeros(P, dtype=wp.mat33, device=device, requires_grad=grad)
    t.v = wp.zeros(P, dtype=wp.vec3, device=device, requires_grad=grad)
    t.C = wp.zeros(P, dtype=wp.mat33, device=device, requires_grad=grad)
    return t


@dataclass
class GridBuffers:
    """One substep's grid, collider marks and particle-grid transfer buffers."""

    grid: K.GridState
    col: K.ColliderGrid
    transfer: K.ParticleTransfer

    @staticmethod
    def alloc(n: int, P: int, device: str, grad: bool, colliders: bool) -> "GridBuffers":
        shape = (n, n, n)
        g = K.GridState()
        g.m = wp.zeros(shape, dtype=float, device=device, requires_grad=grad)
        g.mv = wp.zeros(shape, dtype=wp.vec3, device=device, requires_grad=grad)
        g.v = wp.zeros(shape, dtype=wp.vec3, device=device, requires_grad=grad)
        c = K.ColliderGrid()
        cshape = shape if colliders else (1, 1, 1)
        c.w = wp.zeros(cshape, dtype=float, device=device)
        c.mv = wp.zeros(cshape, dtype=wp.vec3, device=device)
        return GridBuffers(g, c, alloc_transfer(P, device, grad))

    def clear(self) -> None:
        # grid.v is fully overwritten by grid_update, so only the accumulators need zeroing.
        self.grid.m.zero_()
        self.grid.mv.zero_()
        if self.col.w.shape[0] > 1:
            self.col.w.zero_()
            self.col.mv.zero_()

    def zero_accumulated_grads(self) -> None:
        self.grid.m.grad.zero_()
        self.grid.mv.grad.zero_()


@dataclass
class SegmentBuffers:
    """Buffers of a taped segment of ``len(grids)`` substeps; ``used`` once a backward ran through them."""

    states: list[K.ParticleState]
    grids: list[GridBuffers]
    used: bool = False


class Replays:
    """The launches of an untaped rollout, each recorded once as a Warp ``Launch`` and then replayed with only
    the arguments that are not the very objects it had last time packed again. Packing a CPU launch's
    arguments is most of its Python cost (on the pulling clip 87 us of the 0.7 ms an average substep launch
    took); the kernels and their arguments are those of :meth:`MPMEngine.substep`, and so are the numbers.
    An argument must therefore never be changed in place between launches (a struct is built anew)."""

    def __init__(self, device: str):
        self.device = device
        self._kept: dict = {}  # key -> [Launch, dim, inputs]

    def launch(self, key, kernel, dim, inputs: list) -> None:
        """Launch ``kernel`` over ``dim`` with ``inputs``, replaying the launch kept under ``key``."""
        kept = self._kept.get(key)
        if kept is None:
            kept = self._kept[key] = [wp.launch(kernel, dim=dim, inputs=inputs, device=self.device, record_cmd=True),
                                      dim, list(inputs)]
        else:
            cmd, last_dim, last = kept
            if dim != last_dim:
                cmd.set_dim(dim)
                kept[1] = dim
            for i, value in enumerate(inputs):
                if value is not last[i]:
                    cmd.set_param_at_index(i, value)
                    last[i] = value
        kept[0].launch()


@dataclass(frozen=True)
class Timestep:
    """How a rollout steps through time: ``substeps`` per output frame of ``dt`` seconds each."""

    substeps: int
    dt: float


# ---------------------------------------------------------------------------------------------------
# Engine
# ---------------------------------------------------------------------------------------------------


class MPMEngine:
    """Everything about a simulation set-up that does not change with the materials or the initial state.

    Args:
        particles: the simulated particles (rest positions, volumes, object ids).
        scenario: sim box, gravity, anchors, forces, colliders.
        config: numerics (grid, frame interval, walls, damping, device).
        num_frames: T, output frames including the initial one (colliders must cover them).
        frame_damping: grid damping (1/s) of each frame (e.g. stronger while settling); default
            ``config.damping`` throughout.
    """

    def __init__(self, particles: Particles, scenario: Scenario, config: MPMConfig, num_frames: int,
                 frame_damping: list[float] | None = None):
        init_warp()
        self.device = dev = resolve_device(config.device)
        self.cfg = config
        self.box = scenario.box
        self.T = num_frames
        self.inv_frame_dt = 1.0 / config.frame_dt  # one float object: a replayed launch repacks what changed
        self.frame_damping = frame_damping or [config.damping] * num_frames
        self.n = n = config.grid_res
        self.inv_dx = float(n)
        self.P = P = len(particles)
        s = self.box.scale
        x0_world = particles.x.detach().to(torch.float64).cpu().numpy()
        self._segments: dict[int, SegmentBuffers] = {}

        pinned = scenario.pinned(x0_world).astype(np.int32)
        kinds, normals, friction = self._node_conditions(scenario)
        bc_kind = wp.from_numpy(kinds, dtype=wp.int32, device=dev)
        bc_normal = wp.from_numpy(normals.astype(np.float32), dtype=wp.vec3, device=dev)
        bc_friction = wp.from_numpy(friction, dtype=float, device=dev)
        if pinned.any():
            # Pinned particles carry no mass (see kernels.particle_momentum); the nodes they dominate at rest are held.
            x0_sim = wp.from_numpy(self.box.to_sim(torch.from_numpy(x0_world)).float().numpy(), dtype=wp.vec3, device=dev)
            w_pinned = wp.zeros((n,) * 3, dtype=float, device=dev)
            w_free = wp.zeros((n,) * 3, dtype=float, device=dev)
            wp.launch(K.split_weights_to_grid, dim=P, device=dev, inputs=[
                x0_sim, wp.from_numpy(pinned, dtype=wp.int32, device=dev), self.inv_dx, n, w_pinned, w_free])
            wp.launch(K.dominated_nodes_to_bc, dim=(n,) * 3, device=dev, inputs=[w_pinned, w_free, bc_kind])

        region, self.forces = self._force_table(scenario, x0_world)
        pm = K.ParticleModel()
        pm.vol = wp.from_numpy(self.box.volume_to_sim(particles.volume.detach().cpu().numpy().astype(np.float64))
                               .astype(np.float32), dtype=float, device=dev)
        pm.obj = wp.from_numpy(particles.object_ids.cpu().numpy().astype(np.int32), dtype=wp.int32, device=dev)
        pm.pinned = wp.from_numpy(pinned, dtype=wp.int32, device=dev)
        pm.force_region = wp.from_numpy(region, dtype=wp.int32, device=dev)
        self.particles = pm

        d = K.Domain()
        d.n, d.inv_dx, d.pad = n, self.inv_dx, int(config.wall_padding)
        d.sticky_walls = 1 if config.wall == "sticky" else 0
        pad_dx = 2.0 / self.inv_dx
        d.x_lo, d.x_hi = pad_dx, 1.0 - pad_dx
        d.bc_kind, d.bc_normal, d.bc_friction = bc_kind, bc_normal, bc_friction
        d.gravity = wp.vec3(*[float(g) * s for g in scenario.gravity])
        self.domain = d

        # Colliders: trajectories per output frame, in sim units. The particles an instrument holds are
        # collider points too (the nodes around them take the instrument's velocity) and follow it exactly.
        self.colliders = []
        held_index = np.full(self.P, -1, dtype=np.int32)
        held_traj = []

        def to_sim(traj: torch.Tensor) -> torch.Tensor:
            return ((traj - torch.tensor(self.box.lo, dtype=torch.float64)) * s).float()

        def add_collider(traj: torch.Tensor, radius: float) -> None:
            """Collider points on paths ``traj`` [T, Pc, 3] (world), nodes within ``radius`` (sim units)."""
            traj_sim = to_sim(traj)
            self.colliders.append(([wp.array(traj_sim[t].numpy(), dtype=wp.vec3, device=dev)
                                    for t in range(num_frames)], float(radius)))

        def hold(idx: np.ndarray, paths: torch.Tensor, what: str) -> None:
            """Particles ``idx`` [N] held on ``paths`` [T, N, 3] (world; a Dirichlet condition in g2p_update)."""
            if len(idx) and (idx.min() < 0 or idx.max() >= self.P):
                raise SimulationError(f"{what} has particle indices outside [0, {self.P})")
            if (held_index[idx] >= 0).any() or pinned[idx].any():
                raise SimulationError(f"a particle of {what} is also held by another instrument or moving anchor, "
                                      "or anchored")
            held_index[idx] = sum(len(h) for h in held_traj) + np.arange(len(idx), dtype=np.int32)
            held_traj.append(paths[:num_frames].permute(1, 0, 2))

        for c in scenario.colliders:
            traj = c.trajectory()
            if traj.shape[0] < num_frames:
                raise SimulationError(f"a collider trajectory has {traj.shape[0]} frames, the rollout needs {num_frames}")
            if c.holds is not None and len(c.holds):
                idx = c.holds.numpy()
                moved = c.moved(torch.from_numpy(x0_world[idx]), from_first=True)[:traj.shape[0]]
                hold(idx, moved, "RigidCollider.holds")
                traj = torch.cat([traj, moved], 1)
            add_collider(traj, (c.radius * s) if c.radius is not None else 1.0 / self.inv_dx)
        for a in scenario.moving_anchors:  # held on their own paths; the nodes around them take their velocity
            if a.positions.shape[0] < num_frames:
                raise SimulationError(f"a moving anchor has {a.positions.shape[0]} frames, the rollout needs "
                                      f"{num_frames}")
            hold(a.particles.numpy(), a.positions, "MovingAnchor.particles")
            add_collider(a.positions[:num_frames], a.radius * s)
        pm.held = wp.from_numpy(held_index, dtype=wp.int32, device=dev)
        held_sim = torch.zeros(num_frames, 1, 3)
        if held_traj:
            held_sim = to_sim(torch.cat(held_traj).permute(1, 0, 2))
        self.held_frames = [wp.array(held_sim[t].numpy(), dtype=wp.vec3, device=dev) for t in range(num_frames)]

    # -- set-up ----------------------------------------------------------------------------------------
    def _node_conditions(self, scenario: Scenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-node boundary-condition kinds [n, n, n], normals [n, n, n, 3] and Coulomb coefficients [n, n, n]
        of the anchors' boxes and regions (unit-cube sim units share world directions). Later anchors win,
        sticky beats the others."""
        n = self.n
        kinds = np.zeros((n,) * 3, dtype=np.int32)
        normals = np.zeros((n,) * 3 + (3,), dtype=np.float64)
        friction = np.zeros((n,) * 3, dtype=np.float32)
        code = {"fixed": K.BC_STICKY, "sticky": K.BC_STICKY, "slip": K.BC_SLIP, "support": K.BC_SUPPORT,
                "slip_support": K.BC_SLIP_SUPPORT}
        ax = np.arange(n, dtype=np.float64) * (self.box.size / n)
        for i in range(n):  # one plane of nodes at a time keeps the memory bounded
            nodes = np.stack(np.meshgrid([ax[i]], ax, ax, indexing="ij"), -1).reshape(-1, 3) + np.asarray(self.box.lo)
            k_plane, n_plane, f_plane = kinds[i].reshape(-1), normals[i].reshape(-1, 3), friction[i].reshape(-1)
            for a in scenario.anchors:
                inside = a.contains(nodes) & (k_plane != K.BC_STICKY)
                if inside.any():
                    k_plane[inside] = code[a.kind] if a.friction is None else K.BC_COULOMB_SUPPORT
                    f_plane[inside] = a.friction or 0.0
                    if a.kind in NORMAL_KINDS:
                        n_plane[inside] = a.normals(nodes[inside])
        return kinds, normals, friction

    def _force_table(self, scenario: Scenario, x0_world: np.ndarray) -> tuple[np.ndarray, K.ForceTable]:
        """One force region per particle (the last force listed wins where regions overlap)."""
        region = np.full(self.P, -1, dtype=np.int32)
        acc, t0, t1 = [], [], []
        for i, f in enumerate(scenario.forces):
            if f.particle_mask is not None:
                mask = np.asarray(torch.as_tensor(f.particle_mask).cpu().numpy(), dtype=bool).reshape(-1)
                if mask.shape[0] != self.P:
                    raise SimulationError(f"ExternalForce.particle_mask has {mask.shape[0]} entries for {self.P} particles")
            else:
                mask = ((x0_world >= np.asarray(f.lo)) & (x0_world <= np.asarray(f.hi))).all(1)
            region[mask] = i
            acc.append(np.asarray(f.acceleration, float) * self.box.scale)
            t0.append(f.t_start)
            t1.append(-1.0 if f.impulse else min(f.t_end, 1e30))
        if not acc:
            acc, t0, t1 = [np.zeros(3)], [0.0], [0.0]
        ft = K.ForceTable()
        ft.acc = wp.array(np.asarray(acc, np.float32), dtype=wp.vec3, device=self.device)
        ft.t0 = wp.array(np.asarray(t0, np.float32), dtype=float, device=self.device)
        ft.t1 = wp.array(np.asarray(t1, np.float32), dtype=float, device=self.device)
        return region, ft

    # -- materials ---------------------------------------------------------------------------------------
    def material_table(self, E_sim: torch.Tensor, nu: torch.Tensor, rho: torch.Tensor, model: torch.Tensor,
                       yield_sim: torch.Tensor, grad: bool) -> K.MaterialTable:
        """Per-object arrays in sim units; E, nu, rho get adjoints when ``grad``."""
        dev = self.device
        mk = lambda t: wp.array(t.detach().to(torch.float32).cpu().numpy(), dtype=float, device=dev, requires_grad=grad)  # noqa: E731
        m = K.MaterialTable()
        m.E, m.nu, m.rho = mk(E_sim), mk(nu), mk(rho)
        m.model = wp.array(model.cpu().numpy().astype(np.int32), dtype=wp.int32, device=dev)
        m.yield_stress = wp.array(yield_sim.detach().to(torch.float32).cpu().numpy(), dtype=float, device=dev)
        return m

    @staticmethod
    def differentiable_arrays(mats: K.MaterialTable) -> tuple[wp.array, ...]:
        """The material arrays gradients flow to, in :attr:`ObjectMaterials.DIFFERENTIABLE` order."""
        return (mats.E, mats.nu, mats.rho)

    # -- one substep -------------------------------------------------------------------------------------
    def active_block(self, x: wp.array):
        """Lowest and highest grid node (per axis) that the particles' stencils touch (CPU); all on GPU."""
        n = self.n
        if x.device.is_cpu:
            # One contiguous-stride reduction per axis: 8x faster than xs.min(0) on a [P, 3] view, which
            # took a sixth of a CPU substep.
            xt = x.numpy().T
            lo = np.array([xt[a].min() for a in range(3)])
            hi = np.array([xt[a].max() for a in range(3)])
            if np.isfinite(lo).all() and np.isfinite(hi).all():
                lo = np.clip(np.floor(lo * self.inv_dx - 0.5).astype(np.int64), 0, n - 3)
                hi = np.clip(np.floor(hi * self.inv_dx - 0.5).astype(np.int64) + 2, 2, n - 1)
                return lo, hi
        return np.zeros(3, np.int64), np.full(3, n - 1, np.int64)

    def substep(self, s_in: K.ParticleState, s_out: K.ParticleState, buf: GridBuffers, mats: K.MaterialTable,
                step: Timestep, frame: int, sub: int, tape: wp.Tape | None = None,
                replays: Replays | None = None, elastic: bool = False, hand_stress: bool = False) -> None:
        """Advance ``s_in`` by one substep into ``s_out``. On a ``tape``, the stencil transfers and the grid
        update record their hand-written adjoints (:mod:`endogsim.physics.transfer_adjoints`), so does the
        particle update when ``elastic`` (no material of ``mats`` yields) and the particle kernel when
        ``hand_stress`` (every model of ``mats`` gives its stress's adjoint); the rest Warp's generated
        ones. Without a tape, ``replays`` (if given) replays the launches recorded at an earlier substep."""
        dev, dt = self.device, step.dt

        def run(kernel, dim, inputs, slot: int = 0) -> None:
            """One launch (off Warp's global tape); ``slot`` tells apart launches of one kernel in a substep."""
            if replays is not None:
                replays.launch((kernel.key, slot, id(s_in)), kernel, dim, inputs)
            else:
                wp.launch(kernel, dim=dim, device=dev, inputs=inputs, record_tape=False)

        def launch(kernel, dim, inputs) -> None:
            """A launch whose adjoint is Warp's generated one: recorded on ``tape`` (explicitly, not through
            Warp's global tape)."""
            run(kernel, dim, inputs)
            if tape is not None:
                tape.record_launch(kernel, dim, 0, inputs, [], dev)

        t = (frame * step.substeps + sub) * dt  # time at the start of this substep (s)
        if self.colliders:
            alpha = sub / step.substeps
            for c, (frames, radius) in enumerate(self.colliders):  # kinematic: nothing to differentiate, untaped
                run(K.collider_to_grid, frames[0].shape[0], [frames[frame], frames[frame + 1], alpha,
                                                             self.inv_frame_dt, radius, self.domain, buf.col], c)
        tr, grid = buf.transfer, buf.grid
        momentum = [s_in, self.particles, mats, self.forces, self.domain, t, dt, tr]
        if tape is not None and hand_stress:
            run(K.particle_momentum, self.P, momentum)
            # Names of their own: the lambdas read them when the tape runs backwards.
            momentum_adjoints = [adjoints_of(s_in, K.ParticleState), adjoints_of(tr, K.ParticleTransfer),
                                 mats.E.grad, mats.nu.grad, mats.rho.grad]
            tape.record_func(lambda: wp.launch(A.particle_momentum_adjoint, dim=self.P, device=dev, inputs=[
                *momentum, *momentum_adjoints], record_tape=False),
                arrays=[s_in.v, s_in.C, s_in.F, mats.E, mats.nu, mats.rho, tr.mass, tr.momentum, tr.affine])
        else:
            launch(K.particle_momentum, self.P, momentum)
        run(K.p2g_scatter, self.P, [s_in.x, tr, self.domain, grid])
        if tape is not None:
            tape.record_func(lambda: wp.launch(A.p2g_scatter_adjoint, dim=self.P, device=dev, inputs=[
                s_in.x, tr, self.domain, grid.mv.grad, grid.m.grad, s_in.x.grad, tr.mass.grad, tr.momentum.grad,
                tr.affine.grad], record_tape=False), arrays=[s_in.x, tr.mass, tr.momentum, tr.affine, grid.mv, grid.m])
        lo, hi = self.active_block(s_in.x)
        damping_factor = math.exp(-self.frame_damping[min(frame, self.T - 1)] * dt)
        v_max = 1.0 / (self.inv_dx * dt)  # one cell per substep (sim units)
        block = tuple(int(h - l + 1) for l, h in zip(lo, hi))
        update_grid = [buf.grid, buf.col, 1 if self.colliders else 0, self.domain, dt, damping_factor, v_max,
                       wp.vec3i(*[int(v) for v in lo])]
        run(K.grid_update, block, update_grid)
        if tape is not None:
            tape.record_func(lambda: wp.launch(A.grid_update_adjoint, dim=block, device=dev, inputs=[
                *update_grid, grid.v.grad, grid.mv.grad, grid.m.grad], record_tape=False),
                arrays=[grid.m, grid.mv, grid.v])
        held = K.HeldTargets()
        held.x0, held.x1 = self.held_frames[frame], self.held_frames[frame + 1]
        held.alpha_end, held.inv_frame_dt = (sub + 1) / step.substeps, self.inv_frame_dt
        run(K.g2p_gather, self.P, [s_in.x, self.domain, grid, tr])
        if tape is not None:
            tape.record_func(lambda: wp.launch(A.g2p_gather_adjoint, dim=self.P, device=dev, inputs=[
                s_in.x, self.domain, grid, tr, tr.v.grad, tr.C.grad, grid.v.grad, s_in.x.grad], record_tape=False),
                arrays=[s_in.x, grid.v, tr.v, tr.C])
        update = [s_in, self.particles, mats, self.domain, tr, held, dt, s_out]
        if tape is not None and elastic:
            run(K.g2p_update, self.P, update)
            adjoints = [adjoints_of(s_in, K.ParticleState), adjoints_of(tr, K.ParticleTransfer),
                        adjoints_of(s_out, K.ParticleState)]
            tape.record_func(lambda: wp.launch(A.g2p_update_elastic_adjoint, dim=self.P, device=dev, inputs=[
                s_in, self.particles, self.domain, tr, dt, s_out, *adjoints], record_tape=False),
                arrays=[s_in.x, s_in.F, tr.v, tr.C, *state_arrays(s_out)])
        else:
            launch(K.g2p_update, self.P, update)

    # -- untaped forward ---------------------------------------------------------------------------------
    def forward(self, x0: torch.Tensor, v0: torch.Tensor, mats: K.MaterialTable, step: Timestep,
                keep_before_last: bool):
        """Run all frames without a tape.

        Returns the frame states (list of (x, v, C, F) Warp arrays, T entries, [0] = initial) and, if asked,
        the state before the last substep of each frame (T - 1 entries, for "last_substep").
        """
        P, dev = self.P, self.device
        a, b = alloc_state(P, dev, False), alloc_state(P, dev, False)
        buf = GridBuffers.alloc(self.n, P, dev, False, bool(self.colliders))
        replays = Replays(dev)
        load_state(a, (x0, v0, torch.zeros(P, 3, 3), torch.eye(3).expand(P, 3, 3)))
        states = [save_state(a)]
        before_last = []
        for f in range(self.T - 1):
            for sub in range(step.substeps):
                if keep_before_last and sub == step.substeps - 1:
                    before_last.append(save_state(a))
                buf.clear()
                self.substep(a, b, buf, mats, step, f, sub, replays=replays)
                a, b = b, a
            st = save_state(a)
            if not (np.isfinite(st[0].numpy()).all() and np.isfinite(st[3].numpy()).all()):
                raise SimulationError(
                    f"the simulation diverged (NaN/inf) in frame {f + 1} (substep dt {step.dt:.3g} s, "
                    f"{step.substeps} substeps per frame); lower the CFL number or check the materials")
            states.append(st)
        return states, before_last

    # -- taped segment and its adjoint -------------------------------------------------------------------
    def segment_buffers(self, n_sub: int, count: int = 1) -> list[SegmentBuffers]:
        """``count`` buffer sets for taped segments of ``n_sub`` substeps, kept for the next call of the same
        size (free them with :meth:`release_buffers`)."""
        sets = self._segments.get(n_sub, [])
        if len(sets) < count:
            if not sets:
                self._segments.clear()  # free the old buffers before allocating new ones
            dev = self.device
            sets = sets + [SegmentBuffers(
                [alloc_state(self.P, dev, True) for _ in range(n_sub + 1)],
                [GridBuffers.alloc(self.n, self.P, dev, True, bool(self.colliders)) for _ in range(n_sub)])
                for _ in range(count - len(sets))]
            self._segments[n_sub] = sets
        return sets[:count]

    def segment_bytes(self, n_sub: int) -> int:
        """Memory (bytes) of one buffer set of :meth:`segment_buffers` (values and adjoints, float32)."""
        n3 = self.n ** 3
        per_substep = 2 * 4 * (self.P * (24 + 25) + n3 * 7) + 4 * n3 * (4 if self.colliders else 0)
        return n_sub * per_substep + 2 * 4 * self.P * 24

    def release_buffers(self) -> None:
        """Free the taped-segment buffers."""
        self._segments.clear()

    def record_segment(self, seg: SegmentBuffers, mats: K.MaterialTable, step: Timestep, start, frame: int,
                       first_sub: int) -> wp.Tape:
        """Recompute ``len(seg.grids)`` substeps of ``frame`` from ``start`` into ``seg``, recorded on a tape of
        their own (returned; :meth:`pull_back` runs it backwards)."""
        # A fresh buffer set is all zeros. Warp 1.19 consumes (zeroes) the adjoints of arrays written by
        # plain stores during backward, so a used set only needs the tape input (state 0) and the atomically
        # accumulated grid adjoints zeroed. (The multi-frame gradient tests check this against finite
        # differences, and the buffers are reused across calls there.)
        if seg.used:
            for a in state_arrays(seg.states[0]):
                a.grad.zero_()
            for g in seg.grids:
                g.clear()
                g.zero_accumulated_grads()
        seg.used = True
        load_state(seg.states[0], start)
        elastic = not mats.yield_stress.numpy().any()
        hand_stress = mats.E.requires_grad and all(MODELS[m].hand_adjoint for m in set(mats.model.numpy().tolist()))
        tape = wp.Tape()
        try:
            for i, g in enumerate(seg.grids):
                self.substep(seg.states[i], seg.states[i + 1], g, mats, step, frame, first_sub + i, tape,
                             elastic=elastic, hand_stress=hand_stress)
        except BaseException:
            self.release_buffers()  # never reuse buffers a failed recording left half written
            raise
        return tape

    def pull_back(self, seg: SegmentBuffers, tape: wp.Tape, mats: K.MaterialTable, adj_end):
        """Pull ``adj_end`` (adjoint of the segment's last state: x, v, C, F) back through ``tape`` (from
        :meth:`record_segment` into ``seg``).

        Returns the adjoint of the start state (x, v, C, F) and of the differentiable material arrays.
        """
        diff = self.differentiable_arrays(mats)
        for m in diff:
            m.grad.zero_()
        try:
            set_state_grads(seg.states[-1], adj_end)
            tape.backward()
        except BaseException:
            self.release_buffers()  # a half-run backward leaves adjoints behind: never reuse those buffers
            raise
        adj_start = state_grads(seg.states[0])
        adj_mats = tuple(as_torch(m.grad).clone().cpu() for m in diff)
        tape.reset()
        return adj_start, adj_mats
