"""Warp kernels of EoL advection on the intermediate-domain grid (Fan et al. Eq. 15, Algorithm 1).

Semi-Lagrangian (first order, the paper's scheme): every node s traces back along its own
velocity, y* = y_s - dt v_s, and takes the trilinearly interpolated value there (clamped to the
grid box). BFECC (Kim et al. 2005) is the higher-order option: forward, backward, then forward
again on the error-compensated field; it is second order where the field is smooth. Its limited
form (Selle et al. 2008) clamps the last pass to the range of the original values: no new extrema. Values are
vec3 (material coordinates z, or velocities); float64 for z, whose differences carry the strain.
"""

from __future__ import annotations

import warp as wp

from wsim.kernels.eol_grid import Grid, cell_of, corner_value, grid_coordinates, node_at, sample_trilinear


@wp.kernel
def semi_lagrangian(
    q: wp.array3d(dtype=wp.vec3d),
    v: wp.array3d(dtype=wp.vec3d),
    grid: Grid,
    dt: wp.float64,
    out: wp.array3d(dtype=wp.vec3d),
):
    """out_s = q(y_s - dt v_s): one first-order step of dq/dt + v . grad q = 0 (Eq. 15)."""
    i, j, k = wp.tid()
    y = node_at(grid, i, j, k)
    out[i, j, k] = sample_trilinear(q, y - dt * v[i, j, k], grid)


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
    dt: wp.float64,
    out: wp.array3d(dtype=wp.vec3d),
):
    """BFECC's last pass with the limiter of Selle et al. (2008): q at the foot point, clamped per
    component to the range of ``bound`` (the field before advection) over the foot point's cell, so
    the scheme adds no new extrema (unlimited BFECC overshoots where v* jumps, e.g. at a contact)."""
    i, j, k = wp.tid()
    p = node_at(grid, i, j, k) - dt * v[i, j, k]
    value = sample_trilinear(q, p, grid)
    g = grid_coordinates(bound, p, grid)
    cell = cell_of(bound, g)
    lo = corner_value(bound, cell, 0)
    hi = lo
    for c in range(1, 8):
        lo = wp.min(lo, corner_value(bound, cell, c))
        hi = wp.max(hi, corner_value(bound, cell, c))
    out[i, j, k] = wp.max(lo, wp.min(hi, value))
