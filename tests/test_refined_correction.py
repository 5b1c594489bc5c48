"""The refined correction's steps (``identify/refined_correction.py``) on problems whose answer is known."""

import numpy as np
import pytest
import torch

from endogsim.identify.levenberg_marquardt import Evaluation
from endogsim.identify.refined_correction import correct_to_refined, shifted_interval
from endogsim.identify.uncertainty import ParameterInterval

STEPS = np.array([0.05, 0.02, 0.05])


class LossValue:
    """The loss of residuals r [n], each residual one "frame"."""

    def __init__(self, r: torch.Tensor):
        self.parts = {"total": float(r.square().sum())}
        self.per_frame = {i: float(v) ** 2 for i, v in enumerate(r)}


def evaluations(residuals, calls: list):
    """thetas -> Evaluations of ``residuals(theta)`` [n], counting the simulations in ``calls``."""
    def evaluate(thetas):
        out = []
        for t in thetas:
            calls.append(np.array(t))
            r = torch.as_tensor(residuals(np.asarray(t)), dtype=torch.float64)
            out.append(Evaluation(LossValue(r), r, None))
        return out
    return evaluate


def joint(coarse, refined):
    """(thetas, refined thetas) -> (their Evaluations by ``coarse``, by ``refined``): the correction's evaluator."""
    return lambda thetas, refined_thetas: (coarse(thetas), refined(refined_thetas))


def no_box(theta):
    return np.array(theta, dtype=float)


_rng = np.random.default_rng(0)
A = _rng.normal(size=(40, 3))  # 40 compared frames, 3 parameters
Y = A @ np.array([0.3, -0.2, 0.5]) + 0.01 * _rng.normal(size=40)
NOISE = 0.01 * _rng.normal(size=40)


def test_a_defect_that_does_not_depend_on_theta_is_corrected_in_one_step_moving_only_the_free_parameters():
    """Linear residuals: the identification discretisation's A theta - y, the refined one's the same plus a
    constant defect b (output space mapping's premise), here mostly what a shift of the parameters would do (the
    coarse grid acting stiffer). From the coarse optimum of the free parameters the first step lands on the refined
    optimum over them (a gain far above the frames' noise), the fixed parameter stays, and the model predicts
    nothing from a second step."""
    b = A @ np.array([0.2, -0.1, 0.0]) + NOISE
    free = np.array([True, True, False])
    fixed = 0.5
    Af, yf = A[:, free], Y - A[:, ~free][:, 0] * fixed
    coarse_opt = np.linalg.lstsq(Af, yf, rcond=None)[0]
    refined_opt = np.linalg.lstsq(Af, yf - b, rcond=None)[0]
    theta = np.array([*coarse_opt, fixed])
    coarse_calls, fine_calls = [], []
    out, ev, loss, losses, stopped = correct_to_refined(
        theta, free, joint(evaluations(lambda t: A @ t - Y, coarse_calls),
                           evaluations(lambda t: A @ t + b - Y, fine_calls)), no_box, STEPS, max_steps=3, tol=1e-3)
    np.testing.assert_allclose(out[free], refined_opt, atol=1e-9)
    assert out[2] == fixed and stopped == "converged"
    assert len(coarse_calls) == 1 + free.sum()  # theta and one forward difference per free parameter
    assert len(fine_calls) == 3 and len(losses) == 2  # theta, the step and its half; then no simulation
    assert all(c[2] == fixed for c in coarse_calls + fine_calls)
    assert losses[0] > losses[-1] and ev.loss == losses[-1]
    assert loss == pytest.approx(float(np.square(A @ theta - Y).sum()))


def test_a_nonlinear_refined_model_is_approached_with_a_loss_that_falls_at_every_step():
    """The refined model is the coarse one at a shifted, scaled point (the discretisation makes tissue act
    stiffer): the chord steps with the coarse Jacobian approach the refined optimum, the refined loss falling at
    every step taken."""
    s = np.linspace(0.1, 2.0, 40)  # a response over 40 frames
    observed = np.tanh(0.8 * s) * 0.5 + 0.15 * s + NOISE

    def coarse(t):
        return np.tanh(t[0] * s) * t[1] + 0.3 * t[1] * s - observed

    def refined(t):
        return coarse(np.array([t[0] + 0.15, 1.1 * t[1]]))

    x0 = np.array([0.8, 0.5])
    from scipy.optimize import least_squares

    coarse_opt = least_squares(coarse, x0).x
    refined_opt = least_squares(refined, coarse_opt).x
    out, _, _, losses, stopped = correct_to_refined(
        coarse_opt, np.array([True, True]), joint(evaluations(coarse, []), evaluations(refined, [])), no_box,
        STEPS[:2], max_steps=6, tol=1e-6)
    assert all(b < a for a, b in zip(losses, losses[1:]))
    assert np.abs(out - refined_opt).max() < 0.2 * np.abs(coarse_opt - refined_opt).max()


def test_a_gain_within_the_frames_noise_is_not_taken():
    """A defect that no parameter explains (noise over the frames): the Gauss-Newton step lowers the refined loss,
    but by less than the frame-to-frame noise of that loss can tell, so the estimate stays where it was."""
    theta = np.linalg.lstsq(A, Y, rcond=None)[0]
    out, ev, _, losses, stopped = correct_to_refined(
        theta, np.array([True, True, True]), joint(evaluations(lambda t: A @ t - Y, []),
                                                  evaluations(lambda t: A @ t - Y + 3 * NOISE, [])),
        no_box, STEPS, max_steps=3, tol=1e-3)
    assert stopped == "not significant" and np.array_equal(out, theta) and len(losses) == 1


def test_a_step_that_lowers_no_refined_loss_leaves_the_estimate_and_says_so():
    """A refined model whose defect the coarse Jacobian points the wrong way: neither the step nor its half lowers
    the refined loss, so the estimate stays where identification left it."""
    theta = np.array([0.5, 0.5, 0.5])
    fine_calls = []
    out, ev, _, losses, stopped = correct_to_refined(
        theta, np.array([True, False, False]),
        joint(evaluations(lambda t: A @ t - Y, []),
              evaluations(lambda t: np.full(40, 1.0 + abs(t[0] - 0.5)), fine_calls)),
        no_box, STEPS, max_steps=3, tol=1e-3)
    assert stopped == "no descent" and np.array_equal(out, theta) and losses == [40.0]
    assert len(fine_calls) == 3  # theta, then the step and its half side by side


def test_the_steps_stay_in_the_search_box():
    box = lambda t: np.clip(t, -1.0, 0.1)  # noqa: E731
    out, *_ = correct_to_refined(np.array([0.0, 0.0, 0.0]), np.array([True, True, True]),
                                 joint(evaluations(lambda t: A @ t - Y, []),
                                       evaluations(lambda t: A @ t - Y - A @ [1, 1, 1], [])),
                                 box, STEPS, max_steps=3, tol=1e-3)
    assert np.all(out <= 0.1) and np.all(out >= -1.0)


def test_no_free_parameter_is_refused():
    with pytest.raises(ValueError, match="free parameter"):
        correct_to_refined(np.zeros(3), np.zeros(3, dtype=bool), None, no_box, STEPS, 3, 1e-3)


def test_an_interval_moves_with_its_estimate_within_its_search_box_and_keeps_its_slices():
    iv = ParameterInterval(object_id=1, name="sheet", parameter="E", best=2000.0, interval=[500.0, 8000.0],
                           search_box=[50.0, 10000.0], identifiable=True, reason="", slice=[[1000.0, 1.0, 1.0, 1.0]],
                           statistical_interval=[1500.0, 2500.0])
    moved = shifted_interval(iv, -0.1)
    f = 10 ** -0.1
    assert moved.best == pytest.approx(2000 * f) and moved.interval == pytest.approx([500 * f, 8000 * f])
    assert moved.statistical_interval == pytest.approx([1500 * f, 2500 * f]) and moved.correction == -0.1
    assert moved.slice == iv.slice and iv.best == 2000.0  # the original is not changed
    up = shifted_interval(iv, 0.2)
    assert up.interval[1] == 10000.0  # clipped to the search box
    nu = ParameterInterval(object_id=1, name="sheet", parameter="nu", best=0.40, interval=[0.30, 0.48],
                           search_box=[0.0, 0.49], identifiable=True, reason="")
    moved = shifted_interval(nu, 0.03)
    assert moved.best == pytest.approx(0.43) and moved.interval == pytest.approx([0.33, 0.49])
    assert moved.statistical_interval is None and shifted_interval(nu, 0.0) is nu
