"""World <-> simulation-box units: the ONE place where physical quantities are converted.

The simulator runs in a unit cube [0, 1]^3 (the sim box) covered by the background grid. A similarity
transform maps world metres to it: x_sim = s (x_world - lo) with s = 1 / size. With density and time
left unchanged, elastodynamics (rho a = div sigma) keeps its solutions when

    lengths and velocities scale by s,   E_sim = s^2 E_phys (and any stress),   g_sim = s g,

because a_sim = s a_world and div_sim = div_world / s. Everything that enters or leaves
:mod:`endogsim.physics` is in metres, seconds, kg and Pa; only the kernels see sim units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from endogsim.errors import SimulationError


@dataclass(frozen=True)
class SimBox:
    """An axis-aligned cube in world space that the simulation grid covers.

    Attributes:
        lo: (x, y, z) world position of the cube's lowest corner (metres).
        size: edge length of the cube (metres).
    """

    lo: tuple[float, float, float]
    size: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.size) and self.size > 0):
            raise SimulationError(f"SimBox size {self.size} m must be finite and > 0")
        if len(self.lo) != 3 or not all(math.isfinite(float(v)) for v in self.lo):
            raise SimulationError(f"SimBox lo {self.lo} must be 3 finite numbers (metres)")

    @staticmethod
    def around(points: torch.Tensor | np.ndarray, margin: float = 0.25) -> "SimBox":
        """The smallest cube holding ``points`` [N, 3] (metres) with ``margin`` (fraction of the extent) on each side.

        The margin leaves room for the deformation and for the grid's wall padding (3 cells).
        """
        p = torch.as_tensor(points, dtype=torch.float64).reshape(-1, 3)
        if p.numel() == 0 or not torch.isfinite(p).all():
            raise SimulationError("SimBox.around needs a non-empty set of finite points")
        pmin, pmax = p.min(0).values, p.max(0).values
        extent = float((pmax - pmin).max().clamp_min(1e-6))
        size = extent * (1.0 + 2.0 * margin)
        centre = (pmin + pmax) / 2
        lo = centre - size / 2
        return SimBox((float(lo[0]), float(lo[1]), float(lo[2])), size)

    @property
    def scale(self) -> float:
        """s: sim units per metre."""
        return 1.0 / self.size

    def _lo(self, like: torch.Tensor) -> torch.Tensor:
        return torch.tensor(self.lo, dtype=like.dtype, device=like.device)

    # Positions and displacements.
    def to_sim(self, x: torch.Tensor) -> torch.Tensor:
        """World points [..., 3] (m) -> sim coordinates [..., 3] (unit cube)."""
        return (x - self._lo(x)) * self.scale

    def to_world(self, x: torch.Tensor) -> torch.Tensor:
        """Sim coordinates [..., 3] -> world points [..., 3] (m)."""
        return x * self.size + self._lo(x)

    # Vectors (velocity, acceleration), volumes and moduli.
    def vec_to_sim(self, v: torch.Tensor | np.ndarray | float):
        """A velocity (m/s), acceleration (m/s^2) or length (m) -> sim units (scale by s)."""
        return v * self.scale

    def vec_to_world(self, v):
        return v * self.size

    def volume_to_sim(self, vol):
        """Volume (m^3) -> sim units (s^3)."""
        return vol * self.scale**3

    def modulus_to_sim(self, E):
        """Young's modulus or a stress (Pa) -> sim units: E_sim = s^2 E."""
        return E * self.scale**2

    def modulus_to_world(self, E_sim):
        return E_sim * self.size**2
