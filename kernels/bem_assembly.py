"""Collocation assembly of the Laplace-domain BEM matrices (Sugimoto et al., Eq. 8 at one s).

For collocation node i at x_i and triangle t with linear shape functions N_v (v in t):

    H[i, v] += int_t p(x_i, y; s) N_v(y) dA,   G[i, v] += int_t u(x_i, y; s) N_v(y) dA,
    D[i]    += int_t d(x_i, y; s) dA,          L[i]    += int_t l(x_i, y; s) dA,

with the kernels of Eqs. (16), (17), (19), (21) (``bem_kernels``). When x_i is a vertex of t
(the triangle is "incident"), the polar rule about that vertex is used, and the strongly singular
diagonal block is never integrated directly: the rigid-body identity of the static problem,
c(x_i) + CPV int p0(x_i, y) dA = 0 on a closed surface (p0 the Kelvin traction kernel), gives

    c(x_i) + CPV int p0 N_i dA = - sum_{v not at x_i} int p0 N_v dA = - int p0 (1 - N_i) dA,

whose integrand is at most weakly singular (1 - N_i = O(r)); that is accumulated in S[i]. The
dynamic remainder p - p0 = O(1/r) of the diagonal block is weakly singular too and is integrated
with the polar rule. S therefore holds the free term c(x_i) (for any corner: it is Mantic's
c exactly, up to quadrature error) plus the static CPV; it is added to the diagonal block by
``add_diagonal``. Everything is float64.

Races: H and G blocks are written for the three vertices of t, so triangles of one launch must not
share a node (the caller launches per triangle colour on CUDA; a serial CPU launch needs no
colours). D, L and S sum over all triangles of a row: each thread handles a chunk of triangles and
adds its partial sums atomically (float64 atomics; on CUDA their order, and so the last bit, can
vary between runs). The near-field level is a threshold on distance / edge: a pair exactly at a
threshold (common on regular meshes) may pick different rules on CPU and GPU, whose arithmetic
differs by FMA contraction; the results then differ by the quadrature error, not round-off.
"""

from __future__ import annotations

import warp as wp

from wsim.kernels.bem_kernels import cross_matrix, d_from, kernel_scalars, l_from, p_from, u_from

_PI4 = wp.constant(wp.float64(12.566370614359172))  # 4 pi


@wp.func
def static_p_coeffs(r: wp.float64, kappa: wp.float64):
    """Kelvin's traction kernel in the layout of ``p_coeffs``: C1 = C4 = -kappa, C2 = -3 (1 - kappa),
    C3 = kappa, all over 4 pi r^2, with kappa = mu / (lambda + 2 mu) = (1 - 2 nu) / (2 (1 - nu))."""
    f = wp.float64(1.0) / (_PI4 * r * r)
    return -kappa * f, wp.float64(-3.0) * (wp.float64(1.0) - kappa) * f, kappa * f


@wp.func
def triangle_distance(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.float64:
    """Distance from p to the triangle abc (closest point by Voronoi regions, Ericson 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    zero = wp.float64(0.0)
    if d1 <= zero and d2 <= zero:
        return wp.length(ap)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= zero and d4 <= d3:
        return wp.length(bp)
    vc = d1 * d4 - d3 * d2
    if vc <= zero and d1 >= zero and d3 <= zero:
        return wp.length(ap - ab * (d1 / (d1 - d3)))
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= zero and d5 <= d6:
        return wp.length(cp)
    vb = d5 * d2 - d1 * d6
    if vb <= zero and d2 >= zero and d6 <= zero:
        return wp.length(ap - ac * (d2 / (d2 - d6)))
    va = d3 * d6 - d5 * d4
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        return wp.length(bp - (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6))))
    den = wp.float64(1.0) / (va + vb + vc)
    return wp.length(ap - ab * (vb * den) - ac * (vc * den))


@wp.func
def near_level(dist: wp.float64, h: wp.float64, near_ratio: wp.float64, n_levels: int) -> int:
    """0 for a far triangle; one more level per halving of dist / h below near_ratio."""
    level = int(0)
    limit = near_ratio * h
    while level < n_levels and dist < limit:
        level += 1
        limit = limit * wp.float64(0.5)
    return level


@wp.func
def add_block(M_re: wp.array2d(dtype=wp.float64), M_im: wp.array2d(dtype=wp.float64), row: int, col: int,
              re: wp.mat33d, im: wp.mat33d):
    for a in range(3):
        for b in range(3):
            M_re[row + a, col + b] += re[a, b]
            M_im[row + a, col + b] += im[a, b]


@wp.kernel
def assemble_rows(
    row0: int,
    chunk: int,
    tri_begin: int,
    tri_end: int,
    x: wp.array(dtype=wp.vec3d),
    group: wp.array(dtype=wp.int32),
    tri: wp.array(dtype=wp.vec3i),
    tri_order: wp.array(dtype=wp.int32),
    tri_normal: wp.array(dtype=wp.vec3d),
    tri_area: wp.array(dtype=wp.float64),
    tri_h: wp.array(dtype=wp.float64),
    reg_b: wp.array(dtype=wp.vec3d),
    reg_w: wp.array(dtype=wp.float64),
    reg_off: wp.array(dtype=wp.int32),
    n_levels: int,
    near_ratio: wp.float64,
    sing_b: wp.array(dtype=wp.vec3d),
    sing_w: wp.array(dtype=wp.float64),
    s: wp.vec2d,
    a1: wp.float64,
    a2: wp.float64,
    rho: wp.float64,
    kappa: wp.float64,
    H_re: wp.array2d(dtype=wp.float64),
    H_im: wp.array2d(dtype=wp.float64),
    G_re: wp.array2d(dtype=wp.float64),
    G_im: wp.array2d(dtype=wp.float64),
    D_re: wp.array(dtype=wp.mat33d),
    D_im: wp.array(dtype=wp.mat33d),
    L_re: wp.array(dtype=wp.mat33d),
    L_im: wp.array(dtype=wp.mat33d),
    S: wp.array(dtype=wp.mat33d),
):
    """Rows row0 + il of H, G (local row block il) and D, L, S from triangles
    tri_order[tri_begin + c chunk : ...] (at most ``chunk`` of them, below tri_end)."""
    il, c = wp.tid()
    i = row0 + il
    xi = x[i]
    gi = group[i]
    k0 = tri_begin + c * chunk
    k1 = wp.min(k0 + chunk, tri_end)
    eye = wp.identity(n=3, dtype=wp.float64)
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    Dr = wp.mat33d()
    Di = wp.mat33d()
    Lr = wp.mat33d()
    Li = wp.mat33d()
    Sa = wp.mat33d()
    for k in range(k0, k1):
        t = tri_order[k]
        nodes = tri[t]
        # rotate the triangle so that an incident (singular) vertex comes first
        corner = int(-1)
        for j in range(3):
            if group[nodes[j]] == gi:
                corner = j
        sing = zero
        rot = int(0)
        if corner >= 0:
            sing = one
            rot = corner
        v0 = nodes[rot]
        v1 = nodes[(rot + 1) % 3]
        v2 = nodes[(rot + 2) % 3]
        P0 = x[v0]
        P1 = x[v1]
        P2 = x[v2]
        n = tri_normal[t]
        area = tri_area[t]
        q0 = int(0)
        q1 = int(0)
        if corner >= 0:
            q1 = sing_w.shape[0]
        else:
            level = near_level(triangle_distance(xi, P0, P1, P2), tri_h[t], near_ratio, n_levels)
            q0 = reg_off[level]
            q1 = reg_off[level + 1]
        H0r = wp.mat33d()
        H0i = wp.mat33d()
        H1r = wp.mat33d()
        H1i = wp.mat33d()
        H2r = wp.mat33d()
        H2i = wp.mat33d()
        G0r = wp.mat33d()
        G0i = wp.mat33d()
        G1r = wp.mat33d()
        G1i = wp.mat33d()
        G2r = wp.mat33d()
        G2i = wp.mat33d()
        for q in range(q0, q1):
            b = wp.vec3d()
            w = zero
            if corner >= 0:
                b = sing_b[q]
                w = sing_w[q] * area
            else:
                b = reg_b[q]
                w = reg_w[q] * area
            y = P0 * b[0] + P1 * b[1] + P2 * b[2]
            rv = y - xi
            r = wp.length(rv)
            d = rv / r
            dn = wp.dot(d, n)
            dd = wp.outer(d, d)
            dnT = wp.outer(d, n)
            sym = eye * dn + wp.outer(n, d)  # the two terms sharing C1
            E1, E2, p2, Phi = kernel_scalars(r, s, a1, a2)  # the exponentials once for all four kernels
            A, B = u_from(r, E1, E2, Phi, a1, a2, rho)
            Ur = (eye * A[0] + dd * B[0]) * w
            Ui = (eye * A[1] + dd * B[1]) * w
            C1, C2, C3 = p_from(r, s, E1, E2, Phi, a1, a2)
            Pr = (sym * C1[0] + dd * (dn * C2[0]) + dnT * C3[0]) * w
            Pi = (sym * C1[1] + dd * (dn * C2[1]) + dnT * C3[1]) * w
            S1, S2, S3 = static_p_coeffs(r, kappa)
            Ps = (sym * S1 + dd * (dn * S2) + dnT * S3) * w
            H0r += (Pr - Ps * sing) * b[0]
            H0i += Pi * b[0]
            H1r += Pr * b[1]
            H1i += Pi * b[1]
            H2r += Pr * b[2]
            H2i += Pi * b[2]
            G0r += Ur * b[0]
            G0i += Ui * b[0]
            G1r += Ur * b[1]
            G1i += Ui * b[1]
            G2r += Ur * b[2]
            G2i += Ui * b[2]
            Sa -= Ps * (one - sing * b[0])
            Dn, Dd = d_from(p2, Phi, a2)
            Dr += (dnT * Dn[0] + eye * (dn * Dd[0])) * w
            Di += (dnT * Dn[1] + eye * (dn * Dd[1])) * w
            L1, L2 = l_from(r, s, E2, Phi, a2)
            dxn = wp.outer(d, wp.cross(d, n))
            nx = cross_matrix(n)
            Lr += (dxn * L1[0] + nx * L2[0]) * w
            Li += (dxn * L1[1] + nx * L2[1]) * w
        row = 3 * il
        add_block(H_re, H_im, row, 3 * v0, H0r, H0i)
        add_block(H_re, H_im, row, 3 * v1, H1r, H1i)
        add_block(H_re, H_im, row, 3 * v2, H2r, H2i)
        add_block(G_re, G_im, row, 3 * v0, G0r, G0i)
        add_block(G_re, G_im, row, 3 * v1, G1r, G1i)
        add_block(G_re, G_im, row, 3 * v2, G2r, G2i)
    wp.atomic_add(D_re, il, Dr)
    wp.atomic_add(D_im, il, Di)
    wp.atomic_add(L_re, il, Lr)
    wp.atomic_add(L_im, il, Li)
    wp.atomic_add(S, il, Sa)


@wp.kernel
def add_diagonal(row0: int, first: wp.array(dtype=wp.int32), c_own: wp.array(dtype=wp.mat33d),
                 S: wp.array(dtype=wp.mat33d), H_re: wp.array2d(dtype=wp.float64)):
    """H[i, first[i]] += S[i] - c_own[i] and H[i, i] += c_own[i] (S is real: the free term plus the
    static principal value). c_own is zero except at vertices carrying several nodes, where the
    free term must sit on each copy's own column (``wsim.bem.surface``)."""
    il, a, b = wp.tid()
    i = row0 + il
    c = c_own[i][a, b]
    H_re[3 * il + a, 3 * first[i] + b] += S[il][a, b] - c
    H_re[3 * il + a, 3 * i + b] += c


@wp.kernel
def cq_accumulate(
    M_re: wp.array2d(dtype=wp.float64),
    M_im: wp.array2d(dtype=wp.float64),
    w_re: wp.array(dtype=wp.float64),
    w_im: wp.array(dtype=wp.float64),
    out: wp.array2d(dtype=wp.float64),
):
    """Eq. (15) one sample at a time: out_k += Re(w_k M) for k = 0..n_max, where w_k carries
    R^-k zeta^(-k l) / L and the factor 2 of the conjugate sample L - l. out_k is rows
    k R .. (k + 1) R - 1 of ``out`` (R = M's rows): 2-D because a Warp array's strides are 32-bit
    byte counts, and a (n_max + 1, R, 3N) stack's first stride passes 2 GiB for a 10k-node body."""
    r, c = wp.tid()
    mr = M_re[r, c]
    mi = M_im[r, c]
    rows = M_re.shape[0]
    for k in range(w_re.shape[0]):
        out[k * rows + r, c] += w_re[k] * mr - w_im[k] * mi


@wp.kernel
def to_float32(src: wp.array2d(dtype=wp.float64), dst: wp.array2d(dtype=wp.float32)):
    """Storage cast on the device, so only half the bytes cross to the host."""
    r, c = wp.tid()
    dst[r, c] = wp.float32(src[r, c])
