"""Projected Gauss-Seidel over point constraints with a dense linear response (Warp).

A constraint solve sees m points. Point i's world position at the end of the step is affine in
the world forces f_j [N] applied at the points over the step:

    V_i(f) = V0_i + sum_j K_ij f_j        (K_ij: 3 x 3 blocks of the (3m, 3m) response K [m/N])

(for a BEM body, Eq. 14 of Sugimoto et al. 2022 with the tractions of the forces; see
``wsim.bem.constraints``). Each point carries one constraint kind:

* ``FIXED``: V_i = target_i (bilateral, 3 rows);
* ``CONTACT``: a half-space n_i . V_i >= height_i with Coulomb friction mu_i: the normal force
  f_n = n_i . f_i >= 0 is complementary to the gap, and the tangential force opposes the slip
  s_i = P_t (V_i - target_i) (target_i: where the point would be if it moved with the collider's
  material, i.e. its position at the step start carried by the collider) inside |f_t| <= mu f_n.

One sweep visits the points in order and, with B = K_ii and V_i recomputed from the current f
(Gauss-Seidel), updates point i's force: FIXED solves B df = target - V; CONTACT first takes the
normal row, f_n <- max(0, f_n - gap / (n.B n)), then, with V moved by that change, the tangential
2 x 2 block, f_t <- f_t - (T B T^T)^-1 T (V - target), projected onto the disc |f_t| <= mu f_n
(the staggered normal / friction projections of Kaufman et al. 2008 used by the paper). The sweep
residual is max_i |B df_i| [m], the largest position change the sweep made; the solve stops when
it falls below ``tol`` or after ``max_iter`` sweeps. K is not symmetric (H_0 and G_0 are not),
so convergence is not guaranteed: the caller records the iterations and the residual.

The kernel runs on one thread (the points are coupled by the dense K, so a sweep is sequential);
m is the number of points near a collider or held, not the body's vertex count.
"""

from __future__ import annotations

import warp as wp

CONTACT = wp.constant(0)
FIXED = wp.constant(1)


@wp.func
def response_times(K: wp.array2d(dtype=wp.float64), f: wp.array(dtype=wp.vec3d), i: int) -> wp.vec3d:
    """sum_j K_ij f_j (rows 3i..3i+2 of K times the stacked forces)."""
    x = wp.float64(0.0)
    y = wp.float64(0.0)
    z = wp.float64(0.0)
    for j in range(f.shape[0]):
        fj = f[j]
        c = 3 * j
        x += K[3 * i, c] * fj[0] + K[3 * i, c + 1] * fj[1] + K[3 * i, c + 2] * fj[2]
        y += K[3 * i + 1, c] * fj[0] + K[3 * i + 1, c + 1] * fj[1] + K[3 * i + 1, c + 2] * fj[2]
        z += K[3 * i + 2, c] * fj[0] + K[3 * i + 2, c + 1] * fj[1] + K[3 * i + 2, c + 2] * fj[2]
    return wp.vec3d(x, y, z)


@wp.func
def diagonal_block(K: wp.array2d(dtype=wp.float64), i: int) -> wp.mat33d:
    r = 3 * i
    return wp.mat33d(K[r, r], K[r, r + 1], K[r, r + 2],
                     K[r + 1, r], K[r + 1, r + 1], K[r + 1, r + 2],
                     K[r + 2, r], K[r + 2, r + 1], K[r + 2, r + 2])


@wp.func
def tangent_basis(n: wp.vec3d) -> wp.mat33d:
    """Rows t1, t2, n: an orthonormal basis with n last."""
    a = wp.vec3d(wp.float64(1.0), wp.float64(0.0), wp.float64(0.0))
    if wp.abs(n[0]) > wp.float64(0.6):
        a = wp.vec3d(wp.float64(0.0), wp.float64(1.0), wp.float64(0.0))
    t1 = wp.normalize(wp.cross(n, a))
    t2 = wp.cross(n, t1)
    return wp.mat33d(t1[0], t1[1], t1[2], t2[0], t2[1], t2[2], n[0], n[1], n[2])


@wp.func
def contact_update(B: wp.mat33d, V: wp.vec3d, f: wp.vec3d, n: wp.vec3d, height: wp.float64,
                   target: wp.vec3d, mu: wp.float64) -> wp.vec3d:
    """The new force of a CONTACT point (module docstring): normal row, then the friction disc."""
    zero = wp.float64(0.0)
    fn_old = wp.dot(n, f)
    gap = wp.dot(n, V) - height
    bn = wp.dot(n, B * n)
    fn_new = fn_old
    if bn > zero:
        fn_new = wp.max(fn_old - gap / bn, zero)
    f_t = f - fn_old * n
    V = V + B * ((fn_new - fn_old) * n)
    if mu <= zero or fn_new <= zero:
        return fn_new * n
    T = tangent_basis(n)
    t1 = wp.vec3d(T[0, 0], T[0, 1], T[0, 2])
    t2 = wp.vec3d(T[1, 0], T[1, 1], T[1, 2])
    s = V - target
    s1 = wp.dot(t1, s)
    s2 = wp.dot(t2, s)
    b11 = wp.dot(t1, B * t1)
    b12 = wp.dot(t1, B * t2)
    b21 = wp.dot(t2, B * t1)
    b22 = wp.dot(t2, B * t2)
    det = b11 * b22 - b12 * b21
    g1 = wp.dot(t1, f_t)
    g2 = wp.dot(t2, f_t)
    if det > zero:
        g1 = g1 - (b22 * s1 - b12 * s2) / det
        g2 = g2 - (b11 * s2 - b21 * s1) / det
    limit = mu * fn_new
    mag = wp.sqrt(g1 * g1 + g2 * g2)
    if mag > limit:
        g1 = g1 * (limit / mag)
        g2 = g2 * (limit / mag)
    return fn_new * n + g1 * t1 + g2 * t2


@wp.func
def point_update(B: wp.mat33d, V: wp.vec3d, f: wp.vec3d, kind: int, n: wp.vec3d, height: wp.float64,
                 target: wp.vec3d, mu: wp.float64) -> wp.vec3d:
    """The new force of one point given its current position V and diagonal block B (module docstring)."""
    if kind == FIXED:
        return f + wp.inverse(B) * (target - V)
    return contact_update(B, V, f, n, height, target, mu)


@wp.kernel
def pgs_points(
    K: wp.array2d(dtype=wp.float64),
    V0: wp.array(dtype=wp.vec3d),
    kind: wp.array(dtype=int),
    normal: wp.array(dtype=wp.vec3d),
    height: wp.array(dtype=wp.float64),
    target: wp.array(dtype=wp.vec3d),
    mu: wp.array(dtype=wp.float64),
    max_iter: int,
    tol: wp.float64,
    f: wp.array(dtype=wp.vec3d),
    stats: wp.array(dtype=wp.float64),
    V_out: wp.array(dtype=wp.vec3d),
):
    """Sweeps of projected Gauss-Seidel (module docstring) from the forces in ``f`` (a warm start);
    stats = [sweeps, last sweep's residual [m]]; V_out = V0 + K f of the final forces. Launch with dim = 1."""
    m = V0.shape[0]
    sweeps = int(0)
    res = wp.float64(0.0)
    done = int(0)
    for it in range(max_iter):
        if done == 0:
            res = wp.float64(0.0)
            for i in range(m):
                V = V0[i] + response_times(K, f, i)
                B = diagonal_block(K, i)
                fi = f[i]
                new = point_update(B, V, fi, kind[i], normal[i], height[i], target[i], mu[i])
                res = wp.max(res, wp.length(B * (new - fi)))
                f[i] = new
            sweeps = it + 1
            if res <= tol:
                done = 1
    stats[0] = wp.float64(sweeps)
    stats[1] = res
    for i in range(m):
        V_out[i] = V0[i] + response_times(K, f, i)


@wp.kernel
def assemble_delassus(
    K: wp.array(dtype=wp.float64),
    k_offset: wp.array(dtype=int),
    k_rows: wp.array(dtype=int),
    side_body: wp.array2d(dtype=int),
    side_point: wp.array2d(dtype=int),
    side_sign: wp.array2d(dtype=wp.float64),
    out: wp.array2d(dtype=wp.float64),
    out_t: wp.array2d(dtype=wp.float64),
):
    """The response of constraint values to constraint forces, out_cd = sum over the sides s of c
    and s' of d on one body b of sign_s sign_s' K_b[p_s, p_s'] (3 x 3 blocks). A constraint has one
    side (a point held or in contact) or two (a joint: the first point minus the second, its force
    on the first and minus it on the second). Body b's (3 n_b)^2 row-major response starts at
    K[k_offset[b]] with k_rows[b] = 3 n_b rows; out_t = out^T (for ``pgs_block``). Launch with dim = (C, C)."""
    c, d = wp.tid()
    blk = wp.mat33d()
    for s in range(2):
        sc = side_sign[c, s]
        if sc != wp.float64(0.0):
            b = side_body[c, s]
            for t in range(2):
                sd = side_sign[d, t]
                if sd != wp.float64(0.0) and side_body[d, t] == b:
                    o = k_offset[b]
                    n = k_rows[b]
                    r0 = 3 * side_point[c, s]
                    c0 = 3 * side_point[d, t]
                    for p in range(3):
                        for q in range(3):
                            blk[p, q] = blk[p, q] + sc * sd * K[o + (r0 + p) * n + c0 + q]
    for p in range(3):
        for q in range(3):
            out[3 * c + p, 3 * d + q] = blk[p, q]
            out_t[3 * d + q, 3 * c + p] = blk[p, q]


#: threads of the block that runs ``pgs_block`` on CUDA (one block: the sweep is sequential)
PGS_BLOCK = 256


@wp.func
def column_block(Kt: wp.array2d(dtype=wp.float64), j: int, i: int) -> wp.mat33d:
    """K_ji from the transpose Kt = K^T (rows of Kt are columns of K, so a block's lanes j, j+1,
    ... read neighbouring addresses)."""
    r = 3 * i
    c = 3 * j
    return wp.mat33d(Kt[r, c], Kt[r + 1, c], Kt[r + 2, c],
                     Kt[r, c + 1], Kt[r + 1, c + 1], Kt[r + 2, c + 1],
                     Kt[r, c + 2], Kt[r + 1, c + 2], Kt[r + 2, c + 2])


@wp.kernel
def pgs_block(
    K: wp.array2d(dtype=wp.float64),
    Kt: wp.array2d(dtype=wp.float64),
    V0: wp.array(dtype=wp.vec3d),
    kind: wp.array(dtype=int),
    normal: wp.array(dtype=wp.vec3d),
    height: wp.array(dtype=wp.float64),
    target: wp.array(dtype=wp.vec3d),
    mu: wp.array(dtype=wp.float64),
    max_iter: int,
    tol: wp.float64,
    f: wp.array(dtype=wp.vec3d),
    stats: wp.array(dtype=wp.float64),
    V: wp.array(dtype=wp.vec3d),
):
    """``pgs_points`` run by one block: the same sweeps, in the same order, with the same result.

    Lane l owns the points j = l, l + T, ... (T = block_dim) and keeps their current positions
    V_j = V0_j + sum_k K_jk f_k. For each point i in turn, its owner makes the update of
    ``pgs_points`` and the block shares the force change df (``tile_from_thread``); every lane then
    adds K_ji df to its points' V_j (reading column i of K from its transpose, coalesced). The
    sweep is sequential as Gauss-Seidel must be, but each step's work is spread over the block,
    which hides the memory latency a single thread pays on every element of K (on an H100: ~50 us
    per point of a 420-point bunny contact one thread at a time). Launch with
    ``wp.launch_tiled(dim=1, block_dim=PGS_BLOCK)``; on the CPU a block is one lane."""
    _blk, lane = wp.tid()
    T = wp.block_dim()
    m = V0.shape[0]
    j = lane
    while j < m:
        V[j] = V0[j] + response_times(K, f, j)
        j += T
    # a block barrier: no lane may change f (the first sweep) while another still sums it above
    wp.tile_max(wp.tile(wp.float64(0.0)))
    sweeps = int(0)
    res = wp.float64(0.0)
    done = int(0)
    for it in range(max_iter):
        if done == 0:
            local = wp.float64(0.0)
            for i in range(m):
                owner = i % T
                df = wp.vec3d()
                if lane == owner:
                    B = diagonal_block(K, i)
                    fi = f[i]
                    new = point_update(B, V[i], fi, kind[i], normal[i], height[i], target[i], mu[i])
                    df = new - fi
                    local = wp.max(local, wp.length(B * df))
                    f[i] = new
                d = wp.tile_extract(wp.tile_from_thread(shape=1, value=df, thread_idx=owner), 0)
                j = lane
                while j < m:
                    V[j] = V[j] + column_block(Kt, j, i) * d
                    j += T
            res = wp.tile_extract(wp.tile_max(wp.tile(local)), 0)
            sweeps = it + 1
            if res <= tol:
                done = 1
    # the final positions exactly (the running sums above round differently)
    j = lane
    while j < m:
        V[j] = V0[j] + response_times(K, f, j)
        j += T
    if lane == 0:
        stats[0] = wp.float64(sweeps)
        stats[1] = res
