"""Hand-written adjoints of kernels of an MPM substep (:mod:`endogsim.physics.kernels`): the two stencil
transfers, the grid update, the particle update when no material yields, and the particle kernel for
constitutive models that give their stress's adjoint.

Warp generates an adjoint for every kernel by replaying it and keeping each intermediate of the unrolled
27-node stencil; for ``p2g`` and ``g2p`` those adjoints took 4-6x their forward kernels on a CPU, 60% of
an identification iteration's kernel time. The adjoints here gather what each node contributes in one pass
over the stencil, like the forward. The particle update's generated adjoint took 2.6x its forward (it
replays the kernel, plasticity branch included); without plasticity its adjoint is a few products. The
grid update's and the particle kernel's generated adjoints took 3.4x and 3.1x their forwards (replaying
every boundary-condition branch, every registered model's stress); by hand 1.3x and 1.5x (EndoNeRF
pulling, 63 frames: an identification iteration 22-25% shorter, docs/IDENTIFICATION.md section 2). Each
reads the adjoints of its kernel's outputs and adds to those of its inputs (or sets them, for inputs that
no other kernel reads); :meth:`endogsim.physics.engine.MPMEngine.substep` records them on the Warp tape in
place of the generated ones.

Notation: a particle at x (sim units) has stencil offset fx = x / dx - base (grid units) and weights
w_ijk = Wx_i(fx) Wy_j(fx) Wz_k(fx); dW is their derivative (:func:`~endogsim.physics.kernels.
bspline_derivatives`); x only enters through fx (base is piecewise constant), so adj_x = adj_fx / dx.
"""

from __future__ import annotations

import warp as wp

from endogsim.physics.kernels import (
    BC_COULOMB_SUPPORT,
    BC_FREE,
    BC_SLIP,
    BC_SLIP_SUPPORT,
    BC_STICKY,
    BC_SUPPORT,
    ColliderGrid,
    Domain,
    ForceTable,
    GridState,
    MaterialTable,
    ParticleModel,
    ParticleState,
    ParticleTransfer,
    apic_node_terms,
    bspline_derivatives,
    forced_velocity,
    kirchhoff_stress_adjoint,
    lame,
    lame_adjoint,
    quadratic_stencil,
)

__all__ = ["particle_momentum_adjoint", "p2g_scatter_adjoint", "grid_update_adjoint", "g2p_gather_adjoint",
           "g2p_update_elastic_adjoint"]


@wp.func
def weight_gradient(W: wp.mat33, dW: wp.mat33, i: int, j: int, k: int):
    """d w_ijk / d fx (grid units) of the stencil weight w_ijk = W[i, 0] W[j, 1] W[k, 2]."""
    return wp.vec3(dW[i, 0] * W[j, 1] * W[k, 2], W[i, 0] * dW[j, 1] * W[k, 2], W[i, 0] * W[j, 1] * dW[k, 2])


@wp.kernel(enable_backward=False)
def particle_momentum_adjoint(
    state: ParticleState,
    particles: ParticleModel,
    mats: MaterialTable,
    forces: ForceTable,
    domain: Domain,
    t: float,
    dt: float,
    out: ParticleTransfer,
    adj_state: ParticleState,
    adj_out: ParticleTransfer,
    adj_E: wp.array(dtype=float),
    adj_nu: wp.array(dtype=float),
    adj_rho: wp.array(dtype=float),
):
    """Adjoint of :func:`~endogsim.physics.kernels.particle_momentum` for constitutive models without the
    polar rotation that give a ``stress_adjoint``: from the adjoints of the particle's mass, momentum and
    affine momentum (read, then zeroed: consumed) to those of its v, C and F (added to) and of its object's
    E, nu and density (accumulated over particles).

    affine = c tau(F; mu, lam) + m C with c = -dt V 4 / dx^2; momentum = m v' (v' = v and any force region's
    velocity change, which does not depend on v); m = rho V (0 when pinned); (mu, lam) = lame(E, nu)."""
    p = wp.tid()
    o = particles.obj[p]
    E = mats.E[o]
    nu = mats.nu[o]
    ml = lame(E, nu)
    vol = particles.vol[p]
    mass = mats.rho[o] * vol
    pinned = particles.pinned[p] != 0
    if pinned:
        mass = 0.0
    inv_dx = domain.inv_dx
    g_affine = adj_out.affine[p]
    g_momentum = adj_out.momentum[p]
    vp = forced_velocity(state.v[p], particles.force_region[p], forces, t, dt)

    adj_tau = (-dt * vol * 4.0 * inv_dx * inv_dx) * g_affine
    g_F, g_mu, g_lam = kirchhoff_stress_adjoint(mats.model[o], state.F[p], wp.identity(n=3, dtype=float),
                                                ml[0], ml[1], adj_tau)
    adj_state.F[p] = adj_state.F[p] + g_F
    adj_state.C[p] = adj_state.C[p] + mass * g_affine
    adj_state.v[p] = adj_state.v[p] + mass * g_momentum
    if not pinned:
        g_mass = adj_out.mass[p] + wp.dot(g_momentum, vp) + wp.ddot(g_affine, state.C[p])
        wp.atomic_add(adj_rho, o, g_mass * vol)
    g_E_nu = lame_adjoint(E, nu, g_mu, g_lam)
    wp.atomic_add(adj_E, o, g_E_nu[0])
    wp.atomic_add(adj_nu, o, g_E_nu[1])
    adj_out.mass[p] = 0.0
    adj_out.momentum[p] = wp.vec3(0.0)
    adj_out.affine[p] = wp.mat33(0.0)


@wp.kernel(enable_backward=False)
def p2g_scatter_adjoint(
    x: wp.array(dtype=wp.vec3),
    transfer: ParticleTransfer,
    domain: Domain,
    adj_grid_mv: wp.array3d(dtype=wp.vec3),
    adj_grid_m: wp.array3d(dtype=float),
    adj_x: wp.array(dtype=wp.vec3),
    adj_mass: wp.array(dtype=float),
    adj_momentum: wp.array(dtype=wp.vec3),
    adj_affine: wp.array(dtype=wp.mat33),
):
    """Adjoint of :func:`~endogsim.physics.kernels.p2g_scatter`: from the adjoints of the node momenta and
    masses to those of the particle's position (added to), mass, momentum and affine momentum (set).

    Node ijk received w_ijk (q_ij + k a2) and w_ijk m, with w_ijk = Wx_i Wy_j Wz_k and q_ij = q + i a0 + j a1
    (:func:`~endogsim.physics.kernels.apic_node_terms`). Every sum over the stencil factors along the axes:
    the innermost loop only sums the node adjoints (g_mv, g_m) weighted by Wz_k and by dWz_k (and k times
    both); each row ij then contributes through its weights Wx_i Wy_j and their derivatives. The same sums
    as node by node in a fifth of the arithmetic (measured: 10-25% less time on random particles, 3-5% on
    pulling's, where reading the grid's adjoints dominates; the gather's adjoint, factored alike, gained
    nothing and stays node by node)."""
    p = wp.tid()
    inv_dx = domain.inv_dx
    base, fx, W = quadratic_stencil(x[p], inv_dx, domain.n)
    dW = bspline_derivatives(fx)
    mass = transfer.mass[p]
    affine = transfer.affine[p]
    dx = 1.0 / inv_dx
    q, a0, a1, a2 = apic_node_terms(transfer.momentum[p], affine, fx, dx)

    g_q = wp.vec3(0.0)
    g_a0 = wp.vec3(0.0)
    g_a1 = wp.vec3(0.0)
    g_a2 = wp.vec3(0.0)
    g_mass = float(0.0)
    g_fx = wp.vec3(0.0)
    for i in range(3):
        for j in range(3):
            # Row ij: sums over k of the node adjoints weighted by Wz_k (t, m) and dWz_k (tb, mb); u, ub: k times.
            t = wp.vec3(0.0)
            u = wp.vec3(0.0)
            tb = wp.vec3(0.0)
            ub = wp.vec3(0.0)
            m = float(0.0)
            mb = float(0.0)
            for k in range(3):
                g_mv = adj_grid_mv[base[0] + i, base[1] + j, base[2] + k]
                g_m = adj_grid_m[base[0] + i, base[1] + j, base[2] + k]
                t = t + W[k, 2] * g_mv
                tb = tb + dW[k, 2] * g_mv
                m = m + W[k, 2] * g_m
                mb = mb + dW[k, 2] * g_m
                if k > 0:
                    u = u + (float(k) * W[k, 2]) * g_mv
                    ub = ub + (float(k) * dW[k, 2]) * g_mv
            wij = W[i, 0] * W[j, 1]
            wt = wij * t
            g_q = g_q + wt
            g_a0 = g_a0 + float(i) * wt
            g_a1 = g_a1 + float(j) * wt
            g_a2 = g_a2 + wij * u
            g_mass = g_mass + wij * m
            # d loss / d w_ijk = g_mv . (q_ij + k a2) + g_m m, summed against Wz_k (a) and dWz_k (b).
            q_ij = q + float(i) * a0 + float(j) * a1
            a = wp.dot(t, q_ij) + wp.dot(u, a2) + m * mass
            b = wp.dot(tb, q_ij) + wp.dot(ub, a2) + mb * mass
            g_fx = g_fx + wp.vec3(dW[i, 0] * W[j, 1] * a, W[i, 0] * dW[j, 1] * a, wij * b)
    # q = momentum - dx A fx; a_c = dx A[:, c].
    g_fx = g_fx - dx * (wp.transpose(affine) * g_q)
    g_affine = dx * (wp.matrix_from_cols(g_a0, g_a1, g_a2) - wp.outer(g_q, fx))
    adj_x[p] = adj_x[p] + inv_dx * g_fx
    # p2g_scatter is the only reader of mass, momentum and affine: their adjoints are set, not added to.
    adj_mass[p] = g_mass
    adj_momentum[p] = g_q
    adj_affine[p] = g_affine


@wp.kernel(enable_backward=False)
def grid_update_adjoint(
    grid: GridState,
    col: ColliderGrid,
    has_colliders: int,
    domain: Domain,
    dt: float,
    damping_factor: float,
    v_max: float,
    offset: wp.vec3i,
    adj_v: wp.array3d(dtype=wp.vec3),
    adj_mv: wp.array3d(dtype=wp.vec3),
    adj_m: wp.array3d(dtype=float),
):
    """Adjoint of :func:`~endogsim.physics.kernels.grid_update` (same launch): from the adjoints of the node
    velocities (read, then zeroed: consumed) to those of the node momenta and masses (added to).

    The node velocity is v = (mv / m + dt g) damping, then mapped in turn by the node's boundary condition,
    the domain walls and the speed limit; a collider's node takes the collider's velocity, which no grid
    quantity moves. The forward chain is recomputed, then each map's Jacobian is applied transposed, in
    reverse. Each map is a projection or a rescaling, so its Jacobian is a few products, where Warp's
    generated adjoint replays every branch of the kernel (3x the forward's time)."""
    ti, tj, tk = wp.tid()
    i = ti + offset[0]
    j = tj + offset[1]
    k = tk + offset[2]
    g = adj_v[i, j, k]
    adj_v[i, j, k] = wp.vec3(0.0)
    m = grid.m[i, j, k]
    if m <= 1.0e-12:
        return
    if has_colliders != 0:
        if col.w[i, j, k] > 0.0:
            return
    mv = grid.mv[i, j, k]
    v0 = (mv / m + dt * domain.gravity) * damping_factor

    # Forward: the boundary condition (v0 -> v1), the walls (v1 -> v2, a per-axis mask), the speed limit.
    kind = domain.bc_kind[i, j, k]
    if kind == BC_STICKY:
        return
    nrm = wp.vec3(0.0)
    if kind != BC_FREE:
        nrm = domain.bc_normal[i, j, k]
    vn = wp.dot(v0, nrm)
    v1 = v0
    # Coulomb sliding: v1 = s vt with s = 1 + mu vn / st, vt = v0 - vn n, st = |vt| (kept for the reverse).
    mu = float(0.0)
    vt = wp.vec3(0.0)
    st = float(0.0)
    if kind == BC_SLIP:
        v1 = v0 - vn * nrm
    elif kind == BC_SUPPORT:
        if vn < 0.0:
            return
    elif kind == BC_COULOMB_SUPPORT:
        if vn < 0.0:
            mu = domain.bc_friction[i, j, k]
            vt = v0 - vn * nrm
            st = wp.length(vt)
            slip = st + mu * vn
            if slip <= 0.0:
                return
            v1 = vt * (slip / st)
    elif kind == BC_SLIP_SUPPORT:
        if vn < 0.0:
            v1 = v0 - vn * nrm
    n = domain.n
    pad = domain.pad
    idx = wp.vec3i(i, j, k)
    keep = wp.vec3(1.0)
    v2 = v1
    for a in range(3):
        low = idx[a] < pad
        high = idx[a] >= n - pad
        if low or high:
            if domain.sticky_walls != 0:
                return
            if (low and v1[a] < 0.0) or (high and v1[a] > 0.0):
                keep[a] = 0.0
                v2[a] = 0.0

    # Reverse.
    speed = wp.length(v2)
    if speed > v_max:
        vh = v2 / speed
        g = (v_max / speed) * (g - wp.dot(g, vh) * vh)
    g = wp.cw_mul(g, keep)
    if kind == BC_SLIP:
        g = g - wp.dot(g, nrm) * nrm
    elif kind == BC_COULOMB_SUPPORT:
        if vn < 0.0:
            s = (st + mu * vn) / st
            g_s = wp.dot(g, vt)
            g_vt = s * g + (g_s * (-mu * vn / (st * st)) / st) * vt
            g_vn = g_s * mu / st - wp.dot(g_vt, nrm)
            g = g_vt + g_vn * nrm
    elif kind == BC_SLIP_SUPPORT:
        if vn < 0.0:
            g = g - wp.dot(g, nrm) * nrm
    g_base = damping_factor * g
    adj_mv[i, j, k] = adj_mv[i, j, k] + g_base / m
    adj_m[i, j, k] = adj_m[i, j, k] - wp.dot(g_base, mv) / (m * m)


@wp.kernel(enable_backward=False)
def g2p_gather_adjoint(
    x: wp.array(dtype=wp.vec3),
    domain: Domain,
    grid: GridState,
    transfer: ParticleTransfer,
    adj_v: wp.array(dtype=wp.vec3),
    adj_C: wp.array(dtype=wp.mat33),
    adj_grid_v: wp.array3d(dtype=wp.vec3),
    adj_x: wp.array(dtype=wp.vec3),
):
    """Adjoint of :func:`~endogsim.physics.kernels.g2p_gather`: from the adjoints of the gathered velocity
    and C (read, then zeroed: they are consumed, as Warp does for arrays a kernel writes) to those of the
    node velocities and the particle's position (added to)."""
    p = wp.tid()
    inv_dx = domain.inv_dx
    base, fx, W = quadratic_stencil(x[p], inv_dx, domain.n)
    dW = bspline_derivatives(fx)
    new_v = transfer.v[p]

    # C = 4 / dx (S - v fx^T) with S = [sum w v_n i, sum w v_n j, sum w v_n k] (grid units).
    g_S = (4.0 * inv_dx) * adj_C[p]
    g_v = adj_v[p] - g_S * fx
    g_fx = -(wp.transpose(g_S) * new_v)
    g_si = wp.vec3(g_S[0, 0], g_S[1, 0], g_S[2, 0])
    g_sj = wp.vec3(g_S[0, 1], g_S[1, 1], g_S[2, 1])
    g_sk = wp.vec3(g_S[0, 2], g_S[1, 2], g_S[2, 2])
    for i in range(3):
        for j in range(3):
            for k in range(3):
                # v_n enters v with weight w and S's columns with i w, j w, k w.
                g_node = g_v + float(i) * g_si + float(j) * g_sj + float(k) * g_sk
                w = W[i, 0] * W[j, 1] * W[k, 2]
                wp.atomic_add(adj_grid_v, base[0] + i, base[1] + j, base[2] + k, w * g_node)
                g_w = wp.dot(grid.v[base[0] + i, base[1] + j, base[2] + k], g_node)
                g_fx = g_fx + g_w * weight_gradient(W, dW, i, j, k)
    adj_x[p] = adj_x[p] + inv_dx * g_fx
    adj_v[p] = wp.vec3(0.0)
    adj_C[p] = wp.mat33(0.0)


@wp.kernel(enable_backward=False)
def g2p_update_elastic_adjoint(
    state: ParticleState,
    particles: ParticleModel,
    domain: Domain,
    transfer: ParticleTransfer,
    dt: float,
    out: ParticleState,
    adj_state: ParticleState,
    adj_transfer: ParticleTransfer,
    adj_out: ParticleState,
):
    """Adjoint of :func:`~endogsim.physics.kernels.g2p_update` when no material yields (every yield stress
    0: F_new = (I + dt C) F, no return mapping): from the adjoints of the new state (read, then zeroed:
    consumed, as Warp does for arrays a kernel writes) to those of the old state's x and F and of the
    gathered v and C (added to). Pinned and held particles' positions and velocities do not depend on the
    grid (Dirichlet conditions); a coordinate clamped to the padded box passes no gradient (Warp's rule
    for ``clamp``: x passes when lo <= x < hi)."""
    p = wp.tid()
    g_x = adj_out.x[p]
    g_v = adj_out.v[p]
    g_C = adj_out.C[p]
    g_F = adj_out.F[p]
    new_v = transfer.v[p]
    new_C = transfer.C[p]
    F_old = state.F[p]

    x_new = state.x[p] + dt * new_v
    pinned = particles.pinned[p] != 0
    if pinned:
        x_new = state.x[p]
    if particles.held[p] < 0:
        lo = domain.x_lo
        hi = domain.x_hi
        g_xc = wp.vec3(0.0)
        for c in range(3):
            if x_new[c] >= lo and x_new[c] < hi:
                g_xc[c] = g_x[c]
        adj_state.x[p] = adj_state.x[p] + g_xc
        if not pinned:
            adj_transfer.v[p] = adj_transfer.v[p] + (g_v + dt * g_xc)
    M = wp.identity(n=3, dtype=float) + dt * new_C
    adj_state.F[p] = adj_state.F[p] + wp.transpose(M) * g_F
    adj_transfer.C[p] = adj_transfer.C[p] + (g_C + dt * (g_F * wp.transpose(F_old)))
    adj_out.x[p] = wp.vec3(0.0)
    adj_out.v[p] = wp.vec3(0.0)
    adj_out.C[p] = wp.mat33(0.0)
    adj_out.F[p] = wp.mat33(0.0)
