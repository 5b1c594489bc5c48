"""Levenberg-Marquardt (``IdentifyConfig.optimizer = "lm"``): the damped step and the iterations on a problem with a
known answer (scipy's). Identification with it on the synthesized ``tiny`` scene: ``tests/test_identify.py``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from endogsim.identify.levenberg_marquardt import Evaluation, LevenbergMarquardt, damped_step, model_loss
from endogsim.identify.loss import LossValue


def test_the_damped_step_is_gauss_newton_at_zero_damping_and_shrinks_towards_the_gradient():
    rng = np.random.default_rng(0)
    J, r = torch.tensor(rng.normal(size=(50, 3))), torch.tensor(rng.normal(size=50))
    exact = np.linalg.lstsq(J.numpy(), -r.numpy(), rcond=None)[0]
    np.testing.assert_allclose(damped_step(J, r, 0.0), exact, rtol=1e-10)
    assert model_loss(J, r, exact) <= model_loss(J, r, damped_step(J, r, 0.1)) < float(r.square().sum())
    # heavy damping: a short step along -J^T r scaled by diag(J^T J)
    A = (J.T @ J).numpy()
    big = damped_step(J, r, 1e6)
    np.testing.assert_allclose(big, -(J.T @ r).numpy() / (1e6 * np.diag(A)), rtol=1e-4)
    # a parameter that moves nothing gets no Gauss-Newton step
    J0 = torch.cat([J[:, :2], torch.zeros(50, 1, dtype=J.dtype)], 1)
    assert damped_step(J0, r, 0.0)[2] == 0.0


def _curve_fit(box=lambda t: t):
    """r(theta) = a exp(-b x) - y for data made with a = 2, b = 0.7 plus fixed noise: nonlinear least squares whose
    answer scipy gives independently."""
    x = np.linspace(0, 4, 40)
    y = 2.0 * np.exp(-0.7 * x) + 0.01 * np.random.default_rng(1).normal(size=x.size)
    calls = []

    def evaluate(thetas):
        calls.append(len(thetas))
        out = []
        for a, b in thetas:
            r = torch.tensor(a * np.exp(-b * x) - y)
            value = LossValue(r.square().sum(), {"total": float(r.square().sum())}, {})
            out.append(Evaluation(value, r, None))
        return out

    return LevenbergMarquardt(evaluate, box, np.array([1e-4, 1e-4]), tol=1e-6), x, y, calls


def test_levenberg_marquardt_finds_a_nonlinear_least_squares_optimum():
    from scipy.optimize import least_squares

    lm, x, y, calls = _curve_fit()
    theta = np.array([1.0, 0.2])
    losses = []
    for _ in range(50):
        here, grad = lm.linearise(theta)
        losses.append(here.loss)
        if lm.stopped:
            break
        theta = lm.step()
    ref = least_squares(lambda t: t[0] * np.exp(-t[1] * x) - y, [1.0, 0.2], xtol=1e-14, ftol=1e-14).x
    assert lm.stopped == "converged"
    np.testing.assert_allclose(theta, ref, rtol=1e-3)
    assert all(b <= a for a, b in zip(losses, losses[1:]))  # every step taken lowered the loss
    assert calls[0] == 3 and set(calls[1:]) <= {1, 2}  # the point and one per parameter, then the damped steps


def test_levenberg_marquardt_stays_in_its_box_and_stops_at_a_bound():
    """With b held below its optimum (0.7) by the box, the run ends on the bound, converged: no step inside the
    box is predicted to help."""
    lm, x, y, _ = _curve_fit(box=lambda t: np.array([t[0], min(t[1], 0.5)]))
    theta = np.array([1.0, 0.2])
    for _ in range(50):
        lm.linearise(theta)
        if lm.stopped:
            break
        theta = lm.step()
        assert theta[1] <= 0.5
    assert lm.stopped in ("converged", "no descent") and theta[1] == pytest.approx(0.5)
