"""Warp kernels of EoL advection on the intermediate-domain grid (Fan et al. Eq. 15, Algorithm 1).

Semi-Lagrangian (first order, the paper's scheme): every node s traces back along its own
velocity, y* = y_s - dt v_s, and takes the trilinearly interpolated value there (clamped to the
grid box). BFECC (Kim et al. 2005) is the higher-order option: forward, backward, then forward
again on the error-compensated field; it is second order where the field is smooth. Its limited
form (Selle et al. 2008) clamps the last pass to the range of the original values: no new extrema. Values are
vec3 (material coordinates z, or velocities); float64 for z, whose differences carry the strain.

Advection samples z upstream, next to the material, so z is continued into the empty nodes around
it each step (``reference_map_gradient``, ``extend_reference_map``).
"""

from __future__ import annotations

import warp as wp

from wsim.kernels.eol_grid import Grid, cell_of, corner_value, grid_coordinates, node_at, sample_trilinear


@wp.kernel
def semi_lagrangian(
    q: wp.array3d(dtype=wp.vec3d),
    v: wp.array3d(dtype=wp.vec3d),
    grid: Grid,
    dt_at: wp.array(dtype=wp.float64),
    sign: wp.float64,
    out: wp.array3d(dtype=wp.vec3d),
):
    """out_s = q(y_s - dt v_s): one first-order step of dq/dt + v . grad q = 0 (Eq. 15), dt =
    sign dt_at[0] (on the device: a captured step reads each step's dt there)."""
    i, j, k = wp.tid()
    y = node_at(grid, i, j, k)
    out[i, j, k] = sample_trilinear(q, y - sign * dt_at[0] * v[i, j, k], grid)


@wp.kernel
def bfecc_combine(q: wp.array3d(dtype=wp.vec3d), back: wp.array3d(dtype=wp.vec3d), out: wp.array3d(dtype=wp.vec3d)):
    """out = q + (q - back) / 2: the error-compensated field BFECC advects in its last pass."""
    i, j, k = wp.tid()
    out[i, j, k] = q[i, j, k] + wp.float64(0.5) * (q[i, j, k] - back[i, j, k])


@wp.kernel
def semi_lagrangian_limited(
    q: wp.array3d(dtype=wp.vec3d),
    bound: wp.array3d(dtype=wp.vec3d),
    v: wp.array3d(dtype=wp.vec3d),
    grid: Grid,
    dt_at: wp.array(dtype=wp.float64),
    out: wp.array3d(dtype=wp.vec3d),
):
    """BFECC's last pass with the limiter of Selle et al. (2008): q at the foot point, clamped per
    component to the range of ``bound`` (the field before advection) over the foot point's cell, so
    the scheme adds no new extrema (unlimited BFECC overshoots where v* jumps, e.g. at a contact).
    dt = dt_at[0]."""
    i, j, k = wp.tid()
    p = node_at(grid, i, j, k) - dt_at[0] * v[i, j, k]
    value = sample_trilinear(q, p, grid)
    g = grid_coordinates(bound, p, grid)
    cell = cell_of(bound, g)
    lo = corner_value(bound, cell, 0)
    hi = lo
    for c in range(1, 8):
        lo = wp.min(lo, corner_value(bound, cell, c))
        hi = wp.max(hi, corner_value(bound, cell, c))
    out[i, j, k] = wp.max(lo, wp.min(hi, value))


@wp.kernel
def reference_map_gradient(
    z: wp.array3d(dtype=wp.vec3d),
    mass: wp.array3d(dtype=wp.float64),
    h: wp.float64,
    layer: wp.array3d(dtype=wp.int32),
    G: wp.array3d(dtype=wp.mat33d),
):
    """Start of the reference-map extension: layer = 1 on nodes with material (0 elsewhere), and
    there grad_y z by differences with the neighbours that hold material (central where both
    are there, one-sided where one is, the identity column where neither: a rest-like guess)."""
    i, j, k = wp.tid()
    if mass[i, j, k] <= wp.float64(0.0):
        layer[i, j, k] = 0
        return
    layer[i, j, k] = 1
    g = wp.mat33d()
    for a in range(3):
        lo = wp.vec3i(i, j, k)
        hi = wp.vec3i(i, j, k)
        lo[a] = lo[a] - 1
        hi[a] = hi[a] + 1
        has_lo = lo[a] >= 0 and mass[lo[0], lo[1], lo[2]] > wp.float64(0.0)
        has_hi = hi[a] < mass.shape[a] and mass[hi[0], hi[1], hi[2]] > wp.float64(0.0)
        col = wp.vec3d()
        col[a] = wp.float64(1.0)
        if has_lo and has_hi:
            col = (z[hi[0], hi[1], hi[2]] - z[lo[0], lo[1], lo[2]]) / (wp.float64(2.0) * h)
        elif has_hi:
            col = (z[hi[0], hi[1], hi[2]] - z[i, j, k]) / h
        elif has_lo:
            col = (z[i, j, k] - z[lo[0], lo[1], lo[2]]) / h
        for r in range(3):
            g[r, a] = col[r]
    G[i, j, k] = g


@wp.kernel
def extend_reference_map(
    z: wp.array3d(dtype=wp.vec3d),
    layer: wp.array3d(dtype=wp.int32),
    G: wp.array3d(dtype=wp.mat33d),
    h: wp.float64,
    known: int,
):
    """One layer of the reference-map extension into nodes without material.

    A node with no layer yet that touches (26-neighbourhood) nodes of layers 1..known takes the
    mean of their first-order predictions z_n + G_n (y_s - y_n), and the mean G_n, as layer
    known + 1. Semi-Lagrangian advection samples z a fraction of a cell upstream and tracking
    finds surface vertices in cells with empty corners, so z there must continue the material's
    map. Left at stale values (the rest map, or whatever the node held when material left),
    a corner of a squashed body read 2-3 cells of displacement off and a bunny's thin parts
    exploded on landing (issue 16 item 6). In place: a thread writes only its own node of layer 0
    and reads only nodes of layers 1..known."""
    i, j, k = wp.tid()
    if layer[i, j, k] != 0:
        return
    acc = wp.vec3d()
    gacc = wp.mat33d()
    cnt = wp.float64(0.0)
    for d in range(27):
        a = i + d // 9 - 1
        b = j + (d // 3) % 3 - 1
        c = k + d % 3 - 1
        if a >= 0 and b >= 0 and c >= 0 and a < z.shape[0] and b < z.shape[1] and c < z.shape[2]:
            ln = layer[a, b, c]
            if ln > 0 and ln <= known:
                off = h * wp.vec3d(wp.float64(i - a), wp.float64(j - b), wp.float64(k - c))
                acc += z[a, b, c] + G[a, b, c] * off
                gacc += G[a, b, c]
                cnt += wp.float64(1.0)
    if cnt > wp.float64(0.0):
        z[i, j, k] = acc / cnt
        G[i, j, k] = gacc / cnt
        layer[i, j, k] = known + 1
