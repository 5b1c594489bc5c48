"""Stability of explicit MPM: the CFL rule, the substeps it asks for, and the largest stable E.

    dt <= C dx / max(c_p, |v|_max),   c_p = sqrt(E (1 - nu) / ((1 + nu)(1 - 2 nu) rho))

with C the CFL number (``MPMConfig.cfl_number``). :func:`plan_substeps` chooses the substep count of a
frame from it (or refuses an explicit unstable dt, naming the limit); :func:`max_stable_E` bounds an
optimiser's search box.
"""

from __future__ import annotations

import math

import numpy as np

from endogsim.errors import MaterialError, SimulationError
from endogsim.physics.config import MPMConfig

__all__ = ["p_wave_speed", "check_materials", "plan_substeps", "max_stable_E"]


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
    dx = box_size / config.grid_res
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
    dx = box_size / config.grid_res
    return float((config.cfl_number * dx / dt) ** 2 * density * (1 + nu) * (1 - 2 * nu) / (1 - nu))
