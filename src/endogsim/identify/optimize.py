"""The identification loop: Rprop or Adam (one step scale per parameter tensor) on log10 E and bounded nu of the
deformable objects (``IdentifyConfig.optimizer``, :data:`OPTIMIZERS`), or Levenberg-Marquardt on the loss's
residuals ("lm", :mod:`endogsim.identify.levenberg_marquardt`).

One gradient iteration: simulate from the frame-0 state with the current materials (differentiable MLS-MPM,
``config.grad_mode``), render every frame and its Gaussian flow, evaluate the loss against the observed
video and its estimated flow, back-propagate, clip the gradient, take an optimiser step, and project back into
the search box. One Levenberg-Marquardt iteration: the residuals' Jacobian by forward differences (one forward
simulation per parameter, side by side), then damped Gauss-Newton steps until one lowers the loss. Rigid
objects are never parameters (frozen by construction).

Search box: E in [E_min, min(E_max, margin * E_cfl(nu))] where E_cfl(nu) is the stiffest material the
identification discretisation simulates within ``max_substeps`` per frame (times ``refine``:
``IdentifyConfig.substep_limit``, so the box is the same at every refinement; :func:`endogsim.physics.max_stable_E`;
the substeps of every rollout follow the CFL rule); nu in the sigmoid's (lo, hi). An initial material
given explicitly beyond that bound is refused with a message giving it.

After the intervals, the parameters whose value the video gave are corrected to a refined discretisation by
forward simulations there (``IdentifyConfig.refined_correction``; :mod:`endogsim.identify.refined_correction`).

Robustness: the iterate with the lowest loss is kept (not the last); the run stops early when the loss has
not improved by a relative ``tol`` for ``patience`` iterations, or when for ``stationary_patience``
iterations in a row its gradient could not change it by ``tol`` even over a whole unit step (a stationary,
flat loss: :func:`stationary`), or (Levenberg-Marquardt) when the loss changes by less than ``tol`` as its
Gauss-Newton model predicts, or no damped step lowers it (:mod:`endogsim.identify.levenberg_marquardt`); a
checkpoint is written atomically after every iteration and a run resumes from it (same settings) after an
interruption, reaching the same result.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import torch

from endogsim.determinism import deterministic
from endogsim.errors import DataError, EndoGSimError, IdentificationError, MaterialError, SimulationError
from endogsim.gaussians.camera import Camera
from endogsim.identify.config import IdentifyConfig
from endogsim.identify.levenberg_marquardt import FD_STEPS, Evaluation, LevenbergMarquardt
from endogsim.identify.loss import (
    LossValue,
    Observations,
    identification_loss,
    loss_residuals,
    make_observations,
    observed_flow,
)
from endogsim.identify.refined_correction import Correction, correct_to_refined, shifted_interval
from endogsim.identify.uncertainty import ParameterInterval, parameter_intervals, prior_checked
from endogsim.io.atomic import save_torch_atomic
from endogsim.materials.field import MaterialField, MaterialParams, MaterialRecord, nu_to_raw
from endogsim.physics import SimResult, max_stable_E
from endogsim.registry import Registry
from endogsim.scene.folder import SimScene, rediscretised
from endogsim.scene.forward import (
    Rendered,
    Simulations,
    in_view,
    render_sequence,
    same_materials,
    simulate_materials,
)
from endogsim.warp_runtime import run_independent

__all__ = ["IdentifyResult", "identify", "stable_log10_E_max", "check_stable", "CHECKPOINT_NAME"]

CHECKPOINT_NAME = "checkpoint.pt"
_CKPT_VERSION = 3  # 3: substeps planned once, at the initial materials (planned_for)


class SharedScaleAdam(torch.optim.Optimizer):
    """Adam whose second moment is shared by the entries of each parameter tensor (it tracks max g^2).

    Per-entry Adam steps every object by about ``lr`` whatever its gradient, so an object that barely moves
    in the video (gradient 5x smaller than its neighbour's, mostly noise) wanders as far as a well-observed
    one. With one scale per tensor (log10 E of all objects; raw nu of all objects) the best-observed object
    steps by about ``lr`` and the others in proportion to their gradients. With one object this is Adam.
    """

    def __init__(self, params, lr: float, betas: tuple[float, float] = (0.9, 0.99), eps: float = 1e-8):
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps})

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                st = self.state[p]
                if not st:
                    st["step"] = torch.zeros(())
                    st["m"] = torch.zeros_like(p)
                    st["v"] = torch.zeros((), dtype=p.dtype)
                st["step"] += 1
                n = float(st["step"])
                st["m"].mul_(b1).add_(p.grad, alpha=1 - b1)
                st["v"].mul_(b2).add_(p.grad.square().max(), alpha=1 - b2)
                m_hat = st["m"] / (1 - b1 ** n)
                v_hat = st["v"] / (1 - b2 ** n)
                p.add_(m_hat / (v_hat.sqrt() + group["eps"]), alpha=-group["lr"])


class SharedScaleRprop(torch.optim.Optimizer):
    """Rprop (Riedmiller & Braun 1993) with one step size per parameter tensor, shared like
    :class:`SharedScaleAdam`'s scale.

    Identification's loss is deterministic and full-batch (one clip), Rprop's home ground. Adam steps by at
    most about ``lr`` whatever the loss does, so 10 iterations from a schedule decaying from 0.1 to 0.02
    decades travel at most about 0.5 decades of E, and a prior a factor 4.5 off (the suite's ``stomach``: 10
    kPa for 2.2 kPa, whose loss at identification's discretisation is least at the truth) is never reached.
    Here each tensor's step grows by ``etas[1]`` while its gradient keeps its direction (the dot product with
    the previous one is positive) and shrinks by ``etas[0]`` when it turns, within ``step_sizes``; the step
    is ``size * g / max|g|``: the best-observed object steps by the size, the others in proportion to their
    gradients. The first step is ``lr`` (the group's ``lr`` at that step; later changes of it are ignored).
    """

    def __init__(self, params, lr: float, etas: tuple[float, float] = (0.5, 1.2),
                 step_sizes: tuple[float, float] = (0.01, 5.0), eps: float = 1e-12):
        """``step_sizes`` are (least, largest) relative to each group's first ``lr``."""
        super().__init__(params, {"lr": lr, "etas": etas, "step_sizes": step_sizes, "eps": eps})

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            shrink, grow = group["etas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                g = p.grad
                st = self.state[p]
                if not st:
                    st["first"] = torch.tensor(float(group["lr"]))
                    st["size"] = st["first"].clone()
                else:
                    turn = float((g * st["previous"]).sum())
                    factor = grow if turn > 0 else shrink if turn < 0 else 1.0
                    lo, hi = (f * float(st["first"]) for f in group["step_sizes"])
                    st["size"] = torch.tensor(min(max(float(st["size"]) * factor, lo), hi))
                st["previous"] = g.clone()
                p.add_(g / (g.abs().max() + group["eps"]), alpha=-float(st["size"]))


#: Identification's gradient optimisers (``IdentifyConfig.optimizer``): groups [{"params": [...], "lr_scale"}], lr ->
#: a torch optimiser whose groups' "lr" the loop sets every iteration (its schedule). "lm" is not one of them: it
#: needs the residuals and several simulations an iteration (:class:`LevenbergMarquardt`).
OPTIMIZERS: Registry[Callable[..., torch.optim.Optimizer]] = Registry("optimiser", MaterialError)
OPTIMIZERS.register("adam", lambda groups, lr: SharedScaleAdam(groups, lr=lr, betas=(0.9, 0.99)))
OPTIMIZERS.register("rprop", lambda groups, lr: SharedScaleRprop(groups, lr=lr))


@dataclass
class IdentifyResult:
    """Outcome of :func:`identify`.

    Attributes:
        field: identified material field (physical units; deformable objects' source = "identified").
        init_field: the field it started from.
        history: one dict per iteration: iteration, loss, render, flow, lr, grad_norm, E {id: Pa}, nu {id: -}.
        best_iteration: index into ``history`` of the kept iterate (-1 when no iteration ran).
        best_loss: its loss.
        iterations: iterations run in total (over resumes).
        seconds: optimisation wall time in total (over resumes).
        stopped: "converged" (early stop), "iters" (iterations spent), "time_budget" (``config.time_budget``
            seconds spent), "interrupted" (``stop_after``) or "no_iterations".
        intervals: the 90% interval and identifiability of every identified parameter
            (:mod:`endogsim.identify.uncertainty`); a parameter the video does not determine keeps its
            initial value in ``field``.
        evaluation: ``evaluate(field)`` when :func:`identify` was given ``evaluate`` and computed it while the
            intervals' last trials ran, else None.
        simulations: the iterations' simulations of the initial and the best iterate's materials (this
            process's iterations only): a field with the same materials is evaluated without simulating it again.
        correction: the refined correction's record (:mod:`endogsim.identify.refined_correction`; None: none
            was made: ``config.refined_correction`` None, or no parameter the video determines).
        refined: the refined scene ``field`` belongs to after a correction that moved it (None: the
            identification's own discretisation); ``refined_simulations`` holds its simulation there.
        stage_seconds: wall time (s) of this call's stages after the iterations: "intervals" (the evaluation
            of the identified field included where it ran beside their trials) and "refined_correction".
        scene: the scene as identification simulated it, its substeps planned at the initial materials
            (:func:`planned_for`): ``simulations`` are its, and fields are evaluated on it to be seen as
            identification saw them.
    """

    field: MaterialField
    init_field: MaterialField
    history: list[dict] = field(default_factory=list)
    best_iteration: int = -1
    best_loss: float = math.nan
    iterations: int = 0
    seconds: float = 0.0
    stopped: str = "iters"
    notes: list[str] = field(default_factory=list)
    intervals: list[ParameterInterval] = field(default_factory=list)
    evaluation: object | None = None
    simulations: Simulations = field(default_factory=Simulations)
    correction: Correction | None = None
    refined: SimScene | None = None
    refined_simulations: Simulations = field(default_factory=Simulations)
    stage_seconds: dict[str, float] = field(default_factory=dict)
    scene: SimScene | None = None


def stable_log10_E_max(problem: SimScene, nu: torch.Tensor, density: torch.Tensor, config: IdentifyConfig) -> torch.Tensor:
    """Upper end of the search box for log10 E per parameter slot: ``E_max``, and the stiffest material the
    simulation takes within ``substep_limit`` per frame at ``nu`` (the CFL rule; ``stability_margin`` of it).
    ``density`` is the material's; the CFL rule sees it times the scenario's mass scaling, as the simulator does."""
    out = []
    k = problem.scenario.mass_scaling
    for n, rho in zip(nu.detach().double().tolist(), density.detach().double().tolist()):
        e = config.stability_margin * max_stable_E(n, k * rho, problem.mpm, problem.scenario.box.size,
                                                    substeps=config.substep_limit)
        out.append(math.log10(min(e, config.E_max)))
    return torch.tensor(out, dtype=torch.float64)


def check_stable(problem: SimScene, fld: MaterialField, config: IdentifyConfig) -> None:
    """Refuse materials the identification discretisation cannot simulate stably (clear message).

    Used for materials a user asked for explicitly (a materials file); guesses of an initialiser (prior,
    MLLM) are instead clamped into the search box by :func:`identify` (``strict=False``).
    """
    mpm = problem.mpm
    for r in fld.deformable:
        if r.object_id not in problem.deformable_ids:
            continue
        emax = max_stable_E(r.nu, problem.scenario.mass_scaling * r.density, mpm, problem.scenario.box.size,
                            substeps=config.substep_limit)
        if r.E > emax:
            raise SimulationError(
                f"object {r.object_id} ({r.name!r}): E = {r.E:.4g} Pa (nu {r.nu:.3f}) needs more than "
                f"{config.substep_limit} substeps per frame at the identification discretisation (grid "
                f"{mpm.grid_res}, frames {mpm.frame_dt:.4g} s apart, CFL {mpm.cfl_number}): at most "
                f"E = {emax:.4g} Pa; start from a softer material or raise max_substeps")


def _slot_density(problem: SimScene, fld: MaterialField, params: MaterialParams) -> torch.Tensor:
    """Density per parameter slot (the largest of the tied objects under a global material: the stiffer bound)."""
    n = params.log10_E.shape[0]
    rho = [0.0] * n
    for oid in params.object_ids:
        s = params.slot(oid)
        rho[s] = max(rho[s], fld[oid].density)
    return torch.tensor(rho, dtype=torch.float64)


def log10_E_box(problem: SimScene, fld: MaterialField, params: MaterialParams,
                config: IdentifyConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """The search box for log10 E per parameter slot at ``params``' nu: ([M] log10 E_min, [M] log10 E_max(nu))."""
    hi = stable_log10_E_max(problem, params.nu(), _slot_density(problem, fld, params), config)
    return torch.full_like(hi, math.log10(config.E_min)), hi


def project_into_search_box(params: MaterialParams, problem: SimScene, fld: MaterialField, config: IdentifyConfig) -> None:
    """Clamp log10 E into [log10 E_min, log10 E_max(nu)] in place (keeps the simulation stable)."""
    with torch.no_grad():
        lo, hi = log10_E_box(problem, fld, params, config)
        params.log10_E.copy_(torch.maximum(torch.minimum(params.log10_E, hi), lo))


def planned_for(problem: SimScene, init_field: MaterialField, config: IdentifyConfig) -> SimScene:
    """``problem`` with its substeps planned once, at the materials identification starts from (``init_field``
    moved into the search box, as :func:`identify` starts): see :meth:`SimScene.planned_at`. Every
    discretisation identification simulates (its own, the coarser one of the intervals, the refined one of the
    correction) is planned this way, each at its own CFL count for the same starting materials."""
    start = init_field.to_params(global_material=config.global_material, nu_bounds=config.nu_bounds)
    project_into_search_box(start, problem, init_field, config)
    return problem.planned_at(init_field.simulator_materials(start))


def _values(params: MaterialParams) -> tuple[dict[str, float], dict[str, float]]:
    E = params.E().detach().tolist()
    nu = params.nu().detach().tolist()
    return ({str(o): E[params.slot(o)] for o in params.object_ids}, {str(o): nu[params.slot(o)] for o in params.object_ids})


def _signature(problem: SimScene, init: MaterialField, config: IdentifyConfig, run_dir: Path | None) -> dict:
    """What a checkpoint must match to be resumed. The scene is named relative to the run folder, so that
    a run folder moved with its scene (``endogsim run``'s RUN/scene and RUN/identify) still resumes."""
    cfg = config.to_json()
    cfg.pop("iters", None)  # a resumed run may be given a larger budget
    cfg.pop("time_budget", None)
    cfg.pop("device", None)
    for after in ("coarse_factor", "refined_correction", "correction_steps"):  # used after the optimisation,
        cfg.pop(after, None)  # which they do not change
    return {"scene": _scene_name(problem.folder, run_dir), "frames": problem.num_frames, "config": cfg,
            "init": init.to_json()["objects"]}


def _scene_name(scene: str | Path, run_dir: Path | None) -> str:
    """The scene folder relative to the run folder (absolute without one)."""
    scene = Path(scene).resolve()
    return str(scene) if run_dir is None else os.path.relpath(scene, Path(run_dir).resolve())


def _stored_signature(old: dict | None, run_dir: Path) -> dict:
    """A checkpoint's signature as this version writes it: earlier versions named the scene absolutely."""
    if not isinstance(old, dict):
        return {}
    if Path(str(old.get("scene", ""))).is_absolute():
        old = {**old, "scene": _scene_name(old["scene"], run_dir)}
    if isinstance(old.get("config"), dict) and "refine" not in old["config"]:  # before refine: the default's
        old = {**old, "config": {**old["config"], "refine": 1.0}}
    return old


def _signature_change(old: dict, new: dict) -> str:
    """What differs between two checkpoint signatures, named for the user (a moved scene folder is one)."""
    keys = [k for k in new if k != "config" and old.get(k) != new[k]]
    keys += [f"option {k}" for k in sorted(set(old.get("config", {})) | set(new["config"]))
             if old.get("config", {}).get(k) != new["config"].get(k)]
    if old.get("scene") != new["scene"]:
        keys[keys.index("scene")] = f"scene folder {old.get('scene')} -> {new['scene']}"
    return ", ".join(keys) or "unknown"


def prepare_observations(problem: SimScene, config: IdentifyConfig, run_dir: Path | None) -> tuple[Observations, object]:
    """Observed flow (cached in ``run_dir``) and the observations at the rendering scale, plus the camera."""
    cache = None if run_dir is None else Path(run_dir) / "observed_flow.npz"
    cam = problem.camera if config.render_scale == 1 else problem.camera.scaled(config.render_scale)
    if min(cam.width, cam.height) < 8:
        raise DataError(f"render_scale {config.render_scale:g} renders {problem.folder}'s "
                        f"{problem.camera.width}x{problem.camera.height} frames at {cam.width}x{cam.height} px; "
                        "comparing motion needs at least 8 px a side")
    U = observed_flow(problem.frames, config.flow, cache)
    tracks = None
    if problem.tracks is not None:  # the reconstruction's trajectories as camera t saw them
        view = Camera(cam.K, cam.width, cam.height) if problem.viewmats is not None else cam
        pos = problem.tracks.positions
        tracks = torch.stack([view.project(in_view(problem, pos[t], None, t)[0])
                              for t in range(problem.num_frames)])
    obs = make_observations(problem.frames, U, problem.object_masks, problem.deformable_ids, (cam.width, cam.height),
                            tracks)
    return obs, cam


def simulate_and_render(problem: SimScene, fld: MaterialField, params: MaterialParams | None, camera,
                        config: IdentifyConfig) -> tuple[Rendered, SimResult]:
    """Simulate the field (with ``params`` for the deformable objects) and render the compared frames."""
    sim = simulate_materials(problem, fld.simulator_materials(params), config.grad_mode)
    frames = range(0, problem.num_frames, config.stride(problem.num_frames))
    return render_sequence(problem, sim.positions, sim.F, camera, frames=frames), sim


def evaluate_loss(problem: SimScene, fld: MaterialField, params: MaterialParams | None, obs: Observations,
                  camera, config: IdentifyConfig, grad: bool) -> tuple[LossValue, SimResult]:
    """Simulate, render and compute the loss for the field (with ``params`` for the deformable objects); also
    the simulation (its positions and F carry the gradients when ``grad``)."""
    with torch.set_grad_enabled(grad):
        rendered, sim = simulate_and_render(problem, fld, params, camera, config)
        return identification_loss(rendered, obs, config.term_weights()), sim


def evaluate_residuals(problem: SimScene, fld: MaterialField, params: MaterialParams, obs: Observations, camera,
                       config: IdentifyConfig) -> Evaluation:
    """:func:`evaluate_loss` without gradients, with the loss's residuals (for Levenberg-Marquardt)."""
    with torch.no_grad():
        rendered, sim = simulate_and_render(problem, fld, params, camera, config)
        weights = config.term_weights()
        return Evaluation(identification_loss(rendered, obs, weights), loss_residuals(rendered, obs, weights), sim)


class _ParameterVector:
    """The Levenberg-Marquardt view of a field's parameters: theta = (log10 E of each slot, then nu of each slot
    when nu is optimised) as a numpy vector, the search box on it, and the :class:`MaterialParams` at a theta."""

    def __init__(self, problem: SimScene, init_field: MaterialField, config: IdentifyConfig):
        self.problem, self.init, self.config = problem, init_field, config
        self.M = len(init_field.to_params(config.global_material, config.nu_bounds).log10_E)

    def theta(self, params: MaterialParams) -> np.ndarray:
        """[p] theta of ``params``: log10 E (decades of Pa) of each slot, then nu of each slot."""
        E = params.log10_E.detach().double().numpy()
        return np.concatenate([E, params.nu().detach().double().numpy()]) if self.config.optimize_nu else E.copy()

    def params(self, theta: np.ndarray) -> MaterialParams:
        """Fresh :class:`MaterialParams` at ``theta`` [p] (nu through the sigmoid's inverse, clamped just inside
        its bounds); every simulation of a theta is made from these, so the same theta simulates the same."""
        cfg = self.config
        p = self.init.to_params(global_material=cfg.global_material, nu_bounds=cfg.nu_bounds)
        with torch.no_grad():
            p.log10_E.copy_(torch.as_tensor(theta[: self.M], dtype=torch.float64))
            if cfg.optimize_nu:
                p.nu_raw.copy_(torch.tensor([nu_to_raw(float(v), *cfg.nu_bounds) for v in theta[self.M:]],
                                            dtype=torch.float64))
        return p

    def box(self, theta: np.ndarray) -> np.ndarray:
        """theta projected into the search box: nu into its bounds, then log10 E into [E_min, the stability limit at
        that nu] (:func:`project_into_search_box`)."""
        cfg, out = self.config, np.array(theta, dtype=float)
        if cfg.optimize_nu:
            out[self.M:] = np.clip(out[self.M:], *cfg.nu_bounds)
        lo, hi = log10_E_box(self.problem, self.init, self.params(out), cfg)
        out[: self.M] = np.clip(out[: self.M], lo.numpy(), hi.numpy())
        return out

    def steps(self) -> np.ndarray:
        """[p] forward-difference steps: :data:`FD_STEPS` decades for each log10 E, then its nu step."""
        return np.array([FD_STEPS[0]] * self.M + ([FD_STEPS[1]] * self.M if self.config.optimize_nu else []))

    def raw_gradient(self, grad: np.ndarray, params: MaterialParams) -> tuple[torch.Tensor, torch.Tensor | None]:
        """A gradient over theta as the leaves' gradients: per decade of E, per raw unit of nu."""
        g_E = torch.as_tensor(grad[: self.M], dtype=torch.float64)
        if not self.config.optimize_nu:
            return g_E, None
        lo, hi = self.config.nu_bounds
        s = torch.sigmoid(params.nu_raw.detach())
        return g_E, torch.as_tensor(grad[self.M:], dtype=torch.float64) * (hi - lo) * s * (1 - s)


def side_by_side(problem: SimScene, init_field: MaterialField, vector: _ParameterVector, obs: Observations, camera,
                 config: IdentifyConfig) -> Callable[[list[np.ndarray]], list[Evaluation]]:
    """thetas -> their :class:`Evaluation` on ``problem``, simulated side by side (the first one alone: Warp builds
    its kernels on a scene's first simulation)."""
    both = coarse_and_refined(problem, problem, init_field, vector, obs, camera, config)
    return lambda thetas: both(thetas, [])[0]


def coarse_and_refined(problem: SimScene, refined: SimScene, init_field: MaterialField, vector: _ParameterVector,
                       obs: Observations, camera, config: IdentifyConfig, warmed: bool = False,
                       ) -> Callable[[list[np.ndarray], list[np.ndarray]], tuple[list[Evaluation], list[Evaluation]]]:
    """(thetas, refined thetas) -> their :class:`Evaluation` on ``problem`` and on ``refined`` (the same scene at
    another discretisation), all simulated side by side, the refined ones first (the longest start first; the
    first simulation of ``problem`` alone unless ``warmed``, ``problem`` simulated in this process already:
    Warp builds its kernels on a scene's first simulation)."""
    def evaluate(thetas: list[np.ndarray], refined_thetas: list[np.ndarray],
                 ) -> tuple[list[Evaluation], list[Evaluation]]:
        nonlocal warmed
        tasks = [partial(evaluate_residuals, refined, init_field, vector.params(t), obs, camera, config)
                 for t in refined_thetas]
        tasks += [partial(evaluate_residuals, problem, init_field, vector.params(t), obs, camera, config)
                  for t in thetas]
        first = [] if warmed or not thetas else [tasks.pop(len(refined_thetas))()]
        warmed = True
        done = run_independent(tasks, min(problem.independent_simulations(), refined.independent_simulations()))
        n = len(refined_thetas)
        return first + done[n:], done[:n]

    return evaluate


def stationary(leaves: list[torch.Tensor], loss: float, tol: float) -> bool:
    """True when no parameter's gradient (``leaves``' .grad, per decade of E or raw unit of nu) could change
    the loss by a relative ``tol`` over a unit step: the loss is flat where the optimiser stands."""
    largest = max(float(leaf.grad.abs().max()) for leaf in leaves if leaf.grad is not None and leaf.grad.numel())
    return largest < tol * abs(loss)


@deterministic()
def identify(
    problem: SimScene,
    init_field: MaterialField,
    config: IdentifyConfig | None = None,
    run_dir: str | Path | None = None,
    resume: bool = True,
    progress: Callable[[int, int, dict], None] | None = None,
    stop_after: int | None = None,
    strict: bool = False,
    evaluate: Callable[[MaterialField, Simulations], object] | None = None,
    on_trial: Callable[[dict], None] | None = None,
) -> IdentifyResult:
    """Identify E and nu of the deformable objects of ``problem`` from its observed video.

    Args:
        problem: the scene (see :func:`endogsim.identify.load_sim_scene`). Identification simulates it with
            its substeps planned once at the initial materials (:func:`planned_for`; the result's ``scene``).
        init_field: starting materials (every object id of the scene needs a record); rigid objects stay as given.
        config: options (default :class:`IdentifyConfig`).
        run_dir: folder for the flow cache and the checkpoint (None: nothing written, no resume).
        resume: continue from ``run_dir/checkpoint.pt`` when it was made with the same settings.
        progress: callback(iteration done, iters, info) after every iteration.
        stop_after: stop (as if interrupted) after this many iterations in this call; for tests.
        strict: refuse initial materials beyond the stability limit (explicit user request) instead of
            starting from the nearest stable value (an initialiser's guess).
        evaluate: (field, :attr:`IdentifyResult.simulations`) -> the field's evaluation (e.g.
            :func:`endogsim.identify.report.evaluate_field`). When the intervals' trials run side by side, the
            field their slices imply is evaluated while the coarse walks run, and kept as
            ``IdentifyResult.evaluation`` if it is the identified field (the coarse walks change it only where
            their error makes a parameter not identifiable).
        on_trial: callback(trial) after every simulation of the intervals (see
            :func:`~endogsim.identify.uncertainty.parameter_intervals`), from the thread that ran it.
    Returns:
        :class:`IdentifyResult` with the best iterate's materials.
    Raises:
        SimulationError when the initial materials are beyond the stability limit.
    """
    cfg = config or IdentifyConfig()
    torch.manual_seed(cfg.seed)
    missing = [o for o in problem.labels if o not in {r.object_id for r in init_field.records}]
    if missing:
        raise DataError(f"the initial material field has no record for object(s) {missing} of {problem.folder}")
    if strict:
        check_stable(problem, init_field, cfg)
    problem = planned_for(problem, init_field, cfg)  # a caller's run_identify planned it already
    run_dir = None if run_dir is None else Path(run_dir)
    if run_dir is not None:
        run_dir.mkdir(parents=True, exist_ok=True)
    obs, cam = prepare_observations(problem, cfg, run_dir)

    params = init_field.to_params(global_material=cfg.global_material, nu_bounds=cfg.nu_bounds)
    keep_ids = [o for o in params.object_ids if o in problem.deformable_ids]
    if not keep_ids:
        raise DataError(f"{problem.folder}: no deformable object of the scene has a non-rigid initial material")
    before = params.E().detach().clone()
    project_into_search_box(params, problem, init_field, cfg)
    notes = []
    after = params.E().detach()
    for oid in params.object_ids:
        s = params.slot(oid)
        if abs(float(after[s]) - float(before[s])) > 1e-6 * float(before[s]):
            notes.append(f"object {oid}: initial E {float(before[s]):.4g} Pa is outside the search box "
                         f"[E_min, stability limit]; started from {float(after[s]):.4g} Pa")
    leaves = [params.log10_E] + ([params.nu_raw] if cfg.optimize_nu else [])
    groups = [{"params": [params.log10_E], "lr_scale": 1.0}]
    if cfg.optimize_nu:
        groups.append({"params": [params.nu_raw], "lr_scale": cfg.lr_nu / cfg.lr})
    vector = _ParameterVector(problem, init_field, cfg)
    lm = None
    if cfg.optimizer == "lm":
        opt = lm = LevenbergMarquardt(side_by_side(problem, init_field, vector, obs, cam, cfg), vector.box,
                                      vector.steps(), cfg.tol, cfg.lm_damping)
    else:
        opt = OPTIMIZERS.get(cfg.optimizer)(groups, cfg.lr)
    cfg.stride(problem.num_frames)  # a stride that leaves one frame to compare is refused before any work
    sig = _signature(problem, init_field, cfg, None if run_dir is None else Path(run_dir))

    start, history, best, seconds, stale, flat_run = 0, [], None, 0.0, 0, 0
    ckpt_path = None if run_dir is None else run_dir / CHECKPOINT_NAME
    ck = None  # the checkpoint as last written or read
    trials: dict = {}  # the intervals' trial simulations done so far (remembered_trials)
    if ckpt_path is not None and ckpt_path.is_file() and resume:
        ck = torch.load(ckpt_path, weights_only=False)
        stored = _stored_signature(ck.get("signature"), ckpt_path.parent)
        if ck.get("version") != _CKPT_VERSION or stored != sig:
            what = _signature_change(stored, sig) if ck.get("version") == _CKPT_VERSION else "an older version"
            raise DataError(f"{ckpt_path} was written by a run with other settings ({what}); use --fresh to start "
                            "over or choose another --out")
        with torch.no_grad():
            params.log10_E.copy_(ck["log10_E"])
            params.nu_raw.copy_(ck["nu_raw"])
        opt.load_state_dict(ck["optimizer"])
        start, history, best, seconds, stale = ck["iteration"], ck["history"], ck["best"], ck["seconds"], ck["stale"]
        flat_run = ck.get("flat_run", 0)
        trials = ck.setdefault("trials", {})

    stopped = "iters" if cfg.iters > 0 else "no_iterations"
    if history and history[-1].get("converged"):
        stopped, start = "converged", max(start, cfg.iters)
    done_here, simulations = 0, Simulations()
    for k in range(start, cfg.iters):
        if stop_after is not None and done_here >= stop_after:
            stopped = "interrupted"
            break
        if cfg.time_budget is not None and seconds >= cfg.time_budget:
            stopped = "time_budget"
            break
        t0 = time.perf_counter()
        lr = cfg.lr * cfg.lr_final_fraction ** (k / max(cfg.iters - 1, 1))
        if lm is None:
            for gr in opt.param_groups:
                gr["lr"] = lr * gr["lr_scale"]
            opt.zero_grad(set_to_none=True)
            value, sim = evaluate_loss(problem, init_field, params, obs, cam, cfg, grad=True)
            value.total.backward()
        else:  # the point the last step reached (its evaluation is kept), or where the run starts or resumes
            here, grad = lm.linearise(lm.theta if lm.theta is not None else vector.theta(params))
            value, sim = here.value, here.sim
            params = vector.params(lm.theta)
            params.log10_E.grad, params.nu_raw.grad = vector.raw_gradient(grad, params)
            leaves = [params.log10_E] + ([params.nu_raw] if cfg.optimize_nu else [])
        if k == 0:
            simulations.keep("initial", init_field.simulator_materials(params), sim)
        parts = value.parts
        for leaf, what in zip(leaves, ("log10 E", "raw nu")):
            if leaf.grad is None:
                leaf.grad = torch.zeros_like(leaf)
            bad = [o for o in params.object_ids if not bool(torch.isfinite(leaf.grad[params.slot(o)]))]
            if bad:
                raise IdentificationError(f"iteration {k}: the gradient of the loss with respect to {what} of "
                                          f"object(s) {bad} is NaN/inf although every loss term was finite: "
                                          "the backward pass through the renderer produced it")
        flat = stationary(leaves, parts["total"], cfg.tol)
        if lm is None:
            gnorm = float(torch.nn.utils.clip_grad_norm_(leaves, cfg.max_grad_norm))
        else:  # Levenberg-Marquardt steps by its model, not by the gradient: nothing to clip
            gnorm = float(torch.cat([leaf.grad.flatten() for leaf in leaves]).norm())
        E, nu = _values(params)
        rec = {"iteration": k, "loss": parts["total"], "terms": {n: v for n, v in parts.items() if n != "total"}, "lr": lr,
               "grad_norm": gnorm, "grad_log10_E": params.log10_E.grad.tolist(),
               "grad_nu_raw": (params.nu_raw.grad.tolist() if params.nu_raw.grad is not None else None),
               "E": E, "nu": nu}
        if lm is not None:
            rec["damping"], rec["predicted_gain"] = lm.lam, lm.predicted_gain
        if best is None or parts["total"] < best["loss"]:
            improved = best is None or parts["total"] < best["loss"] * (1 - cfg.tol)
            best = {"loss": parts["total"], "iteration": k, "log10_E": params.log10_E.detach().clone(),
                    "nu_raw": params.nu_raw.detach().clone(), "per_frame": dict(value.per_frame)}
            simulations.keep("best", init_field.simulator_materials(params), sim)
            stale = 0 if improved else stale + 1
        else:
            stale += 1
        flat_run = flat_run + 1 if flat else 0
        flat_stop = cfg.stationary_patience > 0 and flat_run >= cfg.stationary_patience
        if lm is None:
            opt.step()
            project_into_search_box(params, problem, init_field, cfg)
        elif not lm.stopped and not flat_stop:
            params = vector.params(lm.step())  # the damped steps' simulations: this iteration's time
            rec["tries"] = lm.tries
        seconds += time.perf_counter() - t0
        rec["seconds"] = seconds
        rec["stationary"] = flat
        rec["converged"] = stale >= cfg.patience or flat_stop or bool(lm is not None and lm.stopped)
        if lm is not None and lm.stopped:
            rec["lm_stopped"] = lm.stopped
        history.append(rec)
        done_here += 1
        if ckpt_path is not None:
            ck = {"version": _CKPT_VERSION, "signature": sig, "iteration": k + 1,
                  "log10_E": params.log10_E.detach().clone(), "nu_raw": params.nu_raw.detach().clone(),
                  "optimizer": opt.state_dict(), "history": history, "best": best,
                  "seconds": seconds, "stale": stale, "flat_run": flat_run, "trials": trials}
            save_torch_atomic(ck, ckpt_path)
        if progress is not None:
            progress(k + 1, cfg.iters, rec)
        if rec["converged"]:
            stopped = "converged"
            break
    if stopped == "converged" and history[-1].get("stationary"):  # also when a resumed run finds it stopped
        run = "" if cfg.stationary_patience == 1 else f" for {cfg.stationary_patience} iterations in a row"
        notes.append(f"stopped at iteration {history[-1]['iteration']}:{run} no parameter's gradient could change "
                     f"the loss by {cfg.tol:g} of itself over a unit step (a flat, stationary loss)")
    elif stopped == "converged" and history[-1].get("lm_stopped") == "converged":
        notes.append(f"stopped at iteration {history[-1]['iteration']}: the loss changes by less than {cfg.tol:g} of "
                     "itself (the last step gained less, as its Gauss-Newton model predicted; or the model predicts "
                     "less from any step in the search box)")
    elif stopped == "converged" and history[-1].get("lm_stopped") == "no descent":
        notes.append(f"stopped at iteration {history[-1]['iteration']}: no damped Gauss-Newton step lowered the loss")
    elif stopped == "time_budget":  # a safety stop: what the run kept follows this machine's speed
        notes.append(f"stopped by the time budget (a safety stop) after {len(history)} iterations ({seconds:.0f} s), "
                     "before converging: the estimate, and which parameters keep their prior as not identifiable, "
                     "are an unfinished run's and depend on this machine's speed (a longer budget, or none, lets it "
                     "finish)")

    intervals: list[ParameterInterval] = []
    evaluated: dict = {}  # {"field", "evaluation"}: the field the slices imply, evaluated during the intervals
    stage_seconds, t_stage = {}, time.perf_counter()
    if best is None:  # optimisation off: the initial materials are the answer
        ident = MaterialField([r.model_copy() for r in init_field.records], meta=dict(init_field.meta))
    else:
        final = init_field.to_params(global_material=cfg.global_material, nu_bounds=cfg.nu_bounds)
        with torch.no_grad():
            final.log10_E.copy_(best["log10_E"])
            final.nu_raw.copy_(best["nu_raw"])
        if cfg.intervals:
            def losses(pb: SimScene) -> Callable[[MaterialParams], dict[int, float]]:
                """Trial parameters -> the per-frame loss of ``pb`` (the scene, or its coarser discretisation)."""
                return lambda trial: evaluate_loss(pb, init_field, trial, obs, cam, cfg, grad=False)[0].per_frame

            remember = partial(remembered_trials, trials=trials, lock=threading.Lock(),
                               save=None if ck is None else partial(save_torch_atomic, ck, ckpt_path))
            coarse, coarse_evaluate = None, None
            if cfg.coarse_factor is not None:
                try:
                    coarse = planned_for(rediscretised(problem, cfg.coarse_factor), init_field, cfg)
                except EndoGSimError as e:  # e.g. a tissue thinner than a coarse particle: intervals without it
                    notes.append(f"the discretisation error was not measured: the scene at {cfg.coarse_factor:g}x "
                                 f"its grid could not be built ({e})")
                else:
                    coarse_evaluate = remember(losses(coarse), ("coarse", cfg.coarse_factor, cfg.device))
            workers = problem.independent_simulations()

            def evaluate_implied(slices: list[ParameterInterval]) -> None:
                fld = identified_field(init_field, final, slices)
                evaluated.update(field=fld, evaluation=evaluate(fld, simulations))

            fine = losses(problem)
            # The optimum's loss from its iteration when this process ran one (its kernels are then built: the
            # trials may start side by side); a run resumed with nothing left to iterate, or from an older
            # checkpoint, simulates it first, alone (never from the remembered trials, for the same reason).
            reference = best.get("per_frame") if done_here else None
            if reference is None:
                reference = fine(final)
            intervals = parameter_intervals(
                final, {o: problem.labels[o].name for o in final.object_ids}, remember(fine, ("fine", cfg.device)),
                lambda trial: tuple(b.tolist() for b in log10_E_box(problem, init_field, trial, cfg)),
                cfg.optimize_nu, {"log10_E": history[0]["grad_log10_E"], "nu_raw": history[0]["grad_nu_raw"]},
                coarse_evaluate=coarse_evaluate,
                coarse_ratio=None if coarse is None else problem.mpm.grid_res / coarse.mpm.grid_res,
                workers=workers, reference=reference,
                then=evaluate_implied if evaluate is not None and workers > 1 else None, on_trial=on_trial,
                min_relative_rise=cfg.tol)
            if coarse_evaluate is not None:  # is a one-sided exclusion of the prior more than the discretisation's?
                one_sided = {}
                for iv in intervals:
                    prior = getattr(init_field[iv.object_id], iv.parameter)
                    if source_of(iv, prior) == ONE_SIDED:
                        one_sided[(iv.object_id, iv.parameter)] = prior
                intervals = prior_checked(intervals, final, one_sided, coarse_evaluate,
                                          problem.mpm.grid_res / coarse.mpm.grid_res, workers, on_trial)
        ident = identified_field(init_field, final, intervals)
        if cfg.intervals:
            stage_seconds["intervals"] = time.perf_counter() - t_stage
    correction, refined, refined_simulations = None, None, Simulations()
    if best is not None and cfg.refined_correction is not None:
        t_stage = time.perf_counter()
        ident, intervals, correction, refined, refined_simulations = corrected_to_refined(
            problem, init_field, vector, ident, intervals, obs, cam, cfg, notes, warmed=done_here > 0)
        stage_seconds["refined_correction"] = time.perf_counter() - t_stage
    evaluation = evaluated["evaluation"] if evaluated and same_simulation(evaluated["field"], ident) else None
    return IdentifyResult(field=ident, init_field=init_field, history=history,
                          best_iteration=-1 if best is None else int(best["iteration"]),
                          best_loss=math.nan if best is None else float(best["loss"]),
                          iterations=len(history), seconds=seconds, stopped=stopped, notes=notes, intervals=intervals,
                          evaluation=evaluation if refined is None else None, simulations=simulations,
                          correction=correction, refined=refined, refined_simulations=refined_simulations,
                          stage_seconds=stage_seconds, scene=problem)


def corrected_to_refined(problem: SimScene, init_field: MaterialField, vector: _ParameterVector,
                         ident: MaterialField, intervals: list[ParameterInterval], obs: Observations, camera,
                         config: IdentifyConfig, notes: list[str], warmed: bool = False,
                         ) -> tuple[MaterialField, list[ParameterInterval], Correction | None, SimScene | None,
                                    Simulations]:
    """The identified field corrected to the discretisation refined ``config.refined_correction`` times
    (:mod:`endogsim.identify.refined_correction`): the parameters whose value the video gave (identified, a
    one-sided estimate, or every parameter without intervals) move, their intervals with them, and their sources
    follow the moved intervals (:func:`identified_field`). ``warmed``: ``problem`` was simulated in this process
    already (its kernels are built: the correction's first simulations start side by side).

    Returns:
        (the field, the intervals, the correction's record (None: no parameter to move, or the refined scene
        could not be built: ``notes`` says why), the refined scene the field now belongs to (None: the field is
        ``ident``: no step was taken or none was tried), the refined simulation of the field)
    """
    here = ident.to_params(global_material=config.global_material, nu_bounds=config.nu_bounds)
    theta = vector.theta(here)
    kinds = ["E"] * vector.M + (["nu"] * vector.M if config.optimize_nu else [])
    slots = {here.slot(o): o for o in reversed(here.object_ids)}  # each slot's first object names it
    by = {(iv.object_id, iv.parameter): iv for iv in intervals}
    free = np.array([source_of(by.get((slots[k % vector.M], what)), getattr(init_field[slots[k % vector.M]], what))
                     != NOT_IDENTIFIABLE for k, what in enumerate(kinds)])
    if not free.any():
        return ident, intervals, None, None, Simulations()
    try:
        refined = planned_for(rediscretised(problem, config.refined_correction), init_field, config)
    except EndoGSimError as e:  # e.g. too many particles for this machine: the field stays as identified
        notes.append(f"no refined correction: the scene at {config.refined_correction:g}x its grid could not be "
                     f"built ({e})")
        return ident, intervals, None, None, Simulations()
    t0 = time.perf_counter()
    corrected, ev, loss, losses, stopped = correct_to_refined(
        theta, free, coarse_and_refined(problem, refined, init_field, vector, obs, camera, config, warmed), vector.box,
        vector.steps(), config.correction_steps, config.tol)
    record = Correction(factor=config.refined_correction,
                        parameters=[f"{problem.labels[slots[k % vector.M]].name} {what}"
                                    for k, what in enumerate(kinds) if free[k]],
                        before=theta[free].tolist(), after=corrected[free].tolist(), loss=loss, refined_loss=losses,
                        stopped=stopped, seconds=time.perf_counter() - t0)
    if len(losses) == 1:  # no step: the record says so wherever the correction is shown (no note repeats it)
        return ident, intervals, record, None, Simulations()
    moved = [shifted_interval(iv, float(corrected[k] - theta[k])) if free[k] else iv
             for iv in intervals for k in [here.slot(iv.object_id) + (vector.M if iv.parameter == "nu" else 0)]]
    params = vector.params(corrected)
    simulations = Simulations()
    simulations.keep("corrected", init_field.simulator_materials(params), ev.sim)
    return identified_field(init_field, params, moved), moved, record, refined, simulations


def remembered_trials(evaluate: Callable[[MaterialParams], dict[int, float]], tag: tuple, trials: dict,
                      lock: threading.Lock, save: Callable[[], object] | None = None,
                      ) -> Callable[[MaterialParams], dict[int, float]]:
    """``evaluate`` (trial parameters -> per-frame loss) with every result kept in ``trials`` under (``tag``,
    log10 E, raw nu) and, through ``save``, in the checkpoint once it is computed: a resumed run (an
    interrupted ``identify``, or ``validate`` run again in its folder) takes a trial from there instead of
    simulating it again, and gets the same numbers (a simulation is deterministic). ``tag`` names what else
    the result depends on (the discretisation, the device); ``lock`` guards ``trials`` and the saving, for
    trials run side by side."""
    def trial(params: MaterialParams) -> dict[int, float]:
        key = (*tag, tuple(params.log10_E.detach().tolist()), tuple(params.nu_raw.detach().tolist()))
        with lock:
            if key in trials:
                return dict(trials[key])
        per_frame = evaluate(params)
        with lock:
            trials[key] = dict(per_frame)
            if save is not None:
                save()
        return per_frame

    return trial


def same_simulation(a: MaterialField, b: MaterialField) -> bool:
    """Whether two fields give the simulator the same materials, to the last bit (every object's E, nu,
    density, constitutive model and yield stress): their simulations are then the same."""
    return same_materials(a.simulator_materials(), b.simulator_materials())


#: The source of a material the video could not determine: its initial value is kept.
NOT_IDENTIFIABLE = "prior (not identifiable from this video)"
#: A parameter bounded by the video on one side only, whose prior lies outside its statistical interval (the
#: reported one, widened by the discretisation's error, may hold the prior: the label says which excludes it).
ONE_SIDED = "estimate (bounded on one side by this video, whose noise alone excludes the prior)"


def source_of(iv: ParameterInterval | None, prior: float) -> str:
    """Where the identified field takes a parameter from, given its interval (None: none measured) and its
    initial value: "identified", :data:`ONE_SIDED` (both: the estimate) or :data:`NOT_IDENTIFIABLE` (the
    initial value; :func:`identified_field` says when)."""
    if iv is None or iv.identifiable:
        return "identified"
    if iv.prior_check is not None and not iv.prior_check["excluded"]:  # a coarser grid does not exclude it
        return NOT_IDENTIFIABLE
    lo, hi = iv.statistical_interval or iv.interval
    return NOT_IDENTIFIABLE if lo <= prior <= hi else ONE_SIDED


def identified_field(init: MaterialField, final: MaterialParams, intervals: list[ParameterInterval]) -> MaterialField:
    """The identified field: every deformable object's E and nu from ``final`` where the video determines
    them (``intervals``; all of them without intervals). A parameter it does not determine keeps its initial
    value while that value lies in the parameter's 90% interval (the video cannot tell the two apart),
    labelled :data:`NOT_IDENTIFIABLE`; when the interval excludes it (the loss rises significantly on one
    side, and the prior lies there), the estimate replaces it, labelled :data:`ONE_SIDED`. "The interval" here
    is the statistical one (the loss's frame-to-frame noise): whether this video moved the parameter away
    from its prior is a question about the data at this discretisation; the discretisation's own error,
    which widens the reported interval, does not make the prior a better estimate. Except where a coarser
    discretisation does not exclude the prior by the same test (``prior_check``,
    :func:`~endogsim.identify.uncertainty.prior_checked`): the exclusion then lies within the discretisation's
    error, and the prior stays, not identifiable."""
    by = {(iv.object_id, iv.parameter): iv for iv in intervals}
    recs = []
    for r in init.from_params(final).records:  # every estimate, then the priors kept
        if not r.rigid and r.object_id in final.object_ids:
            sid = next(o for o in final.object_ids if final.slot(o) == final.slot(r.object_id))
            prior = init[r.object_id]
            values, labels = {}, {}
            for name in ("E", "nu"):
                labels[name] = source_of(by.get((sid, name)), getattr(prior, name))
                values[name] = getattr(prior if labels[name] == NOT_IDENTIFIABLE else r, name)
            if labels["E"] == labels["nu"]:
                source = labels["E"]
            else:
                source = "; ".join(f"{k}: {v}" for k, v in labels.items())
                if "identified" in labels.values():
                    odd = next(k for k, v in labels.items() if v != "identified")
                    source = f"identified ({odd}: {labels[odd]})"
            r = MaterialRecord.model_validate(r.model_copy(update={**values, "source": source}).model_dump())
        recs.append(r)
    return MaterialField(recs, meta=dict(init.meta))
