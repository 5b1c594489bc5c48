"""Constitutive models per object: every registered model's Warp stress against its PyTorch twin, the
Warp simulator against the pure-PyTorch reference for every model, and a scene mixing models (and
plasticity) per object, each object matching a single-model run of itself."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

from endogsim.errors import MaterialError
from endogsim.materials.field import MaterialField, MaterialRecord
from endogsim.physics import Anchor, MPMConfig, ObjectMaterials, Particles, RigidCollider, Scenario, SimBox, simulate
from endogsim.physics import kernels as K
from endogsim.physics.constitutive import MODELS, model_id, model_names, stress_torch
from endogsim.physics.polar import newton_polar_rotation, rotation_with_adjoint
from endogsim.warp_runtime import init_warp

BOX = SimBox((0.0, 0.0, 0.0), 0.1)


@wp.kernel
def _stress(model: wp.array(dtype=wp.int32), F: wp.array(dtype=wp.mat33), mu: float, lam: float,
            out: wp.array(dtype=wp.mat33)):
    i = wp.tid()
    R = wp.identity(n=3, dtype=float)
    if K.uses_rotation(model[i]) != 0:
        R = rotation_with_adjoint(F[i], newton_polar_rotation(F[i]))  # as particle_momentum does
    out[i] = K.kirchhoff_stress(model[i], F[i], R, mu, lam)


def _random_F(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    F = torch.eye(3) + 0.25 * torch.randn(n, 3, 3, generator=g)
    return torch.where(torch.linalg.det(F)[:, None, None] > 0.2, F, torch.eye(3).expand(n, 3, 3))


@pytest.mark.parametrize("name", model_names())
def test_warp_stress_matches_the_pytorch_twin(name):
    init_warp()
    F = _random_F(64)
    ids = torch.full((64,), model_id(name))
    mu, lam = 3.0e3, 9.0e3
    out = wp.zeros(64, dtype=wp.mat33)
    wp.launch(_stress, dim=64, inputs=[wp.array(ids.numpy().astype(np.int32), dtype=wp.int32),
                                       wp.array(F.numpy(), dtype=wp.mat33), mu, lam, out])
    ref = stress_torch(ids, F.double(), torch.full((64,), mu, dtype=torch.float64), torch.full((64,), lam, dtype=torch.float64))
    np.testing.assert_allclose(out.numpy(), ref.numpy(), rtol=2e-4, atol=2e-4 * mu)
    # Every model is stress-free at rest and, for small strains, linear elasticity with (mu, lambda).
    eps = 1e-4 * torch.tensor([[1.0, 0.3, 0.0], [0.3, -0.5, 0.2], [0.0, 0.2, 0.7]], dtype=torch.float64)
    one = torch.full((1,), model_id(name))
    rest = stress_torch(one, torch.eye(3, dtype=torch.float64)[None], torch.tensor([mu]).double(), torch.tensor([lam]).double())
    assert rest.abs().max() < 1e-9
    lin = stress_torch(one, (torch.eye(3, dtype=torch.float64) + eps)[None], torch.tensor([mu]).double(), torch.tensor([lam]).double())[0]
    hooke = 2 * mu * eps + lam * torch.trace(eps) * torch.eye(3, dtype=torch.float64)
    assert (lin - hooke).abs().max() < 1e-3 * hooke.abs().max()


def test_registry_refuses_unknown_and_duplicate_names():
    with pytest.raises(MaterialError, match="not simulated"):
        model_id("hookean_foam")
    from endogsim.physics.constitutive import register_model

    with pytest.raises(MaterialError, match="already registered"):
        register_model(MODELS[0])
    with pytest.raises(MaterialError, match="not one of"):
        MaterialRecord(name="x", object_id=1, klass="liver", model="hookean_foam", E=1e3, nu=0.4, density=1000.0)


def _pushed_block(model: str):
    """An elastic block pushed sideways by a moving line collider, in the Warp solver and in the reference."""
    from endogsim.physics.reference import Capsule, MPMProblem, run_mpm

    E, nu, rho = 2e4, 0.3, 1000.0
    parts = Particles.box((0.04, 0.04, 0.04), (0.06, 0.06, 0.06), 0.002)
    T, r = 3, 0.003
    a, b = np.array([0.0365, 0.05, 0.035]), np.array([0.0365, 0.05, 0.065])
    offsets = np.zeros((T, 3))
    offsets[:, 0] = np.linspace(0.0, 0.003, T)
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    P = len(parts)
    ref = run_mpm(MPMProblem(
        x=parts.x.double().numpy(), vol=parts.volume.double().numpy(), mu=np.full(P, mu), lam=np.full(P, lam),
        density=np.full(P, rho), anchored=np.zeros(P, bool), box_lo=np.zeros(3), box_size=0.1, grid=32,
        dt=2e-4, substeps=25, frames=T, gravity=np.zeros(3), tools=[Capsule(a, b, r, offsets)],
        model=np.full(P, model_id(model))))
    line = torch.as_tensor(np.linspace(a, b, 301))
    traj = line[None] + torch.as_tensor(offsets)[:, None]
    res = simulate(parts, ObjectMaterials.of([E], [nu], [rho], model),
                   Scenario(BOX, colliders=[RigidCollider(positions=traj, radius=r)]), MPMConfig(grid_res=32), T)
    return parts, res, ref


@pytest.mark.parametrize("name", model_names())
def test_every_model_matches_the_pure_pytorch_reference_solver(name):
    parts, res, ref = _pushed_block(name)
    disp_ref = torch.as_tensor(ref.x[-1]) - parts.x.double()
    disp = res.positions[-1].double() - parts.x.double()
    assert disp_ref.abs().max() > 5e-4  # the block was pushed
    assert (disp - disp_ref).abs().max() < 2e-3 * disp_ref.abs().max(), (disp - disp_ref).abs().max()
    assert (res.F[-1].double() - torch.as_tensor(ref.F[-1])).abs().max() < 2e-4


def _two_blocks():
    """Two blocks 2 cm apart (no shared grid node), each pressed by its own plate, held at the base."""
    a = Particles.box((0.02, 0.02, 0.04), (0.04, 0.04, 0.06), 0.0015, object_id=1)
    b = Particles.box((0.06, 0.02, 0.04), (0.08, 0.04, 0.06), 0.0015, object_id=2)
    T = 6
    colliders = []
    for x0 in (0.03, 0.07):
        yy, zz = torch.meshgrid(torch.linspace(x0 - 0.012, x0 + 0.012, 11), torch.linspace(0.035, 0.065, 13), indexing="ij")
        plate = torch.stack([yy, torch.full_like(yy, 0.0435), zz], -1).reshape(-1, 3).double()
        pos = plate[None].repeat(T, 1, 1)
        pos[:, :, 1] -= torch.linspace(0.0, 0.006, T, dtype=torch.float64)[:, None]
        colliders.append(RigidCollider(positions=pos, radius=0.003))
    base = Anchor(lo=(0, 0, 0), hi=(0.1, 0.0211, 0.1))
    return a, b, base, colliders, T


def test_objects_with_different_models_match_their_single_model_runs():
    a, b, base, colliders, T = _two_blocks()
    # object 1: neo-Hookean; object 2: fixed corotated with von Mises plasticity (it yields under the plate)
    field = MaterialField([
        MaterialRecord(name="liver", object_id=1, klass="liver", model="neo_hookean", E=2e4, nu=0.4, density=1060.0),
        MaterialRecord(name="fat", object_id=2, klass="fat", model="fixed_corotated", E=1e4, nu=0.3, density=950.0,
                       yield_stress=400.0),
        MaterialRecord(name="plate", object_id=3, klass="instrument", model="rigid", rigid=True, E=2e11, nu=0.3,
                       density=7850.0),
    ])
    mats = field.simulator_materials()
    assert mats.model[1] != mats.model[2]
    cfg = MPMConfig(grid_res=40, substeps_per_frame=32)  # above either object's CFL need: one dt for all runs
    both = simulate(Particles.concat([a, b]), mats, Scenario(BOX, anchors=[base], colliders=colliders), cfg, T)
    alone_a = simulate(a, mats, Scenario(BOX, anchors=[base], colliders=colliders[:1]), cfg, T)
    alone_b = simulate(b, mats, Scenario(BOX, anchors=[base], colliders=colliders[1:]), cfg, T)
    assert both.substeps == alone_a.substeps == alone_b.substeps
    na = len(a)
    for alone, sl in ((alone_a, slice(0, na)), (alone_b, slice(na, None))):
        moved = (alone.positions[-1] - alone.positions[0]).norm(dim=-1).max()
        assert moved > 2e-3  # the plate pressed the block
        assert (both.positions[:, sl] - alone.positions).abs().max() < 1e-6 * 0.1
        assert (both.F[:, sl] - alone.F).abs().max() < 1e-5
    # The materials did reach the kernel: the other model (or no plasticity) moves the particles differently.
    swapped = field.simulator_materials()
    swapped.model[1] = model_id("fixed_corotated")
    other = simulate(a, swapped, Scenario(BOX, anchors=[base], colliders=colliders[:1]), cfg, T)
    assert (other.F[-1] - alone_a.F[-1]).abs().max() > 1e-3
    elastic = field.simulator_materials()
    elastic.yield_stress[2] = 0.0
    other = simulate(b, elastic, Scenario(BOX, anchors=[base], colliders=colliders[1:]), cfg, T)
    assert (other.F[-1] - alone_b.F[-1]).abs().max() > 1e-3


def test_a_particle_of_a_rigid_object_is_refused():
    a, _, base, colliders, T = _two_blocks()
    field = MaterialField([MaterialRecord(name="tool", object_id=1, klass="instrument", model="rigid", rigid=True,
                                          E=2e11, nu=0.3, density=7850.0)])
    with pytest.raises(MaterialError, match="rigid or fluid"):
        simulate(a, field.simulator_materials(), Scenario(BOX), MPMConfig(grid_res=32), 2)


def test_stvk_uniaxial_stretch_matches_the_closed_form():
    # F = diag(l, 1, 1): Green strain e = (l^2 - 1) / 2 along x, S_xx = (2 mu + lambda) e, S_yy = lambda e,
    # tau = F S F^T: tau_xx = l^2 S_xx, tau_yy = tau_zz = lambda e.
    mu, lam, stretch = 3.0e3, 9.0e3, 1.2
    F = torch.diag(torch.tensor([stretch, 1.0, 1.0], dtype=torch.float64))[None]
    tau = stress_torch(torch.tensor([model_id("stvk")]), F, torch.tensor([mu]).double(), torch.tensor([lam]).double())[0]
    e = (stretch ** 2 - 1) / 2
    expect = torch.diag(torch.tensor([stretch ** 2 * (2 * mu + lam) * e, lam * e, lam * e], dtype=torch.float64))
    assert torch.allclose(tau, expect, rtol=1e-12)
