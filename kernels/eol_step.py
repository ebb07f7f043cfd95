"""Warp kernels of one EoL step on the nodes of the intermediate grid (Fan et al. Algorithm 1, Eqs. 16-25, 30-33).

Nodal arrays are flat (n_nodes,), in the grid's node order s = (i ny + j) nz + k. Velocities are
the material's velocity in the axes of the Lagrangian coordinates ("LS axes": the rigid frame's
body axes, or world axes for affine coordinates), where the Lagrangian part is the affine field
J_L(y) q1_dot = L y + c (rigid: L = [omega]x, c = nu; affine: L = A_dot, c = b_dot) and the
Eulerian part is F_L v (F_L = I rigid, A affine; Eqs. 2 and 9):

    w_s = L y_s + c + F_L v_s.

The velocity-impulse update (Eq. 16) in these axes is w_hat = w + dt a with

    a_s = g_s / m_s + gravity - [rigid] omega x (omega x y_s) - 2 L v_s,

the quadratic-velocity (centrifugal, Coriolis) forces. They come from writing Newton's law for a
material point in moving axes: with V = R^T x_dot, dV/dt = R^T x_ddot - omega x V. The part
-omega x nu is carried exactly by transporting nu between steps (the body holds the world linear
velocity); -omega x (omega x y) is the centrifugal load; one -omega x v comes from the axes, the
other from advecting only v* (not the rigid part) while the material moves (Coriolis, 2 omega x v).
For affine coordinates (inertial world axes) only the advection term remains: -2 A_dot v.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.kernels.eol_grid import (
    Grid,
    node_position,
)

# The reductions over the grid's nodes (the split's moments, the residual's maxima) run in blocks of
# REDUCE_BLOCK threads, each summing every (blocks x REDUCE_BLOCK)-th node (a grid-stride loop: a
# warp reads consecutive nodes), then the block's sum (``wp.tile_sum``) is added with one atomic
# per entry. One atomic per thread, as before, made the 40-entry moments cost 0.06 ms a launch on
# an H100 at 32^3 (50k nodes) with 1024 threads (too few to hide the loads' latency) and 0.26 ms
# with 8192 (the atomics on 40 addresses queue up). ``reduce_blocks`` gives each thread about
# REDUCE_NODES nodes on a GPU; a CPU block is one thread, which runs after the others, so the
# count barely matters there.
REDUCE_BLOCK = 64
REDUCE_NODES = 4
BLOCKS_CPU = 256


def reduce_blocks(n: int, device) -> int:
    """Blocks of a node reduction over n nodes on ``device`` (see ``REDUCE_BLOCK``)."""
    if not device.is_cuda:
        return BLOCKS_CPU
    return max(1, -(-n // (REDUCE_BLOCK * REDUCE_NODES)))


@wp.kernel
def node_velocities(
    v: wp.array(dtype=wp.vec3d),
    mass: wp.array(dtype=wp.float64),
    forces: wp.array(dtype=wp.vec3d),
    grid: Grid,
    L: wp.mat33d,
    c: wp.vec3d,
    F_L: wp.mat33d,
    gravity: wp.vec3d,
    centrifugal: int,
    gyro: wp.mat33d,
    real_mass: wp.array(dtype=wp.float64),
    w: wp.array(dtype=wp.vec3d),
    a: wp.array(dtype=wp.vec3d),
):
    """w_s (current material velocity) and a_s (acceleration) of every node with mass; zero elsewhere.

    a = gyro (f / m + (m_real / m) (-2 L v - L L y)) + gravity. The centrifugal and Coriolis loads
    act on the node's material (``real_mass``, before the ``mass_floor``), not on its phantom mass:
    on a sliver node the floor can be many times its material, so the fictitious loads on the phantom
    mass were unbalanced by any elastic force (issue 16: +21 % angular momentum and +51 % energy in
    20 s at pi rad/s, 6 cells; 0 with this, ``tools/study_eol_loads.py``). ``gyro`` = (I + tau L)^-1
    makes the Coriolis term implicit-midpoint (see ``coriolis_matrix``); the identity gives the
    explicit (forward Euler) form."""
    s = wp.tid()
    if mass[s] <= wp.float64(0.0):
        w[s] = wp.vec3d()
        a[s] = wp.vec3d()
        return
    y = node_position(s, grid)
    Ly = L * y
    w[s] = Ly + c + F_L * v[s]
    fict = -wp.float64(2.0) * (L * v[s])
    if centrifugal != 0:
        fict = fict - L * Ly
    acc = forces[s] / mass[s] + (real_mass[s] / mass[s]) * fict
    a[s] = gyro * acc + gravity


def coriolis_matrix(L: np.ndarray, tau: float, implicit: bool) -> np.ndarray:
    """(I + tau L)^-1: the Coriolis term -2 L v taken at the step's midpoint velocity.

    The forward Euler update v' = v + dt (f - 2 L v) has, for the skew L of a rigid frame,
    eigenvalues of modulus sqrt(1 + (2 |omega| dt)^2); coupled with the explicit (symplectic-Euler)
    elasticity, a linear oscillator x'' = -k x - 2 omega x x' then grows at every dt (by 1.6e-2
    per step at omega_e dt = 1.7, omega dt = 0.01). The implicit midpoint v' = v + dt (f - L (v + v'))
    is v' = v + dt (I + dt L)^-1 (f - 2 L v): a linear map of the same acceleration, so the step
    keeps its w_hat = w + dt a form (and its split and QP), and the oscillator's map is neutrally
    stable (|eigenvalues| = 1) up to the elastic limit. Exact when the step's dt equals tau (free
    flight: tau is the step's cap); a CFL- or contact-shortened step uses its guess's factor
    (first order). It was not the main cause of issue 16's spin-up (the phantom mass was: see
    ``node_velocities``); there it halves the remaining drift (``tools/study_eol_loads.py``)."""
    if not implicit or tau <= 0.0:
        return np.eye(3)
    return np.linalg.inv(np.eye(3) + tau * np.asarray(L, dtype=np.float64))


@wp.kernel
def velocity_moments(
    w0: wp.array(dtype=wp.vec3d),
    w1: wp.array(dtype=wp.vec3d),
    mass: wp.array(dtype=wp.float64),
    grid: Grid,
    weighted: int,
    blocks: int,
    out: wp.array(dtype=wp.float64),
):
    """Moments over nodes with mass (y about the centre of mass, the intermediate origin): out[0:16] =
    sum k yb yb^T, out[16:28] = sum k w0 yb^T, out[28:40] = sum k w1 yb^T with yb = (y, 1) and k = 1
    (the paper's 2-norm, Eq. 23) or k = m_s (``weighted``: the mass norm): everything the
    least-squares split needs, for rigid and affine coordinates alike. Launched tiled, ``blocks``
    blocks (``reduce_blocks``); ``out`` zeroed beforehand."""
    block, lane = wp.tid()
    n = mass.shape[0]
    C = wp.mat44d()
    B0 = wp.mat44d()
    B1 = wp.mat44d()
    one = wp.float64(1.0)
    for s in range(block * wp.block_dim() + lane, n, blocks * wp.block_dim()):
        if mass[s] > wp.float64(0.0):
            y = node_position(s, grid)
            yb = wp.vec4d(y[0], y[1], y[2], one)
            m = one
            if weighted != 0:
                m = mass[s]
            C += m * wp.outer(yb, yb)
            B0 += m * wp.outer(wp.vec4d(w0[s][0], w0[s][1], w0[s][2], wp.float64(0.0)), yb)
            B1 += m * wp.outer(wp.vec4d(w1[s][0], w1[s][1], w1[s][2], wp.float64(0.0)), yb)
    tC = wp.tile_sum(wp.tile(C, preserve_type=True))
    tB0 = wp.tile_sum(wp.tile(B0, preserve_type=True))
    tB1 = wp.tile_sum(wp.tile(B1, preserve_type=True))
    if lane == 0:
        sC = tC[0]
        sB0 = tB0[0]
        sB1 = tB1[0]
        for r in range(4):
            for q in range(4):
                wp.atomic_add(out, 4 * r + q, sC[r, q])
        for r in range(3):
            for q in range(4):
                wp.atomic_add(out, 16 + 4 * r + q, sB0[r, q])
                wp.atomic_add(out, 28 + 4 * r + q, sB1[r, q])


# layout of the split's fields on the device (``split_fields``): L_0 (9, row-major), c_0 (3),
# L_1 (9), c_1 (3) and C[3, 3] (the moments' total weight: the body's mass under the mass norm)
FIELDS = 25


@wp.func
def fields_of_moments(kind: int, C: wp.mat44d, B: wp.mat44d) -> wp.mat44d:
    """(L, c) of the least-squares split (Eq. 23) from the moments C = sum k yb yb^T and B = sum k
    w yb^T (rows 0-2), returned as the 3x4 block [L | c] of a 4x4 (``wsim.eol.split`` derives it).

    Affine (kind 1): [L | c] = B C^-1. Rigid (kind 0): the normal equations of J_L = [-[y]x, I]
    with S = C[:3, :3], s = C[:3, 3], k = C[3, 3]: (tr S I - S) omega + [s]x c = r_omega and
    -[s]x omega + k c = r_c. Eliminating c leaves the weighted inertia about the centroid,
    (tr S I - S + [s]x [s]x / k) omega = r_omega - [s]x r_c / k, then c = (r_c + [s]x omega) / k;
    L = [omega]x."""
    out = wp.mat44d()
    if C[3, 3] <= wp.float64(0.0):
        return out
    if kind == 1:
        Q = B * wp.inverse(C)
        for r in range(3):
            for q in range(4):
                out[r, q] = Q[r, q]
        return out
    S = wp.mat33d(C[0, 0], C[0, 1], C[0, 2], C[1, 0], C[1, 1], C[1, 2], C[2, 0], C[2, 1], C[2, 2])
    sy = wp.vec3d(C[0, 3], C[1, 3], C[2, 3])
    k = C[3, 3]
    r_w = wp.vec3d(B[2, 1] - B[1, 2], B[0, 2] - B[2, 0], B[1, 0] - B[0, 1])
    r_c = wp.vec3d(B[0, 3], B[1, 3], B[2, 3])
    X = wp.skew(sy)
    A = wp.trace(S) * wp.identity(n=3, dtype=wp.float64) - S + X * X / k
    omega = wp.inverse(A) * (r_w - X * r_c / k)
    c = (r_c + X * omega) / k
    L = wp.skew(omega)
    for r in range(3):
        for q in range(3):
            out[r, q] = L[r, q]
        out[r, 3] = c[r]
    return out


@wp.kernel
def split_fields(moments: wp.array(dtype=wp.float64), kind: int, fields: wp.array(dtype=wp.float64)):
    """One thread: the split's (L_0, c_0), (L_1, c_1) from ``velocity_moments`` into ``fields``
    (layout ``FIELDS``), so the step's kernels read them without a round trip to the host; then
    zeroes ``moments`` (allocated zero) for the next split, which saves each split a memset."""
    C = wp.mat44d()
    B0 = wp.mat44d()
    B1 = wp.mat44d()
    for r in range(4):
        for q in range(4):
            C[r, q] = moments[4 * r + q]
    for r in range(3):
        for q in range(4):
            B0[r, q] = moments[16 + 4 * r + q]
            B1[r, q] = moments[28 + 4 * r + q]
    F0 = fields_of_moments(kind, C, B0)
    F1 = fields_of_moments(kind, C, B1)
    for r in range(3):
        for q in range(3):
            fields[3 * r + q] = F0[r, q]
            fields[12 + 3 * r + q] = F1[r, q]
        fields[9 + r] = F0[r, 3]
        fields[21 + r] = F1[r, 3]
    fields[24] = C[3, 3]
    for e in range(40):  # ready for the next split's sums (``split_on_device`` zeroes it no more)
        moments[e] = wp.float64(0.0)


@wp.func
def field_L(fields: wp.array(dtype=wp.float64), at: int) -> wp.mat33d:
    return wp.mat33d(fields[at], fields[at + 1], fields[at + 2], fields[at + 3], fields[at + 4], fields[at + 5],
                     fields[at + 6], fields[at + 7], fields[at + 8])


@wp.func
def field_c(fields: wp.array(dtype=wp.float64), at: int) -> wp.vec3d:
    return wp.vec3d(fields[at], fields[at + 1], fields[at + 2])


@wp.kernel
def eulerian_residual(
    w0: wp.array(dtype=wp.vec3d),
    w1: wp.array(dtype=wp.vec3d),
    mass: wp.array(dtype=wp.float64),
    grid: Grid,
    fields: wp.array(dtype=wp.float64),
    F_L_inv: wp.mat33d,
    blocks: int,
    v0: wp.array(dtype=wp.vec3d),
    v1: wp.array(dtype=wp.vec3d),
    vmax: wp.array(dtype=wp.float64),
):
    """v*_i = F_L^-1 (w_i - L_i y - c_i) (Eq. 24 for both parts of Eq. 32), and per axis max |v*_i|
    (Eq. 33); (L_i, c_i) from ``fields`` (``split_fields``). Launched tiled like
    ``velocity_moments``."""
    block, lane = wp.tid()
    n = mass.shape[0]
    L0 = field_L(fields, 0)
    c0 = field_c(fields, 9)
    L1 = field_L(fields, 12)
    c1 = field_c(fields, 21)
    m0 = wp.vec3d()
    m1 = wp.vec3d()
    for s in range(block * wp.block_dim() + lane, n, blocks * wp.block_dim()):
        if mass[s] > wp.float64(0.0):
            y = node_position(s, grid)
            a = F_L_inv * (w0[s] - L0 * y - c0)
            b = F_L_inv * (w1[s] - L1 * y - c1)
            v0[s] = a
            v1[s] = b
            for d in range(3):
                m0[d] = wp.max(m0[d], wp.abs(a[d]))
                m1[d] = wp.max(m1[d], wp.abs(b[d]))
        else:
            v0[s] = wp.vec3d()
            v1[s] = wp.vec3d()
    for d in range(3):
        t0 = wp.tile_max(wp.tile(m0[d]))
        t1 = wp.tile_max(wp.tile(m1[d]))
        if lane == 0:
            wp.atomic_max(vmax, d, t0[0])
            wp.atomic_max(vmax, 3 + d, t1[0])


@wp.kernel
def remove_lagrangian_part(v: wp.array(dtype=wp.vec3d), mass: wp.array(dtype=wp.float64), grid: Grid,
                           fields: wp.array(dtype=wp.float64)):
    """v_s -= L y_s + c at the nodes with mass: the residual loses the Lagrangian field (L, c) that
    the least-squares split (Eq. 23) finds in it (``fields``' first part, ``split_fields``), so
    that it carries no momentum of its own."""
    s = wp.tid()
    if mass[s] > wp.float64(0.0):
        v[s] = v[s] - field_L(fields, 0) * node_position(s, grid) - field_c(fields, 9)


@wp.kernel
def combine(v0: wp.array(dtype=wp.vec3d), v1: wp.array(dtype=wp.vec3d), dt_at: wp.array(dtype=wp.float64),
            out: wp.array(dtype=wp.vec3d)):
    """v* = v*_0 + dt v*_1 (Eq. 32c), dt = dt_at[0]."""
    s = wp.tid()
    out[s] = v0[s] + dt_at[0] * v1[s]


@wp.kernel
def extrapolate(v: wp.array3d(dtype=wp.vec3d), mass: wp.array3d(dtype=wp.float64), out: wp.array3d(dtype=wp.vec3d)):
    """Nodes without mass take the mean v of their face neighbours with mass (one layer): the empty
    nodes of a cell the material is flowing into carry its velocity, so advecting z moves the
    material boundary instead of pinning it."""
    i, j, k = wp.tid()
    if mass[i, j, k] > wp.float64(0.0):
        out[i, j, k] = v[i, j, k]
        return
    acc = wp.vec3d()
    cnt = wp.float64(0.0)
    for d in range(6):
        a = i
        b = j
        c = k
        if d == 0:
            a = i - 1
        elif d == 1:
            a = i + 1
        elif d == 2:
            b = j - 1
        elif d == 3:
            b = j + 1
        elif d == 4:
            c = k - 1
        else:
            c = k + 1
        if a >= 0 and b >= 0 and c >= 0 and a < v.shape[0] and b < v.shape[1] and c < v.shape[2]:
            if mass[a, b, c] > wp.float64(0.0):
                acc += v[a, b, c]
                cnt += wp.float64(1.0)
    if cnt > wp.float64(0.0):
        out[i, j, k] = acc / cnt
    else:
        out[i, j, k] = wp.vec3d()


@wp.kernel
def add_acceleration(forces: wp.array(dtype=wp.vec3d), mass: wp.array(dtype=wp.float64), a: wp.array(dtype=wp.vec3d)):
    """a_s += f_s / m_s on nodes with mass."""
    s = wp.tid()
    if mass[s] > wp.float64(0.0):
        a[s] = a[s] + forces[s] / mass[s]


@wp.kernel
def floor_mass(mass: wp.array(dtype=wp.float64), floor: wp.float64):
    """m_s <- max(m_s, floor) on nodes with mass: a node whose support barely holds material (a
    Gauss point in the far corner of its cell) is otherwise flung by stress gradients and contact
    impulses acting on almost no mass, the small-mass instability of grid methods (see ``EolBody``)."""
    s = wp.tid()
    if mass[s] > wp.float64(0.0):
        mass[s] = wp.max(mass[s], floor)
