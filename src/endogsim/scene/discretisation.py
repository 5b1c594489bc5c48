"""How finely a scene is simulated: grid and particle spacing from the tissue's thickness, substeps from CFL.

A thin tissue (a few millimetres behind its visible surface) bending under a tool is resolved only with
several grid cells across its thickness and at least two particles per cell and axis (fewer particles than
cells fracture numerically; DESIGN.md section 10). :func:`plan_discretisation` therefore sizes the cell from
the thinnest deformable object: dx = thickness / ``cells_across``, the particle spacing dx / 2, and the grid
as many cells as the sim box needs; the substep count per frame follows the CFL rule for the materials
(:func:`endogsim.physics.plan_substeps`). :func:`refine` gives the discretisation a benchmark's ground
truth is simulated at (2x the grid, half the spacing, 2x the substeps), and ``endogsim bench convergence``
measures how much the motion changes between the two.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from endogsim.errors import DataError
from endogsim.physics.config import MPMConfig
from endogsim.physics.stability import p_wave_speed, plan_substeps
from endogsim.scene.schema import SceneObject, SimSettings

__all__ = ["CELLS_ACROSS_THICKNESS", "MAX_GRID", "REFINE_PARTS", "at_materials", "plan_discretisation", "refine",
           "sim_settings"]

#: Grid cells across the thinnest tissue's thickness (measured by ``endogsim bench convergence``).
CELLS_ACROSS_THICKNESS = 3
#: The finest grid a plan may ask for (memory: 3 arrays of grid^3 per taped substep).
MAX_GRID = 256
#: What :func:`refine` can refine: the grid, the particle spacing, the substeps per frame.
REFINE_PARTS = ("grid", "particles", "substeps")


def sim_settings(objects: Sequence[SceneObject], box_size: float, grid: int, frame_dt: float, substeps: int,
                 max_speed: float = 0.0, cfl_number: float = 0.5,
                 particle_spacing: float | None = None) -> SimSettings:
    """The discretisation the simulator takes for ``grid`` cells over ``box_size`` metres with at least
    ``substeps`` per frame: :func:`endogsim.physics.plan_substeps` (CFL number ``cfl_number``, tool speed
    ``max_speed`` m/s) over the deformable objects whose materials are known, and the CFL number c_p dt / dx
    it reaches (NaN when no material is known: a real video, whose substeps follow its materials at run time)."""
    soft = [o for o in objects if not o.rigid and o.E is not None]
    cfg = MPMConfig(grid_res=int(grid), frame_dt=frame_dt, substeps_per_frame=int(substeps), cfl_number=cfl_number)
    if not soft:
        return SimSettings(grid=int(grid), dt=frame_dt / substeps, substeps=int(substeps), cfl=float("nan"),
                           particle_spacing=particle_spacing)
    E, nu, rho = (np.array([getattr(o, k) for o in soft], float) for k in ("E", "nu", "density"))
    n, dt = plan_substeps(cfg, box_size, E, nu, rho, max_speed)
    cfl = float(np.max(p_wave_speed(E, nu, rho))) * dt / (box_size / grid)
    return SimSettings(grid=int(grid), dt=float(dt), substeps=int(n), cfl=cfl, particle_spacing=particle_spacing)


def plan_discretisation(objects: Sequence[SceneObject], box_size: float, thickness: float, frame_dt: float,
                        max_speed: float = 0.0, cells_across: int = CELLS_ACROSS_THICKNESS,
                        min_substeps: int = 1, cfl_number: float = 0.5) -> SimSettings:
    """Identification's discretisation of a scene whose thinnest deformable object is ``thickness`` metres.

    Args:
        objects: the scene's objects (the deformable ones with known materials set the substeps).
        box_size: edge of the cubic sim box (metres).
        thickness: the thinnest deformable object's thickness (metres).
        frame_dt: time between frames (s).
        max_speed: fastest tool or particle (m/s), for the CFL rule.
        cells_across: grid cells across ``thickness``.
        min_substeps: the least substeps per frame.
    Returns:
        :class:`SimSettings` with grid = ceil(box / dx), dx = thickness / cells_across, particle spacing dx / 2.
    """
    if not (thickness > 0 and box_size > 0):
        raise DataError(f"thickness {thickness} m and sim box {box_size} m must be > 0")
    grid = math.ceil(box_size * cells_across / thickness)
    if grid > MAX_GRID:
        raise DataError(f"{cells_across} cells across {thickness * 1e3:.1f} mm of tissue need a {grid}^3 grid over "
                        f"the {box_size * 1e3:.0f} mm sim box, above {MAX_GRID}^3: use a smaller box or fewer cells")
    return sim_settings(objects, box_size, grid, frame_dt, min_substeps, max_speed, cfl_number,
                        particle_spacing=box_size / grid / 2)


def at_materials(settings: SimSettings, objects: Sequence[SceneObject], box_size: float, frame_dt: float,
                 max_speed: float = 0.0, cfl_number: float = 0.5) -> SimSettings:
    """``settings`` with the substeps the CFL rule takes for ``objects``' known materials (never fewer than
    ``settings.substeps``): what a simulation of those materials at ``settings`` runs at (the simulator plans
    the same way at run time). A ground truth is refined from its materials' plan, not from identification's
    settings, which are planned without them (:func:`endogsim.synth.scenes.scene_discretisations`)."""
    return sim_settings(objects, box_size, settings.grid, frame_dt, settings.substeps, max_speed, cfl_number,
                        particle_spacing=settings.particle_spacing)


def refine(settings: SimSettings, objects: Sequence[SceneObject], box_size: float, frame_dt: float,
           max_speed: float = 0.0, factor: float = 2, cfl_number: float = 0.5,
           parts: Sequence[str] = REFINE_PARTS) -> SimSettings:
    """``settings`` refined by ``factor``: the grid times ``factor`` (rounded), the particle spacing divided by
    the grid's ratio (the same particles per cell), and at least that ratio times the substeps (more if the
    new cell's CFL rule asks for them). A ``factor`` below 1 coarsens (identification's discretisation-error
    estimate, :mod:`endogsim.identify.uncertainty`). ``parts``: refine only these of :data:`REFINE_PARTS`
    (``endogsim bench convergence --refine``); a grid refined alone takes the substeps its CFL rule asks for."""
    if not factor > 0:
        raise DataError(f"refinement factor {factor} must be > 0")
    ratio = max(1, round(settings.grid * factor)) / settings.grid
    grid = round(settings.grid * ratio) if "grid" in parts else settings.grid
    if grid > MAX_GRID:
        raise DataError(f"grid {settings.grid} refined {factor:g}x is {grid}^3, above the {MAX_GRID}^3 the simulator "
                        "allows: use a smaller factor")
    substeps = max(1, math.ceil(settings.substeps * ratio - 1e-9)) if "substeps" in parts else settings.substeps
    spacing = settings.particle_spacing or box_size / settings.grid / 2
    return sim_settings(objects, box_size, grid, frame_dt, substeps, max_speed, cfl_number,
                        particle_spacing=spacing / ratio if "particles" in parts else spacing)
