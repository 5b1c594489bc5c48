"""Relative error of identified materials (DESIGN.md section 7, as in VoMP).

For Young's modulus E, shear modulus G = E / (2 (1 + nu)) and bulk modulus K = E / (3 (1 - 2 nu)), all in Pa:

    RE(p) = |log10 p^ - log10 p| / |log10 p|       (values clamped at 1e-8 Pa before the log)

and for Poisson's ratio RE(nu) = |nu^ - nu| / |nu| (|nu| clamped at 1e-8). Each is reported per object;
the object's mean is the mean of the four; the scene's ``re_mean`` is the mean over objects of those means
(equal to the mean of the four scene-level means).

RE in log space hides size (RE 0.05 at E = 2.5 kPa is a factor 1.5 in E), so every report also gives
``e_rel_error`` = |E^ / E - 1| per object (in Pa terms) and its mean and median.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Mapping

__all__ = ["shear_modulus", "bulk_modulus", "relative_error_log", "relative_error", "material_relative_errors",
           "scene_relative_errors"]

CLAMP = 1e-8


def shear_modulus(E: float, nu: float) -> float:
    """G = E / (2 (1 + nu)) in Pa."""
    return E / (2.0 * (1.0 + nu))


def bulk_modulus(E: float, nu: float) -> float:
    """K = E / (3 (1 - 2 nu)) in Pa (infinite at nu = 0.5)."""
    d = 3.0 * (1.0 - 2.0 * nu)
    return math.inf if d <= 0 else E / d


def relative_error_log(est: float, true: float) -> float:
    """|log10 est - log10 true| / |log10 true|, both clamped at 1e-8 (Pa)."""
    le, lt = math.log10(max(est, CLAMP)), math.log10(max(true, CLAMP))
    return abs(le - lt) / max(abs(lt), CLAMP)


def relative_error(est: float, true: float) -> float:
    """|est - true| / |true| with |true| clamped at 1e-8."""
    return abs(est - true) / max(abs(true), CLAMP)


def material_relative_errors(E_est: float, nu_est: float, E_true: float, nu_true: float) -> dict[str, float]:
    """RE of E, nu, G, K and their mean for one object (E in Pa)."""
    out = {
        "E": relative_error_log(E_est, E_true),
        "nu": relative_error(nu_est, nu_true),
        "G": relative_error_log(shear_modulus(E_est, nu_est), shear_modulus(E_true, nu_true)),
        "K": relative_error_log(bulk_modulus(E_est, nu_est), bulk_modulus(E_true, nu_true)),
    }
    out["mean"] = sum(out.values()) / 4.0
    out["e_rel_error"] = relative_error(E_est, E_true)
    return out


def scene_relative_errors(estimated: Mapping[str, tuple[float, float]], truth: Mapping[str, tuple[float, float]]) -> dict:
    """Per-object and scene-mean RE.

    Args:
        estimated: object name -> (E Pa, nu) identified.
        truth: object name -> (E Pa, nu) ground truth (only these objects are scored: the deformable ones).
    Returns:
        {"objects": {name: {E, nu, G, K, mean, e_rel_error}}, "re_E", "re_nu", "re_G", "re_K", "re_mean",
        "e_rel_error_mean", "e_rel_error_median"}.
    """
    objs = {}
    for name, (E_t, nu_t) in truth.items():
        if name not in estimated:
            raise KeyError(f"no identified material for object {name!r}")
        E_e, nu_e = estimated[name]
        objs[name] = material_relative_errors(E_e, nu_e, E_t, nu_t)
    out: dict = {"objects": objs}
    for k in ("E", "nu", "G", "K"):
        out[f"re_{k}"] = sum(o[k] for o in objs.values()) / max(len(objs), 1)
    out["re_mean"] = sum(o["mean"] for o in objs.values()) / max(len(objs), 1)
    errs = sorted(o["e_rel_error"] for o in objs.values())
    out["e_rel_error_mean"] = sum(errs) / max(len(errs), 1)
    out["e_rel_error_median"] = statistics.median(errs) if errs else math.nan
    return out
