"""Levenberg-Marquardt on the identification loss's residuals, with a forward-difference Jacobian.

The loss is a sum of squares (:func:`endogsim.identify.loss.loss_residuals`: L = ||r(theta)||^2), and a scene
has few material parameters: theta = (log10 E of each deformable object, then its nu), 2-10 numbers. So the
Jacobian J = dr / dtheta costs one forward simulation per parameter (theta + h e_i), and those simulations are
independent: a CPU runs them side by side, one per core, where a gradient through the simulator (the adjoint
pass) runs on little more than one core and costs about twice a forward simulation. The Gauss-Newton model
L(theta + d) ~ ||r + J d||^2 then gives the step, damped as Marquardt did (Marquardt 1963; Nielsen 1999):

    (J^T J + lambda diag(J^T J)) d = -J^T r

Each iteration: the Jacobian at theta (p simulations), then two damped steps (lambda and 10 lambda, side by side);
the better is taken when it lowers the loss (lambda / 3 after it), else lambda grows 100-fold and two more are
tried (:data:`MAX_TRIES` rounds; none lowering the loss ends the run). The run has converged, as MINPACK's
``lmder`` decides with its ``ftol`` (More, Garbow & Hillstrom 1980), when a step's actual and predicted relative
reductions of the loss are both at most ``tol``; or when, at a point the last step reached by less than ``tol``
(or at the start), the model predicts that no step within the search box (the undamped Gauss-Newton step,
projected into it) lowers the loss by ``tol`` of itself. Either way the loss has stopped changing at the scale
the run cares about; a model alone predicting little after a step that gained more is not enough (on EndoNeRF
pulling it predicted 8e-4 and the next step gained 1.2e-3: docs/IDENTIFICATION.md section 2).

Forward differences step ``FD_STEPS`` (0.05 decades of E, 0.02 of nu) into the search box: large against the
simulation's float32 rounding (a relative change of E of 1e-3 moves particles by rounding alone:
docs/IDENTIFICATION.md section 1), small against the scale on which the motion changes.

The pieces here are pure functions of arrays; :func:`endogsim.identify.optimize.identify` runs them with the
scene's simulations (:class:`LevenbergMarquardt`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["FD_STEPS", "MAX_TRIES", "damped_step", "boxed_step", "model_loss", "jacobian_points", "jacobian", "Evaluation",
           "LevenbergMarquardt"]

#: Forward-difference steps: (log10 E in decades, nu).
FD_STEPS = (0.05, 0.02)
#: Rounds of damped steps per iteration before the run ends with no descent.
MAX_TRIES = 3


def damped_step(J: torch.Tensor, r: torch.Tensor, lam: float) -> np.ndarray:
    """The Levenberg-Marquardt step d [p] for residuals r [n] with Jacobian J [n, p] and damping ``lam``
    (Marquardt's scaling: lam times the diagonal of J^T J; lam = 0 is the Gauss-Newton step, solved by least
    squares so that a column of zeros, a parameter that moves nothing, gets no step)."""
    if lam == 0.0:
        return torch.linalg.lstsq(J.double(), -r.double().unsqueeze(1), driver="gelsd").solution[:, 0].numpy()
    A = (J.T @ J).double()
    g = (J.T @ r).double()
    D = torch.diag(torch.diagonal(A).clamp_min(1e-30 * float(torch.diagonal(A).max().clamp_min(1e-300))))
    return torch.linalg.solve(A + lam * D, -g).numpy()


def boxed_step(J: torch.Tensor, r: torch.Tensor, lam: float, theta: np.ndarray,
               box: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The damped step from theta kept inside the search box: a parameter the step would carry out of the box
    moves only to the box's edge, and the step of the others is solved again with that move fixed (their
    residuals r + J_fixed d_fixed), until none leaves it. Projecting the free step alone would also keep the
    other parameters' moves that assumed the bound one went further."""
    p = J.shape[1]
    fixed = np.zeros(p, dtype=bool)
    d = np.zeros(p)
    for _ in range(p):
        free = ~fixed
        r_fixed = r.double() + J.double()[:, fixed] @ torch.as_tensor(d[fixed], dtype=torch.float64)
        d[free] = damped_step(J[:, free], r_fixed, lam)
        inside = box(theta + d) - theta
        leaving = ~np.isclose(inside, d, rtol=0.0, atol=1e-12) & free
        if not leaving.any():
            return inside
        fixed |= leaving
        d[leaving] = inside[leaving]
        if fixed.all():
            return inside
    return box(theta + d) - theta


def model_loss(J: torch.Tensor, r: torch.Tensor, d: np.ndarray) -> float:
    """The Gauss-Newton model's loss ||r + J d||^2 after the step d."""
    return float((r.double() + J.double() @ torch.as_tensor(d, dtype=torch.float64)).square().sum())


def jacobian_points(theta: np.ndarray, steps: np.ndarray, box: Callable[[np.ndarray], np.ndarray]) -> list[np.ndarray]:
    """theta + h_i e_i for each parameter i, or theta - h_i e_i where the + step leaves the search box."""
    points = []
    for i, h in enumerate(steps):
        up = theta.copy()
        up[i] += h
        if not np.array_equal(box(up), up):
            up[i] -= 2 * h
        points.append(up)
    return points


def jacobian(r: torch.Tensor, theta: np.ndarray, points: list[np.ndarray], residuals: list[torch.Tensor]) -> torch.Tensor:
    """[n, p] forward differences (r(point_i) - r) / (point_i - theta)_i."""
    return torch.stack([(ri - r) / float(pt[i] - theta[i]) for i, (pt, ri) in enumerate(zip(points, residuals))], 1)


@dataclass
class Evaluation:
    """One simulation's score: ``value`` (:class:`~endogsim.identify.loss.LossValue`), ``residuals`` [n]
    (float64; their squares sum to the loss) and ``sim`` (the :class:`~endogsim.physics.SimResult`)."""

    value: object
    residuals: torch.Tensor
    sim: object

    @property
    def loss(self) -> float:
        return float(self.value.parts["total"])


class LevenbergMarquardt:
    """The iterations' state: the damping and the current point's evaluation.

    Args:
        evaluate: thetas -> their :class:`Evaluation`, in order (simulated side by side).
        box: theta -> theta projected into the search box.
        steps: [p] forward-difference steps per parameter.
        tol: the least relative improvement that counts (identification's ``tol``).
        lam: the initial damping (a resumed run passes its checkpoint's).
    """

    def __init__(self, evaluate: Callable[[list[np.ndarray]], list[Evaluation]],
                 box: Callable[[np.ndarray], np.ndarray], steps: np.ndarray, tol: float, lam: float = 1e-2):
        self.evaluate, self.box, self.steps, self.tol, self.lam = evaluate, box, np.asarray(steps, float), tol, lam
        self.theta: np.ndarray | None = None
        self.here: Evaluation | None = None  # theta's evaluation, once known
        self.J: torch.Tensor | None = None
        self.predicted_gain = float("nan")  # the undamped model's relative gain at theta
        self.last_gain = float("nan")  # the last step's actual relative gain (nan before the first)
        self.small_step = False  # the last step's actual and predicted gains were both at most tol
        self.step_gradient: list[float] = []  # the gradient where that step ended (the step's Jacobian)
        self.stopped = ""  # "converged" or "no descent"
        self.tries = 0

    def state_dict(self) -> dict:
        """What a checkpoint keeps: the damping and the current point (its evaluation is simulated again)."""
        return {"lam": self.lam, "theta": None if self.theta is None else self.theta.tolist(),
                "last_gain": self.last_gain, "small_step": self.small_step, "step_gradient": self.step_gradient}

    def load_state_dict(self, state: dict) -> None:
        self.lam = float(state["lam"])
        self.theta = None if state.get("theta") is None else np.asarray(state["theta"], dtype=float)
        self.last_gain = float(state.get("last_gain", float("nan")))
        self.small_step = bool(state.get("small_step", False))
        self.step_gradient = list(state.get("step_gradient", []))
        self.here = None

    def linearise(self, theta: np.ndarray) -> tuple[Evaluation, np.ndarray]:
        """Evaluate theta (unless it is the point the last step reached) and the Jacobian there; returns theta's
        evaluation and the loss's gradient 2 J^T r [p]. Sets :attr:`stopped` to "converged" when the undamped
        Gauss-Newton step, projected into the box, is predicted to lower the loss by less than ``tol`` of it and
        the last step (if any) gained less than ``tol`` too."""
        if self.here is None or self.theta is None or not np.array_equal(theta, self.theta):
            self.theta, self.here, self.small_step = theta.copy(), None, False
        if self.small_step:  # the step here gained less than tol, as its model predicted: no Jacobian is needed
            self.stopped = "converged"
            if self.here is None:  # a resumed run
                self.here = self.evaluate([self.theta])[0]
            return self.here, np.asarray(self.step_gradient, dtype=float)
        points = jacobian_points(self.theta, self.steps, self.box)
        results = self.evaluate(([self.theta] if self.here is None else []) + points)
        if self.here is None:
            self.here, results = results[0], results[1:]
        r = self.here.residuals
        self.J = jacobian(r, self.theta, points, [e.residuals for e in results])
        L = self.here.loss
        gn = boxed_step(self.J, r, 0.0, self.theta, self.box)
        self.predicted_gain = (L - model_loss(self.J, r, gn)) / max(abs(L), 1e-300)
        if self.predicted_gain < self.tol and not self.last_gain >= self.tol:
            self.stopped = "converged"
        return self.here, 2.0 * (self.J.T.double() @ r.double()).numpy()

    def step(self) -> np.ndarray:
        """Take the damped step from theta (after :meth:`linearise`); returns the new theta (theta itself when
        no step lowered the loss: :attr:`stopped` is then "converged" if the model predicted less than ``tol``
        too, else "no descent"). When the step's actual and predicted
        relative gains were both at most ``tol``, the next :meth:`linearise` there reports "converged" (the
        gradient from this Jacobian) without simulating."""
        r, L = self.here.residuals, self.here.loss
        for self.tries in range(1, MAX_TRIES + 1):
            lams = (self.lam, 10.0 * self.lam)
            cands = [self.theta + boxed_step(self.J, r, lam, self.theta, self.box) for lam in lams]
            moving = [i for i, c in enumerate(cands) if not np.array_equal(c, self.theta)]
            if moving:
                if np.array_equal(cands[0], cands[-1]):
                    moving = moving[:1]
                results = self.evaluate([cands[i] for i in moving])
                best = min(range(len(moving)), key=lambda j: results[j].loss)
                if results[best].loss < L:
                    taken = cands[moving[best]]
                    self.last_gain = (L - results[best].loss) / max(abs(L), 1e-300)
                    predicted = (L - model_loss(self.J, r, taken - self.theta)) / max(abs(L), 1e-300)
                    self.small_step = self.last_gain <= self.tol and predicted <= self.tol
                    # the gradient there, from this Jacobian, for the record of a run that stops there
                    self.step_gradient = (2.0 * (self.J.T.double() @ results[best].residuals.double())).tolist()
                    self.lam = lams[moving[best]] / 3.0
                    self.theta, self.here = taken, results[best]
                    return self.theta
            self.lam *= 100.0
        # No step lowered the loss: converged where the model, too, predicted less than tol (an optimum within
        # the rounding of the loss), otherwise a model that does not describe the loss here.
        self.stopped = "converged" if self.predicted_gain < self.tol else "no descent"
        return self.theta
