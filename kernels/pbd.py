"""XPBD kernels: prediction, constraint projection, velocity update.

Notation follows Macklin, Müller & Chentanez, "XPBD: Position-Based Simulation of Compliant
Constrained Dynamics" (MIG 2016), cited below as [XPBD], and Müller et al., "Position Based
Dynamics" (2007), cited as [PBD]. For one constraint C(x) with compliance alpha and Lagrange
multiplier lambda, one projection is ([XPBD] Eq. 18 with the Rayleigh damping of Eq. 26):

    alpha_t = alpha / h^2                       (h: substep [s])
    gamma   = beta / h                          (beta: stiffness-proportional Rayleigh damping [s])
    dlambda = (-C - alpha_t * lambda - gamma * grad C . (x - x_n))
              / ((1 + gamma) * sum_i w_i |grad_i C|^2 + alpha_t)
    x_i    += w_i * grad_i C * dlambda,     lambda += dlambda

w_i = 1/m_i is the inverse mass (0 for pinned and kinematic particles). Every correction is
weighted by w_i and every constraint below is invariant under translation and rotation, so one
projection changes neither linear nor angular momentum.

Positions during a substep are x = x_pred + dx: the prediction x_pred stays fixed and the
constraint and contact corrections accumulate in dx. The velocity update adds dx / h, so each
correction changes the momentum by exactly what it should (+-n dlambda, rounded relative to the
correction): with corrections added to absolute float32 positions, each one was rounded to
ulp(|x|) and the rounding, divided by h, became momentum from nothing (1 % of sum m|v| in 0.4 s
for a breathing 0.5 m ball at 4000 substeps/s; the float64 numpy reference: 4e-12 %).

Parallel projection is race-free because constraints are coloured (no two constraints of one
colour share a particle; see ``wsim.colouring``) and each launch covers one colour,
starting at ``offset`` in the colour-sorted arrays (Gauss-Seidel between colours). In the Jacobi
mode (``omega`` > 0) one launch covers a whole family: every constraint reads the positions as
they were before the launch, scales its multiplier increment by omega / (the largest count of
the family's constraints on any of its particles) - the same factor for every particle of the
constraint, so each projection still changes neither momentum - and adds its corrections to
``acc`` atomically; ``apply_jacobi`` then moves them into dx. Fewer launches (one a family
instead of one a colour) for slower convergence per iteration. Positions and multipliers are float32
(bandwidth); the global volume sums and the rigid-motion moments are accumulated in float64
because they add up O(N) terms of alternating sign.
"""

from __future__ import annotations

import warp as wp


@wp.func
def xpbd_delta_lambda(
    C: float, lam: float, w_grad2: float, dC: float, compliance: float, beta: float, h: float
) -> float:
    """Multiplier increment of [XPBD] Eq. 18 with Rayleigh damping (Eq. 26); see module docstring.

    [XPBD] writes gamma = alpha_t beta_t / h with beta_t = h^2 c for a damping coefficient c; for
    stiffness-proportional Rayleigh damping c = beta k = beta / alpha, so gamma = beta / h: a mode
    of angular frequency omega gets the damping ratio beta omega / 2, for every constraint type.
    ``dC`` = C(x) - C(x_prev), the constraint's change over the substep: grad C . (x - x_prev) to
    first order, but exactly 0 for a rigid motion (grad C . (x - x_prev) is not: a rotation by
    omega h moves it by |e| (omega h)^2 / 2 for an edge e, which damped spin).
    """
    alpha_t = compliance / (h * h)
    gamma = beta / h
    denom = (1.0 + gamma) * w_grad2 + alpha_t
    if denom <= 0.0:
        return 0.0
    return (-C - alpha_t * lam - gamma * dC) / denom


@wp.struct
class Particles4:
    """What a 4-particle projection reads of its particles, loaded together (``load4``): inverse
    masses w, the corrections so far d0..d3 (dx), positions x0..x3 (x_pred + dx) and positions at
    the substep start p0..p3 (x_prev)."""

    w: wp.vec4
    d0: wp.vec3
    d1: wp.vec3
    d2: wp.vec3
    d3: wp.vec3
    x0: wp.vec3
    x1: wp.vec3
    x2: wp.vec3
    x3: wp.vec3
    p0: wp.vec3
    p1: wp.vec3
    p2: wp.vec3
    p3: wp.vec3


@wp.func
def load4(
    x_pred: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    ids: wp.vec4i,
) -> Particles4:
    """Every load of a 4-particle projection, issued before its first branch (see
    ``solve_distance``)."""
    q = Particles4()
    q.w = wp.vec4(inv_mass[ids[0]], inv_mass[ids[1]], inv_mass[ids[2]], inv_mass[ids[3]])
    q.d0 = dx[ids[0]]
    q.d1 = dx[ids[1]]
    q.d2 = dx[ids[2]]
    q.d3 = dx[ids[3]]
    q.x0 = x_pred[ids[0]] + q.d0
    q.x1 = x_pred[ids[1]] + q.d1
    q.x2 = x_pred[ids[2]] + q.d2
    q.x3 = x_pred[ids[3]] + q.d3
    q.p0 = x_prev[ids[0]]
    q.p1 = x_prev[ids[1]]
    q.p2 = x_prev[ids[2]]
    q.p3 = x_prev[ids[3]]
    return q


@wp.func
def project4(
    dx: wp.array(dtype=wp.vec3),
    lam: wp.array(dtype=float),
    c: int,
    ids: wp.vec4i,
    q: Particles4,
    lam_c: float,
    g0: wp.vec3,
    g1: wp.vec3,
    g2: wp.vec3,
    g3: wp.vec3,
    C: float,
    dC: float,
    compliance: float,
    beta: float,
    h: float,
    acc: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=float),
    omega: float,
):
    """One XPBD projection of a 4-particle constraint with value C, change dC over the substep and
    gradients g0..g3 (module docstring), given its particles ``q`` and multiplier lam_c (loaded
    by the caller with everything else, ``load4``); the correction is added to ``dx``, or in the
    Jacobi mode (omega > 0, module docstring) scaled and added to ``acc``."""
    w = q.w
    w_grad2 = w[0] * wp.dot(g0, g0) + w[1] * wp.dot(g1, g1) + w[2] * wp.dot(g2, g2) + w[3] * wp.dot(g3, g3)
    dl = xpbd_delta_lambda(C, lam_c, w_grad2, dC, compliance, beta, h)
    if omega > 0.0:
        dl = dl * omega / wp.max(wp.max(count[ids[0]], count[ids[1]]), wp.max(count[ids[2]], count[ids[3]]))
        lam[c] = lam_c + dl
        wp.atomic_add(acc, ids[0], g0 * (w[0] * dl))
        wp.atomic_add(acc, ids[1], g1 * (w[1] * dl))
        wp.atomic_add(acc, ids[2], g2 * (w[2] * dl))
        wp.atomic_add(acc, ids[3], g3 * (w[3] * dl))
        return
    lam[c] = lam_c + dl
    dx[ids[0]] = q.d0 + g0 * (w[0] * dl)
    dx[ids[1]] = q.d1 + g1 * (w[1] * dl)
    dx[ids[2]] = q.d2 + g2 * (w[2] * dl)
    dx[ids[3]] = q.d3 + g3 * (w[3] * dl)


@wp.kernel
def handle_targets(
    rest: wp.array(dtype=wp.vec3d),
    handle: wp.array(dtype=wp.int32),
    mats: wp.array(dtype=wp.mat44d),
    n_handles: int,
    first: int,
    out: wp.array(dtype=wp.vec3),
):
    """Targets of rigidly moved handles: thread i = (s - first) k + j (k handle slots) sets slot j at
    substep s to R p + t, p its rest position and [R t] the 4x4 pose of its handle at that substep
    (mats[s n_handles + handle]), in float64 like the host evaluation it replaces, stored float32."""
    k = rest.shape[0]
    i = wp.tid() + first * k
    s = i // k
    j = i - s * k
    M = mats[s * n_handles + int(handle[j])]
    p = rest[j]
    out[i] = wp.vec3(wp.vec3d(M[0, 0] * p[0] + M[0, 1] * p[1] + M[0, 2] * p[2] + M[0, 3],
                              M[1, 0] * p[0] + M[1, 1] * p[1] + M[1, 2] * p[2] + M[1, 3],
                              M[2, 0] * p[0] + M[2, 1] * p[1] + M[2, 2] * p[2] + M[2, 3]))


@wp.kernel
def predict_positions(
    # state in/out
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    # substep out
    x_prev: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    # model and inputs
    inv_mass: wp.array(dtype=float),
    handle_slot: wp.array(dtype=int),
    handle_targets: wp.array(dtype=wp.vec3),
    target_offset: int,
    gravity: wp.vec3,
    drag: float,
    h: float,
):
    """[PBD] Alg. 1 lines 5-7, straight-line prediction: v += h g (times exp(-drag h)); x_prev = x;
    x_pred = x + h v; dx = 0.

    Particles with w = 0 keep their position and get v = 0 (pinned), or jump to their kinematic
    handle target handle_targets[target_offset + handle_slot[i]] when handle_slot[i] >= 0 (as
    dx = target - x, with x_pred = x_prev, so the velocity update gives them the handle's velocity).
    """
    i = wp.tid()
    xi = x[i]
    vi = v[i]  # loaded with the mass, not after the test of it (one memory round trip less)
    slot = handle_slot[i]
    x_prev[i] = xi
    x_pred[i] = xi
    dx[i] = wp.vec3(0.0)
    if inv_mass[i] == 0.0:
        v[i] = wp.vec3(0.0)
        if slot >= 0:
            dx[i] = handle_targets[target_offset + slot] - xi
        return
    vi = (vi + gravity * h) * wp.exp(-drag * h)
    v[i] = vi
    x_pred[i] = xi + vi * h


#: float64 sums of ``moments`` (free particles, about o = x[0]): mass, m r [3], m v [3],
#: m r r^T [6: xx yy zz xy xz yz], m r x v [3], m dxc [3], m r x dxc [3]
MOMENT_SUMS = 22
MOMENT_BLOCK = 256


@wp.func
def _block_add(sums: wp.array(dtype=wp.float64), value: wp.float64, slot: int):
    wp.tile_atomic_add(sums, wp.tile_sum(wp.tile(value)), offset=slot)


@wp.kernel
def moments(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dxc: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    sums: wp.array(dtype=wp.float64),
    base: int,
    seg: wp.array(dtype=int),
    first: wp.array(dtype=int),
    stride: int,
):
    """Block sums (float64, one atomic per block and slot) of the free particles' mass, first and
    second moments of position about o = x[first[s]] (r = x - o), momentum, angular momentum about
    o, and the contact corrections dxc with their moment (``MOMENT_SUMS`` slots from
    sums[s stride + base]), per body s = seg[i] of the particles (one body: seg all 0, first [0]).
    o removes the float32 cancellation of a body far from the origin. Launch with dim rounded up
    to a multiple of MOMENT_BLOCK and block_dim = MOMENT_BLOCK; ``sums`` zeroed before. Every
    block must hold particles of one body only (a ``PbdBatch`` pads each body to whole blocks).
    """
    i = wp.tid()
    z = wp.float64(0.0)
    m = z
    r = wp.vec3d(z, z, z)
    u = wp.vec3d(z, z, z)
    q = wp.vec3d(z, z, z)
    s = int(0)
    if i < x.shape[0]:
        s = seg[i]
        if inv_mass[i] > 0.0:
            m = wp.float64(1.0) / wp.float64(inv_mass[i])
            r = wp.vec3d(x[i] - x[first[s]])
            u = wp.vec3d(v[i])
            q = wp.vec3d(dxc[i])
    L = wp.cross(r, u)
    T = wp.cross(r, q)
    o = s * stride + base
    _block_add(sums, m, o)
    for k in range(3):
        _block_add(sums, m * r[k], o + 1 + k)
        _block_add(sums, m * u[k], o + 4 + k)
        _block_add(sums, m * r[k] * r[k], o + 7 + k)
        _block_add(sums, m * L[k], o + 13 + k)
        _block_add(sums, m * q[k], o + 16 + k)
        _block_add(sums, m * T[k], o + 19 + k)
    _block_add(sums, m * r[0] * r[1], o + 10)
    _block_add(sums, m * r[0] * r[2], o + 11)
    _block_add(sums, m * r[1] * r[2], o + 12)


@wp.kernel
def moments_serial(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dxc: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    sums: wp.array(dtype=wp.float64),
    base: int,
    first: wp.array(dtype=int),
    count: wp.array(dtype=int),
    stride: int,
):
    """``moments`` for the CPU: thread s loops over body s's particles first[s] .. first[s] +
    count[s] (Warp CPU kernels are serial, where 22 block reductions per particle cost 1.5x the
    whole constraint solve). Launch with dim = the number of bodies."""
    b = wp.tid()
    z = wp.float64(0.0)
    M = z
    r1 = wp.vec3d(z, z, z)
    P = wp.vec3d(z, z, z)
    d2 = wp.vec3d(z, z, z)
    off = wp.vec3d(z, z, z)
    Lo = wp.vec3d(z, z, z)
    Q = wp.vec3d(z, z, z)
    To = wp.vec3d(z, z, z)
    i0 = first[b]
    for i in range(i0, i0 + count[b]):
        if inv_mass[i] > 0.0:
            m = wp.float64(1.0) / wp.float64(inv_mass[i])
            r = wp.vec3d(x[i] - x[i0])
            u = wp.vec3d(v[i])
            q = wp.vec3d(dxc[i])
            M += m
            r1 += m * r
            P += m * u
            d2 += m * wp.cw_mul(r, r)
            off += m * wp.vec3d(r[0] * r[1], r[0] * r[2], r[1] * r[2])
            Lo += m * wp.cross(r, u)
            Q += m * q
            To += m * wp.cross(r, q)
    o = b * stride + base
    sums[o] = M
    for k in range(3):
        sums[o + 1 + k] = r1[k]
        sums[o + 4 + k] = P[k]
        sums[o + 7 + k] = d2[k]
        sums[o + 10 + k] = off[k]
        sums[o + 13 + k] = Lo[k]
        sums[o + 16 + k] = Q[k]
        sums[o + 19 + k] = To[k]


@wp.func
def _about_com(s: wp.array(dtype=wp.float64), b: int) -> wp.vec3d:
    """Angular momentum about the centre of mass from ``moments`` sums: L_o - d x P, d = c - o."""
    M = s[b]
    d = wp.vec3d(s[b + 1], s[b + 2], s[b + 3]) / M
    return wp.vec3d(s[b + 13], s[b + 14], s[b + 15]) - wp.cross(d, wp.vec3d(s[b + 4], s[b + 5], s[b + 6]))


@wp.kernel
def restore_angular_momentum(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    sums: wp.array(dtype=wp.float64),
    inv_h: wp.float64,
    seg: wp.array(dtype=int),
    first: wp.array(dtype=int),
    stride: int,
    enabled: wp.array(dtype=int),
):
    """Give back the angular momentum the implicit (XPBD) solve of the internal constraints took.

    sums[0:22]: ``moments`` after the prediction (L_0 about the centre of mass: the straight-line
    prediction conserves it exactly, and uniform gravity has no torque about the centre of mass);
    sums[22:44]: after the velocity update, with the contact corrections dxc (their angular
    impulse about the centre of mass is T = (sum m r x dxc - d x sum m dxc) / h). Internal forces
    exert no net torque, but the projection of a straight-line prediction back onto a rotating
    body's constraints is implicit Euler, which loses about (omega h)^2 of the spin per substep
    (the chord is shorter than the arc). With dL = L_0 + T - L_1 and I_1 the inertia tensor now,
    every free particle gets v += (I_1^-1 dL) x (x - c_1): a rigid rotation increment, which
    changes no linear momentum and restores L exactly. Each thread solves the 3x3 itself (no
    single-thread launch). Per body s = seg[i] (its sums from s stride, its origin x[first[s]]),
    where enabled[s] (a ``PbdBatch`` of bodies with and without the restoration).
    """
    i = wp.tid()
    if inv_mass[i] == 0.0:
        return
    s = seg[i]
    if enabled[s] == 0:
        return
    a = s * stride
    b = a + 22
    M = sums[b]
    if M <= wp.float64(0.0):
        return
    d = wp.vec3d(sums[b + 1], sums[b + 2], sums[b + 3]) / M
    T = wp.vec3d(sums[b + 19], sums[b + 20], sums[b + 21]) - wp.cross(d, wp.vec3d(sums[b + 16], sums[b + 17], sums[b + 18]))
    dL = _about_com(sums, a) + T * inv_h - _about_com(sums, b)
    S = wp.mat33d(sums[b + 7], sums[b + 10], sums[b + 11], sums[b + 10], sums[b + 8], sums[b + 12],
                  sums[b + 11], sums[b + 12], sums[b + 9]) - M * wp.outer(d, d)
    t = S[0, 0] + S[1, 1] + S[2, 2]
    I = wp.mat33d(t, wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), t, wp.float64(0.0),
                  wp.float64(0.0), wp.float64(0.0), t) - S
    det = wp.determinant(I)
    if t <= wp.float64(0.0) or det <= wp.float64(1.0e-9) * t * t * t:
        return  # particles on a line: no rotation to restore
    dw = wp.inverse(I) * dL
    r = wp.vec3d(x[i] - x[first[s]]) - d
    v[i] = v[i] + wp.vec3(wp.cross(dw, r))


@wp.kernel
def solve_distance(
    x_pred: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    pairs: wp.array(dtype=wp.vec2i),
    rest: wp.array(dtype=float),
    compliance: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    offset: int,
    beta: float,
    h: float,
    acc: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=float),
    omega: float,
):
    """Edge stretch, [PBD] Eq. 10: C = |x_i - x_j| - L0, grad_i C = n, grad_j C = -n.

    Positions are x = x_pred + dx (module docstring). Compliance [m/N] (the inverse of a spring
    stiffness k [N/m]).
    """
    c = wp.tid() + offset
    i = pairs[c][0]
    j = pairs[c][1]
    # every load is issued before the first branch: a test of the masses first made the positions
    # wait for them, one more memory round trip in each colour's launch, and a frame's launches
    # run one after another (tools/bench_graph_nodes.py)
    wi = inv_mass[i]
    wj = inv_mass[j]
    xi = x_pred[i]
    xj = x_pred[j]
    dxi = dx[i]
    dxj = dx[j]
    pi = x_prev[i]
    pj = x_prev[j]
    lam_c = lam[c]
    rest_c = rest[c]
    compliance_c = compliance[c]
    if wi + wj == 0.0:
        return
    n, dl, defined = stretch((xi - xj) + (dxi - dxj), pi - pj, rest_c, lam_c, wi + wj, compliance_c, beta, h)
    if not defined:
        return
    if omega > 0.0:  # Jacobi (module docstring): both ends get the same scaled multiplier
        dl = dl * omega / wp.max(count[i], count[j])
        lam[c] = lam_c + dl
        wp.atomic_add(acc, i, n * (wi * dl))
        wp.atomic_add(acc, j, -n * (wj * dl))
        return
    lam[c] = lam_c + dl
    dx[i] = dxi + n * (wi * dl)
    dx[j] = dxj - n * (wj * dl)


@wp.func
def stretch(d: wp.vec3, prev: wp.vec3, rest: float, lam: float, w: float, compliance: float, beta: float, h: float):
    """An edge's stretch step, [PBD] Eq. 10 through [XPBD] Eq. 18: its direction n = d / |d| and
    multiplier increment for C = |d| - rest (``prev``: the edge at the substep's start, for the
    damping's dC), and whether it is defined (not for a collapsed edge, |d| < 1e-12). The one
    edge projection of ``solve_distance`` and ``solve_hinge_edge``."""
    length = wp.length(d)
    if length < 1.0e-12:
        return wp.vec3(), 0.0, False
    return d / length, xpbd_delta_lambda(length - rest, lam, w, length - wp.length(prev), compliance, beta, h), True


@wp.func
def dihedral(w1: wp.vec3, w2: wp.vec3, e0: wp.vec3, e1: wp.vec3) -> float:
    """Signed dihedral angle of the hinge (see ``solve_bending``)."""
    E = e1 - e0
    n1 = wp.cross(E, w1 - e0)
    n2 = wp.cross(e0 - e1, w2 - e1)
    return wp.atan2(wp.dot(wp.cross(n1, n2), E) / wp.max(wp.length(E), 1.0e-30), wp.dot(n1, n2))


@wp.func
def wrap_angle(a: float) -> float:
    b = a
    if b > wp.pi:
        b = b - 2.0 * wp.pi
    if b < -wp.pi:
        b = b + 2.0 * wp.pi
    return b


@wp.func
def project_hinge(
    dx: wp.array(dtype=wp.vec3),
    lam: wp.array(dtype=float),
    c: int,
    ids: wp.vec4i,
    q: Particles4,
    lam_c: float,
    rest_c: float,
    compliance_c: float,
    beta: float,
    h: float,
    acc: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=float),
    omega: float,
):
    """Dihedral bending, [PBD] §4.2 with the angle gradient of Bridson et al. (SCA 2003), of hinge
    c with particles ``q`` (wing w1, wing w2, edge e0, edge e1):

    theta is the signed angle between the faces (e0, e1, w1) and (e1, e0, w2): 0 for a flat hinge.
    C = theta - theta0 (wrapped to (-pi, pi]); with E = e1 - e0, n1 = E x (w1 - e0),
    n2 = (e0 - e1) x (w2 - e1), and t_k = (w_k - e0).E / |E|^2:
        grad_w1 = -|E| n1/|n1|^2,  grad_w2 = -|E| n2/|n2|^2,
        grad_e0 = -((1 - t1) grad_w1 + (1 - t2) grad_w2),  grad_e1 = -(t1 grad_w1 + t2 grad_w2).
    Compliance [rad/(N m)] (the inverse of a hinge stiffness).
    """
    w1 = q.x0
    w2 = q.x1
    e0 = q.x2
    e1 = q.x3
    E = e1 - e0
    len2 = wp.dot(E, E)
    n1 = wp.cross(E, w1 - e0)
    n2 = wp.cross(e0 - e1, w2 - e1)
    n1sq = wp.dot(n1, n1)
    n2sq = wp.dot(n2, n2)
    if len2 < 1.0e-20 or n1sq < 1.0e-24 or n2sq < 1.0e-24:
        return
    elen = wp.sqrt(len2)
    g1 = n1 * (-elen / n1sq)
    g2 = n2 * (-elen / n2sq)
    t1 = wp.dot(w1 - e0, E) / len2
    t2 = wp.dot(w2 - e0, E) / len2
    g3 = -((1.0 - t1) * g1 + (1.0 - t2) * g2)
    g4 = -(t1 * g1 + t2 * g2)
    # theta = atan2((n1^ x n2^).E^, n1^.n2^): atan2 is scale-free, so the unnormalized normals do
    theta = wp.atan2(wp.dot(wp.cross(n1, n2), E) / elen, wp.dot(n1, n2))
    # keep C in (-pi, pi] so a hinge that passes through +-pi is pulled the short way round
    C = wrap_angle(theta - rest_c)
    dC = wrap_angle(theta - dihedral(q.p0, q.p1, q.p2, q.p3))
    project4(dx, lam, c, ids, q, lam_c, g1, g2, g3, g4, C, dC, compliance_c, beta, h, acc, count, omega)


@wp.kernel
def solve_bending(
    x_pred: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    hinges: wp.array(dtype=wp.vec4i),
    rest: wp.array(dtype=float),
    compliance: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    offset: int,
    beta: float,
    h: float,
    acc: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=float),
    omega: float,
):
    """Hinges offset + tid (``project_hinge``)."""
    c = wp.tid() + offset
    ids = hinges[c]
    q = load4(x_pred, dx, x_prev, inv_mass, ids)  # every load before the first branch
    lam_c = lam[c]
    rest_c = rest[c]
    compliance_c = compliance[c]
    if q.w[0] + q.w[1] + q.w[2] + q.w[3] == 0.0:
        return
    project_hinge(dx, lam, c, ids, q, lam_c, rest_c, compliance_c, beta, h, acc, count, omega)


@wp.kernel
def solve_hinge_edge(
    x_pred: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    hinges: wp.array(dtype=wp.vec4i),
    rest: wp.array(dtype=float),
    compliance: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    offset: int,
    beta: float,
    h: float,
    edge: wp.array(dtype=wp.int32),
    edge_rest: wp.array(dtype=float),
    edge_compliance: wp.array(dtype=float),
    edge_lam: wp.array(dtype=float),
):
    """Hinge offset + tid with the stretch of its own edge (e0, e1) first, in one thread
    (Gauss-Seidel; ``PbdBody`` pairs each hinge with its edge's distance constraint, ``edge[c]``,
    -1 for none): the edge projection of ``solve_distance`` on the particles already in registers,
    then ``project_hinge`` on the corrected positions. An edge shares its particles with its hinge
    only, so the hinge colouring holds both, and the distance colours these edges took are not
    launched: a frame launches the hinge colours alone."""
    c = wp.tid() + offset
    ids = hinges[c]
    k = edge[c]
    q = load4(x_pred, dx, x_prev, inv_mass, ids)  # every load before the first branch
    lam_c = lam[c]
    rest_c = rest[c]
    compliance_c = compliance[c]
    kk = wp.max(k, 0)
    lam_e = edge_lam[kk]
    rest_e = edge_rest[kk]
    compliance_e = edge_compliance[kk]
    if q.w[0] + q.w[1] + q.w[2] + q.w[3] == 0.0:
        return
    wi = q.w[2]
    wj = q.w[3]
    if k >= 0 and wi + wj > 0.0:
        n, dl, defined = stretch(q.x2 - q.x3, q.p2 - q.p3, rest_e, lam_e, wi + wj, compliance_e, beta, h)
        if defined:
            edge_lam[k] = lam_e + dl
            q.d2 = q.d2 + n * (wi * dl)
            q.d3 = q.d3 - n * (wj * dl)
            q.x2 = q.x2 + n * (wi * dl)
            q.x3 = q.x3 - n * (wj * dl)
            dx[ids[2]] = q.d2  # kept should the hinge be degenerate (project_hinge returns early)
            dx[ids[3]] = q.d3
    project_hinge(dx, lam, c, ids, q, lam_c, rest_c, compliance_c, beta, h, dx, edge_lam, 0.0)


@wp.func
def tet_volume6(x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, x3: wp.vec3) -> float:
    return wp.dot(x1 - x0, wp.cross(x2 - x0, x3 - x0))


@wp.kernel
def solve_tet_volume(
    x_pred: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    tets: wp.array(dtype=wp.vec4i),
    rest: wp.array(dtype=float),
    compliance: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    offset: int,
    beta: float,
    h: float,
    acc: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=float),
    omega: float,
):
    """Per-tetrahedron volume, [PBD] Eq. 12: C = (1/6) (x1-x0).((x2-x0) x (x3-x0)) - V0.

    grad_1 = (x2-x0)x(x3-x0)/6, grad_2 = (x3-x0)x(x1-x0)/6, grad_3 = (x1-x0)x(x2-x0)/6,
    grad_0 = -(grad_1 + grad_2 + grad_3). Compliance [m^3/Pa] (V0/(lambda - mu), ``wsim.pbd.model``).
    """
    c = wp.tid() + offset
    ids = tets[c]
    q = load4(x_pred, dx, x_prev, inv_mass, ids)  # every load before the first branch
    lam_c = lam[c]
    rest_c = rest[c]
    compliance_c = compliance[c]
    if q.w[0] + q.w[1] + q.w[2] + q.w[3] == 0.0:
        return
    x0 = q.x0
    d1 = q.x1 - x0
    d2 = q.x2 - x0
    d3 = q.x3 - x0
    g1 = wp.cross(d2, d3) / 6.0
    g2 = wp.cross(d3, d1) / 6.0
    g3 = wp.cross(d1, d2) / 6.0
    V = wp.dot(d1, g1)
    C = V - rest_c
    dC = V - tet_volume6(q.p0, q.p1, q.p2, q.p3) / 6.0
    project4(dx, lam, c, ids, q, lam_c, -(g1 + g2 + g3), g1, g2, g3, C, dC, compliance_c, beta, h, acc, count, omega)


#: threads per block of the volume reduction (one float64 atomic per block and sum)
VOLUME_BLOCK = 256


@wp.kernel
def volume_gradient(
    x_pred: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    vertex_face_start: wp.array(dtype=int),
    face_pairs: wp.array(dtype=wp.vec2i),
    grad: wp.array(dtype=wp.vec3),
    sums: wp.array(dtype=wp.float64),
    slot: int,
):
    """Global enclosed volume of a closed surface and its gradient, one thread per vertex.

    V = (1/6) sum_f (x_a - o).((x_b - o) x (x_c - o)); grad_i V = (1/6) sum_{f containing i}
    (x_b - o) x (x_c - o) with (i, b, c) the face read cyclically from i: ``face_pairs`` holds
    (b, c) for each entry of the vertex -> face adjacency (CSR, ``vertex_face_start``), so a
    face's positions wait for one index load, not two. o = x[0] removes the
    float32 cancellation of a body far from the origin (V and its gradient do not depend on o
    for a closed surface). V is homogeneous of degree 3 in (x - o), so V = (1/3) sum_i (x_i - o).grad_i V.
    The shares and w_i |grad_i V|^2 are summed per block (tile reduction) and added, one float64
    atomic per block, to sums[2 slot] and sums[2 slot + 1] (this iteration's slot, zeroed each
    substep): per-thread atomics on two addresses serialized ~30k updates per launch.
    Launch with dim rounded up to a multiple of VOLUME_BLOCK and block_dim = VOLUME_BLOCK.
    Positions are x = x_pred + dx.
    """
    i = wp.tid()
    share = wp.float64(0.0)
    w_g2 = wp.float64(0.0)
    if i < grad.shape[0]:
        o = x_pred[0] + dx[0]
        g = wp.vec3(0.0)
        for k in range(vertex_face_start[i], vertex_face_start[i + 1]):
            bc = face_pairs[k]
            g = g + wp.cross((x_pred[bc[0]] + dx[bc[0]]) - o, (x_pred[bc[1]] + dx[bc[1]]) - o)
        g = g / 6.0
        grad[i] = g
        share = wp.float64(wp.dot((x_pred[i] + dx[i]) - o, g)) / wp.float64(3.0)
        w_g2 = wp.float64(inv_mass[i] * wp.dot(g, g))
    wp.tile_atomic_add(sums, wp.tile_sum(wp.tile(share)), offset=2 * slot)
    wp.tile_atomic_add(sums, wp.tile_sum(wp.tile(w_g2)), offset=2 * slot + 1)


@wp.kernel
def volume_apply(
    dx: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    grad: wp.array(dtype=wp.vec3),
    sums: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    slot: int,
    target_volume: wp.float64,
    compliance: wp.float64,
    h: wp.float64,
):
    """Global volume constraint C = V - V_target ([XPBD] Eq. 18): dx_i += w_i grad_i V dlambda.

    Every thread computes the same dlambda from sums[2 slot:2 slot + 2] and lam[slot]; thread 0
    stores lam[slot + 1] = lam[slot] + dlambda for the next iteration (lam[0] = 0 each substep),
    so no single-thread launch is needed. No Rayleigh term: the rate of the whole-body volume is
    damped by the edge and tet constraints already. Compliance [m^3/Pa] (V0/K for bulk modulus K).
    """
    i = wp.tid()
    alpha_t = compliance / (h * h)
    C = sums[2 * slot] - target_volume
    denom = sums[2 * slot + 1] + alpha_t
    d = wp.float64(0.0)
    if denom > wp.float64(0.0):
        d = (-C - alpha_t * lam[slot]) / denom
    if i == 0:
        lam[slot + 1] = lam[slot] + d
    dx[i] = dx[i] + grad[i] * (inv_mass[i] * float(d))


@wp.kernel
def apply_jacobi(dx: wp.array(dtype=wp.vec3), acc: wp.array(dtype=wp.vec3)):
    """The Jacobi sweep's corrections applied at once: dx += acc, acc = 0 for the next sweep."""
    i = wp.tid()
    dx[i] = dx[i] + acc[i]
    acc[i] = wp.vec3(0.0, 0.0, 0.0)


@wp.kernel
def update_velocities(
    x: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_h: float,
):
    """[PBD] Alg. 1 line 12, v = (x - x_prev) / h, evaluated as v_pred + dx / h; then x = x_pred + dx.

    The two are equal in exact arithmetic (x_pred = x_prev + h v_pred), but in float32 the first
    divides the rounding error of every position update (ulp(x) / h: 6e-5 m/s at 5 m and
    h = 8 ms) into the velocity. Keeping the correction dx apart from x_pred during the iterations
    (module docstring) makes the velocity change exactly the sum of the corrections, rounded
    relative to |dx|, not to |x|. Kinematic particles get their handle velocity (v_pred = 0,
    dx = target - x_prev).
    """
    i = wp.tid()
    d = dx[i]
    v[i] = v[i] + d * inv_h
    x[i] = x_pred[i] + d


MEMBER_BLOCK = 256  # threads of a member's block in ``member_bounds``


@wp.kernel
def member_bounds(
    # state in
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    # the batch's layout
    first: wp.array(dtype=int),
    count: wp.array(dtype=int),
    n_surface: wp.array(dtype=int),
    # out
    bounds: wp.array2d(dtype=float),
):
    """Per member m of a batch (one block each, launched tiled with dim = members): bounds[m, 0:3]
    = min and bounds[m, 3:6] = max of its surface particles' positions (its first n_surface[m]),
    bounds[m, 6] = the largest |v| component of its count[m] particles from first[m] (the broad
    phase's swept box, ``wsim.pbd.contact.candidate_pairs``). Each lane takes every block_dim-th
    particle, then the block reduces (``wp.tile_min``/``wp.tile_max``) and lane 0 writes: no atomics
    and no initial values to set, so one launch and the same result every time."""
    m, lane = wp.tid()
    big = float(3.0e38)
    lo = wp.vec3(big, big, big)
    hi = wp.vec3(-big, -big, -big)
    v_max = float(0.0)
    f = first[m]
    for i in range(f + lane, f + count[m], wp.block_dim()):
        vi = v[i]
        v_max = wp.max(v_max, wp.max(wp.abs(vi[0]), wp.max(wp.abs(vi[1]), wp.abs(vi[2]))))
        if i - f < n_surface[m]:
            lo = wp.min(lo, x[i])
            hi = wp.max(hi, x[i])
    for d in range(3):
        t_lo = wp.tile_min(wp.tile(lo[d]))
        t_hi = wp.tile_max(wp.tile(hi[d]))
        if lane == 0:
            bounds[m, d] = t_lo[0]
            bounds[m, 3 + d] = t_hi[0]
    t_v = wp.tile_max(wp.tile(v_max))
    if lane == 0:
        bounds[m, 6] = t_v[0]


@wp.kernel
def check_finite(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    flags: wp.array(dtype=int),
):
    """flags[0] = 1 if any position is NaN/Inf, flags[1] = 1 if any velocity is (benign same-value writes)."""
    i = wp.tid()
    xi = x[i]
    vi = v[i]
    if not (wp.isfinite(xi[0]) and wp.isfinite(xi[1]) and wp.isfinite(xi[2])):
        flags[0] = 1
    if not (wp.isfinite(vi[0]) and wp.isfinite(vi[1]) and wp.isfinite(vi[2])):
        flags[1] = 1
