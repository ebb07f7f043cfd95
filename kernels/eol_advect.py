"""Warp kernels of EoL advection on the intermediate-domain grid (Fan et al. Eq. 15, Algorithm 1).

Semi-Lagrangian (first order, the paper's scheme): every node s traces back along its own
velocity, y* = y_s - dt v_s, and takes the trilinearly interpolated value there (clamped to the
grid box). BFECC (Kim et al. 2005) is the higher-order option: forward, backward, then forward
again on the error-compensated field; it is second order where the field is smooth. Values are
vec3 (material coordinates z, or velocities); float64 for z, whose differences carry the strain.
"""

from __future__ import annotations

import warp as wp


@wp.func
def sample_trilinear(q: wp.array3d(dtype=wp.vec3d), p: wp.vec3d, origin: wp.vec3d, h: wp.float64) -> wp.vec3d:
    """q at point p (trilinear; p clamped into the grid box)."""
    nx = q.shape[0] - 1
    ny = q.shape[1] - 1
    nz = q.shape[2] - 1
    g = (p - origin) / h
    gx = wp.clamp(g[0], wp.float64(0.0), wp.float64(nx))
    gy = wp.clamp(g[1], wp.float64(0.0), wp.float64(ny))
    gz = wp.clamp(g[2], wp.float64(0.0), wp.float64(nz))
    i = wp.min(int(gx), nx - 1)
    j = wp.min(int(gy), ny - 1)
    k = wp.min(int(gz), nz - 1)
    tx = gx - wp.float64(i)
    ty = gy - wp.float64(j)
    tz = gz - wp.float64(k)
    one = wp.float64(1.0)
    c00 = q[i, j, k] * (one - tx) + q[i + 1, j, k] * tx
    c10 = q[i, j + 1, k] * (one - tx) + q[i + 1, j + 1, k] * tx
    c01 = q[i, j, k + 1] * (one - tx) + q[i + 1, j, k + 1] * tx
    c11 = q[i, j + 1, k + 1] * (one - tx) + q[i + 1, j + 1, k + 1] * tx
    c0 = c00 * (one - ty) + c10 * ty
    c1 = c01 * (one - ty) + c11 * ty
    return c0 * (one - tz) + c1 * tz


@wp.kernel
def semi_lagrangian(
    q: wp.array3d(dtype=wp.vec3d),
    v: wp.array3d(dtype=wp.vec3d),
    origin: wp.vec3d,
    h: wp.float64,
    dt: wp.float64,
    out: wp.array3d(dtype=wp.vec3d),
):
    """out_s = q(y_s - dt v_s): one first-order step of dq/dt + v . grad q = 0 (Eq. 15)."""
    i, j, k = wp.tid()
    y = origin + h * wp.vec3d(wp.float64(i), wp.float64(j), wp.float64(k))
    out[i, j, k] = sample_trilinear(q, y - dt * v[i, j, k], origin, h)


@wp.kernel
def bfecc_combine(q: wp.array3d(dtype=wp.vec3d), back: wp.array3d(dtype=wp.vec3d), out: wp.array3d(dtype=wp.vec3d)):
    """out = q + (q - back) / 2: the error-compensated field BFECC advects in its last pass."""
    i, j, k = wp.tid()
    out[i, j, k] = q[i, j, k] + wp.float64(0.5) * (q[i, j, k] - back[i, j, k])
