"""Differentiable MLS-MPM simulator in NVIDIA Warp (DESIGN.md section 4).

Everything here takes and returns physical units (metres, seconds, kg, Pa) in world coordinates; the
sim-box conversion (E_sim = s^2 E, g_sim = s g) happens only in :mod:`endogsim.physics.units`.

Typical use::

    from endogsim.physics import (MPMConfig, Scenario, SimBox, Anchor, RigidCollider, ObjectMaterials,
                                  particles_from_gaussians, simulate, mpm_rollout, bind_gaussians,
                                  drive_gaussians)

    parts = particles_from_gaussians(gaussians, spacing=0.002, object_ids=[21], thickness=0.01, camera=cam)
    box = SimBox.around(parts.x, margin=0.3)
    scen = Scenario(box, gravity=(0, 9.81, 0), anchors=[Anchor(lo=..., hi=..., kind="fixed")],
                    colliders=[RigidCollider(positions=tool_xyz)])          # tool_xyz [T, Pc, 3]
    mats = ObjectMaterials.of(E=E_obj, nu=nu_obj, density=rho_obj, model="neo_hookean")   # per object id
    res = simulate(parts, mats, scen, MPMConfig(), num_frames=T)           # res.positions [T, P, 3]
    pos, F = mpm_rollout(parts, mats, scen, MPMConfig(), T, grad_mode="frame")   # differentiable in E, nu, rho
    binding = bind_gaussians(gaussians.means, gaussians.object_ids, parts)
    means, covs, sh = drive_gaussians(gaussians, binding, pos[t], F[t])     # render with covars=covs

Layout: :mod:`~endogsim.physics.config` (numerics and the world), :mod:`~endogsim.physics.materials`
(per-object material arrays), :mod:`~endogsim.physics.constitutive` (one module per constitutive model,
a name -> id registry), :mod:`~endogsim.physics.kernels` (the substep's Warp kernels and their structs),
:mod:`~endogsim.physics.engine` (static arrays, launches, taped segments), :mod:`~endogsim.physics.rollout`
(forward and differentiable rollouts), :mod:`~endogsim.physics.stability` (CFL rules),
:mod:`~endogsim.physics.particles` (particles from Gaussians, Gaussians that follow particles),
:mod:`~endogsim.physics.reference` (a pure-PyTorch reference solver for the tests).

Public API
----------
- :class:`SimBox` (lo, size): world cube covered by the grid; ``SimBox.around(points, margin)``.
- :class:`MPMConfig`: grid_res=50, frame_dt=5e-3 s, substeps_per_frame=25 (minimum), dt=None (auto from
  CFL; explicit unstable dt refused), cfl_number=0.5, damping (1/s), wall "slip"|"sticky", device "cpu"|"cuda".
- :class:`ObjectMaterials` (per object id: E Pa, nu, density kg/m^3, constitutive model, von Mises yield
  stress Pa); constitutive models: :func:`~endogsim.physics.constitutive.model_names`.
- :class:`Scenario` (box, gravity m/s^2, anchors, forces, colliders); :class:`Anchor` (world box and/or
  particle mask; "fixed" | "sticky" | "slip"); :class:`ExternalForce` (acceleration m/s^2 on a region over
  [t_start, t_end), or an impulse = velocity change); :class:`RigidCollider` (points [Pc,3] + transforms
  [T,4,4], or positions [T,Pc,3]; kinematic, sticky contact; ``holds``: grasped particles);
  :class:`MovingAnchor` (particles [N] held on paths [T,N,3]: a boundary that moves as observed).
- :class:`Particles` (x [P,3] m, volume [P] m^3, object_ids [P], v [P,3] m/s or None);
  ``Particles.box(lo, hi, spacing, object_id)``; :func:`particles_from_gaussians`.
- :func:`capsule_collider_points`: points filling a tool capsule for a :class:`RigidCollider`;
  :func:`capsule_collider` the collider itself (a pushing one grown by :data:`PUSH_CONTACT_CELLS`, 0 cells),
  :func:`grasped_particles` the tissue a grasper's jaws hold (``RigidCollider.holds``: held particles move
  rigidly with the instrument); :func:`bite_ring_distance` how far the tissue around a bite has come from
  it (a bite tears out past :data:`BITE_TEAR_CELLS`), :func:`bite_records` that for every grasp of a run.
- :func:`simulate` (particles, materials, scenario, config, num_frames, v0=None) -> :class:`SimResult`
  (positions [T,P,3] m, F [T,P,3,3], times [T] s, substeps, dt). Frame 0 = initial.
- :func:`mpm_rollout` (particles, materials, scenario, config, num_frames, grad_mode
  "last_substep"|"frame"|"full", x0=None, v0=None) -> (positions [T,P,3], F [T,P,3,3]), differentiable
  w.r.t. the materials' E, nu, density, x0 and v0. :class:`Simulator`: the same set-up rolled out many times.
- :func:`plan_substeps`, :func:`max_stable_E`, :func:`p_wave_speed`: the CFL rules.
- :func:`bind_gaussians`, :func:`drive_gaussians` (means, F Sigma F^T covariances, rotated SH),
  :func:`rotate_sh`, :func:`polar_rotation_torch`.

Errors: :class:`~endogsim.errors.MaterialError` for impossible materials, and
:class:`~endogsim.errors.SimulationError` for unstable dt (the message gives the limit), materials that
need more than ``max_substeps_per_frame``, or a diverged rollout (the message names the frame).
"""

from importlib import import_module

# Names load lazily (PEP 562): callers that need only the light modules (``modes``, ``units``) do not pull
# in Warp and the kernels.
_EXPORTS = {
    "GRAD_MODES": "modes", "GradMode": "modes",
    "Anchor": "config", "ExternalForce": "config", "MovingAnchor": "config", "MPMConfig": "config", "RigidCollider": "config",
    "Scenario": "config", "SETTLING_TOLERANCE": "config",
    "ObjectMaterials": "materials",
    "GaussianBinding": "particles", "Particles": "particles", "bind_gaussians": "particles",
    "BITE_TEAR_CELLS": "particles", "GRASP_MARGIN": "particles", "bite_records": "particles",
    "bite_ring_distance": "particles",
    "PUSH_CONTACT_CELLS": "particles", "capsule_collider": "particles",
    "capsule_collider_points": "particles",
    "grasped_particles": "particles", "drive_gaussians": "particles", "extrude_along_rays": "particles",
    "particles_from_gaussians": "particles", "rotate_sh": "particles",
    "polar_rotation_torch": "polar",
    "SimResult": "rollout", "Simulator": "rollout", "mpm_rollout": "rollout", "simulate": "rollout",
    "check_materials": "stability", "max_stable_E": "stability", "p_wave_speed": "stability",
    "plan_substeps": "stability",
    "SimBox": "units",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(f"endogsim.physics.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'endogsim.physics' has no attribute {name!r}")
