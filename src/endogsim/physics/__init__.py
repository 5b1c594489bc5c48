"""Differentiable MLS-MPM simulator in NVIDIA Warp (DESIGN.md section 4).

Everything here takes and returns physical units (metres, seconds, kg, Pa) in world coordinates; the
sim-box conversion (E_sim = s^2 E, g_sim = s g) happens only in :mod:`endogsim.physics.units`.

Typical use::

    from endogsim.physics import (MPMConfig, Scenario, SimBox, Anchor, RigidCollider, ExternalForce,
                                  Particles, particles_from_gaussians, simulate, mpm_rollout,
                                  bind_gaussians, drive_gaussians)

    parts = particles_from_gaussians(gaussians, spacing=0.002, object_ids=[21], thickness=0.01, camera=cam)
    box = SimBox.around(parts.x, margin=0.3)
    scen = Scenario(box, gravity=(0, 9.81, 0), anchors=[Anchor(lo=..., hi=..., kind="fixed")],
                    colliders=[RigidCollider(positions=tool_xyz)])          # tool_xyz [T, Pc, 3]
    res = simulate(parts, E=E_obj, nu=nu_obj, density=rho_obj, scenario=scen, config=MPMConfig(),
                   num_frames=T)                                           # res.positions [T, P, 3]
    pos, F = mpm_rollout(parts, log10_E, nu, rho, scen, MPMConfig(), T, grad_mode="frame")
    binding = bind_gaussians(gaussians.means, gaussians.object_ids, parts)
    means, covs, sh = drive_gaussians(gaussians, binding, pos[t], F[t])     # render with covars=covs

Per-object material arrays (E, nu, density, log10_E) are indexed by object id (length max_id + 1, as
:meth:`endogsim.materials.field.MaterialField.per_object` returns them); only ids carried by particles
are read.

Public API
----------
- :class:`SimBox` (lo, size): world cube covered by the grid; ``SimBox.around(points, margin)``.
- :class:`MPMConfig`: grid_res=50, frame_dt=5e-3 s, substeps_per_frame=25 (minimum), dt=None (auto from
  CFL; explicit unstable dt refused), material_model "fixed_corotated"|"neo_hookean", yield_stress (Pa,
  von Mises) or None, cfl_number=0.5, damping (1/s), wall "slip"|"sticky", device "cpu"|"cuda".
- :class:`Scenario` (box, gravity m/s^2, anchors, forces, colliders); :class:`Anchor` (world box and/or
  particle mask; "fixed" | "sticky" | "slip"); :class:`ExternalForce` (acceleration m/s^2 on a region over
  [t_start, t_end), or an impulse = velocity change); :class:`RigidCollider` (points [Pc,3] + transforms
  [T,4,4], or positions [T,Pc,3]; kinematic, sticky contact).
- :class:`Particles` (x [P,3] m, volume [P] m^3, object_ids [P], v [P,3] m/s or None);
  ``Particles.box(lo, hi, spacing, object_id)``; :func:`particles_from_gaussians`.
- :func:`capsule_collider_points`: points filling a tool capsule for a :class:`RigidCollider`.
- :func:`simulate` (particles, E [M] Pa, nu [M], density [M] kg/m^3, scenario, config, num_frames, v0=None)
  -> :class:`SimResult` (positions [T,P,3] m, F [T,P,3,3], times [T] s, substeps, dt). Frame 0 = initial.
- :func:`mpm_rollout` (particles, log10_E [M], nu [M], density [M], scenario, config, num_frames,
  grad_mode "last_substep"|"frame"|"full", x0=None, v0=None) -> (positions [T,P,3], F [T,P,3,3]),
  differentiable w.r.t. log10_E, nu, density, x0 and v0.
- :func:`plan_substeps`, :func:`max_stable_E`, :func:`p_wave_speed`: the CFL rules.
- :func:`bind_gaussians`, :func:`drive_gaussians` (means, F Sigma F^T covariances, rotated SH),
  :func:`rotate_sh`, :func:`polar_rotation`.

Errors: :class:`~endogsim.errors.MaterialError` for impossible materials, and
:class:`~endogsim.errors.SimulationError` for unstable dt (the message gives the limit), materials that
need more than ``max_substeps_per_frame``, or a diverged rollout (the message names the frame).
"""

from endogsim.physics.config import Anchor, ExternalForce, MPMConfig, RigidCollider, Scenario
from endogsim.physics.particles import (
    GaussianBinding,
    Particles,
    bind_gaussians,
    capsule_collider_points,
    drive_gaussians,
    extrude_along_rays,
    particles_from_gaussians,
    polar_rotation,
    rotate_sh,
)
from endogsim.physics.rollout import (
    SimResult,
    max_stable_E,
    mpm_rollout,
    p_wave_speed,
    plan_substeps,
    simulate,
)
from endogsim.physics.units import SimBox

__all__ = [
    "Anchor", "ExternalForce", "GaussianBinding", "MPMConfig", "Particles", "RigidCollider", "Scenario",
    "SimBox", "SimResult", "bind_gaussians", "capsule_collider_points", "drive_gaussians", "extrude_along_rays", "max_stable_E",
    "mpm_rollout", "p_wave_speed", "particles_from_gaussians", "plan_substeps", "polar_rotation",
    "rotate_sh", "simulate",
]
