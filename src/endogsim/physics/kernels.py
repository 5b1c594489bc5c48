"""Warp kernels of one MLS-MPM substep (Hu et al. 2018), in sim-box units (the unit cube).

One substep is: ``collider_to_grid`` (kinematic instruments) -> ``p2g`` (APIC transfer of mass and
momentum, plus the elastic force) -> ``grid_update`` (momentum -> velocity, gravity, damping, boundary
conditions) -> ``g2p`` (velocity, affine matrix C, F update, plasticity return mapping, advection).

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

# Material models (an int kernel argument, so both share one compiled kernel).
FIXED_COROTATED = 0
NEO_HOOKEAN = 1

# Per-node boundary condition kinds.
BC_FREE = 0
BC_STICKY = 1
BC_SLIP = 2


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
def proper_svd_rotations(F: wp.mat33):
    """SVD F = U diag(s) V^T with U, V proper rotations (a reflection moves into the last singular value)."""
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    if wp.determinant(U) < 0.0:
        U = wp.mat33(U[0, 0], U[0, 1], -U[0, 2], U[1, 0], U[1, 1], -U[1, 2], U[2, 0], U[2, 1], -U[2, 2])
        s = wp.vec3(s[0], s[1], -s[2])
    if wp.determinant(V) < 0.0:
        V = wp.mat33(V[0, 0], V[0, 1], -V[0, 2], V[1, 0], V[1, 1], -V[1, 2], V[2, 0], V[2, 1], -V[2, 2])
        s = wp.vec3(s[0], s[1], -s[2])
    return U, s, V


@wp.func
def polar_rotation(F: wp.mat33):
    """Rotation R of the polar decomposition F = R S.

    Scaled Newton iteration X <- (g X + X^-T / g) / 2 (Higham 1986): a few 3x3 inverses instead of an
    SVD, about 5x cheaper on CPU, and exact at F = I. An inverted or degenerate F (det <= 1e-6) takes
    the SVD path, whose proper rotations keep R a rotation. Its gradient is the custom adjoint below, so
    this loop needs no autodiff.
    """
    R = wp.identity(n=3, dtype=float)
    if wp.determinant(F) <= 1.0e-6:
        U, s, V = proper_svd_rotations(F)
        R = U * wp.transpose(V)
    else:
        X = F
        it = int(0)
        change = float(1.0)
        while it < 20 and change > 1.0e-6:
            Xit = wp.transpose(wp.inverse(X))
            g = wp.sqrt(wp.sqrt(wp.ddot(Xit, Xit) / wp.ddot(X, X)))
            Xn = 0.5 * (g * X + Xit / g)
            D = Xn - X
            change = wp.sqrt(wp.ddot(D, D))
            X = Xn
            it = it + 1
        R = X
    return R


@wp.func
def skew_axial(M: wp.mat33):
    """Axial vector w of the skew part of M, (M - M^T) / 2 = [w]_x."""
    return 0.5 * wp.vec3(M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1])


@wp.func_grad(polar_rotation)
def adj_polar_rotation(F: wp.mat33, adj_ret: wp.mat33):
    # With F = R S and R^T dR = [w]_x: S [w]_x + [w]_x S = R^T dF - dF^T R, i.e. (tr(S) I - S) w =
    # 2 axial(R^T dF). The adjoint is adj_F = 2 R [q]_x with q = (tr(S) I - S)^-1 axial(R^T adj_R).
    # It divides by sums of singular values (never their differences, which vanish at F = I where every
    # particle starts and make generic SVD adjoints blow up).
    R = polar_rotation(F)
    S = wp.transpose(R) * F
    S = 0.5 * (S + wp.transpose(S))
    G = wp.trace(S) * wp.identity(n=3, dtype=float) - S
    if wp.abs(wp.determinant(G)) < 1.0e-12:
        G = G + 1.0e-4 * wp.identity(n=3, dtype=float)
    q = wp.inverse(G) * skew_axial(wp.transpose(R) * adj_ret)
    Q = wp.mat33(0.0, -q[2], q[1], q[2], 0.0, -q[0], -q[1], q[0], 0.0)
    wp.adjoint[F] += 2.0 * R * Q


@wp.func
def kirchhoff_stress(F: wp.mat33, R: wp.mat33, mu: float, lam: float, model: int):
    """Kirchhoff stress tau = P F^T of the hyperelastic model (sim-unit moduli); R = polar rotation of F
    (fixed corotated only; computed by the caller so the adjoint pass does not recompute it twice)."""
    J = wp.determinant(F)
    I = wp.identity(n=3, dtype=float)
    if model == FIXED_COROTATED:
        return 2.0 * mu * (F - R) * wp.transpose(F) + lam * (J - 1.0) * J * I
    # neo-Hookean: tau = mu (F F^T - I) + lambda ln J I. J is kept positive so an inverted particle pushes
    # back instead of producing NaN.
    return mu * (F * wp.transpose(F) - I) + lam * wp.log(wp.max(J, 1.0e-4)) * I


@wp.kernel
def collider_to_grid(
    col_x0: wp.array(dtype=wp.vec3),
    col_x1: wp.array(dtype=wp.vec3),
    alpha: float,
    inv_frame_dt: float,
    radius: float,
    inv_dx: float,
    n: int,
    col_w: wp.array3d(dtype=float),
    col_mv: wp.array3d(dtype=wp.vec3),
):
    """Mark grid nodes within ``radius`` of a collider point and accumulate the collider velocity there.

    The collider moves at constant velocity between two output frames: x = lerp(x0, x1, alpha).
    """
    c = wp.tid()
    x = col_x0[c] + alpha * (col_x1[c] - col_x0[c])
    v = (col_x1[c] - col_x0[c]) * inv_frame_dt
    base = stencil_base(x, inv_dx, n)
    dx = 1.0 / inv_dx
    for i in range(3):
        for j in range(3):
            for k in range(3):
                node = wp.vec3(float(base[0] + i), float(base[1] + j), float(base[2] + k)) * dx
                if wp.length(node - x) <= radius:
                    wp.atomic_add(col_w, base[0] + i, base[1] + j, base[2] + k, 1.0)
                    wp.atomic_add(col_mv, base[0] + i, base[1] + j, base[2] + k, v)


@wp.kernel
def p2g(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    vol: wp.array(dtype=float),
    obj: wp.array(dtype=wp.int32),
    pinned: wp.array(dtype=wp.int32),
    E_obj: wp.array(dtype=float),
    nu_obj: wp.array(dtype=float),
    rho_obj: wp.array(dtype=float),
    force_region: wp.array(dtype=wp.int32),
    force_acc: wp.array(dtype=wp.vec3),
    force_t0: wp.array(dtype=float),
    force_t1: wp.array(dtype=float),
    t: float,
    dt: float,
    inv_dx: float,
    n: int,
    model: int,
    grid_m: wp.array3d(dtype=float),
    grid_mv: wp.array3d(dtype=wp.vec3),
):
    """Particle to grid: APIC momentum, mass and the elastic force (MLS-MPM).

    A pinned (anchored) particle passes on its elastic force but neither mass nor momentum: its inertia
    belongs to the fixed anatomy. Were its mass (at rest) averaged into a node shared with free particles,
    the node would lose that fraction of its momentum every substep, a damping per substep, not per second,
    that makes the motion shrink with dt.
    """
    p = wp.tid()
    o = obj[p]
    E = E_obj[o]
    nu = nu_obj[o]
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    mass = rho_obj[o] * vol[p]
    if pinned[p] != 0:
        mass = 0.0

    xp = x[p]
    base = stencil_base(xp, inv_dx, n)
    fx = xp * inv_dx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    W = bspline_weights(fx)

    Fp = F[p]
    R = wp.identity(n=3, dtype=float)
    if model == FIXED_COROTATED:
        R = polar_rotation(Fp)
    tau = kirchhoff_stress(Fp, R, mu, lam, model)
    affine = (-dt * vol[p] * 4.0 * inv_dx * inv_dx) * tau + mass * C[p]

    vp = v[p]
    r = force_region[p]
    if r >= 0:
        # An impulse is a velocity change over one substep (t1 < 0 marks it; its window is [t0, t0 + dt)).
        t0 = force_t0[r]
        t1 = force_t1[r]
        if t1 < 0.0:
            if t >= t0 and t < t0 + dt:
                vp = vp + force_acc[r]
        elif t >= t0 and t < t1:
            vp = vp + dt * force_acc[r]

    # Node momentum w (m v + A (node - x)) with node - x = (ijk - fx) dx, split as
    # q + dx (i A_0 + j A_1 + k A_2): vector sums only, which keeps the unrolled adjoint small.
    dx = 1.0 / inv_dx
    q = mass * vp - dx * (affine * fx)
    a0 = dx * wp.vec3(affine[0, 0], affine[1, 0], affine[2, 0])
    a1 = dx * wp.vec3(affine[0, 1], affine[1, 1], affine[2, 1])
    a2 = dx * wp.vec3(affine[0, 2], affine[1, 2], affine[2, 2])
    for i in range(3):
        qi = q + float(i) * a0
        for j in range(3):
            qij = qi + float(j) * a1
            wij = W[i, 0] * W[j, 1]
            for k in range(3):
                w = wij * W[k, 2]
                wp.atomic_add(grid_mv, base[0] + i, base[1] + j, base[2] + k, w * (qij + float(k) * a2))
                wp.atomic_add(grid_m, base[0] + i, base[1] + j, base[2] + k, w * mass)


@wp.kernel
def grid_update(
    grid_m: wp.array3d(dtype=float),
    grid_mv: wp.array3d(dtype=wp.vec3),
    col_w: wp.array3d(dtype=float),
    col_mv: wp.array3d(dtype=wp.vec3),
    has_colliders: int,
    bc_kind: wp.array3d(dtype=wp.int32),
    bc_normal: wp.array3d(dtype=wp.vec3),
    gravity: wp.vec3,
    dt: float,
    damping_factor: float,
    v_max: float,
    n: int,
    pad: int,
    sticky_walls: int,
    offset: wp.vec3i,
    grid_v: wp.array3d(dtype=wp.vec3),
):
    """Grid momentum -> velocity with gravity, damping, colliders, anchors and domain walls.

    Launched over the block of nodes that particles can touch (starting at ``offset``): nodes outside it
    are never read by ``g2p``, and skipping them makes the grid cost follow the particles, not the grid.
    """
    ti, tj, tk = wp.tid()
    i = ti + offset[0]
    j = tj + offset[1]
    k = tk + offset[2]
    m = grid_m[i, j, k]
    v = wp.vec3(0.0)
    if m > 1.0e-12:
        v = (grid_mv[i, j, k] / m + dt * gravity) * damping_factor

    if has_colliders != 0:
        cw = col_w[i, j, k]
        if cw > 0.0:
            v = col_mv[i, j, k] / cw

    kind = bc_kind[i, j, k]
    if kind == BC_STICKY:
        v = wp.vec3(0.0)
    elif kind == BC_SLIP:
        nrm = bc_normal[i, j, k]
        v = v - wp.dot(v, nrm) * nrm

    # Domain walls: nodes within `pad` cells of a face. Slip walls only stop motion through the wall.
    idx = wp.vec3i(i, j, k)
    for a in range(3):
        low = idx[a] < pad
        high = idx[a] >= n - pad
        if low or high:
            if sticky_walls != 0:
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
    grid_v[i, j, k] = v


@wp.kernel
def g2p(
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    obj: wp.array(dtype=wp.int32),
    pinned: wp.array(dtype=wp.int32),
    E_obj: wp.array(dtype=float),
    nu_obj: wp.array(dtype=float),
    grid_v: wp.array3d(dtype=wp.vec3),
    dt: float,
    inv_dx: float,
    n: int,
    x_lo: float,
    x_hi: float,
    yield_stress: float,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    C_out: wp.array(dtype=wp.mat33),
    F_out: wp.array(dtype=wp.mat33),
):
    """Grid to particle: velocity, APIC affine matrix, F update with optional von Mises plasticity, advection."""
    p = wp.tid()
    xp = x[p]
    base = stencil_base(xp, inv_dx, n)
    fx = xp * inv_dx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    W = bspline_weights(fx)
    dx = 1.0 / inv_dx

    # C = 4 / dx^2 sum w v (node - x)^T with node - x = (ijk - fx) dx: accumulate sum w v i, sum w v j,
    # sum w v k as vectors (cheaper, and a much smaller unrolled adjoint than 27 outer products).
    new_v = wp.vec3(0.0)
    si = wp.vec3(0.0)
    sj = wp.vec3(0.0)
    sk = wp.vec3(0.0)
    for i in range(3):
        for j in range(3):
            wij = W[i, 0] * W[j, 1]
            for k in range(3):
                wv = (wij * W[k, 2]) * grid_v[base[0] + i, base[1] + j, base[2] + k]
                new_v = new_v + wv
                si = si + float(i) * wv
                sj = sj + float(j) * wv
                sk = sk + float(k) * wv
    new_C = (4.0 * inv_dx) * (wp.matrix_from_cols(si, sj, sk) - wp.outer(new_v, fx))

    F_new = (wp.identity(n=3, dtype=float) + dt * new_C) * F[p]

    if yield_stress > 0.0:
        # Return mapping on the Hencky strain: project its deviatoric part onto the von Mises cylinder;
        # F keeps only the elastic part F^E (the plastic part is never needed for the stress).
        o = obj[p]
        mu = E_obj[o] / (2.0 * (1.0 + nu_obj[o]))
        U, s, V = proper_svd_rotations(F_new)
        eps = wp.vec3(wp.log(wp.max(s[0], 1.0e-4)), wp.log(wp.max(s[1], 1.0e-4)), wp.log(wp.max(s[2], 1.0e-4)))
        eps_dev = eps - wp.vec3((eps[0] + eps[1] + eps[2]) / 3.0)
        norm_dev = wp.length(eps_dev)
        excess = norm_dev - yield_stress / (2.0 * mu)
        if excess > 0.0:
            eps = eps - (excess / norm_dev) * eps_dev
            S = wp.mat33(wp.exp(eps[0]), 0.0, 0.0, 0.0, wp.exp(eps[1]), 0.0, 0.0, 0.0, wp.exp(eps[2]))
            F_new = U * S * wp.transpose(V)

    x_new = xp + dt * new_v
    if pinned[p] != 0:
        x_new = xp
        new_v = wp.vec3(0.0)
    # Keep every particle inside the padded box (its stencil then always lies inside the grid).
    x_new = wp.vec3(wp.clamp(x_new[0], x_lo, x_hi), wp.clamp(x_new[1], x_lo, x_hi), wp.clamp(x_new[2], x_lo, x_hi))

    x_out[p] = x_new
    v_out[p] = new_v
    C_out[p] = new_C
    F_out[p] = F_new


@wp.kernel
def node_boxes_to_bc(
    box_lo: wp.array(dtype=wp.vec3),
    box_hi: wp.array(dtype=wp.vec3),
    box_kind: wp.array(dtype=wp.int32),
    box_normal: wp.array(dtype=wp.vec3),
    n_boxes: int,
    dx: float,
    bc_kind: wp.array3d(dtype=wp.int32),
    bc_normal: wp.array3d(dtype=wp.vec3),
):
    """Bake anchor boxes into per-node boundary conditions once (later boxes win; sticky beats slip)."""
    i, j, k = wp.tid()
    node = wp.vec3(float(i), float(j), float(k)) * dx
    for b in range(n_boxes):
        lo = box_lo[b]
        hi = box_hi[b]
        if node[0] >= lo[0] and node[0] <= hi[0] and node[1] >= lo[1] and node[1] <= hi[1] and node[2] >= lo[2] and node[2] <= hi[2]:
            if bc_kind[i, j, k] != BC_STICKY:
                bc_kind[i, j, k] = box_kind[b]
                bc_normal[i, j, k] = box_normal[b]


@wp.kernel
def anchor_weights_to_grid(
    x: wp.array(dtype=wp.vec3),
    pinned: wp.array(dtype=wp.int32),
    inv_dx: float,
    n: int,
    w_pinned: wp.array3d(dtype=float),
    w_free: wp.array3d(dtype=float),
):
    """Splat each particle's B-spline weights onto the grid, pinned and free particles separately."""
    p = wp.tid()
    xp = x[p]
    base = stencil_base(xp, inv_dx, n)
    fx = xp * inv_dx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    W = bspline_weights(fx)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = W[i, 0] * W[j, 1] * W[k, 2]
                if pinned[p] != 0:
                    wp.atomic_add(w_pinned, base[0] + i, base[1] + j, base[2] + k, w)
                else:
                    wp.atomic_add(w_free, base[0] + i, base[1] + j, base[2] + k, w)


@wp.kernel
def anchored_nodes_to_bc(
    w_pinned: wp.array3d(dtype=float),
    w_free: wp.array3d(dtype=float),
    bc_kind: wp.array3d(dtype=wp.int32),
):
    """Nodes that pinned particles dominate at rest hold still (sticky), like the anchored tissue itself."""
    i, j, k = wp.tid()
    wpin = w_pinned[i, j, k]
    if wpin > 0.0 and wpin >= w_free[i, j, k]:
        bc_kind[i, j, k] = BC_STICKY
