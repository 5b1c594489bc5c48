"""Rollouts of the MLS-MPM simulator: forward (:func:`simulate`) and differentiable (:func:`mpm_rollout`).

  - :func:`simulate`: forward rollout (no gradients) -> :class:`SimResult`, positions and deformation
    gradients per output frame.
  - :func:`mpm_rollout`: the same as a differentiable PyTorch op: gradients flow to the per-object
    materials (E, nu, density of :class:`~endogsim.physics.materials.ObjectMaterials`) and to the initial
    positions and velocities, in one of three modes:

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

    The backward pass of every mode recomputes each frame it pulls adjoints through (a third of its time).
    With two or more torch threads on a CPU it recomputes the next frame back on a second core while the
    adjoints of this one run (:class:`_SegmentPipeline`): the same kernels on the same inputs, so the same
    gradients to the last bit, for a second set of segment buffers when the memory holds it.

  - :class:`Simulator`: the same for a set-up that is simulated many times (identification): the engine's
    static arrays and taped-segment buffers are built once.

The substep count of every rollout follows the CFL rule for its materials (:mod:`endogsim.physics.stability`).
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import torch

from endogsim.errors import SimulationError
from endogsim.physics.config import MPMConfig, Scenario
from endogsim.physics.engine import MPMEngine, Timestep, stack_arrays
from endogsim.physics.materials import ObjectMaterials
from endogsim.physics.modes import GRAD_MODES, GradMode
from endogsim.physics.particles import Particles
from endogsim.physics.stability import check_materials, plan_substeps
from endogsim.warp_runtime import independent_runs

__all__ = ["SimResult", "Simulator", "simulate", "mpm_rollout"]


def _check_adjoints(frame: int, adj_state, adj_mats) -> None:
    """Refuse NaN/inf adjoints of the backward pass, naming the frame and the quantity (never a silent zero)."""
    names = ("positions", "velocities", "affine matrices C", "deformation gradients F")
    for name, a in list(zip(names, adj_state)) + list(zip(("E", "nu", "density"), adj_mats)):
        if not bool(torch.isfinite(a).all()):
            raise SimulationError(f"the backward pass through the simulator produced NaN/inf in frame {frame}: "
                                  f"the adjoint of the {name} (a state the rollout reached without NaN)")


class _MPMRolloutFn(torch.autograd.Function):
    """Sim-unit autograd op: (x0, v0, *differentiable materials) -> (positions [T,P,3], F [T,P,3,3]).

    The differentiable materials are the sim-unit arrays of :attr:`ObjectMaterials.DIFFERENTIABLE` (E_sim,
    nu, rho); ``static`` holds the rest of the table (model ids, yield stress in sim units).
    """

    @staticmethod
    def forward(ctx, x0, v0, engine: MPMEngine, step: Timestep, mode: str, static, *diff):
        mats = engine.material_table(*diff, *static, grad=False)
        states, before_last = engine.forward(x0.detach().float().cpu(), v0.detach().float().cpu(), mats, step,
                                             keep_before_last=(mode == "last_substep"))
        ctx.engine, ctx.step, ctx.mode, ctx.static = engine, step, mode, static
        ctx.states, ctx.before_last = states, before_last
        ctx.diff = tuple(d.detach() for d in diff)
        xs = stack_arrays([s[0] for s in states]).to(x0.device)
        Fs = stack_arrays([s[3] for s in states]).to(x0.device)
        return xs, Fs

    @staticmethod
    def backward(ctx, g_x, g_F):
        eng: MPMEngine = ctx.engine
        step, mode = ctx.step, ctx.mode
        T, P = eng.T, eng.P
        out_device = g_x.device if g_x is not None else g_F.device
        g_x = torch.zeros(T, P, 3) if g_x is None else g_x.detach().float().cpu()
        g_F = torch.zeros(T, P, 3, 3) if g_F is None else g_F.detach().float().cpu()
        mats = eng.material_table(*ctx.diff, *ctx.static, grad=True)
        g_mats = [torch.zeros(d.shape, dtype=torch.float64) for d in ctx.diff]
        zeros_v, zeros_C = torch.zeros(P, 3), torch.zeros(P, 3, 3)
        adj_x0, adj_v0 = g_x[0].clone(), torch.zeros(P, 3)

        def segment(f: int):
            """(start state, first substep) of the segment that ends at frame f."""
            if mode == "last_substep":
                return ctx.before_last[f - 1], step.substeps - 1
            return ctx.states[f - 1], 0

        # The frames whose adjoint will not be zero (recomputed ahead; the loop below decides).
        outputs = [f for f in range(T - 1, 0, -1) if bool(g_x[f].abs().max() > 0) or bool(g_F[f].abs().max() > 0)]
        ahead = [f for f in range(T - 1, 0, -1) if f <= outputs[0]] if mode == "full" and outputs else outputs
        pipe = _SegmentPipeline(eng, mats, step, 1 if mode == "last_substep" else step.substeps, segment,
                                ahead) if T > 1 else None
        carry = None  # "full": adjoint of the state at the end of the frame being processed
        try:
            for f in range(T - 1, 0, -1):
                adj_end = [g_x[f].clone(), zeros_v.clone(), zeros_C.clone(), g_F[f].clone()]
                if mode == "full" and carry is not None:
                    adj_end = [a + c for a, c in zip(adj_end, carry)]
                if not any(bool(a.abs().max() > 0) for a in adj_end):
                    pipe.skip(f)
                    carry = None if mode != "full" else [torch.zeros_like(a) for a in adj_end]
                    continue
                adj_start, adj_m = pipe.pull_back(f, adj_end)
                _check_adjoints(f, adj_start, adj_m)
                for acc, a in zip(g_mats, adj_m):
                    acc += a.double()
                if mode == "full":
                    carry = list(adj_start)
                elif f == 1 and mode == "frame":
                    adj_x0 += adj_start[0]
                    adj_v0 += adj_start[1]
        finally:
            if pipe is not None:
                pipe.close()
        if mode == "full" and carry is not None:
            adj_x0 += carry[0]
            adj_v0 += carry[1]
        grads = tuple(g.to(d.dtype).to(d.device) for g, d in zip(g_mats, ctx.diff))
        return (adj_x0.to(out_device), adj_v0.to(out_device), None, None, None, None, *grads)


class _SegmentPipeline:
    """The backward pass's segments, each recomputed on a tape (:meth:`MPMEngine.record_segment`) and pulled
    back (:meth:`MPMEngine.pull_back`), frame by frame from the last.

    With two buffer sets, the segment of the next frame in ``ahead`` is recomputed on a second thread while
    this one's adjoints run; Warp releases the GIL in its CPU launches, so the two use two cores. One set
    (one torch thread, a CUDA device, or memory for one set only): each segment is recomputed when its turn
    comes. Either way each segment is the same recomputation and the adjoints run in the same order: the
    gradients are identical.

    Args:
        engine, mats, step: the rollout's.
        n_sub: substeps per segment.
        segment: frame f -> (start state, first substep) of the segment ending at f.
        ahead: the frames expected to need a segment, in the order they come (a frame that turns out not
            to is skipped, :meth:`skip`; one that was not expected is recomputed when it comes).
    """

    def __init__(self, engine: MPMEngine, mats, step: Timestep, n_sub: int, segment, ahead: list[int]):
        self.engine, self.mats, self.step, self.segment = engine, mats, step, segment
        self.ahead = list(ahead)
        # Two buffer sets work side by side under the rule of any two simulations at a time (a CPU, two torch
        # threads, half the available memory holds both).
        sets = 2 if len(self.ahead) > 1 and independent_runs(engine.device, engine.segment_bytes(n_sub)) >= 2 else 1
        self.free = engine.segment_buffers(n_sub, sets)
        self.pending: dict[int, tuple[Future, object]] = {}
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="endogsim-segment") if sets > 1 else None

    def _record(self, f: int, seg):
        start, first = self.segment(f)
        return self.engine.record_segment(seg, self.mats, self.step, start, f - 1, first)

    def _prefetch(self, after: int) -> None:
        """Start recomputing the first frame of ``ahead`` below ``after`` on the second thread."""
        nxt = next((g for g in self.ahead if g < after), None)
        if self.pool is not None and nxt is not None and nxt not in self.pending and self.free:
            seg = self.free.pop()
            self.pending[nxt] = (self.pool.submit(self._record, nxt, seg), seg)

    def pull_back(self, f: int, adj_end):
        """The adjoints of the start state and of the materials of the segment ending at frame f."""
        if f in self.pending:
            job, seg = self.pending.pop(f)
            tape = job.result()
        else:
            seg = self.free.pop()
            tape = self._record(f, seg)
        self._prefetch(f)
        try:
            return self.engine.pull_back(seg, tape, self.mats, adj_end)
        finally:
            self.free.append(seg)

    def skip(self, f: int) -> None:
        """Frame f needs no segment after all: drop one recomputed for it."""
        if f in self.pending:
            job, seg = self.pending.pop(f)
            try:
                job.result().reset()
            except Exception:  # a recomputation the one-set pass would not have run: not its error
                return  # (its buffer set is dropped: the recording left it half written)
            self.free.append(seg)

    def close(self) -> None:
        """Wait for a recomputation still running (an error stops the pass before its frame comes)."""
        for job, _ in self.pending.values():
            try:
                job.result()
            except Exception:  # the error that stopped the pass is the one raised
                pass
        self.pending.clear()
        if self.pool is not None:
            self.pool.shutdown(wait=True)


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
        settling_left: the largest particle displacement (metres) over the last settling frame, what the
            settling had not yet reached of the equilibrium (0 without settling); it moves on in the clip.
    """

    positions: torch.Tensor
    F: torch.Tensor
    times: torch.Tensor
    substeps: int
    dt: float
    colliders: list[torch.Tensor] = field(default_factory=list)
    settling_left: float = 0.0


class Simulator:
    """One simulation set-up (particles, scenario, numerics, frame count), rolled out with any materials.

    Args:
        particles: the simulated particles.
        scenario: sim box, gravity, anchors, forces, colliders.
        config: numerics (the substeps of a rollout are raised to satisfy the CFL condition).
        num_frames: T, output frames including the initial one.
    """

    def __init__(self, particles: Particles, scenario: Scenario, config: MPMConfig, num_frames: int):
        if num_frames < 1:
            raise SimulationError(f"num_frames = {num_frames} must be >= 1")
        if len(particles) == 0:
            raise SimulationError("no particles to simulate")
        # Quasi-static mass scaling (Scenario.mass_scaling): the engine sees the scaled world; densities are
        # scaled per rollout (they may carry gradients).
        self.mass_scaling = float(scenario.mass_scaling)
        scenario = scenario.mass_scaled()
        config = replace(config, damping=config.damping / self.mass_scaling)
        self.particles, self.scenario, self.config, self.num_frames = particles, scenario, config, num_frames
        self._engine: MPMEngine | None = None
        self._collider_speed = 0.0
        for traj in [c.trajectory() for c in scenario.colliders] + [a.positions for a in scenario.moving_anchors]:
            if traj.shape[0] > 1:
                self._collider_speed = max(self._collider_speed,
                                           float((traj[1:] - traj[:-1]).norm(dim=-1).max()) / config.frame_dt)

    @property
    def engine(self) -> MPMEngine:
        """The engine over the settling frames and the clip (built on first use)."""
        if self._engine is None:
            self._engine = MPMEngine(self.particles, self.scenario.with_settling(self.config.frame_dt), self.config,
                                     self.scenario.settle_frames + self.num_frames, frame_damping=self._frame_damping())
        return self._engine

    def _frame_damping(self) -> list[float]:
        """Grid damping (1/s) of every frame of the rollout over settling + clip."""
        sc = self.scenario
        return [sc.damping_of_frame(f, self.config.damping) for f in range(sc.settle_frames + self.num_frames)]

    def _clip(self, xs: torch.Tensor, Fs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The clip's frames of a rollout over settling + clip (see :attr:`Scenario.settle`)."""
        S = self.scenario.settle_frames
        if S == 0:
            return xs, Fs
        if self.scenario.settle == "keep":
            return xs[S:], Fs[S:]
        sag = xs[S] - xs[0]
        F_rest_inv = torch.linalg.inv(Fs[S].double()).to(Fs.dtype)
        return xs[S:] - sag, Fs[S:] @ F_rest_inv

    def _scaled(self, materials: ObjectMaterials) -> ObjectMaterials:
        """``materials`` with the densities times the mass scaling (differentiable)."""
        if self.mass_scaling == 1.0:
            return materials
        return replace(materials, density=materials.density * self.mass_scaling)

    def timestep(self, materials: ObjectMaterials, v0: torch.Tensor | None = None) -> Timestep:
        """The CFL-respecting substeps for these materials (checked: impossible values are refused)."""
        used = self._scaled(materials).used(self.particles.object_ids)
        check_materials(used.E.numpy(), used.nu.numpy(), used.density.numpy(), where="object")
        speed = self._collider_speed
        if v0 is not None and len(v0):
            speed = max(speed, float(torch.as_tensor(v0).detach().norm(dim=-1).max()))
        substeps, dt = plan_substeps(self.config, self.scenario.box.size, used.E.numpy(), used.nu.numpy(),
                                     used.density.numpy(), speed)
        return Timestep(substeps, dt)

    def engine_inputs(self, materials: ObjectMaterials) -> tuple:
        """What a rollout of ``materials`` hands the engine: its substeps and their length (the CFL plan), the
        per-object float32 E, nu and density in sim units (the density mass-scaled), the model ids and the yield
        stress. Materials with equal inputs roll out to the same numbers, to the last bit, even where their
        float64 values differ (a Poisson's ratio sent through the optimiser's raw parameter and back differs from
        the prior it came from in the 17th digit, not in float32)."""
        with torch.no_grad():
            # simulate's default initial velocity, p.v or zeros: zeros plan as no velocity at all.
            step = self.timestep(materials, self.particles.v)
            E, nu, density, model, yield_stress = self._engine_materials(materials)
            return (step.substeps, step.dt, model,
                    *(t.detach().cpu().to(torch.float32) for t in (E, nu, density, yield_stress)))

    def _engine_materials(self, materials: ObjectMaterials) -> tuple[torch.Tensor, ...]:
        """(E, nu, density, model ids, yield stress) of ``materials`` as the engine's material table takes them
        for a forward rollout: moduli in sim units, the density mass-scaled."""
        m = self._scaled(materials)
        return (self.scenario.box.modulus_to_sim(m.E.double()), m.nu, m.density, *self._static(m))

    def _static(self, materials: ObjectMaterials):
        box = self.scenario.box
        return (materials.model.detach().cpu(), box.modulus_to_sim(materials.yield_stress.detach().double()))

    def run(self, materials: ObjectMaterials, grad_mode: GradMode = "frame", x0: torch.Tensor | None = None,
            v0: torch.Tensor | None = None) -> SimResult:
        """Differentiable rollout (see :func:`mpm_rollout`) as a :class:`SimResult` whose positions and F carry
        the gradients: the same numbers as :meth:`simulate` of the same materials."""
        if grad_mode not in GRAD_MODES:
            raise SimulationError(f"grad_mode {grad_mode!r} is not one of {GRAD_MODES}")
        p = self.particles
        x0 = p.x if x0 is None else x0
        v0 = (p.v if p.v is not None else torch.zeros_like(x0)) if v0 is None else v0
        step = self.timestep(materials, v0)
        materials = self._scaled(materials)
        box = self.scenario.box
        x0_sim = box.to_sim(x0.to(torch.float64)).float()
        v0_sim = box.vec_to_sim(v0.to(torch.float64)).float()
        diff = (box.modulus_to_sim(materials.E), materials.nu, materials.density)
        xs, Fs = _MPMRolloutFn.apply(x0_sim, v0_sim, self.engine, step, grad_mode, self._static(materials), *diff)
        positions = box.to_world(xs.to(torch.float64)).to(x0.dtype)
        # Index 0 is exactly the input (no float32 round trip), so its gradient is the identity.
        return self._result(torch.cat([x0[None], positions[1:]], 0), Fs, step)

    def rollout(self, materials: ObjectMaterials, grad_mode: GradMode = "frame", x0: torch.Tensor | None = None,
                v0: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Differentiable rollout (see :func:`mpm_rollout`): positions [T, P, 3] (m) and F [T, P, 3, 3]."""
        res = self.run(materials, grad_mode, x0, v0)
        return res.positions, res.F

    def simulate(self, materials: ObjectMaterials, v0: torch.Tensor | None = None) -> SimResult:
        """Forward rollout without gradients (see :func:`simulate`)."""
        p, box = self.particles, self.scenario.box
        with torch.no_grad():
            x0 = p.x.detach()
            v0 = (p.v if p.v is not None else torch.zeros_like(x0)) if v0 is None else v0
            step = self.timestep(materials, v0)
            mats = self.engine.material_table(*self._engine_materials(materials), grad=False)
            states, _ = self.engine.forward(box.to_sim(x0.double()).float().cpu(),
                                            box.vec_to_sim(v0.double()).float().cpu(), mats, step, keep_before_last=False)
            # On the particles' device whatever the simulator's (a CUDA rollout of CPU particles returns CPU
            # tensors, as the differentiable rollout does).
            xs = box.to_world(stack_arrays([s[0] for s in states]).double()).to(device=x0.device, dtype=x0.dtype)
            xs[0] = x0
            return self._result(xs, stack_arrays([s[3] for s in states]).to(x0.device), step)

    def _result(self, xs: torch.Tensor, Fs: torch.Tensor, step: Timestep) -> SimResult:
        """The clip of a rollout over settling + clip (``xs`` [S + T, P, 3] metres, ``Fs`` [S + T, P, 3, 3])."""
        S = self.scenario.settle_frames
        settling_left = float((xs[S] - xs[S - 1]).detach().norm(dim=-1).max()) if S > 0 else 0.0
        positions, F = self._clip(xs, Fs)
        times = torch.arange(self.num_frames, dtype=torch.float64) * self.config.frame_dt
        return SimResult(positions, F, times, step.substeps, step.dt,
                         [c.trajectory()[: self.num_frames].to(xs.dtype) for c in self.scenario.colliders],
                         settling_left)


def mpm_rollout(
    particles: Particles,
    materials: ObjectMaterials,
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
        materials: per-object materials; gradients flow to ``E``, ``nu`` and ``density`` (e.g. build E as
            ``10 ** log10_E`` to optimise log10 E).
        scenario: sim box, gravity, anchors, forces, colliders.
        config: numerics (substeps are raised to satisfy the CFL condition).
        num_frames: T, number of output frames including the initial one.
        grad_mode: "last_substep" | "frame" | "full" (see the module docstring).
        x0: [P, 3] initial positions (m), default ``particles.x``; differentiable.
        v0: [P, 3] initial velocities (m/s), default ``particles.v`` or zeros; differentiable.
    Returns:
        positions [T, P, 3] (m) and F [T, P, 3, 3]; index 0 is the initial state.
    """
    return Simulator(particles, scenario, config, num_frames).rollout(materials, grad_mode, x0, v0)


def simulate(
    particles: Particles,
    materials: ObjectMaterials,
    scenario: Scenario,
    config: MPMConfig,
    num_frames: int,
    v0: torch.Tensor | None = None,
) -> SimResult:
    """Forward rollout without gradients.

    Args:
        particles: the simulated particles.
        materials: per-object materials (E Pa, nu, density kg/m^3, constitutive model, yield stress).
        scenario, config: the world and the numerics.
        num_frames: T output frames including the initial one.
        v0: [P, 3] initial velocities (m/s), default ``particles.v`` or zeros.
    Returns:
        :class:`SimResult` with positions [T, P, 3] (m) and F [T, P, 3, 3].
    Raises:
        MaterialError for impossible materials, SimulationError for an unstable explicit dt, too stiff
        materials, or a diverged rollout (naming the frame).
    """
    return Simulator(particles, scenario, config, num_frames).simulate(materials, v0)
