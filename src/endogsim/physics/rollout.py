"""Forward rollouts and gradients of the MLS-MPM simulator.

Entry points:
  - :func:`simulate`: forward rollout (no gradients) -> :class:`SimResult`, positions and deformation
    gradients per output frame.
  - :func:`mpm_rollout`: the same as a differentiable PyTorch op: gradients flow to per-object log10 E,
    nu and density and to the initial positions and velocities, in one of three modes:

      "last_substep"  the paper's: only the last substep of each frame is differentiated (the state before
                      it is a constant). Cheap, but its gradient is far smaller than the true one and can
                      flip sign when E is far off (measured in tests/test_physics_gradients.py: ~100x
                      smaller, wrong sign at log10 E one decade above the optimum). The initial state only
                      gets the direct gradient of frame 0.
      "frame"         through every substep of each frame; the state is detached between frames (the
                      initial state gets the gradient through frame 1).
      "full"          through the whole rollout. Memory stays bounded by segment checkpointing: the forward
                      pass stores the state at each frame; the backward pass recomputes one frame at a time
                      on a Warp tape and carries the adjoint of the state to the frame before.

  - :func:`plan_substeps`, :func:`max_stable_E`, :func:`p_wave_speed`: the stability rules.

Why tapes are built per frame during backward (never across the whole forward): Warp replays adjoints
with arrays' *current* contents, so every substep inside a taped segment writes fresh buffers (a pool
of ``substeps + 1`` particle states and ``substeps`` grids, reused from one frame to the next).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
import warp as wp

from endogsim.errors import MaterialError, SimulationError
from endogsim.physics import kernels as K
from endogsim.physics.config import GradMode, MPMConfig, Scenario
from endogsim.physics.particles import Particles
from endogsim.warp_runtime import init_warp

GRAD_MODES = ("last_substep", "frame", "full")

_POOL_CACHE = None  # (key, pool) of the last taped-segment buffers


def release_buffers() -> None:
    """Free the cached backward buffers (they are kept between calls of the same size)."""
    global _POOL_CACHE
    _POOL_CACHE = None


def resolve_device(device: str) -> str:
    """A Warp device name that exists here ("cuda" without a GPU is refused with a clear error)."""
    init_warp()
    if device.startswith("cuda") and not wp.is_cuda_available():
        raise SimulationError(f"device {device!r} requested but CUDA is not available to Warp on this machine")
    return device


# --------------------------------------------------------------------------------------------------
# Stability
# --------------------------------------------------------------------------------------------------


def p_wave_speed(E, nu, density):
    """Dilatational wave speed c_p = sqrt(E (1 - nu) / ((1 + nu)(1 - 2 nu) rho)) in m/s (numpy-broadcast)."""
    E, nu, density = np.asarray(E, float), np.asarray(nu, float), np.asarray(density, float)
    return np.sqrt(E * (1 - nu) / ((1 + nu) * (1 - 2 * nu) * density))


def check_materials(E, nu, density, where: str = "material") -> None:
    """Raise :class:`MaterialError` for impossible values (E <= 0, nu outside (-1, 0.5), rho <= 0, NaN)."""
    E, nu, density = (np.atleast_1d(np.asarray(a, float)) for a in (E, nu, density))
    for i in range(len(E)):
        if not (np.isfinite(E[i]) and E[i] > 0):
            raise MaterialError(f"{where} {i}: Young's modulus E = {E[i]} Pa must be finite and > 0")
        if not (np.isfinite(nu[i]) and -1.0 < nu[i] < 0.5):
            raise MaterialError(f"{where} {i}: Poisson ratio nu = {nu[i]} must lie in (-1, 0.5)")
        if not (np.isfinite(density[i]) and density[i] > 0):
            raise MaterialError(f"{where} {i}: density = {density[i]} kg/m^3 must be finite and > 0")


def _dx_world(config: MPMConfig, box_size: float) -> float:
    return box_size / config.grid_res


def plan_substeps(config: MPMConfig, box_size: float, E, nu, density, max_speed: float = 0.0) -> tuple[int, float]:
    """Substeps per frame and substep dt (s) that respect the CFL condition.

    dt <= C dx / max(c_p, |v|_max), with c_p from the stiffest material present. With ``config.dt = None``
    the substep count is the least >= ``substeps_per_frame`` that satisfies it; an explicit ``config.dt``
    above the limit is refused. Refuses too (clear message) when more than ``max_substeps_per_frame``
    would be needed.

    Args:
        config: numerics.
        box_size: sim box edge (m).
        E, nu, density: per-material values (Pa, -, kg/m^3) of the materials present (arrays or scalars).
        max_speed: largest speed expected at the start (particles, colliders), m/s.
    Returns:
        (substeps, dt) with dt = frame_dt / substeps.
    """
    check_materials(E, nu, density)
    dx = _dx_world(config, box_size)
    speed = max(float(np.max(p_wave_speed(E, nu, density))), float(max_speed), 1e-12)
    dt_limit = config.cfl_number * dx / speed
    if config.dt is not None:
        if config.dt > dt_limit * (1 + 1e-6):
            raise SimulationError(
                f"substep dt = {config.dt:.3g} s is unstable: the CFL limit is {dt_limit:.3g} s "
                f"(C = {config.cfl_number}, dx = {dx:.3g} m, wave speed {speed:.3g} m/s); use dt <= {dt_limit:.3g} s "
                "or dt = None to choose it automatically"
            )
        substeps = max(config.substeps_per_frame, math.ceil(config.frame_dt / config.dt - 1e-9))
    else:
        substeps = max(config.substeps_per_frame, math.ceil(config.frame_dt / dt_limit))
    if substeps > config.max_substeps_per_frame:
        raise SimulationError(
            f"the materials need {substeps} substeps per frame (wave speed {speed:.3g} m/s, CFL limit dt = "
            f"{dt_limit:.3g} s), above max_substeps_per_frame = {config.max_substeps_per_frame}; "
            "lower E, move nu away from 0.5, or raise the limit"
        )
    return substeps, config.frame_dt / substeps


def max_stable_E(nu, density, config: MPMConfig, box_size: float, substeps: int | None = None) -> float:
    """Largest E (Pa) that is stable at ``substeps`` per frame (default: ``config.substeps_per_frame``).

    The bound for an optimiser's box: E_max = (C dx / dt)^2 rho (1 + nu)(1 - 2 nu) / (1 - nu).
    """
    n = substeps or config.substeps_per_frame
    dt = config.dt if config.dt is not None else config.frame_dt / n
    dx = _dx_world(config, box_size)
    return float((config.cfl_number * dx / dt) ** 2 * density * (1 + nu) * (1 - 2 * nu) / (1 - nu))


# --------------------------------------------------------------------------------------------------
# Engine: static arrays, buffers and substep launches (sim units)
# --------------------------------------------------------------------------------------------------


def _torch_device(device) -> torch.device:
    return torch.device("cpu") if device.is_cpu else torch.device(f"cuda:{device.ordinal}")


def _as_torch(a: wp.array) -> torch.Tensor:
    """A torch view of a Warp array (numpy route on CPU: it avoids torch's thread pool, slow on busy CPUs)."""
    return torch.from_numpy(a.numpy()) if a.device.is_cpu else wp.to_torch(a)


def _all_finite(a: wp.array) -> bool:
    return bool(np.isfinite(a.numpy()).all())


def _stack(arrays: list[wp.array]) -> torch.Tensor:
    if arrays[0].device.is_cpu:
        return torch.from_numpy(np.stack([a.numpy() for a in arrays]))
    return torch.stack([wp.to_torch(a) for a in arrays])


@dataclass
class _State:
    x: wp.array
    v: wp.array
    C: wp.array
    F: wp.array

    @staticmethod
    def alloc(P: int, device: str, grad: bool) -> "_State":
        return _State(
            wp.zeros(P, dtype=wp.vec3, device=device, requires_grad=grad),
            wp.zeros(P, dtype=wp.vec3, device=device, requires_grad=grad),
            wp.zeros(P, dtype=wp.mat33, device=device, requires_grad=grad),
            wp.zeros(P, dtype=wp.mat33, device=device, requires_grad=grad),
        )

    def arrays(self):
        return (self.x, self.v, self.C, self.F)

    def load(self, src) -> None:
        """Copy a saved state (warp arrays) or torch tensors (x, v, C, F) into this state."""
        for a, t in zip(self.arrays(), src):
            if isinstance(t, torch.Tensor):
                t = wp.from_torch(t.detach().float().contiguous().to(_torch_device(a.device)), dtype=a.dtype)
            wp.copy(a, t)

    def save(self) -> tuple[wp.array, ...]:
        return tuple(wp.clone(a, requires_grad=False) for a in self.arrays())

    def grads(self) -> tuple[torch.Tensor, ...]:
        return tuple(_as_torch(a.grad).cpu().clone() for a in self.arrays())

    def set_grads(self, tensors) -> None:
        for a, t in zip(self.arrays(), tensors):
            wp.copy(a.grad, wp.from_torch(t.detach().float().contiguous().to(_torch_device(a.device)), dtype=a.dtype))

    def zero_grads(self) -> None:
        for a in self.arrays():
            a.grad.zero_()


@dataclass
class _Grid:
    m: wp.array
    mv: wp.array
    v: wp.array
    col_w: wp.array
    col_mv: wp.array

    @staticmethod
    def alloc(n: int, device: str, grad: bool, colliders: bool) -> "_Grid":
        shape = (n, n, n)
        cshape = shape if colliders else (1, 1, 1)
        return _Grid(
            wp.zeros(shape, dtype=float, device=device, requires_grad=grad),
            wp.zeros(shape, dtype=wp.vec3, device=device, requires_grad=grad),
            wp.zeros(shape, dtype=wp.vec3, device=device, requires_grad=grad),
            wp.zeros(cshape, dtype=float, device=device),
            wp.zeros(cshape, dtype=wp.vec3, device=device),
        )

    def clear(self) -> None:
        # grid_v is fully overwritten by grid_update, so only the accumulators need zeroing.
        self.m.zero_()
        self.mv.zero_()
        if self.col_w.shape[0] > 1:
            self.col_w.zero_()
            self.col_mv.zero_()

    def zero_grads(self) -> None:
        for a in (self.m, self.mv, self.v):
            a.grad.zero_()


class _Engine:
    """Everything about one rollout that does not change with the materials or the initial state."""

    def __init__(self, particles: Particles, scenario: Scenario, config: MPMConfig, num_frames: int,
                 substeps: int, dt: float):
        init_warp()
        self.device = resolve_device(config.device)
        self.cfg = config
        self.box = scenario.box
        self.T = num_frames
        self.substeps = substeps
        self.dt = dt
        self.n = config.grid_res
        self.inv_dx = float(config.grid_res)
        self.P = len(particles)
        self.model = K.FIXED_COROTATED if config.material_model == "fixed_corotated" else K.NEO_HOOKEAN
        s = self.box.scale
        dev = self.device

        x0_world = particles.x.detach().to(torch.float64).cpu()
        self.obj = wp.from_numpy(particles.object_ids.cpu().numpy().astype(np.int32), dtype=wp.int32, device=dev)
        self.vol = wp.from_numpy(self.box.volume_to_sim(particles.volume.detach().cpu().numpy().astype(np.float64)).astype(np.float32), dtype=float, device=dev)
        self.gravity = wp.vec3(*[float(g) * s for g in scenario.gravity])
        self.damping_factor = math.exp(-config.damping * dt)
        self.v_max = 1.0 / (self.inv_dx * dt)  # one cell per substep (sim units)
        pad_dx = 2.0 / self.inv_dx
        self.x_lo, self.x_hi = pad_dx, 1.0 - pad_dx
        self.yield_stress = float(self.box.modulus_to_sim(config.yield_stress)) if config.yield_stress else 0.0

        # Pinned particles: "fixed" anchors by box (initial position) or mask.
        pinned = np.zeros(self.P, dtype=np.int32)
        boxes = []
        for a in scenario.anchors:
            if a.particle_mask is not None:
                mask = np.asarray(torch.as_tensor(a.particle_mask).cpu().numpy(), dtype=bool).reshape(-1)
                if mask.shape[0] != self.P:
                    raise SimulationError(f"Anchor.particle_mask has {mask.shape[0]} entries for {self.P} particles")
                pinned[mask] = 1
            if a.lo is not None:
                lo, hi = np.asarray(a.lo, float), np.asarray(a.hi, float)
                if a.kind == "fixed":
                    inside = ((x0_world.numpy() >= lo) & (x0_world.numpy() <= hi)).all(1)
                    pinned[inside] = 1
                kind = K.BC_SLIP if a.kind == "slip" else K.BC_STICKY
                nrm = np.asarray(a.normal, float)
                nrm = nrm / max(np.linalg.norm(nrm), 1e-12)
                boxes.append(((lo - self.box.lo) * s, (hi - self.box.lo) * s, kind, nrm))
        self.pinned = wp.from_numpy(pinned, dtype=wp.int32, device=dev)
        self.bc_kind = wp.zeros((self.n,) * 3, dtype=wp.int32, device=dev)
        self.bc_normal = wp.zeros((self.n,) * 3, dtype=wp.vec3, device=dev)
        if boxes:
            wp.launch(K.node_boxes_to_bc, dim=(self.n,) * 3, device=dev, inputs=[
                wp.array([b[0] for b in boxes], dtype=wp.vec3, device=dev),
                wp.array([b[1] for b in boxes], dtype=wp.vec3, device=dev),
                wp.array([b[2] for b in boxes], dtype=wp.int32, device=dev),
                wp.array([b[3] for b in boxes], dtype=wp.vec3, device=dev),
                len(boxes), 1.0 / self.inv_dx, self.bc_kind, self.bc_normal])
        if pinned.any():
            # Pinned particles carry no mass (see kernels.p2g); the nodes they dominate at rest are held.
            x0_sim = wp.from_numpy(self.box.to_sim(x0_world).float().numpy(), dtype=wp.vec3, device=dev)
            w_pinned = wp.zeros((self.n,) * 3, dtype=float, device=dev)
            w_free = wp.zeros((self.n,) * 3, dtype=float, device=dev)
            wp.launch(K.anchor_weights_to_grid, dim=self.P, device=dev,
                      inputs=[x0_sim, self.pinned, self.inv_dx, self.n, w_pinned, w_free])
            wp.launch(K.anchored_nodes_to_bc, dim=(self.n,) * 3, device=dev, inputs=[w_pinned, w_free, self.bc_kind])

        # External forces: one force per particle (the last one listed wins where regions overlap).
        region = np.full(self.P, -1, dtype=np.int32)
        acc, t0, t1 = [], [], []
        for i, f in enumerate(scenario.forces):
            if f.particle_mask is not None:
                mask = np.asarray(torch.as_tensor(f.particle_mask).cpu().numpy(), dtype=bool).reshape(-1)
                if mask.shape[0] != self.P:
                    raise SimulationError(f"ExternalForce.particle_mask has {mask.shape[0]} entries for {self.P} particles")
            else:
                mask = ((x0_world.numpy() >= np.asarray(f.lo)) & (x0_world.numpy() <= np.asarray(f.hi))).all(1)
            region[mask] = i
            acc.append(np.asarray(f.acceleration, float) * s)
            t0.append(f.t_start)
            t1.append(-1.0 if f.impulse else min(f.t_end, 1e30))
        if not acc:
            acc, t0, t1 = [np.zeros(3)], [0.0], [0.0]
        self.force_region = wp.from_numpy(region, dtype=wp.int32, device=dev)
        self.force_acc = wp.array(np.asarray(acc, np.float32), dtype=wp.vec3, device=dev)
        self.force_t0 = wp.array(np.asarray(t0, np.float32), dtype=float, device=dev)
        self.force_t1 = wp.array(np.asarray(t1, np.float32), dtype=float, device=dev)

        # Colliders: trajectories per output frame, in sim units.
        self.colliders = []
        for c in scenario.colliders:
            traj = c.trajectory()
            if traj.shape[0] < num_frames:
                raise SimulationError(f"a collider trajectory has {traj.shape[0]} frames, the rollout needs {num_frames}")
            traj_sim = ((traj - torch.tensor(self.box.lo, dtype=torch.float64)) * s).float()
            radius = (c.radius * s) if c.radius is not None else 1.0 / self.inv_dx
            frames = [wp.array(traj_sim[t].numpy(), dtype=wp.vec3, device=dev) for t in range(num_frames)]
            self.colliders.append((frames, float(radius)))

    # -- materials ------------------------------------------------------------------------------
    def material_arrays(self, E_sim: torch.Tensor, nu: torch.Tensor, rho: torch.Tensor, grad: bool):
        dev = self.device
        mk = lambda t: wp.array(t.detach().to(torch.float32).cpu().numpy(), dtype=float, device=dev, requires_grad=grad)  # noqa: E731
        return mk(E_sim), mk(nu), mk(rho)

    def active_block(self, x: wp.array):
        """Lowest and highest grid node (per axis) that the particles' stencils touch (CPU); all on GPU."""
        n = self.n
        if x.device.is_cpu:
            xs = x.numpy()
            lo, hi = xs.min(0), xs.max(0)
            if np.isfinite(lo).all() and np.isfinite(hi).all():
                lo = np.clip(np.floor(lo * self.inv_dx - 0.5).astype(np.int64), 0, n - 3)
                hi = np.clip(np.floor(hi * self.inv_dx - 0.5).astype(np.int64) + 2, 2, n - 1)
                return lo, hi
        return np.zeros(3, np.int64), np.full(3, n - 1, np.int64)

    # -- one substep ------------------------------------------------------------------------------
    def substep(self, s_in: _State, s_out: _State, grid: _Grid, mats, frame: int, sub: int) -> None:
        dev, n, dt = self.device, self.n, self.dt
        t = (frame * self.substeps + sub) * dt  # time at the start of this substep (s)
        E, nu, rho = mats
        if self.colliders:
            alpha = sub / self.substeps
            for frames, radius in self.colliders:
                wp.launch(K.collider_to_grid, dim=frames[0].shape[0], device=dev, inputs=[
                    frames[frame], frames[frame + 1], alpha, 1.0 / self.cfg.frame_dt, radius, self.inv_dx, n,
                    grid.col_w, grid.col_mv])
        wp.launch(K.p2g, dim=self.P, device=dev, inputs=[
            s_in.x, s_in.v, s_in.C, s_in.F, self.vol, self.obj, self.pinned, E, nu, rho,
            self.force_region, self.force_acc, self.force_t0, self.force_t1,
            t, dt, self.inv_dx, n, self.model, grid.m, grid.mv])
        lo, hi = self.active_block(s_in.x)
        wp.launch(K.grid_update, dim=tuple(int(h - l + 1) for l, h in zip(lo, hi)), device=dev, inputs=[
            grid.m, grid.mv, grid.col_w, grid.col_mv, 1 if self.colliders else 0, self.bc_kind, self.bc_normal,
            self.gravity, dt, self.damping_factor, self.v_max, n, self.cfg.wall_padding,
            1 if self.cfg.wall == "sticky" else 0, wp.vec3i(*[int(v) for v in lo]), grid.v])
        wp.launch(K.g2p, dim=self.P, device=dev, inputs=[
            s_in.x, s_in.F, self.obj, self.pinned, E, nu, grid.v, dt, self.inv_dx, n, self.x_lo, self.x_hi,
            self.yield_stress, s_out.x, s_out.v, s_out.C, s_out.F])

    # -- untaped forward --------------------------------------------------------------------------
    def forward(self, x0: torch.Tensor, v0: torch.Tensor, mats, keep_before_last: bool):
        """Run all frames without a tape.

        Returns the frame states (list of (x, v, C, F) tensors, T entries, [0] = initial) and, if asked,
        the state before the last substep of each frame (T - 1 entries, for "last_substep").
        """
        P, dev = self.P, self.device
        a, b = _State.alloc(P, dev, False), _State.alloc(P, dev, False)
        grid = _Grid.alloc(self.n, dev, False, bool(self.colliders))
        eye = torch.eye(3).expand(P, 3, 3)
        a.load((x0, v0, torch.zeros(P, 3, 3), eye))
        states = [a.save()]
        before_last = []
        for f in range(self.T - 1):
            for sub in range(self.substeps):
                if keep_before_last and sub == self.substeps - 1:
                    before_last.append(a.save())
                grid.clear()
                self.substep(a, b, grid, mats, f, sub)
                a, b = b, a
            st = a.save()
            if not (_all_finite(st[0]) and _all_finite(st[3])):
                raise SimulationError(
                    f"the simulation diverged (NaN/inf) in frame {f + 1} (substep dt {self.dt:.3g} s, "
                    f"{self.substeps} substeps per frame); lower the CFL number or check the materials")
            states.append(st)
        return states, before_last

    # -- taped segment and its adjoint -------------------------------------------------------------
    def alloc_pool(self, n_sub: int):
        """Buffers for a taped segment of ``n_sub`` substeps: [states, grids, used]. The last pool is kept
        for the next call of the same size (an optimisation loop calls backward many times); free it
        with :func:`release_buffers`."""
        global _POOL_CACHE
        key = (self.device, self.P, self.n, n_sub, bool(self.colliders))
        if _POOL_CACHE is not None and _POOL_CACHE[0] == key:
            return _POOL_CACHE[1]
        _POOL_CACHE = None  # free the old pool before allocating a new one
        dev = self.device
        states = [_State.alloc(self.P, dev, True) for _ in range(n_sub + 1)]
        grids = [_Grid.alloc(self.n, dev, True, bool(self.colliders)) for _ in range(n_sub)]
        pool = [states, grids, False]
        _POOL_CACHE = (key, pool)
        return pool

    def backprop_segment(self, pool, mats, start, adj_end, frame: int, first_sub: int):
        """Recompute ``len(grids)`` substeps of ``frame`` from ``start`` on a tape and pull ``adj_end`` back.

        Returns the adjoint of the start state (x, v, C, F) and of the material arrays (E_sim, nu, rho).
        """
        states, grids, used = pool
        # A fresh pool is all zeros. Warp 1.19 consumes (zeroes) the adjoints of arrays written by plain
        # stores during backward, so a used pool only needs the tape input (state 0) and the atomically
        # accumulated grid adjoints zeroed. (The multi-frame gradient tests check this against finite
        # differences, and the pool is reused across calls there.)
        if used:
            states[0].zero_grads()
        for g in grids:
            if used:
                g.clear()
                g.m.grad.zero_()
                g.mv.grad.zero_()
        pool[2] = True
        for m in mats:
            m.grad.zero_()
        states[0].load(start)
        tape = wp.Tape()
        try:
            with tape:
                for i, g in enumerate(grids):
                    self.substep(states[i], states[i + 1], g, mats, frame, first_sub + i)
            states[-1].set_grads(adj_end)
            tape.backward()
        except BaseException:
            release_buffers()  # a half-run backward leaves adjoints behind: never reuse that pool
            raise
        adj_start = states[0].grads()
        adj_mats = tuple(_as_torch(m.grad).clone().cpu() for m in mats)
        tape.reset()
        return adj_start, adj_mats


# --------------------------------------------------------------------------------------------------
# PyTorch op
# --------------------------------------------------------------------------------------------------


class _MPMRolloutFn(torch.autograd.Function):
    """Sim-unit autograd op: (x0, v0, E_sim, nu, rho) -> (positions [T,P,3], F [T,P,3,3])."""

    @staticmethod
    def forward(ctx, x0, v0, E_sim, nu, rho, engine: _Engine, mode: str):
        mats = engine.material_arrays(E_sim, nu, rho, grad=False)
        states, before_last = engine.forward(x0.detach().float().cpu(), v0.detach().float().cpu(), mats,
                                             keep_before_last=(mode == "last_substep"))
        ctx.engine, ctx.mode = engine, mode
        ctx.states, ctx.before_last = states, before_last
        ctx.mat_values = (E_sim.detach(), nu.detach(), rho.detach())
        xs = _stack([s[0] for s in states]).to(x0.device)
        Fs = _stack([s[3] for s in states]).to(x0.device)
        return xs, Fs

    @staticmethod
    def backward(ctx, g_x, g_F):
        eng: _Engine = ctx.engine
        mode = ctx.mode
        T, P = eng.T, eng.P
        out_device = g_x.device if g_x is not None else g_F.device
        g_x = torch.zeros(T, P, 3) if g_x is None else g_x.detach().float().cpu()
        g_F = torch.zeros(T, P, 3, 3) if g_F is None else g_F.detach().float().cpu()
        mats = eng.material_arrays(*ctx.mat_values, grad=True)
        gE = torch.zeros(ctx.mat_values[0].shape, dtype=torch.float64)
        gnu, grho = torch.zeros_like(gE), torch.zeros_like(gE)
        zeros_v, zeros_C = torch.zeros(P, 3), torch.zeros(P, 3, 3)
        adj_x0, adj_v0 = g_x[0].clone(), torch.zeros(P, 3)

        n_sub = 1 if mode == "last_substep" else eng.substeps
        pool = eng.alloc_pool(n_sub) if T > 1 else None
        carry = None  # "full": adjoint of the state at the end of the frame being processed
        for f in range(T - 1, 0, -1):
            adj_end = [g_x[f].clone(), zeros_v.clone(), zeros_C.clone(), g_F[f].clone()]
            if mode == "full" and carry is not None:
                adj_end = [a + c for a, c in zip(adj_end, carry)]
            if not any(bool(a.abs().max() > 0) for a in adj_end):
                carry = None if mode != "full" else [torch.zeros_like(a) for a in adj_end]
                continue
            if mode == "last_substep":
                start, first = ctx.before_last[f - 1], eng.substeps - 1
            else:
                start, first = ctx.states[f - 1], 0
            adj_start, adj_m = eng.backprop_segment(pool, mats, start, adj_end, f - 1, first)
            gE += adj_m[0].double()
            gnu += adj_m[1].double()
            grho += adj_m[2].double()
            if mode == "full":
                carry = list(adj_start)
            elif f == 1 and mode == "frame":
                adj_x0 += adj_start[0]
                adj_v0 += adj_start[1]
        if mode == "full" and carry is not None:
            adj_x0 += carry[0]
            adj_v0 += carry[1]
        dt_ = ctx.mat_values[0].dtype
        return (adj_x0.to(out_device), adj_v0.to(out_device), gE.to(dt_).to(ctx.mat_values[0].device),
                gnu.to(dt_).to(ctx.mat_values[1].device), grho.to(dt_).to(ctx.mat_values[2].device), None, None)


# --------------------------------------------------------------------------------------------------
# Public entry points
# --------------------------------------------------------------------------------------------------


@dataclass
class SimResult:
    """A rollout in world units.

    Attributes:
        positions: [T, P, 3] particle positions per output frame (metres); [0] is the initial state.
        F: [T, P, 3, 3] deformation gradients (elastic part under plasticity); [0] = identity.
        times: [T] time of each frame (s).
        substeps: substeps per frame actually used.
        dt: substep (s).
        colliders: per collider, [T, Pc, 3] world positions it followed (kinematic: exactly as prescribed).
    """

    positions: torch.Tensor
    F: torch.Tensor
    times: torch.Tensor
    substeps: int
    dt: float
    colliders: list[torch.Tensor] = field(default_factory=list)


def _max_speed(particles: Particles, v0, scenario: Scenario, config: MPMConfig) -> float:
    speed = 0.0
    if v0 is not None and len(v0):
        speed = float(torch.as_tensor(v0).detach().norm(dim=-1).max())
    for c in scenario.colliders:
        traj = c.trajectory()
        if traj.shape[0] > 1:
            speed = max(speed, float((traj[1:] - traj[:-1]).norm(dim=-1).max()) / config.frame_dt)
    return speed


def _used_materials(particles: Particles, E, nu, rho):
    ids = torch.from_numpy(np.unique(particles.object_ids.cpu().numpy())).long()
    M = E.shape[0]
    if int(ids.min()) < 0 or int(ids.max()) >= M:
        raise MaterialError(f"particle object ids span [{int(ids.min())}, {int(ids.max())}], "
                            f"but materials are given for ids 0..{M - 1}")
    pick = lambda a: a.detach().double().cpu()[ids].numpy()  # noqa: E731
    return pick(E), pick(nu), pick(rho)


def _prepare(particles, E, nu, density, scenario, config, num_frames, v0):
    if num_frames < 1:
        raise SimulationError(f"num_frames = {num_frames} must be >= 1")
    if len(particles) == 0:
        raise SimulationError("no particles to simulate")
    for name, a in (("E", E), ("nu", nu), ("density", density)):
        if a.ndim != 1:
            raise MaterialError(f"{name} must be a 1-D per-object tensor, got shape {tuple(a.shape)}")
    Eu, nuu, rhou = _used_materials(particles, E, nu, density)
    check_materials(Eu, nuu, rhou, where="object")
    substeps, dt = plan_substeps(config, scenario.box.size, Eu, nuu, rhou, _max_speed(particles, v0, scenario, config))
    return _Engine(particles, scenario, config, num_frames, substeps, dt)


def mpm_rollout(
    particles: Particles,
    log10_E: torch.Tensor,
    nu: torch.Tensor,
    density: torch.Tensor,
    scenario: Scenario,
    config: MPMConfig,
    num_frames: int,
    grad_mode: GradMode = "frame",
    x0: torch.Tensor | None = None,
    v0: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable rollout: per-frame positions and deformation gradients.

    Args:
        particles: the simulated particles (rest positions, volumes, object ids).
        log10_E: [M] log10 of Young's modulus (Pa) per object id (indexed by ``particles.object_ids``).
        nu: [M] Poisson ratio per object id.
        density: [M] density (kg/m^3) per object id.
        scenario: sim box, gravity, anchors, forces, colliders.
        config: numerics (substeps are raised to satisfy the CFL condition).
        num_frames: T, number of output frames including the initial one.
        grad_mode: "last_substep" | "frame" | "full" (see the module docstring).
        x0: [P, 3] initial positions (m), default ``particles.x``; differentiable.
        v0: [P, 3] initial velocities (m/s), default ``particles.v`` or zeros; differentiable.
    Returns:
        positions [T, P, 3] (m) and F [T, P, 3, 3]; index 0 is the initial state.
    """
    if grad_mode not in GRAD_MODES:
        raise SimulationError(f"grad_mode {grad_mode!r} is not one of {GRAD_MODES}")
    x0 = particles.x if x0 is None else x0
    v0 = (particles.v if particles.v is not None else torch.zeros_like(x0)) if v0 is None else v0
    E = torch.pow(10.0, log10_E)
    engine = _prepare(particles, E, nu, density, scenario, config, num_frames, v0)
    box = scenario.box
    x0_sim = box.to_sim(x0.to(torch.float64)).float()
    v0_sim = box.vec_to_sim(v0.to(torch.float64)).float()
    xs, Fs = _MPMRolloutFn.apply(x0_sim, v0_sim, box.modulus_to_sim(E), nu, density, engine, grad_mode)
    positions = box.to_world(xs.to(torch.float64)).to(x0.dtype)
    # Index 0 is exactly the input (no float32 round trip), so its gradient is the identity.
    positions = torch.cat([x0[None], positions[1:]], 0)
    return positions, Fs


def simulate(
    particles: Particles,
    E: torch.Tensor | np.ndarray,
    nu: torch.Tensor | np.ndarray,
    density: torch.Tensor | np.ndarray,
    scenario: Scenario,
    config: MPMConfig,
    num_frames: int,
    v0: torch.Tensor | None = None,
) -> SimResult:
    """Forward rollout without gradients.

    Args:
        particles: the simulated particles.
        E: [M] Young's modulus (Pa) per object id; nu: [M] Poisson ratio; density: [M] kg/m^3.
        scenario, config: the world and the numerics.
        num_frames: T output frames including the initial one.
        v0: [P, 3] initial velocities (m/s), default ``particles.v`` or zeros.
    Returns:
        :class:`SimResult` with positions [T, P, 3] (m) and F [T, P, 3, 3].
    Raises:
        MaterialError for impossible materials, SimulationError for an unstable explicit dt, too stiff
        materials, or a diverged rollout (naming the frame).
    """
    E, nu, density = (torch.as_tensor(a, dtype=torch.float64).reshape(-1) for a in (E, nu, density))
    with torch.no_grad():
        x0 = particles.x.detach()
        v0 = (particles.v if particles.v is not None else torch.zeros_like(x0)) if v0 is None else v0
        engine = _prepare(particles, E, nu, density, scenario, config, num_frames, v0)
        box = scenario.box
        mats = engine.material_arrays(box.modulus_to_sim(E), nu, density, grad=False)
        states, _ = engine.forward(box.to_sim(x0.double()).float().cpu(), box.vec_to_sim(v0.double()).float().cpu(),
                                   mats, keep_before_last=False)
        xs = box.to_world(_stack([s[0] for s in states]).double()).to(x0.dtype)
        xs[0] = x0
        Fs = _stack([s[3] for s in states])
    times = torch.arange(num_frames, dtype=torch.float64) * config.frame_dt
    return SimResult(xs, Fs, times, engine.substeps, engine.dt,
                     [c.trajectory()[:num_frames].to(x0.dtype) for c in scenario.colliders])
