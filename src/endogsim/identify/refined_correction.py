"""The identified materials corrected to a refined discretisation by a few forward simulations there.

Identification's discretisation is not converged (docs/IDENTIFICATION.md section 3): its optimum absorbs the
discretisation's error (the suite's grasper lifts come out 1.2-1.4x too stiff), and identifying at a finer one
costs this CPU 4.4x an iteration at 1.5x (the adjoint pass). The error is nearly the same at nearby materials, so
the refined simulation's residuals r_f are, to first order, the identification discretisation's r_c plus a
defect d = r_f - r_c that does not depend on theta (Bandler's output space mapping: the coarse model plus the
fine model's defect stands in for the fine model; Bandler et al. 2004, "Space mapping: the state of the art").
Minimised to first order, with J = dr_c / dtheta at the identified materials:

    d_theta = -J^+ r_f(theta)

a Gauss-Newton step on the refined loss whose Jacobian comes from the identification discretisation (a chord
step: J is not taken again). Steps repeat from the point reached, with r_f simulated there, at most ``max_steps``
times. The better of the step and its half (side by side) is taken only where it lowers the refined loss by more
than ``tol`` of it *and* significantly above the loss's frame-to-frame noise: the paired comparison of the two
simulations frame by frame (:func:`~endogsim.identify.uncertainty.paired_z`) gives z below -z_s, the one-sided 5%
test of docs/IDENTIFICATION.md section 1 that decides identifiability. A move the refined loss does not support
is not made: where the loss is flat (the demo's probe-driven clip, whose render residual dominates), a
Gauss-Newton step travels far on a gain of a fraction of a percent. No step is simulated where the Gauss-Newton
model predicts a gain of at most ``tol``.
Cost: one simulation per moved parameter at the identification discretisation (the Jacobian, side by side with
the refined one at the identified materials) and one or two refined ones per step, all forward.

Only parameters whose value the video gave move (identified, or a one-sided estimate whose statistical interval
excludes the prior): a parameter kept at its prior stays there. Their intervals move with them
(:func:`shifted_interval`).

The pieces here are pure functions of arrays and evaluations; :func:`endogsim.identify.optimize.identify` runs
them with the scene's simulations.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from endogsim.identify.levenberg_marquardt import Evaluation, boxed_step, jacobian, jacobian_points, model_loss
from endogsim.identify.uncertainty import ParameterInterval, paired_z, significant_z

__all__ = ["Correction", "correct_to_refined", "shifted_interval"]


@dataclass
class Correction:
    """What the correction did (metrics.json's ``refined_correction``).

    Attributes:
        factor: the refined discretisation's grid over the identification discretisation's.
        parameters: the moved parameters, "<object> E" or "<object> nu".
        before, after: [k] their values before and after (log10 E in decades of Pa; nu).
        loss: the identification discretisation's loss at ``before``.
        refined_loss: the refined simulation's loss at ``before``, then after every step taken.
        stopped: "converged" (the step would gain, or the model predicted, at most ``tol`` of the refined loss),
            "not significant" (its gain lay within the frame-to-frame noise), "steps" (``max_steps`` taken)
            or "no descent" (neither the step nor its half lowered the refined loss).
        seconds: wall time of the correction's simulations.
    """

    factor: float
    parameters: list[str]
    before: list[float]
    after: list[float]
    loss: float
    refined_loss: list[float] = field(default_factory=list)
    stopped: str = "steps"
    seconds: float = 0.0

    def to_json(self) -> dict:
        return asdict(self)


def correct_to_refined(theta: np.ndarray, free: np.ndarray,
                       evaluate: Callable[[list[np.ndarray], list[np.ndarray]],
                                          tuple[list[Evaluation], list[Evaluation]]],
                       box: Callable[[np.ndarray], np.ndarray], steps: np.ndarray, max_steps: int, tol: float,
                       ) -> tuple[np.ndarray, Evaluation, float, list[float], str]:
    """Chord Gauss-Newton steps on the refined residuals (module docstring).

    Args:
        theta: [p] the identified parameters (log10 E of each slot, then nu of each slot).
        free: [p] bool, the parameters that may move (at least one).
        evaluate: (thetas, refined thetas) -> their :class:`Evaluation` at the identification discretisation and
            at the refined one, all side by side (the Jacobian's simulations beside the refined one at ``theta``).
        box: theta -> theta projected into the search box.
        steps: [p] forward-difference steps (:data:`~endogsim.identify.levenberg_marquardt.FD_STEPS`).
        max_steps: the most steps.
        tol: a step that gains at most this share of the refined loss ends the correction.
    Returns:
        (the corrected theta [p], its refined evaluation, the loss at ``theta``, the refined losses (at
        ``theta``, then after each step), why it stopped).
    """
    free = np.asarray(free, dtype=bool)
    if not free.any():
        raise ValueError("the correction needs at least one free parameter")

    def full(x: np.ndarray) -> np.ndarray:
        out = np.array(theta, dtype=float)
        out[free] = x
        return out

    def box_free(x: np.ndarray) -> np.ndarray:
        return box(full(x))[free]

    x = np.asarray(theta, dtype=float)[free]
    points = jacobian_points(x, np.asarray(steps, dtype=float)[free], box_free)
    (here, *around), (fine,) = evaluate([full(x)] + [full(p) for p in points], [full(x)])
    J = jacobian(here.residuals, x, points, [e.residuals for e in around])
    losses, stopped = [fine.loss], "steps"
    for _ in range(max_steps):
        d = boxed_step(J, fine.residuals, 0.0, x, box_free)
        if fine.loss - model_loss(J, fine.residuals, d) <= tol * abs(fine.loss):  # the model expects nothing more
            stopped = "converged"
            break
        cands = [box_free(x + d), box_free(x + 0.5 * d)]
        moving = [c for c in cands if not np.array_equal(c, x)]
        results = evaluate([], [full(c) for c in moving])[1] if moving else []
        best = min(range(len(results)), key=lambda i: results[i].loss, default=None)
        if best is None or not results[best].loss < fine.loss:
            stopped = "no descent"
            break
        if fine.loss - results[best].loss <= tol * abs(fine.loss):
            stopped = "converged"
            break
        _, _, z = paired_z(results[best].value.per_frame, fine.value.per_frame)
        if not z < -significant_z(len(fine.value.per_frame)):
            stopped = "not significant"
            break
        x, fine = moving[best], results[best]
        losses.append(fine.loss)
    return full(x), fine, here.loss, losses, stopped


def shifted_interval(iv: ParameterInterval, by: float) -> ParameterInterval:
    """``iv`` moved with its estimate by ``by`` (decades for E, units of nu), clipped to its search box: to first
    order the corrected model's loss is the identification discretisation's shifted by the correction, so its
    slices, and the intervals read from them, move with it. The slices themselves stay where they were measured."""
    if by == 0.0:
        return iv

    def move(v: float) -> float:
        lo, hi = iv.search_box
        w = v * 10.0 ** by if iv.parameter == "E" else v + by
        return float(min(max(w, lo), hi))

    def move_all(pair: list[float] | None) -> list[float] | None:
        return None if pair is None else [move(v) for v in pair]

    return replace(iv, best=move(iv.best), interval=move_all(iv.interval),
                   statistical_interval=move_all(iv.statistical_interval), correction=by)
