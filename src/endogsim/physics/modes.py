"""Names shared by the simulator and its callers, importable without the simulator (no Warp, no torch)."""

from __future__ import annotations

from typing import Literal, get_args

__all__ = ["GradMode", "GRAD_MODES"]

#: Gradient modes of :func:`endogsim.physics.mpm_rollout` (see :mod:`endogsim.physics.rollout`).
GradMode = Literal["last_substep", "frame", "full"]
GRAD_MODES: tuple[str, ...] = get_args(GradMode)
