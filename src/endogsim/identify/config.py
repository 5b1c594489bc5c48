"""Typed options of material identification (:func:`endogsim.identify.identify`)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Literal, get_args

from endogsim.errors import MaterialError
from endogsim.physics.modes import GRAD_MODES, GradMode
from endogsim.priors.flow import FlowConfig

LossKind = Literal["joint_track", "joint", "render", "flow", "track"]
LOSSES: tuple[str, ...] = get_args(LossKind)
#: Identification's optimisers (the gradient ones: ``endogsim.identify.optimize.OPTIMIZERS``; "lm":
#: ``endogsim.identify.levenberg_marquardt``).
OptimizerKind = Literal["rprop", "adam", "lm"]
OPTIMIZER_KINDS: tuple[str, ...] = get_args(OptimizerKind)
#: The automatic frame stride compares at least this many frames (the intervals' t-test then has 9 degrees of
#: freedom or more): a 10-frame clip is compared at every frame, a 20-frame one at every second.
MIN_COMPARED_FRAMES = 10
#: The default refined correction's factor (``IdentifyConfig.refined_correction``; docs/IDENTIFICATION.md section 3).
DEFAULT_REFINED_CORRECTION = 1.5


@dataclass
class IdentifyConfig:
    """How identification runs.

    Attributes:
        loss: "joint" (the paper's L = render + lambda * flow; the default), "joint_track" (plus the track
            term against the reconstruction's tissue trajectories; on a scene without tracks the same as
            "joint"), "render" (appearance only), "flow" (motion only) or "track" (trajectories only).
            "joint" is the default because of an ablation on the demo path (``endogsim demo --seed 0..9``,
            docs/IDENTIFICATION.md section 5): with the track term 2 of 10 seeds ended further from the true E
            than the prior (the reconstruction's trajectories move less than the tissue, which reads as
            stiffer tissue: E 13.7 and 14.5 kPa for a true 2.5 kPa); without it none did.
        flow_weight: lambda, the weight of the flow term (paper: 0.1).
        track_weight: mu, the weight of the track term (pixels^2, like the flow term).
        loss_terms: explicit {term: weight} over the registered loss terms
            (:data:`endogsim.identify.loss.LOSS_TERMS`), replacing the ``loss`` preset when given.
        grad_mode: gradient through the simulator: "last_substep" (paper), "frame" or "full"
            (see :func:`endogsim.physics.mpm_rollout`). Default "full": on ``tiny`` (10 frames, E 2x and
            3x too stiff) its d loss / d log10 E is within 3% of central finite differences of the same
            loss, at the cost of "frame" (one taped frame at a time either way); "frame" has the right
            sign but 40-60% of the size, and "last_substep" is 100-300x too small with the wrong sign.
        iters: the most optimisation iterations (each = one simulation + render + backward).
        optimizer: "rprop" (:class:`~endogsim.identify.optimize.SharedScaleRprop`, the default: the first step
            is ``lr``, then it grows by 1.2 while the gradient keeps its direction and halves when it turns,
            within 0.01-5 ``lr``; the schedule below is not used) or "adam"
            (:class:`~endogsim.identify.optimize.SharedScaleAdam`: steps of about ``lr`` on the schedule below,
            so 10 iterations travel at most about half a decade of E; docs/IDENTIFICATION.md section 4) or "lm"
            (Levenberg-Marquardt on the loss's residuals with a forward-difference Jacobian,
            :mod:`endogsim.identify.levenberg_marquardt`: forward simulations only, one per parameter and
            iteration, side by side on the cores; no gradient through the simulator, so ``grad_mode``, ``lr``,
            ``lr_nu`` and ``max_grad_norm`` do not apply; docs/IDENTIFICATION.md section 2).
        lr: the first step on log10 E (decades).
        lr_nu: the first step on the raw (pre-sigmoid) Poisson parameter; larger than ``lr`` because the
            sigmoid is flat near the bounds, where tissue's nu (0.4 to 0.49) lies.
        lr_final_fraction: Adam's step decays exponentially to ``lr * lr_final_fraction`` at the last iteration.
        max_grad_norm: gradient clipping (L2 norm over all parameters).
        lm_damping: Levenberg-Marquardt's first damping lambda (relative to the diagonal of J^T J).
        time_budget: a safety stop: no new iteration starts once this many seconds of optimisation have
            passed (None: no limit); the best iterate so far is kept and ``metrics.json`` says
            ``stopped_by_budget``. The learning-rate schedule follows ``iters`` only, so a stopped run is an
            unstopped one cut short, whatever the machine's speed; but how many iterations it got follows the
            machine's speed, so the benchmarks (``bench suite``, ``bench identify``) run without it.
        tol: relative loss improvement below which an iteration does not count as progress; also the least
            relative rise of the loss that counts as evidence on a parameter's slice
            (:func:`endogsim.identify.uncertainty.counted_z`).
        patience: stop after this many iterations without progress (early stopping).
        stationary_patience: stop after this many consecutive iterations whose gradient could not make
            progress even over a whole unit step: |d loss / d log10 E| (per decade) and |d loss / d raw nu|
            (per raw unit) all below ``tol`` times the loss. Both optimisers normalise their steps, so on a
            flat loss they walk a full step on noise; this ends such a run (e.g. a real clip where no instrument
            moves the tissue: relative gradients 1e-5 to 6e-4 per decade, against 6e-3 to 1 on the suite's
            and the demo's scenes; docs/IDENTIFICATION.md section 2: one such iteration already separates
            the regimes, so one is enough). 0: never.
        global_material: tie every deformable object to one (E, nu) pair (the "no material field" ablation).
        nu_bounds: (lo, hi) of the bounded Poisson parametrisation nu = lo + (hi - lo) sigmoid(raw).
        E_min, E_max: the search box for E (Pa): soft tissue in vivo is 0.5-20 kPa, tensile tests of organ
            walls reach MPa (``shared/docs/tissue_mechanics.md``); the upper end is also bounded by
            ``max_substeps``.
        max_substeps: the most substeps per frame a rollout may take at the scene's default discretisation: E
            is kept below the stiffness whose CFL rule would ask for more (an iteration's cost grows with
            sqrt(E)). Refined ``refine`` times, a rollout may take ``refine`` times as many
            (:attr:`substep_limit`), so that the search box for E is the same at every refinement.
        stability_margin: keep E below this fraction of that CFL-limited maximum.
        optimize_nu: also optimise nu (else only E moves).
        intervals: after optimising, measure each parameter's 90% interval and whether the video determines
            it (:mod:`endogsim.identify.uncertainty`: a few forward simulations per parameter); a parameter it
            does not determine keeps its initial value, labelled "prior (not identifiable from this video)".
        coarse_factor: with ``intervals``, the discretisation's own error is measured too: each parameter's
            optimum is found again along its slice at a coarser discretisation (grid x ``coarse_factor``, the
            particle spacing and substeps scaled with it), and the grid convergence index of the move widens
            the interval (:func:`~endogsim.identify.uncertainty.discretisation_error`; a few forward
            simulations per parameter, each about a third of the cost of one at full resolution). None: the
            interval holds the loss's frame-to-frame noise alone.
        refine: simulate at the scene's identification discretisation refined by this factor (grid x
            ``refine``, particle spacing / ``refine``, substeps x ``refine``;
            :func:`~endogsim.scene.folder.load_sim_scene`). The default discretisation is not converged
            (docs/IDENTIFICATION.md section 3), and its error moves the optimum; a finer one moves it less, at
            up to ``refine``^4 the cost of an iteration and ``refine``^3 its memory. ``coarse_factor`` is
            relative to it.
        refined_correction: after the intervals, correct the parameters whose value the video gave to the
            discretisation refined by this factor (relative to ``refine``'s): chord Gauss-Newton steps on the
            refined simulation's residuals with the Jacobian of this one
            (:mod:`endogsim.identify.refined_correction`; forward simulations only: one per moved parameter
            here, one or two refined ones a step). The materials then belong to the refined discretisation
            (``endogsim simulate`` simulates them there). At 1.5x (the default) on the suite's scenes at 1x it
            brings the median |E/E_true - 1| from 0.27 to 0.12; its simulations run side by side, and the
            slowest suite scene, `lift_real`, takes 555 s in all on a 2-core CPU (docs/IDENTIFICATION.md section
            3). None: no correction.
        correction_steps: the most steps of that correction. Each costs one or two refined simulations (a pair side
            by side); on the suite no scene gained from a third (docs/IDENTIFICATION.md section 3).
        render_scale: render (and compare) at this fraction of the image size; flows scale with it. Rendering
            dominates an iteration on a CPU, and 0.5 quarters it. The rasteriser's fixed screen-space
            low-pass makes reduced-scale renders differ from the area-downsampled observations by a
            near-constant offset (1e-3 per frame on ``tiny``, 1e-4 at scale 1); over a whole clip it does not
            move the loss minimum (on ``tiny`` the joint loss is least at the true E at 0.5 and at 1).
        flow: the observed-flow estimator (:class:`~endogsim.priors.flow.FlowConfig`; default "dis_fine",
            DIS tuned for sub-pixel motion; "raft" needs a local weights file).
        frames: use only the first ``frames`` frames (None = all).
        frame_stride: compare every k-th frame (t = 0, k, 2k, ...: its image and its flow to t + 1); the
            simulation still runs through every frame. None (default): 2 where that still compares at least
            :data:`MIN_COMPARED_FRAMES` frames, else 1 (:meth:`stride`). Rendering dominates a CPU iteration,
            so k = 2 halves its cost while the compared frames still span the whole clip; but the intervals
            measure the loss's noise from frame to frame, and with 5 frames (a 10-frame clip at k = 2) that
            t-test has 4 degrees of freedom (k = 1: the paper's sums).
        seed: torch seed (the loop itself is deterministic).
        device: "cpu" or "cuda" for the simulator and renderer.
    """

    loss: LossKind = "joint"
    flow_weight: float = 0.1
    track_weight: float = 0.1
    loss_terms: dict[str, float] | None = None
    grad_mode: GradMode = "full"
    iters: int = 30
    optimizer: OptimizerKind = "rprop"
    lr: float = 0.1
    lr_nu: float = 0.3
    lr_final_fraction: float = 0.2
    max_grad_norm: float = 10.0
    lm_damping: float = 1e-2
    time_budget: float | None = 480.0
    tol: float = 1e-3
    patience: int = 10
    stationary_patience: int = 1
    global_material: bool = False
    nu_bounds: tuple[float, float] = (0.0, 0.49)
    E_min: float = 50.0
    E_max: float = 1.0e6
    max_substeps: int = 400
    stability_margin: float = 0.95
    optimize_nu: bool = True
    intervals: bool = True
    coarse_factor: float | None = 0.7
    refine: float = 1.0
    refined_correction: float | None = DEFAULT_REFINED_CORRECTION
    correction_steps: int = 2
    render_scale: float = 0.5
    flow: FlowConfig = field(default_factory=lambda: FlowConfig("dis_fine"))
    frames: int | None = None
    frame_stride: int | None = None
    seed: int = 0
    device: str = "cpu"

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise MaterialError(f"loss {self.loss!r} is not one of {', '.join(LOSSES)}")
        if self.grad_mode not in GRAD_MODES:
            raise MaterialError(f"grad mode {self.grad_mode!r} is not one of {', '.join(GRAD_MODES)}")
        if self.iters < 0:
            raise MaterialError(f"iters = {self.iters} must be >= 0")
        if self.optimizer not in OPTIMIZER_KINDS:
            raise MaterialError(f"optimiser {self.optimizer!r} is not one of {', '.join(OPTIMIZER_KINDS)}")
        if not (self.lr > 0 and self.lr_nu > 0):
            raise MaterialError(f"lr = {self.lr}, lr_nu = {self.lr_nu} must be > 0")
        if not self.lm_damping > 0:
            raise MaterialError(f"lm_damping = {self.lm_damping} must be > 0")
        if not (0 < self.render_scale <= 1):
            raise MaterialError(f"render_scale = {self.render_scale} must lie in (0, 1]")
        if not 0 < self.E_min < self.E_max:
            raise MaterialError(f"the E search box [{self.E_min}, {self.E_max}] Pa must satisfy 0 < E_min < E_max")
        if self.max_substeps < 1:
            raise MaterialError(f"max_substeps = {self.max_substeps} must be >= 1")
        if self.patience < 1 or self.stationary_patience < 0:
            raise MaterialError(f"patience = {self.patience} must be >= 1 and stationary_patience = "
                                f"{self.stationary_patience} >= 0")
        if self.time_budget is not None and not self.time_budget > 0:
            raise MaterialError(f"time_budget = {self.time_budget} s must be > 0 (or None)")
        if self.coarse_factor is not None and not 0 < self.coarse_factor < 1:
            raise MaterialError(f"coarse_factor = {self.coarse_factor} must lie in (0, 1) (or None: not measured)")
        if not (self.refine > 0 and math.isfinite(self.refine)):
            raise MaterialError(f"refine = {self.refine} must be a finite factor > 0")
        if self.refined_correction is not None and not (1 < self.refined_correction <= 4):
            raise MaterialError(f"refined_correction = {self.refined_correction} must lie in (1, 4] (or None: no "
                                "correction)")
        if self.correction_steps < 1:
            raise MaterialError(f"correction_steps = {self.correction_steps} must be >= 1")
        if self.frame_stride is not None and self.frame_stride < 1:
            raise MaterialError(f"frame_stride = {self.frame_stride} must be >= 1 (or None: automatic)")
        if self.flow_weight < 0 or self.track_weight < 0:
            raise MaterialError(f"flow_weight = {self.flow_weight}, track_weight = {self.track_weight} must be >= 0")
        self.nu_bounds = (float(self.nu_bounds[0]), float(self.nu_bounds[1]))
        if isinstance(self.flow, dict):
            self.flow = FlowConfig(**self.flow)
        if self.loss_terms is not None:
            from endogsim.identify.loss import LOSS_TERMS

            for name, w in self.loss_terms.items():
                LOSS_TERMS.get(name)
                if not w >= 0:
                    raise MaterialError(f"loss term {name!r} weight {w} must be >= 0")

    def stride(self, num_frames: int) -> int:
        """The frame stride of a clip of ``num_frames`` frames: ``frame_stride``, or when it is None 2 if that
        still compares at least :data:`MIN_COMPARED_FRAMES` frames, else 1."""
        if self.frame_stride is not None:
            if math.ceil(num_frames / self.frame_stride) < 2:
                raise MaterialError(f"frame_stride {self.frame_stride} compares "
                                    f"{math.ceil(num_frames / self.frame_stride)} of {num_frames} frames; motion "
                                    "needs at least 2")
            return self.frame_stride
        return 2 if math.ceil(num_frames / 2) >= MIN_COMPARED_FRAMES else 1

    def term_weights(self) -> dict[str, float]:
        """{loss term: weight} of this run: ``loss_terms``, or the ``loss`` preset with ``flow_weight``."""
        if self.loss_terms is not None:
            return dict(self.loss_terms)
        return {"joint_track": {"render": 1.0, "flow": self.flow_weight, "track": self.track_weight},
                "joint": {"render": 1.0, "flow": self.flow_weight}, "render": {"render": 1.0},
                "flow": {"flow": self.flow_weight}, "track": {"track": self.track_weight}}[self.loss]

    @property
    def substep_limit(self) -> int:
        """The most substeps per frame at this configuration's discretisation: ``max_substeps`` x ``refine``
        (the CFL rule's substeps grow with the grid, so the same stiffest material stays in the box)."""
        return math.ceil(self.max_substeps * self.refine - 1e-9)

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["nu_bounds"] = list(self.nu_bounds)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "IdentifyConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: (tuple(v) if k == "nu_bounds" else v) for k, v in d.items() if k in known})
