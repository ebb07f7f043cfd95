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

Parallel projection is race-free because constraints are coloured (no two constraints of one
colour share a particle; see ``wsim.colouring``) and each launch covers one colour,
starting at ``offset`` in the colour-sorted arrays. Positions and multipliers are float32
(bandwidth); the global volume sums are accumulated in float64 because they add up
O(N) terms of alternating sign.
"""

from __future__ import annotations

import warp as wp


@wp.func
def xpbd_delta_lambda(
    C: float, lam: float, w_grad2: float, grad_dot_dx: float, compliance: float, beta: float, h: float
) -> float:
    """Multiplier increment of [XPBD] Eq. 18 with Rayleigh damping (Eq. 26); see module docstring.

    [XPBD] writes gamma = alpha_t beta_t / h with beta_t = h^2 c for a damping coefficient c; for
    stiffness-proportional Rayleigh damping c = beta k = beta / alpha, so gamma = beta / h: a mode
    of angular frequency omega gets the damping ratio beta omega / 2, for every constraint type.
    """
    alpha_t = compliance / (h * h)
    gamma = beta / h
    denom = (1.0 + gamma) * w_grad2 + alpha_t
    if denom <= 0.0:
        return 0.0
    return (-C - alpha_t * lam - gamma * grad_dot_dx) / denom


@wp.func
def project4(
    x: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    c: int,
    ids: wp.vec4i,
    g0: wp.vec3,
    g1: wp.vec3,
    g2: wp.vec3,
    g3: wp.vec3,
    C: float,
    compliance: float,
    beta: float,
    h: float,
):
    """One XPBD projection of a 4-particle constraint with value C and gradients g0..g3 (module docstring)."""
    w0 = inv_mass[ids[0]]
    w1 = inv_mass[ids[1]]
    w2 = inv_mass[ids[2]]
    w3 = inv_mass[ids[3]]
    w_grad2 = w0 * wp.dot(g0, g0) + w1 * wp.dot(g1, g1) + w2 * wp.dot(g2, g2) + w3 * wp.dot(g3, g3)
    grad_dot_dx = (
        wp.dot(g0, x[ids[0]] - x_prev[ids[0]])
        + wp.dot(g1, x[ids[1]] - x_prev[ids[1]])
        + wp.dot(g2, x[ids[2]] - x_prev[ids[2]])
        + wp.dot(g3, x[ids[3]] - x_prev[ids[3]])
    )
    dl = xpbd_delta_lambda(C, lam[c], w_grad2, grad_dot_dx, compliance, beta, h)
    lam[c] = lam[c] + dl
    x[ids[0]] = x[ids[0]] + g0 * (w0 * dl)
    x[ids[1]] = x[ids[1]] + g1 * (w1 * dl)
    x[ids[2]] = x[ids[2]] + g2 * (w2 * dl)
    x[ids[3]] = x[ids[3]] + g3 * (w3 * dl)


@wp.kernel
def predict_positions(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    handle_slot: wp.array(dtype=int),
    handle_targets: wp.array(dtype=wp.vec3),
    target_offset: int,
    gravity: wp.vec3,
    drag: float,
    h: float,
):
    """[PBD] Alg. 1 lines 5-7: v += h g (times the drag decay exp(-drag h)); x_prev = x; x += h v.

    The predicted position is kept in ``x_pred`` (see ``update_velocities``). Particles with
    w = 0 keep their position and get v = 0 (pinned), or jump to their kinematic handle target
    handle_targets[target_offset + handle_slot[i]] when handle_slot[i] >= 0, with x_pred = x_prev
    so that the velocity update gives them the handle's velocity.
    """
    i = wp.tid()
    xi = x[i]
    x_prev[i] = xi
    if inv_mass[i] == 0.0:
        v[i] = wp.vec3(0.0)
        x_pred[i] = xi
        slot = handle_slot[i]
        if slot >= 0:
            x[i] = handle_targets[target_offset + slot]
        return
    vi = (v[i] + gravity * h) * wp.exp(-drag * h)
    v[i] = vi
    xn = xi + vi * h
    x[i] = xn
    x_pred[i] = xn


@wp.kernel
def solve_distance(
    x: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    pairs: wp.array(dtype=wp.vec2i),
    rest: wp.array(dtype=float),
    compliance: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    offset: int,
    beta: float,
    h: float,
):
    """Edge stretch, [PBD] Eq. 10: C = |x_i - x_j| - L0, grad_i C = n, grad_j C = -n.

    Compliance [m/N] (the inverse of a spring stiffness k [N/m]).
    """
    c = wp.tid() + offset
    i = pairs[c][0]
    j = pairs[c][1]
    wi = inv_mass[i]
    wj = inv_mass[j]
    if wi + wj == 0.0:
        return
    d = x[i] - x[j]
    length = wp.length(d)
    if length < 1.0e-12:
        return
    n = d / length
    C = length - rest[c]
    grad_dot_dx = wp.dot(n, (x[i] - x_prev[i]) - (x[j] - x_prev[j]))
    dl = xpbd_delta_lambda(C, lam[c], wi + wj, grad_dot_dx, compliance[c], beta, h)
    lam[c] = lam[c] + dl
    x[i] = x[i] + n * (wi * dl)
    x[j] = x[j] - n * (wj * dl)


@wp.kernel
def solve_bending(
    x: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    hinges: wp.array(dtype=wp.vec4i),
    rest: wp.array(dtype=float),
    compliance: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    offset: int,
    beta: float,
    h: float,
):
    """Dihedral bending, [PBD] §4.2 with the angle gradient of Bridson et al. (SCA 2003):

    theta is the signed angle between the faces (e0, e1, w1) and (e1, e0, w2): 0 for a flat hinge.
    C = theta - theta0 (wrapped to (-pi, pi]); with E = e1 - e0, n1 = E x (w1 - e0),
    n2 = (e0 - e1) x (w2 - e1), and t_k = (w_k - e0).E / |E|^2:
        grad_w1 = -|E| n1/|n1|^2,  grad_w2 = -|E| n2/|n2|^2,
        grad_e0 = -((1 - t1) grad_w1 + (1 - t2) grad_w2),  grad_e1 = -(t1 grad_w1 + t2 grad_w2).
    Compliance [rad/(N m)] (the inverse of a hinge stiffness).
    """
    c = wp.tid() + offset
    ids = hinges[c]
    if inv_mass[ids[0]] + inv_mass[ids[1]] + inv_mass[ids[2]] + inv_mass[ids[3]] == 0.0:
        return
    w1 = x[ids[0]]
    w2 = x[ids[1]]
    e0 = x[ids[2]]
    e1 = x[ids[3]]
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
    C = wp.atan2(wp.dot(wp.cross(n1, n2), E) / elen, wp.dot(n1, n2)) - rest[c]
    # keep C in (-pi, pi] so a hinge that passes through +-pi is pulled the short way round
    if C > wp.pi:
        C = C - 2.0 * wp.pi
    if C < -wp.pi:
        C = C + 2.0 * wp.pi
    project4(x, x_prev, inv_mass, lam, c, ids, g1, g2, g3, g4, C, compliance[c], beta, h)


@wp.kernel
def solve_tet_volume(
    x: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    tets: wp.array(dtype=wp.vec4i),
    rest: wp.array(dtype=float),
    compliance: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    offset: int,
    beta: float,
    h: float,
):
    """Per-tetrahedron volume, [PBD] Eq. 12: C = (1/6) (x1-x0).((x2-x0) x (x3-x0)) - V0.

    grad_1 = (x2-x0)x(x3-x0)/6, grad_2 = (x3-x0)x(x1-x0)/6, grad_3 = (x1-x0)x(x2-x0)/6,
    grad_0 = -(grad_1 + grad_2 + grad_3). Compliance [m^3/Pa] (V0/K for bulk modulus K).
    """
    c = wp.tid() + offset
    ids = tets[c]
    if inv_mass[ids[0]] + inv_mass[ids[1]] + inv_mass[ids[2]] + inv_mass[ids[3]] == 0.0:
        return
    x0 = x[ids[0]]
    d1 = x[ids[1]] - x0
    d2 = x[ids[2]] - x0
    d3 = x[ids[3]] - x0
    g1 = wp.cross(d2, d3) / 6.0
    g2 = wp.cross(d3, d1) / 6.0
    g3 = wp.cross(d1, d2) / 6.0
    C = wp.dot(d1, g1) - rest[c]
    project4(x, x_prev, inv_mass, lam, c, ids, -(g1 + g2 + g3), g1, g2, g3, C, compliance[c], beta, h)


#: threads per block of the volume reduction (one float64 atomic per block and sum)
VOLUME_BLOCK = 256


@wp.kernel
def volume_gradient(
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    faces: wp.array(dtype=wp.vec3i),
    vertex_face_start: wp.array(dtype=int),
    vertex_faces: wp.array(dtype=int),
    grad: wp.array(dtype=wp.vec3),
    sums: wp.array(dtype=wp.float64),
    slot: int,
):
    """Global enclosed volume of a closed surface and its gradient, one thread per vertex.

    V = (1/6) sum_f (x_a - o).((x_b - o) x (x_c - o)); grad_i V = (1/6) sum_{f containing i}
    (x_b - o) x (x_c - o) with (i, b, c) the face read cyclically from i. o = x[0] removes the
    float32 cancellation of a body far from the origin (V and its gradient do not depend on o
    for a closed surface). V is homogeneous of degree 3 in (x - o), so V = (1/3) sum_i (x_i - o).grad_i V.
    The shares and w_i |grad_i V|^2 are summed per block (tile reduction) and added, one float64
    atomic per block, to sums[2 slot] and sums[2 slot + 1] (this iteration's slot, zeroed each
    substep): per-thread atomics on two addresses serialized ~30k updates per launch.
    Launch with dim rounded up to a multiple of VOLUME_BLOCK and block_dim = VOLUME_BLOCK.
    """
    i = wp.tid()
    share = wp.float64(0.0)
    w_g2 = wp.float64(0.0)
    if i < grad.shape[0]:
        o = x[0]
        g = wp.vec3(0.0)
        for k in range(vertex_face_start[i], vertex_face_start[i + 1]):
            f = faces[vertex_faces[k]]
            b = f[1]
            c = f[2]
            if f[1] == i:
                b = f[2]
                c = f[0]
            elif f[2] == i:
                b = f[0]
                c = f[1]
            g = g + wp.cross(x[b] - o, x[c] - o)
        g = g / 6.0
        grad[i] = g
        share = wp.float64(wp.dot(x[i] - o, g)) / wp.float64(3.0)
        w_g2 = wp.float64(inv_mass[i] * wp.dot(g, g))
    wp.tile_atomic_add(sums, wp.tile_sum(wp.tile(share)), offset=2 * slot)
    wp.tile_atomic_add(sums, wp.tile_sum(wp.tile(w_g2)), offset=2 * slot + 1)


@wp.kernel
def volume_apply(
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    grad: wp.array(dtype=wp.vec3),
    sums: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    slot: int,
    target_volume: wp.float64,
    compliance: wp.float64,
    h: wp.float64,
):
    """Global volume constraint C = V - V_target ([XPBD] Eq. 18): x_i += w_i grad_i V dlambda.

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
    x[i] = x[i] + grad[i] * (inv_mass[i] * float(d))


@wp.kernel
def update_velocities(
    x: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_h: float,
):
    """[PBD] Alg. 1 line 12, v = (x - x_prev) / h, evaluated as v_pred + (x - x_pred) / h.

    The two are equal in exact arithmetic (x_pred = x_prev + h v_pred), but in float32 the first
    divides the rounding error of every position update (ulp(x) / h: 6e-5 m/s at 5 m and
    h = 8 ms) into the velocity, a bias that made free fall 2 % off after one second; the second
    divides only the constraint and contact corrections. Kinematic particles get their handle
    velocity (v_pred = 0, x_pred = x_prev).
    """
    i = wp.tid()
    v[i] = v[i] + (x[i] - x_pred[i]) * inv_h


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
