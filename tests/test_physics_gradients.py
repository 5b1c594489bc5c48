"""Gradients of the Warp MPM rollout against central finite differences.

The scene is small (216 particles, 16^3 grid) but dynamic: a block thrown down at 0.5 m/s onto its own
fixed bottom layer under gravity, so E, nu and density all change the trajectory a lot within 3 frames
(E = 1e5 Pa in a 1 m box: the P wave crosses the block in about one frame). The loss is a random
projection of the displacements plus a term in F, in float64 on the PyTorch side; simulation is float32,
so steps are chosen large enough (0.5 % relative) that rounding noise stays far below 1 %, and small
enough that the O(h^2) error does too (checked: halving h changes the FD by < 0.1 %).
"""

from __future__ import annotations

import pytest
import torch

from endogsim.physics import Anchor, MPMConfig, ObjectMaterials, Particles, Scenario, SimBox, mpm_rollout

T = 4
BOX = SimBox((0.0, 0.0, 0.0), 1.0)


def _setup(model: str, plastic: bool = False):
    parts = Particles.box((0.35, 0.3, 0.35), (0.65, 0.6, 0.65), 0.05)
    scen = Scenario(BOX, gravity=(0.0, -9.81, 0.0), anchors=[Anchor(lo=(0, 0, 0), hi=(1, 0.36, 1), kind="fixed")])
    cfg = MPMConfig(grid_res=16, frame_dt=0.01, substeps_per_frame=10)
    g = torch.Generator().manual_seed(0)
    w = torch.randn(T, len(parts), 3, generator=g, dtype=torch.float64)
    v0 = torch.zeros(len(parts), 3)
    v0[:, 1] = -0.5
    return parts, scen, cfg, w, v0, (model, [2e3] if plastic else None)


def _materials(setup, lE, nu, rho):
    model, yield_stress = setup[5]
    return ObjectMaterials.of(10.0 ** lE, nu, rho, model, yield_stress=yield_stress)


def _loss(setup, lE, nu, rho, mode, x0=None, v0=None, frames=T):
    parts, scen, cfg, w, v0_default, _ = setup
    v0 = v0_default if v0 is None else v0
    pos, F = mpm_rollout(parts, _materials(setup, lE, nu, rho), scen, cfg, frames, grad_mode=mode, x0=x0, v0=v0)
    return 10.0 * (w[1:frames] * (pos[1:].double() - parts.x.double())).sum() + 0.1 * (F[1:].double() ** 2).sum()


def _params():
    return (torch.tensor([5.0], dtype=torch.float64, requires_grad=True),
            torch.tensor([0.3], dtype=torch.float64, requires_grad=True),
            torch.tensor([1000.0], dtype=torch.float64, requires_grad=True))


def _fd(setup, params, which, h, mode, frames=T):
    vals = []
    with torch.no_grad():
        for sgn in (1.0, -1.0):
            p = [a.detach().clone() for a in params]
            p[which] += sgn * h
            vals.append(float(_loss(setup, *p, mode=mode, frames=frames)))
    return (vals[0] - vals[1]) / (2 * h)


STEPS = (0.01, 0.003, 5.0)  # log10 E, nu, density (kg/m^3)


@pytest.mark.parametrize("model", ["neo_hookean", "fixed_corotated"])
def test_full_mode_matches_finite_differences(model):
    setup = _setup(model)
    params = _params()
    _loss(setup, *params, mode="full").backward()
    for i, name in enumerate(("log10_E", "nu", "density")):
        fd = _fd(setup, params, i, STEPS[i], "full")
        ad = float(params[i].grad)
        assert abs(ad - fd) <= 0.01 * abs(fd), (name, ad, fd)


@pytest.mark.gpu
def test_cuda_rollout_and_gradients_equal_the_cpu_ones():
    """The rollout and its hand-written adjoints run on CUDA as on the CPU: the same loss and gradients
    (float32 sums in another order: a relative 1e-3)."""
    import dataclasses

    import warp as wp

    from endogsim.warp_runtime import init_warp

    init_warp()
    if not wp.is_cuda_available():
        pytest.skip("CUDA is not available")
    parts, scen, cfg, *rest = _setup("neo_hookean")
    results = {}
    for device in ("cpu", "cuda"):
        params = _params()
        loss = _loss((parts, scen, dataclasses.replace(cfg, device=device), *rest), *params, mode="full")
        loss.backward()
        results[device] = [float(loss.detach())] + [float(p.grad) for p in params]
    for name, a, b in zip(("loss", "log10_E", "nu", "density"), results["cpu"], results["cuda"]):
        assert abs(a - b) <= 1e-3 * abs(a), (name, a, b)


def test_frame_mode_matches_finite_differences_of_one_frame():
    # With one simulated frame, frame mode is the exact gradient, and it equals full mode.
    setup = _setup("fixed_corotated")
    params = _params()
    _loss(setup, *params, mode="frame", frames=2).backward()
    grads = [float(p.grad) for p in params]
    for i in range(3):
        fd = _fd(setup, params, i, STEPS[i], "frame", frames=2)
        assert abs(grads[i] - fd) <= 0.01 * abs(fd), (i, grads[i], fd)
    params_full = _params()
    _loss(setup, *params_full, mode="full", frames=2).backward()
    for g, p in zip(grads, params_full):
        assert abs(g - float(p.grad)) <= 1e-6 * abs(g)


def test_initial_state_gradients_match_finite_differences():
    setup = _setup("neo_hookean")
    parts, v0 = setup[0], setup[4]
    lE, nu, rho = (a.detach() for a in _params())
    g = torch.Generator().manual_seed(1)
    dv, dx = torch.randn(v0.shape, generator=g), torch.randn(parts.x.shape, generator=g)
    x0 = parts.x.clone().requires_grad_(True)
    v0r = v0.clone().requires_grad_(True)
    _loss(setup, lE, nu, rho, "full", x0=x0, v0=v0r).backward()
    with torch.no_grad():
        hv, hx = 0.01, 1e-3
        fd_v = (_loss(setup, lE, nu, rho, "full", v0=v0 + hv * dv) - _loss(setup, lE, nu, rho, "full", v0=v0 - hv * dv)) / (2 * hv)
        fd_x = (_loss(setup, lE, nu, rho, "full", x0=parts.x + hx * dx) - _loss(setup, lE, nu, rho, "full", x0=parts.x - hx * dx)) / (2 * hx)
    ad_v = float((v0r.grad.double() * dv.double()).sum())
    ad_x = float((x0.grad.double() * dx.double()).sum())
    assert abs(ad_v - float(fd_v)) <= 0.01 * abs(float(fd_v)), (ad_v, float(fd_v))
    assert abs(ad_x - float(fd_x)) <= 0.01 * abs(float(fd_x)), (ad_x, float(fd_x))


def test_last_substep_gradient_sign_matches_near_the_optimum():
    setup = _setup("fixed_corotated")
    parts, scen, cfg, _, v0, _ = setup
    with torch.no_grad():
        target, _ = mpm_rollout(parts, _materials(setup, torch.tensor([5.0]), [0.3], [1000.0]), scen, cfg, T, v0=v0)
    results = {}
    for lE0 in (4.95, 5.05):
        for mode in ("last_substep", "full"):
            lE = torch.tensor([lE0], dtype=torch.float64, requires_grad=True)
            pos, _ = mpm_rollout(parts, _materials(setup, lE, [0.3], [1000.0]), scen, cfg, T, grad_mode=mode, v0=v0)
            ((pos[1:].double() - target[1:].double()) ** 2).sum().backward()
            results[(lE0, mode)] = float(lE.grad)
    assert results[(4.95, "full")] < 0 < results[(5.05, "full")]
    assert results[(4.95, "last_substep")] < 0 < results[(5.05, "last_substep")]
    # The paper's mode sees a much smaller gradient than the true one (DESIGN.md section 4).
    assert abs(results[(5.05, "last_substep")]) < abs(results[(5.05, "full")])


def test_plastic_rollout_gradients_are_finite():
    setup = _setup("fixed_corotated", plastic=True)
    params = _params()
    _loss(setup, *params, mode="frame").backward()
    assert all(torch.isfinite(p.grad).all() and float(p.grad.abs()) > 0 for p in params)


def _transfer_case(seed: int = 0, P: int = 60, n: int = 12):
    """Random particles inside an n^3 grid (sim units), with random transfer quantities and grid velocities."""
    import warp as wp

    from endogsim.physics import kernels as K
    from endogsim.physics.engine import alloc_transfer
    from endogsim.warp_runtime import init_warp

    init_warp()
    g = torch.Generator().manual_seed(seed)
    x = 0.3 + 0.4 * torch.rand(P, 3, generator=g)
    mass, momentum = torch.rand(P, generator=g) + 0.5, torch.randn(P, 3, generator=g)
    affine = torch.randn(P, 3, 3, generator=g)
    grid_v = torch.randn(n, n, n, 3, generator=g)
    d = K.Domain()
    d.n, d.inv_dx, d.pad, d.sticky_walls, d.x_lo, d.x_hi = n, float(n), 2, 1, 0.0, 1.0
    d.bc_kind = wp.zeros((n,) * 3, dtype=wp.int32)
    d.bc_normal = wp.zeros((n,) * 3, dtype=wp.vec3)
    d.bc_friction = wp.zeros((n,) * 3, dtype=float)
    d.gravity = wp.vec3(0.0)
    tr = alloc_transfer(P, "cpu", False)
    wp.copy(tr.mass, wp.from_torch(mass))
    wp.copy(tr.momentum, wp.from_torch(momentum, dtype=wp.vec3))
    wp.copy(tr.affine, wp.from_torch(affine, dtype=wp.mat33))
    grid = K.GridState()
    grid.m, grid.mv = wp.zeros((n,) * 3, dtype=float), wp.zeros((n,) * 3, dtype=wp.vec3)
    grid.v = wp.from_torch(grid_v.contiguous(), dtype=wp.vec3)
    return g, x, mass, momentum, affine, grid_v, d, tr, grid


def test_hand_written_transfer_adjoints_match_pytorch_autograd():
    """The hand-written adjoints of p2g's scatter and g2p's gather (physics/transfer_adjoints.py) equal
    PyTorch's autograd (float64) of the same transfers written with the reference solver's stencil, for
    random particles, transfer quantities, grid velocities and output adjoints."""
    import warp as wp

    from endogsim.physics import kernels as K
    from endogsim.physics import transfer_adjoints as A
    from endogsim.physics.reference import _g2p, _p2g, _weights

    g, x, mass, momentum, affine, grid_v, d, tr, grid = _transfer_case()
    P, n = x.shape[0], grid_v.shape[0]
    adj_mv, adj_m = torch.randn(n, n, n, 3, generator=g), torch.randn(n, n, n, generator=g)
    adj_v, adj_C = torch.randn(P, 3, generator=g), torch.randn(P, 3, 3, generator=g)
    xw = wp.from_torch(x, dtype=wp.vec3)

    # PyTorch: the same two transfers, differentiated by autograd.
    xd, md, pd, ad, vd = (t.double().requires_grad_() for t in (x, mass, momentum, affine, grid_v))
    stencil = _weights(xd * n)
    gm, gmv = _p2g(md, pd, ad, n, 1.0 / n, stencil)
    scatter_loss = (gmv * adj_mv.reshape(-1, 3).double()).sum() + (gm * adj_m.reshape(-1).double()).sum()
    ref_scatter = torch.autograd.grad(scatter_loss, (xd, md, pd, ad), retain_graph=True)
    v, C = _g2p(vd.reshape(-1, 3), n, float(n), stencil)
    gather_loss = (v * adj_v.double()).sum() + (C * adj_C.double()).sum()
    ref_gather = torch.autograd.grad(gather_loss, (xd, vd))

    # Warp: the forward gather (the adjoint reads the gathered velocity), then both adjoints.
    wp.launch(K.g2p_gather, dim=P, inputs=[xw, d, grid, tr], device="cpu")
    assert torch.allclose(wp.to_torch(tr.v).double(), v, atol=1e-5)
    a_x, a_mass = wp.zeros(P, dtype=wp.vec3), wp.zeros(P, dtype=float)
    a_mom, a_aff = wp.zeros(P, dtype=wp.vec3), wp.zeros(P, dtype=wp.mat33)
    wp.launch(A.p2g_scatter_adjoint, dim=P, device="cpu", inputs=[
        xw, tr, d, wp.from_torch(adj_mv.contiguous(), dtype=wp.vec3), wp.from_torch(adj_m.contiguous()),
        a_x, a_mass, a_mom, a_aff])
    got_scatter = [wp.to_torch(a).clone() for a in (a_x, a_mass, a_mom, a_aff)]
    a_x.zero_()
    a_v, a_C = wp.from_torch(adj_v.clone(), dtype=wp.vec3), wp.from_torch(adj_C.clone(), dtype=wp.mat33)
    a_grid_v = wp.zeros((n,) * 3, dtype=wp.vec3)
    wp.launch(A.g2p_gather_adjoint, dim=P, device="cpu", inputs=[xw, d, grid, tr, a_v, a_C, a_grid_v, a_x])
    got_gather = [wp.to_torch(a_x), wp.to_torch(a_grid_v)]

    for name, got, ref in zip(("x (scatter)", "mass", "momentum", "affine", "x (gather)", "grid v"),
                              got_scatter + got_gather, list(ref_scatter) + list(ref_gather)):
        err = float((got.double() - ref).abs().max() / ref.abs().max())
        assert err < 1e-5, (name, err)
    # The gathered adjoints are consumed (zeroed), as Warp does for the arrays a kernel writes.
    assert not wp.to_torch(a_v).any() and not wp.to_torch(a_C).any()


def test_hand_written_elastic_update_adjoint_equals_warps_generated_one():
    """The hand-written adjoint of g2p_update without plasticity (physics/transfer_adjoints.py) gives the
    adjoints of the old state and of the gathered v and C that Warp's generated adjoint gives, to the last
    bit, for free, pinned and held particles and for coordinates clamped to the padded box (and at its
    edges); both consume (zero) the new state's adjoints."""
    import warp as wp

    from endogsim.physics import kernels as K
    from endogsim.physics import transfer_adjoints as A
    from endogsim.physics.engine import adjoints_of, alloc_state, alloc_transfer

    g, x, _, _, _, _, d, _, _ = _transfer_case(seed=3, P=64)
    P = x.shape[0]
    d.x_lo, d.x_hi = 0.35, 0.65  # some particles start (or land) outside the box: their coordinates clamp
    x[0, 0], x[1, 1] = 0.35, 0.65  # exactly on the box's edges
    v, C = torch.randn(P, 3, generator=g), 0.3 * torch.randn(P, 3, 3, generator=g)
    F = torch.eye(3) + 0.2 * torch.randn(P, 3, 3, generator=g)
    v[0:2] = 0.0
    pm = K.ParticleModel()
    pm.vol, pm.obj = wp.full(P, 1e-3, dtype=float), wp.zeros(P, dtype=wp.int32)
    pinned, held = torch.zeros(P, dtype=torch.int32), torch.full((P,), -1, dtype=torch.int32)
    pinned[5:15], held[10:20] = 1, torch.arange(10, dtype=torch.int32)  # pinned, pinned and held, held
    pm.pinned, pm.held = wp.from_torch(pinned), wp.from_torch(held)
    pm.force_region = wp.full(P, -1, dtype=wp.int32)
    mats = K.MaterialTable()
    mats.E, mats.nu, mats.rho = wp.full(1, 1e3, dtype=float), wp.full(1, 0.3, dtype=float), wp.full(1, 1.0, dtype=float)
    mats.model, mats.yield_stress = wp.zeros(1, dtype=wp.int32), wp.zeros(1, dtype=float)
    hold = K.HeldTargets()
    hold.x0 = wp.from_torch(0.5 + 0.01 * torch.randn(10, 3, generator=g), dtype=wp.vec3)
    hold.x1 = wp.from_torch(0.5 + 0.01 * torch.randn(10, 3, generator=g), dtype=wp.vec3)
    hold.alpha_end, hold.inv_frame_dt = 0.5, 30.0
    dt = 0.05
    adj_out = [torch.randn(P, 3, generator=g), torch.randn(P, 3, generator=g), torch.randn(P, 3, 3, generator=g),
               torch.randn(P, 3, 3, generator=g)]

    results = []
    for hand in (False, True):
        s, out = alloc_state(P, "cpu", True), alloc_state(P, "cpu", True)
        tr = alloc_transfer(P, "cpu", True)
        for a, t in ((s.x, x), (s.F, F), (tr.v, v), (tr.C, C)):
            wp.copy(a, wp.from_torch(t.contiguous(), dtype=a.dtype))
        for a, t in zip((out.x.grad, out.v.grad, out.C.grad, out.F.grad), adj_out):
            wp.copy(a, wp.from_torch(t.contiguous(), dtype=a.dtype))
        inputs = [s, pm, mats, d, tr, hold, dt, out]
        wp.launch(K.g2p_update, dim=P, inputs=inputs, device="cpu")
        if hand:
            adjoints = [adjoints_of(s, K.ParticleState), adjoints_of(tr, K.ParticleTransfer),
                        adjoints_of(out, K.ParticleState)]
            wp.launch(A.g2p_update_elastic_adjoint, dim=P, device="cpu", inputs=[s, pm, d, tr, dt, out, *adjoints])
        else:
            tape = wp.Tape()
            tape.record_launch(K.g2p_update, P, 0, inputs, [], "cpu")
            tape.backward()
        results.append([wp.to_torch(a).clone() for a in (s.x.grad, s.F.grad, tr.v.grad, tr.C.grad, out.x.grad,
                                                          out.v.grad, out.C.grad, out.F.grad)])
    names = ("x", "F", "gathered v", "gathered C", "new x", "new v", "new C", "new F")
    for name, generated, hand in zip(names, *results):
        assert torch.equal(generated, hand), (name, float((generated - hand).abs().max()))
    assert results[0][0].abs().sum() > 0 and results[0][2].abs().sum() > 0
    assert not any(r.any() for r in results[1][4:])  # consumed


@pytest.mark.parametrize("model", ["neo_hookean", "stvk"])
def test_hand_written_particle_kernel_adjoint_equals_warps_generated_one(model):
    """The hand-written adjoint of particle_momentum (physics/transfer_adjoints.py) gives the adjoints of the
    particles' v, C, F and of each object's E, nu and density that Warp's generated adjoint gives, for two
    objects, pinned particles, an impulse and a force window, and particles compressed below the
    neo-Hookean J clamp; both consume (zero) the adjoints of mass, momentum and affine momentum."""
    import warp as wp

    from endogsim.physics import kernels as K
    from endogsim.physics import transfer_adjoints as A
    from endogsim.physics.constitutive import model_id
    from endogsim.physics.engine import adjoints_of, alloc_state, alloc_transfer

    g, x, _, _, _, _, d, _, _ = _transfer_case(seed=4, P=64)
    P = x.shape[0]
    v, C = torch.randn(P, 3, generator=g), 0.3 * torch.randn(P, 3, 3, generator=g)
    F = torch.eye(3) + 0.2 * torch.randn(P, 3, 3, generator=g)
    F[0] = 0.01 * torch.eye(3)  # J = 1e-6, below the clamp
    pm = K.ParticleModel()
    pm.vol = wp.from_torch(1e-3 * (0.5 + torch.rand(P, generator=g)))
    pm.obj = wp.from_torch((torch.arange(P) % 2).to(torch.int32))
    pinned = torch.zeros(P, dtype=torch.int32)
    pinned[5:15] = 1
    pm.pinned, pm.held = wp.from_torch(pinned), wp.full(P, -1, dtype=wp.int32)
    region = torch.full((P,), -1, dtype=torch.int32)
    region[20:30], region[30:40] = 0, 1
    pm.force_region = wp.from_torch(region)
    forces = K.ForceTable()
    forces.acc = wp.from_torch(torch.randn(2, 3, generator=g), dtype=wp.vec3)
    forces.t0, forces.t1 = wp.array([0.1, 0.0], dtype=float), wp.array([-1.0, 1.0], dtype=float)  # impulse, window
    t, dt = 0.1, 0.01
    adj_out = [torch.randn(P, generator=g), torch.randn(P, 3, generator=g), torch.randn(P, 3, 3, generator=g)]

    results = []
    for hand in (False, True):
        mats = K.MaterialTable()
        mats.E = wp.array([3.0, 5.0], dtype=float, requires_grad=True)
        mats.nu = wp.array([0.3, 0.45], dtype=float, requires_grad=True)
        mats.rho = wp.array([1.0, 1.2], dtype=float, requires_grad=True)
        mats.model = wp.full(2, model_id(model), dtype=wp.int32)
        mats.yield_stress = wp.zeros(2, dtype=float)
        s, tr = alloc_state(P, "cpu", True), alloc_transfer(P, "cpu", True)
        for a, val in ((s.x, x), (s.v, v), (s.C, C), (s.F, F)):
            wp.copy(a, wp.from_torch(val.contiguous(), dtype=a.dtype))
        for a, val in zip((tr.mass.grad, tr.momentum.grad, tr.affine.grad), adj_out):
            wp.copy(a, wp.from_torch(val.contiguous(), dtype=a.dtype))
        inputs = [s, pm, mats, forces, d, t, dt, tr]
        wp.launch(K.particle_momentum, dim=P, inputs=inputs, device="cpu")
        if hand:
            wp.launch(A.particle_momentum_adjoint, dim=P, device="cpu", inputs=[
                *inputs, adjoints_of(s, K.ParticleState), adjoints_of(tr, K.ParticleTransfer),
                mats.E.grad, mats.nu.grad, mats.rho.grad])
        else:
            tape = wp.Tape()
            tape.record_launch(K.particle_momentum, P, 0, inputs, [], "cpu")
            tape.backward()
        results.append([wp.to_torch(a).clone() for a in (s.v.grad, s.C.grad, s.F.grad, mats.E.grad, mats.nu.grad,
                                                          mats.rho.grad, tr.mass.grad, tr.momentum.grad,
                                                          tr.affine.grad)])
    names = ("v", "C", "F", "E", "nu", "rho", "mass", "momentum", "affine")
    for name, generated, hand in zip(names, *results):
        assert (generated - hand).abs().max() <= 1e-5 * generated.abs().max().clamp_min(1e-30), (
            name, generated, hand)
    assert all(r.abs().sum() > 0 for r in results[0][:6])
    assert not any(r.any() for r in results[1][6:])  # consumed


@pytest.mark.parametrize("sticky_walls", [0, 1])
def test_hand_written_grid_update_adjoint_equals_warps_generated_one(sticky_walls):
    """The hand-written adjoint of grid_update (physics/transfer_adjoints.py) gives the adjoints of the node
    momenta and masses that Warp's generated adjoint gives, on a block of nodes (offset) that holds every
    boundary condition kind (Coulomb friction sliding and sticking), collider nodes, empty nodes, the domain
    walls (sticky or slip) and nodes over the speed limit; both consume (zero) the velocities' adjoints."""
    import warp as wp

    from endogsim.physics import kernels as K
    from endogsim.physics import transfer_adjoints as A
    from endogsim.warp_runtime import init_warp

    init_warp()
    n, g = 10, torch.Generator().manual_seed(5)
    shape = (n, n, n)
    m = torch.rand(shape, generator=g) + 0.2
    m[torch.rand(shape, generator=g) < 0.1] = 0.0  # empty nodes
    mv = torch.randn(*shape, 3, generator=g)
    kind = torch.randint(0, 6, shape, generator=g, dtype=torch.int32)
    nrm = torch.nn.functional.normalize(torch.randn(*shape, 3, generator=g), dim=-1)
    friction = 2.0 * torch.rand(shape, generator=g)
    col_w = (torch.rand(shape, generator=g) < 0.1).float()
    d = K.Domain()
    d.n, d.inv_dx, d.pad, d.sticky_walls, d.x_lo, d.x_hi = n, float(n), 2, sticky_walls, 0.0, 1.0
    d.bc_kind = wp.from_torch(kind)
    d.bc_normal = wp.from_torch(nrm.contiguous(), dtype=wp.vec3)
    d.bc_friction = wp.from_torch(friction)
    d.gravity = wp.vec3(0.0, -1.0, 0.5)
    col = K.ColliderGrid()
    col.w = wp.from_torch(col_w)
    col.mv = wp.from_torch(torch.randn(*shape, 3, generator=g).contiguous(), dtype=wp.vec3)
    adj_v = torch.randn(*shape, 3, generator=g)
    offset, dim = wp.vec3i(1, 0, 1), (8, 10, 9)
    # v_max below the largest speeds: some nodes are limited. dt, damping as a substep's.
    args = [col, 1, d, 0.05, 0.97, 2.0, offset]

    results = []
    for hand in (False, True):
        grid = K.GridState()
        grid.m = wp.from_torch(m.clone(), requires_grad=True)
        grid.mv = wp.from_torch(mv.clone().contiguous(), dtype=wp.vec3, requires_grad=True)
        grid.v = wp.zeros(shape, dtype=wp.vec3, requires_grad=True)
        wp.copy(grid.v.grad, wp.from_torch(adj_v.clone().contiguous(), dtype=wp.vec3))
        inputs = [grid, *args]
        wp.launch(K.grid_update, dim=dim, inputs=inputs, device="cpu")
        if hand:
            wp.launch(A.grid_update_adjoint, dim=dim, device="cpu",
                      inputs=[*inputs, grid.v.grad, grid.mv.grad, grid.m.grad])
        else:
            tape = wp.Tape()
            tape.record_launch(K.grid_update, dim, 0, inputs, [], "cpu")
            tape.backward()
        results.append([wp.to_torch(a).clone() for a in (grid.mv.grad, grid.m.grad, grid.v.grad)])
    speeds = wp.to_torch(grid.v).norm(dim=-1)
    assert (speeds > 1.999).sum() > 10  # the speed limit acts
    v0 = (mv / m.clamp_min(1e-12)[..., None] + 0.05 * torch.tensor([0.0, -1.0, 0.5])) * 0.97
    vn = (v0 * nrm).sum(-1)
    slip = (v0 - vn[..., None] * nrm).norm(dim=-1) + friction * vn
    pressed = (kind == K.BC_COULOMB_SUPPORT) & (vn < 0) & (m > 0) & (col_w == 0)
    assert (pressed & (slip > 0)).sum() > 5 and (pressed & (slip <= 0)).sum() > 5  # Coulomb: slides and sticks
    # The same products in another order: equal to float32 rounding, relative to each array's scale.
    for name, generated, hand in zip(("momentum", "mass", "velocity"), *results):
        assert (generated - hand).abs().max() <= 1e-5 * generated.abs().max(), (name, (generated - hand).abs().max())
    assert results[0][0].abs().sum() > 0 and results[0][1].abs().sum() > 0
    block = (slice(1, 9), slice(0, 10), slice(1, 10))
    assert not results[1][2][block].any() and results[1][2].any()  # consumed in the block, kept outside it


@pytest.mark.parametrize("mode", ["full", "frame", "last_substep"])
def test_recomputing_the_next_segment_on_a_second_thread_gives_the_same_gradients(mode, monkeypatch):
    """The backward pass recomputes the next frame's segment on a second thread while this frame's adjoints
    run (two buffer sets): the same recomputation, the adjoints in the same order, so every gradient is
    identical to the one-set pass to the last bit. The last frame is not compared: its segment is skipped."""
    from endogsim.physics import rollout

    setup = _setup("neo_hookean")
    parts, scen, cfg, w, v0, _ = setup
    grads = {}
    for pipelined in (False, True):
        monkeypatch.setattr(rollout, "independent_runs", lambda *a: 2 if pipelined else 1)
        x0 = parts.x.clone().requires_grad_(True)
        params = _params()
        pos, F = mpm_rollout(parts, _materials(setup, *params), scen, cfg, T, grad_mode=mode, x0=x0, v0=v0)
        moved = pos[1:T - 1].double() - parts.x.double()
        loss = 10.0 * (w[1:T - 1] * moved).sum() + 0.1 * (F[T - 2].double() ** 2).sum()
        loss.backward()
        grads[pipelined] = [p.grad.clone() for p in params] + [x0.grad.clone()]
    for a, b in zip(grads[False], grads[True]):
        assert torch.equal(a, b), (a, b)
    assert all(bool(g.abs().max() > 0) for g in grads[True][:3])
