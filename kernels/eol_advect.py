"""Warp kernels of EoL advection on the intermediate-domain grid (Fan et al. Eq. 15, Algorithm 1).

Semi-Lagrangian (first order, the paper's scheme): every node s traces back along its own
velocity, y* = y_s - dt v_s, and takes the trilinearly interpolated value there (clamped to the
grid box). BFECC (Kim et al. 2005) is the higher-order option: forward, backward, then forward
again on the error-compensated field; it is second order where the field is smooth. Values are
vec3 (material coordinates z, or velocities); float64 for z, whose differences carry the strain.
"""

from __future__ import annotations

import warp as wp

from wsim.kernels.eol_grid import sample_trilinear


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
