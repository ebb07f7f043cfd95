"""Warp kernels of the BEM time step (paper Eqs. 9 and 12): the two dense matrix-vector passes.

Both are memory-bandwidth bound: every step reads 2 n_max + 2 dense 3N x 3N matrices once.
One block of ``MATVEC_BLOCK`` threads computes one output row: each thread strides over the
columns four at a time (vec4 loads; consecutive threads read consecutive 16-byte words, so every
load is coalesced and wide) and keeps one running sum; the block then reduces its partial sums
(``tile_sum``). Rows are stored with a pitch padded to a multiple of 4 columns (zeros), and the
vectors with the same zero padding. The kernels are generic over the storage precision:
float32 (default, half the bytes; vec4) or float64 (vec4d), partial sums in the storage type.

Launch with ``wp.launch_tiled(..., dim=rows, block_dim=MATVEC_BLOCK)``. The stride is read with
``wp.block_dim()``: on the CPU Warp runs a block as one thread, which then sums the whole row.
"""

from __future__ import annotations

from typing import Any

import warp as wp

MATVEC_BLOCK = wp.constant(256)


@wp.kernel
def history_matvec(
    H: wp.array2d(dtype=Any),
    G: wp.array2d(dtype=Any),
    U: wp.array2d(dtype=Any),
    P: wp.array2d(dtype=Any),
    DQ: wp.array3d(dtype=Any),
    B: wp.array2d(dtype=Any),
    step: int,
    h: wp.array(dtype=Any),
):
    """History term of Eq. (9) at step n = ``step``:

        h_n = sum_{k=1}^{n_max} ( -H_k u_{n-k} + G_k p_{n-k} + [D_k Q_k] [a - g', alpha]_{n-k} ).

    H, G (n_max 3N rows of vec4 columns) hold H_k, G_k (k = 1..n_max) one after the other: row
    (k - 1) 3N + i is row i of H_k. Two-dimensional on purpose: a Warp array's strides are 32-bit
    byte counts, and a (n_max, 3N, 3N) float32 stack's first stride passes 2 GiB at N ~ 7.7k. DQ[k-1]
    is the (3N, 6) block [D_k Q_k]. The ring buffers U, P (n_max, pitch / 4) and B (n_max, 6) hold
    step m in row m mod n_max.
    """
    row, lane = wp.tid()
    stride = wp.block_dim()
    n_max = U.shape[0]
    n = H.shape[0] // n_max
    cols = H.shape[1]
    acc = h.dtype(0.0)
    for k in range(1, n_max + 1):
        slot = (step - k) % n_max
        r = (k - 1) * n + row
        c = lane
        while c < cols:
            acc += wp.dot(G[r, c], P[slot, c]) - wp.dot(H[r, c], U[slot, c])
            c += stride
        j = lane
        while j < 6:
            acc += DQ[k - 1, row, j] * B[slot, j]
            j += stride
    total = wp.tile_sum(wp.tile(acc))
    wp.tile_store(h, total, offset=row)


@wp.kernel
def solve_matvec(
    H0_inv_Gp: wp.array2d(dtype=Any),
    H0_inv: wp.array2d(dtype=Any),
    p: wp.array(dtype=Any),
    h: wp.array(dtype=Any),
    with_p: int,
    u: wp.array(dtype=Any),
):
    """Displacement of Eq. (12): u_n = H_0^-1 G' p_n + H_0^-1 h_n (the first term only if ``with_p``:
    a step without tractions reads one matrix instead of two)."""
    row, lane = wp.tid()
    stride = wp.block_dim()
    cols = H0_inv.shape[1]
    acc = u.dtype(0.0)
    c = lane
    if with_p != 0:
        while c < cols:
            acc += wp.dot(H0_inv_Gp[row, c], p[c]) + wp.dot(H0_inv[row, c], h[c])
            c += stride
    else:
        while c < cols:
            acc += wp.dot(H0_inv[row, c], h[c])
            c += stride
    total = wp.tile_sum(wp.tile(acc))
    wp.tile_store(u, total, offset=row)


@wp.kernel
def write_ring_rows(
    src: wp.array2d(dtype=Any),
    rows: wp.array(dtype=wp.int32),
    slots: wp.array(dtype=wp.int32),
    ring: wp.array3d(dtype=Any),
):
    """ring[rows[i], slots[i], j] = src[rows[i], j]: the bodies of an instance set store their
    step's u, p or [a - g', alpha] (the rings of Eq. 9) in one launch (``wsim.bem.instances``).
    Launch with dim = (len(rows), src.shape[1])."""
    i, j = wp.tid()
    r = rows[i]
    ring[r, slots[i], j] = src[r, j]


# -- the rest of a free step on the device (``wsim.bem.device_step``) ---------------------------

FRAME_SIZE = wp.constant(21)  # R (row-major 9), T, T_dot, omega, L: the frame state of Eq. (11)


@wp.func
def frobenius2(A: wp.mat33d) -> wp.float64:
    return wp.ddot(A, A)


@wp.func
def polar_rotation(A: wp.mat33d) -> wp.mat33d:
    """The rotation nearest A in the Frobenius norm (its orthogonal polar factor): the R_e of the
    shape matching of Sec. 3.2.1 (``wsim.rigid.nearest_rotation`` on the host).

    Newton's iteration X <- (g X + X^-T / g) / 2 with the scaling g = (|X^-1|_F / |X|_F)^(1/2)
    [Higham 1986] converges quadratically to the polar factor of a nonsingular A, in float64 to
    round-off (the 3 x 3 Jacobi SVD is tuned for float32). For det A > 0 that factor is a rotation;
    A here is the weighted moment of the body's points against its rest points, a symmetric
    positive definite matrix times a rotation, so det A > 0 unless the body has turned inside out,
    where the SVD (with the reflection flipped) is the fallback."""
    if wp.determinant(A) <= wp.float64(0.0):
        U = wp.mat33d()
        s = wp.vec3d()
        V = wp.mat33d()
        wp.svd3(A, U, s, V)
        d = wp.float64(1.0)
        if wp.determinant(U * wp.transpose(V)) < wp.float64(0.0):
            d = wp.float64(-1.0)
        D = wp.mat33d(wp.float64(1.0), wp.float64(0.0), wp.float64(0.0),
                      wp.float64(0.0), wp.float64(1.0), wp.float64(0.0),
                      wp.float64(0.0), wp.float64(0.0), d)
        return U * D * wp.transpose(V)
    X = A
    for _it in range(40):
        Xi = wp.inverse(X)
        g = wp.sqrt(wp.sqrt(frobenius2(Xi) / frobenius2(X)))
        Y = wp.float64(0.5) * (g * X + wp.transpose(Xi) / g)
        change = frobenius2(Y - X)
        X = Y
        if change < wp.float64(1.0e-30):
            break
    return X


@wp.func
def rodrigues(phi: wp.vec3d) -> wp.mat33d:
    """exp([phi]x) (``wsim.rigid.rodrigues``; the same small-angle branch)."""
    angle = wp.length(phi)
    I = wp.identity(n=3, dtype=wp.float64)
    if angle < wp.float64(1.0e-12):
        return I + wp.skew(phi)
    K = wp.skew(phi / angle)
    return I + wp.sin(angle) * K + (wp.float64(1.0) - wp.cos(angle)) * (K * K)


@wp.func
def load_frame(frame: wp.array(dtype=wp.float64), k: int) -> wp.vec3d:
    return wp.vec3d(frame[k], frame[k + 1], frame[k + 2])


@wp.func
def store_frame(frame: wp.array(dtype=wp.float64), k: int, v: wp.vec3d):
    frame[k] = v[0]
    frame[k + 1] = v[1]
    frame[k + 2] = v[2]


@wp.func
def node_u(u: wp.array(dtype=Any), n: int) -> wp.vec3d:
    return wp.vec3d(wp.float64(u[3 * n]), wp.float64(u[3 * n + 1]), wp.float64(u[3 * n + 2]))


@wp.kernel
def correct_step(
    u: wp.array(dtype=Any),
    p: wp.array(dtype=Any),
    ext: wp.array(dtype=wp.float64),
    with_p: int,
    q: wp.array(dtype=wp.vec3d),
    wq: wp.array(dtype=wp.vec3d),
    w: wp.array(dtype=wp.float64),
    cx: wp.array(dtype=wp.vec3d),
    PQH: wp.array(dtype=wp.mat33d),
    Ea: wp.array(dtype=wp.mat33d),
    Eb: wp.array(dtype=wp.mat33d),
    w_sum: wp.float64,
    sum_wq: wp.vec3d,
    K_a: wp.mat33d,
    M_t: wp.mat33d,
    M_a: wp.mat33d,
    inertia: wp.mat33d,
    inertia_inv: wp.mat33d,
    gravity: wp.vec3d,
    dt: wp.float64,
    gyroscopic: int,
    slot: int,
    U: wp.array2d(dtype=Any),
    P: wp.array2d(dtype=Any),
    B: wp.array2d(dtype=Any),
    u64: wp.array(dtype=wp.float64),
    frame: wp.array(dtype=wp.float64),
    log: wp.array2d(dtype=wp.float64),
    counter: wp.array(dtype=wp.int32),
    divergence_limit: wp.float64,
    halt: wp.array(dtype=wp.int32),
):
    """The ERRCR stage of a free step (paper Sec. 3.2.1 and Eq. 11) by one block, in float64, after
    u_n of Eq. (12) (``wsim.bem.correction.Correction.apply``, then ``BemBody._finish_step``).
    ``ext`` = [A p_n, C p_n + f, X p_n, f] (X: ``correction.load_balance``; f: the push's torque
    fix, ``BemBody._push_torque``), read only ``with_p``; u_n first takes the loads' balance,
    u_i += Ea_i X_a p + Eb_i X_alpha p:

    1. t = sum_i w_i u_i / sum_i w_i and the moment A = sum_i (q_i + u_i - t) (w_i q_i)^T
       (q_i = x_i - c_0; the t term is t (sum_i w_i q_i)^T, zero up to round-off);
    2. R_e = polar(A) (shape matching), da = -K_a t;
    3. dalpha = M_t t + M_a da + P_Q H_0 du, du_i = R_e^T (q_i + u_i - t) + c_0 - x_i - (u_i - t)
       (M_t = -P_Q H_0 (1 (x) I), M_a = -P_Q D_0: the residual r_1 of step 5 projected);
    4. u_n <- u_n + E [da; dalpha] (float64 out, and the ring row U[slot] in storage precision),
       P[slot] = p_n, B[slot] = b + X p_n - [0; f] with b = [a_ext + da, alpha_ext + dalpha]
       = [a - g', alpha] (the BEM's terms: the balance in, the frame's torque fix out);
    5. the frame (Eq. 11d-g, ``wsim.rigid.RigidFrame.update``): T_dot += dt (g + R b_a);
       L += dt R I b_alpha, omega = R I^-1 R^T L (``gyroscopic``) or omega += dt R b_alpha;
       R <- exp(dt [omega]x) R; T += dt T_dot;
    6. the log row ``counter`` (mod its length): [max_i |u_i|, flags], flags 1: u non-finite,
       2: T, 4: T_dot, 8: omega (the host's ``_check_step`` reads them after the batch); with a
       flag or max |u| > ``divergence_limit``, ``halt`` is set and the batch's later steps
       change nothing (the host stops the body at this step).

    A non-finite u_n gets no correction (da = dalpha = 0), as on the host.

    Per-node blocks: PQH_i = P_Q H_0 columns 3i..3i+2; Ea_i, Eb_i = rows 3i..3i+2 of H_0^-1 D_0 and
    H_0^-1 Q_0. Launch with ``wp.launch_tiled(dim=1, block_dim=...)``; the sums are tile
    reductions, so the result does not depend on timing."""
    _blk, lane = wp.tid()
    if halt[0] != 0:  # an earlier step of the batch failed: the state stays at that step
        return
    T = wp.block_dim()
    N = q.shape[0]
    s_u = wp.vec3d()
    s_A = wp.mat33d()
    bad_in = int(0)
    bal_a = wp.vec3d()
    bal_w = wp.vec3d()
    fix = wp.vec3d()
    if with_p != 0:
        bal_a = load_frame(ext, 6)
        bal_w = load_frame(ext, 9)
        fix = load_frame(ext, 12)
    i = lane
    while i < N:
        un = node_u(u, i) + Ea[i] * bal_a + Eb[i] * bal_w
        if not (wp.isfinite(un[0]) and wp.isfinite(un[1]) and wp.isfinite(un[2])):
            bad_in = 1
        s_u += w[i] * un
        s_A += wp.outer(q[i] + un, wq[i])
        i += T
    bad_in = wp.tile_extract(wp.tile_max(wp.tile(bad_in)), 0)
    t = wp.tile_extract(wp.tile_sum(wp.tile(s_u, preserve_type=True)), 0) / w_sum
    A = wp.tile_extract(wp.tile_sum(wp.tile(s_A, preserve_type=True)), 0) - wp.outer(t, sum_wq)
    # a non-finite u gets no correction (as on the host, whose SVD cannot take it): the frame
    # moves with the loads alone and the log reports the displacement
    R_e = wp.identity(n=3, dtype=wp.float64)
    da = wp.vec3d()
    if bad_in == 0:
        R_e = polar_rotation(A)
        da = -(K_a * t)
    s_d = wp.vec3d()
    i = lane
    while i < N and bad_in == 0:
        un = node_u(u, i) + Ea[i] * bal_a + Eb[i] * bal_w
        pn = q[i] + un - t
        du = wp.transpose(R_e) * pn + cx[i] - (un - t)
        s_d += PQH[i] * du
        i += T
    dalpha = M_t * t + M_a * da + wp.tile_extract(wp.tile_sum(wp.tile(s_d, preserve_type=True)), 0)
    if bad_in != 0:
        dalpha = wp.vec3d()
    peak = wp.float64(0.0)
    bad = int(0)
    i = lane
    while i < N:
        un = node_u(u, i) + Ea[i] * (bal_a + da) + Eb[i] * (bal_w + dalpha)
        for c in range(3):
            value = un[c]
            u64[3 * i + c] = value
            U[slot, 3 * i + c] = U.dtype(value)
            if wp.isfinite(value):
                peak = wp.max(peak, wp.abs(value))
            else:
                bad = 1
        i += T
    j = lane
    while j < P.shape[1]:
        if with_p != 0:
            P[slot, j] = p[j]
        else:
            P[slot, j] = P.dtype(0.0)
        j += T
    peak = wp.tile_extract(wp.tile_max(wp.tile(peak)), 0)
    bad = wp.tile_extract(wp.tile_max(wp.tile(bad)), 0)
    if lane == 0:
        a_ext = wp.vec3d()
        alpha_ext = wp.vec3d()
        if with_p != 0:
            a_ext = load_frame(ext, 0)
            alpha_ext = load_frame(ext, 3)
        b_a = a_ext + da
        b_w = alpha_ext + dalpha
        for c in range(3):
            B[slot, c] = B.dtype(b_a[c] + bal_a[c])
            B[slot, 3 + c] = B.dtype(b_w[c] + bal_w[c] - fix[c])
        R = wp.mat33d(frame[0], frame[1], frame[2], frame[3], frame[4], frame[5], frame[6], frame[7], frame[8])
        Tx = load_frame(frame, 9)
        v = load_frame(frame, 12) + dt * (gravity + R * b_a)
        omega = load_frame(frame, 15)
        L = load_frame(frame, 18)
        if gyroscopic != 0:
            L = L + dt * (R * (inertia * b_w))
            omega = R * (inertia_inv * (wp.transpose(R) * L))
        else:
            omega = omega + dt * (R * b_w)
            L = R * (inertia * (wp.transpose(R) * omega))
        R = rodrigues(dt * omega) * R
        Tx = Tx + dt * v
        for r in range(3):
            for c in range(3):
                frame[3 * r + c] = R[r, c]
        store_frame(frame, 9, Tx)
        store_frame(frame, 12, v)
        store_frame(frame, 15, omega)
        store_frame(frame, 18, L)
        flags = wp.float64(bad)
        if not (wp.isfinite(Tx[0]) and wp.isfinite(Tx[1]) and wp.isfinite(Tx[2])):
            flags += wp.float64(2.0)
        if not (wp.isfinite(v[0]) and wp.isfinite(v[1]) and wp.isfinite(v[2])):
            flags += wp.float64(4.0)
        if not (wp.isfinite(omega[0]) and wp.isfinite(omega[1]) and wp.isfinite(omega[2])):
            flags += wp.float64(8.0)
        k = counter[0]
        row = k % log.shape[0]
        log[row, 0] = peak
        log[row, 1] = flags
        counter[0] = k + 1
        if flags != wp.float64(0.0) or peak > divergence_limit:
            halt[0] = 1


@wp.kernel
def reorthonormalize(frame: wp.array(dtype=wp.float64)):
    """R <- polar(R): the round-off of repeated products removed (``RigidFrame.reorthonormalize``)."""
    R = wp.mat33d(frame[0], frame[1], frame[2], frame[3], frame[4], frame[5], frame[6], frame[7], frame[8])
    R = polar_rotation(R)
    for r in range(3):
        for c in range(3):
            frame[3 * r + c] = R[r, c]
