"""Warp kernels of one MLS-MPM substep (Hu et al. 2018), in sim-box units (the unit cube).

One substep is: ``collider_to_grid`` (kinematic instruments) -> ``particle_momentum`` (each particle's
mass, momentum and MLS-MPM affine momentum, the elastic force included) -> ``p2g_scatter`` (APIC transfer to
the grid) -> ``grid_update`` (momentum -> velocity, gravity, damping, boundary conditions) -> ``g2p_gather``
(velocity and affine matrix C from the grid) -> ``g2p_update`` (F update, plasticity return mapping,
advection).

The two stencil transfers (``p2g_scatter``, ``g2p_gather``) have hand-written adjoints in
:mod:`endogsim.physics.transfer_adjoints`: Warp's generated ones unroll the 27-node stencil with every
intermediate kept, and took 4-6x their forward (measured: 60% of an identification iteration's kernel
time). So do the grid update, the particle update without plasticity and the particle kernel for
constitutive models that give their stress's adjoint; the rest (plasticity, models that use the polar
rotation) keep Warp's generated adjoints.

Inputs are packed in structs, Newton-style: :class:`ParticleState` (what a substep advances),
:class:`ParticleTransfer` (what a substep carries between particles and grid), :class:`ParticleModel`
(what never changes in a rollout), :class:`MaterialTable` (per object id: moduli,
density, constitutive model, yield stress), :class:`ForceTable`, :class:`Domain` (grid geometry, boundary
conditions, gravity) and :class:`GridState` / :class:`ColliderGrid` (per-substep grid buffers).

Rules followed so that Warp's tape gives correct gradients (DESIGN.md section 4):
  - no kernel reads an array that it (or a later kernel of the same taped segment) overwrites: every
    substep reads state k and writes fresh arrays for state k + 1 and for its own grid;
  - stencil loops have constant bounds (range(3)), so Warp unrolls them;
  - boundary conditions are looked up from per-node arrays built once, not from dynamic loops.

Safety: grid indices are clamped to the grid before any read or atomic add, and particle positions are
clamped into the padded box after advection, so no input (NaN, huge velocities, absurd materials) can
write out of bounds -- the classic Warp MPM crash. The same kernels run on "cpu" and "cuda".
"""

from __future__ import annotations

import warp as wp

from endogsim.physics.constitutive import MODELS
from endogsim.physics.polar import newton_polar_rotation, proper_svd_rotations, rotation_with_adjoint

# Per-node boundary condition kinds.
BC_FREE = 0
BC_STICKY = 1
BC_SLIP = 2
BC_SUPPORT = 3  # separable: a node moving into the support stops, one moving away is free
BC_SLIP_SUPPORT = 4  # separable and frictionless: a node moving into the support loses that component only
BC_COULOMB_SUPPORT = 5  # separable with Coulomb friction (per-node coefficient): continuous in the velocity


@wp.struct
class ParticleState:
    """Particle state at one instant: positions, velocities, APIC affine matrices, deformation gradients."""

    x: wp.array(dtype=wp.vec3)
    v: wp.array(dtype=wp.vec3)
    C: wp.array(dtype=wp.mat33)
    F: wp.array(dtype=wp.mat33)


@wp.struct
class ParticleTransfer:
    """What one substep carries between the particles and the grid (sim units), per particle: mass, momentum
    (external forces applied), MLS-MPM affine momentum (mass C minus the stress term), and the velocity and
    APIC matrix C gathered back from the grid. Fresh per taped substep, like the grids."""

    mass: wp.array(dtype=float)
    momentum: wp.array(dtype=wp.vec3)
    affine: wp.array(dtype=wp.mat33)
    v: wp.array(dtype=wp.vec3)
    C: wp.array(dtype=wp.mat33)


@wp.struct
class ParticleModel:
    """Per-particle data that a rollout never changes: volume, object id, pinned flag, force region (-1:
    none), index of the particle in :class:`HeldTargets` (-1: not held by an instrument)."""

    vol: wp.array(dtype=float)
    obj: wp.array(dtype=wp.int32)
    pinned: wp.array(dtype=wp.int32)
    force_region: wp.array(dtype=wp.int32)
    held: wp.array(dtype=wp.int32)


@wp.struct
class HeldTargets:
    """Where the particles an instrument holds are during one substep: their positions at the two output
    frames around it (x0, x1; they move at constant velocity in between), the fraction of the frame reached
    at the end of the substep, and 1 / frame interval."""

    x0: wp.array(dtype=wp.vec3)
    x1: wp.array(dtype=wp.vec3)
    alpha_end: float
    inv_frame_dt: float


@wp.struct
class MaterialTable:
    """Per-object-id materials (sim units): E, nu, density, constitutive model id, von Mises yield stress
    (0: purely elastic). E, nu and rho are differentiable."""

    E: wp.array(dtype=float)
    nu: wp.array(dtype=float)
    rho: wp.array(dtype=float)
    model: wp.array(dtype=wp.int32)
    yield_stress: wp.array(dtype=float)


@wp.struct
class ForceTable:
    """External accelerations per force region: value, window [t0, t1) (s); t1 < 0 marks an impulse (a
    velocity change applied once, over the substep that starts at t0)."""

    acc: wp.array(dtype=wp.vec3)
    t0: wp.array(dtype=float)
    t1: wp.array(dtype=float)


@wp.struct
class Domain:
    """The grid: n nodes per axis, 1 / dx, wall padding (cells) and kind, the band particles stay in
    [x_lo, x_hi], per-node boundary conditions, gravity (sim units)."""

    n: int
    inv_dx: float
    pad: int
    sticky_walls: int
    x_lo: float
    x_hi: float
    bc_kind: wp.array3d(dtype=wp.int32)
    bc_normal: wp.array3d(dtype=wp.vec3)
    bc_friction: wp.array3d(dtype=float)
    gravity: wp.vec3


@wp.struct
class GridState:
    """Per-substep grid: mass, momentum, velocity."""

    m: wp.array3d(dtype=float)
    mv: wp.array3d(dtype=wp.vec3)
    v: wp.array3d(dtype=wp.vec3)


@wp.struct
class ColliderGrid:
    """Per-substep collider marks: number of collider points near each node and their summed velocity."""

    w: wp.array3d(dtype=float)
    mv: wp.array3d(dtype=wp.vec3)


@wp.func
def stencil_base(x: wp.vec3, inv_dx: float, n: int):
    """Lowest node of the 3x3x3 quadratic B-spline stencil, clamped so base..base+2 lies inside the grid."""
    bx = wp.clamp(int(wp.floor(x[0] * inv_dx - 0.5)), 0, n - 3)
    by = wp.clamp(int(wp.floor(x[1] * inv_dx - 0.5)), 0, n - 3)
    bz = wp.clamp(int(wp.floor(x[2] * inv_dx - 0.5)), 0, n - 3)
    return wp.vec3i(bx, by, bz)


@wp.func
def bspline_weights(fx: wp.vec3):
    """Quadratic B-spline weights: row r holds the weights of stencil node r along x, y, z."""
    a = wp.vec3(1.5) - fx
    b = fx - wp.vec3(1.0)
    c = fx - wp.vec3(0.5)
    w0 = 0.5 * wp.cw_mul(a, a)
    w1 = wp.vec3(0.75) - wp.cw_mul(b, b)
    w2 = 0.5 * wp.cw_mul(c, c)
    return wp.mat33(w0[0], w0[1], w0[2], w1[0], w1[1], w1[2], w2[0], w2[1], w2[2])


@wp.func
def bspline_derivatives(fx: wp.vec3):
    """d/dfx of :func:`bspline_weights`, laid out the same (row r: stencil node r; column: axis)."""
    d0 = fx - wp.vec3(1.5)
    d1 = -2.0 * (fx - wp.vec3(1.0))
    d2 = fx - wp.vec3(0.5)
    return wp.mat33(d0[0], d0[1], d0[2], d1[0], d1[1], d1[2], d2[0], d2[1], d2[2])


@wp.func
def quadratic_stencil(x: wp.vec3, inv_dx: float, n: int):
    """The quadratic B-spline stencil of position ``x``: its lowest node (:func:`stencil_base`), the offset
    fx = x / dx - base (grid units) and the weights (:func:`bspline_weights`)."""
    base = stencil_base(x, inv_dx, n)
    fx = x * inv_dx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    return base, fx, bspline_weights(fx)


@wp.func
def apic_node_terms(momentum: wp.vec3, affine: wp.mat33, fx: wp.vec3, dx: float):
    """The particle's APIC momentum at stencil node ijk, m v + A (node - x) with node - x = (ijk - fx) dx,
    split as q + i a0 + j a1 + k a2 (vector sums only): returns q, a0, a1, a2."""
    q = momentum - dx * (affine * fx)
    a0 = dx * wp.vec3(affine[0, 0], affine[1, 0], affine[2, 0])
    a1 = dx * wp.vec3(affine[0, 1], affine[1, 1], affine[2, 1])
    a2 = dx * wp.vec3(affine[0, 2], affine[1, 2], affine[2, 2])
    return q, a0, a1, a2


@wp.func
def lame(E: float, nu: float):
    """Lame parameters (mu, lambda) of Young's modulus E and Poisson's ratio nu."""
    return wp.vec2(E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)))


@wp.func
def lame_adjoint(E: float, nu: float, adj_mu: float, adj_lam: float):
    """(adj_E, adj_nu) of adj_mu mu + adj_lam lam through :func:`lame`."""
    d = (1.0 + nu) * (1.0 - 2.0 * nu)
    return wp.vec2(adj_mu / (2.0 * (1.0 + nu)) + adj_lam * nu / d,
                   -adj_mu * E / (2.0 * (1.0 + nu) * (1.0 + nu)) + adj_lam * E * (1.0 + 2.0 * nu * nu) / (d * d))


@wp.func
def uses_rotation(model: int):
    """1 when the registered constitutive model ``model`` reads the polar rotation of F, else 0."""
    r = int(0)
    for i in range(wp.static(len(MODELS))):
        if model == i:
            r = wp.static(int(MODELS[i].uses_rotation))
    return r


@wp.func
def kirchhoff_stress(model: int, F: wp.mat33, R: wp.mat33, mu: float, lam: float):
    """Kirchhoff stress tau = P F^T of the registered constitutive model ``model`` (sim-unit moduli); R is
    the polar rotation of F for models that use it (:func:`uses_rotation`), else anything."""
    tau = wp.mat33(0.0)
    for i in range(wp.static(len(MODELS))):
        if model == i:
            tau = wp.static(MODELS[i].stress)(F, R, mu, lam)
    return tau


@wp.func
def _no_stress_adjoint(F: wp.mat33, R: wp.mat33, mu: float, lam: float, adj_tau: wp.mat33):
    return wp.mat33(0.0), float(0.0), float(0.0)


@wp.func
def kirchhoff_stress_adjoint(model: int, F: wp.mat33, R: wp.mat33, mu: float, lam: float, adj_tau: wp.mat33):
    """(adj_F, adj_mu, adj_lam) of adj_tau : :func:`kirchhoff_stress` for a model with a ``stress_adjoint``
    (zeros for the others: the engine then keeps Warp's generated adjoint)."""
    adj_F = wp.mat33(0.0)
    adj_mu = float(0.0)
    adj_lam = float(0.0)
    for i in range(wp.static(len(MODELS))):
        if model == i:
            adj_F, adj_mu, adj_lam = wp.static(MODELS[i].stress_adjoint or _no_stress_adjoint)(F, R, mu, lam, adj_tau)
    return adj_F, adj_mu, adj_lam


@wp.func
def forced_velocity(v: wp.vec3, r: int, forces: ForceTable, t: float, dt: float):
    """The velocity after force region ``r``'s acceleration over the substep [t, t + dt) (an impulse: its
    whole velocity change in the substep that starts at its t0); ``r`` < 0: none."""
    vp = v
    if r >= 0:
        t0 = forces.t0[r]
        t1 = forces.t1[r]
        if t1 < 0.0:
            if t >= t0 and t < t0 + dt:
                vp = vp + forces.acc[r]
        elif t >= t0 and t < t1:
            vp = vp + dt * forces.acc[r]
    return vp


@wp.func
def von_mises_return(F: wp.mat33, yield_stress: float, mu: float):
    """Elastic part of F after von Mises plasticity: the deviatoric Hencky strain is projected onto the
    cylinder of radius yield_stress / (2 mu) (F = F^E F^P; the plastic part is never needed for the stress)."""
    U, s, V = proper_svd_rotations(F)
    eps = wp.vec3(wp.log(wp.max(s[0], 1.0e-4)), wp.log(wp.max(s[1], 1.0e-4)), wp.log(wp.max(s[2], 1.0e-4)))
    eps_dev = eps - wp.vec3((eps[0] + eps[1] + eps[2]) / 3.0)
    norm_dev = wp.length(eps_dev)
    excess = norm_dev - yield_stress / (2.0 * mu)
    F_el = F
    if excess > 0.0:
        eps = eps - (excess / norm_dev) * eps_dev
        S = wp.mat33(wp.exp(eps[0]), 0.0, 0.0, 0.0, wp.exp(eps[1]), 0.0, 0.0, 0.0, wp.exp(eps[2]))
        F_el = U * S * wp.transpose(V)
    return F_el


@wp.kernel(enable_backward=False)
def collider_to_grid(
    col_x0: wp.array(dtype=wp.vec3),
    col_x1: wp.array(dtype=wp.vec3),
    alpha: float,
    inv_frame_dt: float,
    radius: float,
    domain: Domain,
    col: ColliderGrid,
):
    """Mark grid nodes within ``radius`` of a collider point and accumulate the collider velocity there.

    The collider moves at constant velocity between two output frames: x = lerp(x0, x1, alpha).
    """
    c = wp.tid()
    x = col_x0[c] + alpha * (col_x1[c] - col_x0[c])
    v = (col_x1[c] - col_x0[c]) * inv_frame_dt
    base = stencil_base(x, domain.inv_dx, domain.n)
    dx = 1.0 / domain.inv_dx
    for i in range(3):
        for j in range(3):
            for k in range(3):
                node = wp.vec3(float(base[0] + i), float(base[1] + j), float(base[2] + k)) * dx
                if wp.length(node - x) <= radius:
                    wp.atomic_add(col.w, base[0] + i, base[1] + j, base[2] + k, 1.0)
                    wp.atomic_add(col.mv, base[0] + i, base[1] + j, base[2] + k, v)


@wp.kernel
def particle_momentum(
    state: ParticleState,
    particles: ParticleModel,
    mats: MaterialTable,
    forces: ForceTable,
    domain: Domain,
    t: float,
    dt: float,
    out: ParticleTransfer,
):
    """Each particle's mass, momentum (external forces applied) and MLS-MPM affine momentum, the elastic
    force included: affine = mass C - dt V 4 / dx^2 tau(F) (Hu et al. 2018).

    A pinned (anchored) particle passes on its elastic force but neither mass nor momentum: its inertia
    belongs to the fixed anatomy. Were its mass (at rest) averaged into a node shared with free particles,
    the node would lose that fraction of its momentum every substep, a damping per substep, not per second,
    that makes the motion shrink with dt.
    """
    p = wp.tid()
    o = particles.obj[p]
    ml = lame(mats.E[o], mats.nu[o])
    vol = particles.vol[p]
    mass = mats.rho[o] * vol
    if particles.pinned[p] != 0:
        mass = 0.0

    inv_dx = domain.inv_dx
    model = mats.model[o]
    Fp = state.F[p]
    R = wp.identity(n=3, dtype=float)
    if uses_rotation(model) != 0:
        # Inline, not wrapped in a function: the adjoint's replay then runs the Newton iteration once.
        R = rotation_with_adjoint(Fp, newton_polar_rotation(Fp))
    tau = kirchhoff_stress(model, Fp, R, ml[0], ml[1])
    affine = (-dt * vol * 4.0 * inv_dx * inv_dx) * tau + mass * state.C[p]

    vp = forced_velocity(state.v[p], particles.force_region[p], forces, t, dt)
    out.mass[p] = mass
    out.momentum[p] = mass * vp
    out.affine[p] = affine


@wp.kernel(enable_backward=False)
def p2g_scatter(x: wp.array(dtype=wp.vec3), transfer: ParticleTransfer, domain: Domain, grid: GridState):
    """Particle to grid (APIC): node mass += w m, node momentum += w (m v + A (node - x)).

    Its adjoint is :func:`endogsim.physics.transfer_adjoints.p2g_scatter_adjoint`.
    """
    p = wp.tid()
    inv_dx = domain.inv_dx
    base, fx, W = quadratic_stencil(x[p], inv_dx, domain.n)
    mass = transfer.mass[p]
    affine = transfer.affine[p]

    q, a0, a1, a2 = apic_node_terms(transfer.momentum[p], affine, fx, 1.0 / inv_dx)
    for i in range(3):
        qi = q + float(i) * a0
        for j in range(3):
            qij = qi + float(j) * a1
            wij = W[i, 0] * W[j, 1]
            for k in range(3):
                w = wij * W[k, 2]
                wp.atomic_add(grid.mv, base[0] + i, base[1] + j, base[2] + k, w * (qij + float(k) * a2))
                wp.atomic_add(grid.m, base[0] + i, base[1] + j, base[2] + k, w * mass)


@wp.kernel
def grid_update(
    grid: GridState,
    col: ColliderGrid,
    has_colliders: int,
    domain: Domain,
    dt: float,
    damping_factor: float,
    v_max: float,
    offset: wp.vec3i,
):
    """Grid momentum -> velocity with gravity, damping, colliders, anchors and domain walls.

    Launched over the block of nodes that particles can touch (starting at ``offset``): nodes outside it
    are never read by ``g2p``, and skipping them makes the grid cost follow the particles, not the grid.
    """
    ti, tj, tk = wp.tid()
    i = ti + offset[0]
    j = tj + offset[1]
    k = tk + offset[2]
    m = grid.m[i, j, k]
    v = wp.vec3(0.0)
    if m > 1.0e-12:
        v = (grid.mv[i, j, k] / m + dt * domain.gravity) * damping_factor

    if has_colliders != 0:
        cw = col.w[i, j, k]
        if cw > 0.0:
            v = col.mv[i, j, k] / cw

    kind = domain.bc_kind[i, j, k]
    if kind == BC_STICKY:
        v = wp.vec3(0.0)
    elif kind == BC_SLIP:
        nrm = domain.bc_normal[i, j, k]
        v = v - wp.dot(v, nrm) * nrm
    elif kind == BC_SUPPORT:
        # Separable contact with friction: a node moving into the support stops (tissue pressed on the
        # anatomy behind it does not slide on it); one moving away from it is free (it lifts off).
        if wp.dot(v, domain.bc_normal[i, j, k]) < 0.0:
            v = wp.vec3(0.0)
    elif kind == BC_COULOMB_SUPPORT:
        # Separable, with Coulomb friction: pressed on the support, a node loses its normal velocity and its
        # tangential speed shrinks by mu times the normal speed it lost (to rest when that is more). The
        # velocity is continuous as the normal speed crosses 0, unlike BC_SUPPORT's stick-or-free switch.
        nrm = domain.bc_normal[i, j, k]
        vn = wp.dot(v, nrm)
        if vn < 0.0:
            vt = v - vn * nrm
            st = wp.length(vt)
            slip = st + domain.bc_friction[i, j, k] * vn
            if slip > 0.0:
                v = vt * (slip / st)
            else:
                v = wp.vec3(0.0)
    elif kind == BC_SLIP_SUPPORT:
        # Separable, frictionless: pressed on the support, a node keeps only its tangential velocity.
        nrm = domain.bc_normal[i, j, k]
        vn = wp.dot(v, nrm)
        if vn < 0.0:
            v = v - vn * nrm

    # Domain walls: nodes within `pad` cells of a face. Slip walls only stop motion through the wall.
    idx = wp.vec3i(i, j, k)
    n = domain.n
    pad = domain.pad
    for a in range(3):
        low = idx[a] < pad
        high = idx[a] >= n - pad
        if low or high:
            if domain.sticky_walls != 0:
                v = wp.vec3(0.0)
            elif (low and v[a] < 0.0) or (high and v[a] > 0.0):
                if a == 0:
                    v = wp.vec3(0.0, v[1], v[2])
                elif a == 1:
                    v = wp.vec3(v[0], 0.0, v[2])
                else:
                    v = wp.vec3(v[0], v[1], 0.0)

    # Safety limit: no node moves more than one cell per substep (explicit MPM is unstable past it).
    speed = wp.length(v)
    if speed > v_max:
        v = v * (v_max / speed)
    grid.v[i, j, k] = v


@wp.kernel(enable_backward=False)
def g2p_gather(x: wp.array(dtype=wp.vec3), domain: Domain, grid: GridState, transfer: ParticleTransfer):
    """Grid to particle: the velocity v = sum w v_node and the APIC matrix C = 4 / dx^2 sum w v_node
    (node - x)^T at each particle.

    Its adjoint is :func:`endogsim.physics.transfer_adjoints.g2p_gather_adjoint`.
    """
    p = wp.tid()
    inv_dx = domain.inv_dx
    base, fx, W = quadratic_stencil(x[p], inv_dx, domain.n)

    # With node - x = (ijk - fx) dx: accumulate sum w v i, sum w v j, sum w v k as vectors (cheaper than
    # 27 outer products).
    new_v = wp.vec3(0.0)
    si = wp.vec3(0.0)
    sj = wp.vec3(0.0)
    sk = wp.vec3(0.0)
    for i in range(3):
        for j in range(3):
            wij = W[i, 0] * W[j, 1]
            for k in range(3):
                wv = (wij * W[k, 2]) * grid.v[base[0] + i, base[1] + j, base[2] + k]
                new_v = new_v + wv
                si = si + float(i) * wv
                sj = sj + float(j) * wv
                sk = sk + float(k) * wv
    transfer.v[p] = new_v
    transfer.C[p] = (4.0 * inv_dx) * (wp.matrix_from_cols(si, sj, sk) - wp.outer(new_v, fx))


@wp.kernel
def g2p_update(
    state: ParticleState,
    particles: ParticleModel,
    mats: MaterialTable,
    domain: Domain,
    transfer: ParticleTransfer,
    held: HeldTargets,
    dt: float,
    out: ParticleState,
):
    """The particle's new state from what :func:`g2p_gather` brought back: F update with optional von Mises
    plasticity, advection.

    Pinned particles stay where they are and held ones go where their instrument takes them (Dirichlet
    conditions on particles); their F still follows the grid."""
    p = wp.tid()
    xp = state.x[p]
    new_v = transfer.v[p]
    new_C = transfer.C[p]

    F_new = (wp.identity(n=3, dtype=float) + dt * new_C) * state.F[p]
    o = particles.obj[p]
    yield_stress = mats.yield_stress[o]
    if yield_stress > 0.0:
        F_new = von_mises_return(F_new, yield_stress, lame(mats.E[o], mats.nu[o])[0])

    x_new = xp + dt * new_v
    if particles.pinned[p] != 0:
        x_new = xp
        new_v = wp.vec3(0.0)
    h = particles.held[p]
    if h >= 0:
        step = held.x1[h] - held.x0[h]
        x_new = held.x0[h] + held.alpha_end * step
        new_v = step * held.inv_frame_dt
    # Keep every particle inside the padded box (its stencil then always lies inside the grid).
    x_lo = domain.x_lo
    x_hi = domain.x_hi
    x_new = wp.vec3(wp.clamp(x_new[0], x_lo, x_hi), wp.clamp(x_new[1], x_lo, x_hi), wp.clamp(x_new[2], x_lo, x_hi))

    out.x[p] = x_new
    out.v[p] = new_v
    out.C[p] = new_C
    out.F[p] = F_new


@wp.kernel(enable_backward=False)
def split_weights_to_grid(
    x: wp.array(dtype=wp.vec3),
    flag: wp.array(dtype=wp.int32),
    inv_dx: float,
    n: int,
    w_flagged: wp.array3d(dtype=float),
    w_other: wp.array3d(dtype=float),
):
    """Splat each particle's B-spline weights onto the grid, flagged and other particles separately."""
    p = wp.tid()
    xp = x[p]
    base, fx, W = quadratic_stencil(xp, inv_dx, n)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = W[i, 0] * W[j, 1] * W[k, 2]
                if flag[p] != 0:
                    wp.atomic_add(w_flagged, base[0] + i, base[1] + j, base[2] + k, w)
                else:
                    wp.atomic_add(w_other, base[0] + i, base[1] + j, base[2] + k, w)


@wp.kernel(enable_backward=False)
def dominated_nodes_to_bc(
    w_flagged: wp.array3d(dtype=float),
    w_other: wp.array3d(dtype=float),
    bc_kind: wp.array3d(dtype=wp.int32),
):
    """Nodes that pinned particles dominate at rest hold still (sticky), like the anchored tissue itself."""
    i, j, k = wp.tid()
    wf = w_flagged[i, j, k]
    if wf > 0.0 and wf >= w_other[i, j, k]:
        bc_kind[i, j, k] = BC_STICKY
