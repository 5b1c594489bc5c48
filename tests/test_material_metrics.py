"""Relative-error metrics of identified materials (DESIGN.md section 7)."""

from __future__ import annotations

import math

import pytest

from endogsim.evaluate.material_metrics import (
    bulk_modulus,
    material_relative_errors,
    relative_error,
    relative_error_log,
    scene_relative_errors,
    shear_modulus,
)


def test_moduli_formulas():
    assert shear_modulus(2600.0, 0.3) == pytest.approx(1000.0)
    assert bulk_modulus(3000.0, 0.25) == pytest.approx(2000.0)
    assert bulk_modulus(1.0, 0.5) == math.inf


def test_log_relative_error_known_values():
    # log10(1e4) = 4, log10(1e3) = 3: |4 - 3| / 3.
    assert relative_error_log(1e4, 1e3) == pytest.approx(1 / 3)
    assert relative_error_log(1e3, 1e3) == 0.0
    # A factor of 10 off at E = 1e5 Pa: 1 / 5.
    assert relative_error_log(1e6, 1e5) == pytest.approx(0.2)
    assert relative_error_log(1e4, 1e5) == pytest.approx(0.2)


def test_clamp_at_1e8():
    # Non-positive estimates are clamped at 1e-8 (log10 = -8) instead of failing.
    assert relative_error_log(0.0, 1e4) == pytest.approx(12 / 4)
    assert relative_error_log(-5.0, 1e4) == pytest.approx(12 / 4)
    # A true value of exactly 1 Pa (log10 = 0) is divided by the clamp, not by zero.
    assert math.isfinite(relative_error_log(10.0, 1.0))
    assert relative_error(0.1, 0.0) == pytest.approx(0.1 / 1e-8)


def test_poisson_relative_error_is_linear():
    assert relative_error(0.45, 0.4) == pytest.approx(0.125)
    assert relative_error(0.35, 0.4) == pytest.approx(0.125)


def test_object_errors_and_mean():
    E, nu = 5000.0, 0.4
    zero = material_relative_errors(E, nu, E, nu)
    assert all(v == 0.0 for v in zero.values())
    r = material_relative_errors(2 * E, 0.45, E, nu)
    G_t, G_e = E / 2.8, 2 * E / 2.9
    K_t, K_e = E / 0.6, 2 * E / 0.3
    assert r["E"] == pytest.approx(math.log10(2) / math.log10(E))
    assert r["nu"] == pytest.approx(0.125)
    assert r["G"] == pytest.approx(abs(math.log10(G_e) - math.log10(G_t)) / math.log10(G_t))
    assert r["K"] == pytest.approx(abs(math.log10(K_e) - math.log10(K_t)) / math.log10(K_t))
    assert r["mean"] == pytest.approx((r["E"] + r["nu"] + r["G"] + r["K"]) / 4)


def test_scene_mean_over_objects():
    truth = {"liver": (3000.0, 0.4), "gallbladder": (9000.0, 0.4)}
    est = {"liver": (3000.0, 0.4), "gallbladder": (900.0, 0.4), "probe": (2e11, 0.3)}
    s = scene_relative_errors(est, truth)
    assert set(s["objects"]) == {"liver", "gallbladder"}  # only objects with ground truth are scored
    assert s["objects"]["liver"]["mean"] == 0.0
    gb = s["objects"]["gallbladder"]
    assert s["re_mean"] == pytest.approx(gb["mean"] / 2)
    assert s["re_E"] == pytest.approx(gb["E"] / 2)
    assert s["re_mean"] == pytest.approx((s["re_E"] + s["re_nu"] + s["re_G"] + s["re_K"]) / 4)
    with pytest.raises(KeyError):
        scene_relative_errors({}, truth)
