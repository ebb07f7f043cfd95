"""Adaptive time step of EoL (Fan et al. Sec. 3.6, Eqs. 30-33).

First-order advection is stable when Eq. (30) holds:
dt * max_i(|v*_x| / dx, |v*_y| / dy, |v*_z| / dz) <= alpha (alpha < 1, the CFL number).

The contact QP's velocities are affine in dt, v = v_0 + dt v_1 (Eq. 31), and the least-squares
split is linear, so the Eulerian velocity is too: v* = v*_0 + dt v*_1 (Eq. 32). With
gamma_i = max|v*_ix| / dx + max|v*_iy| / dy + max|v*_iz| / dz (a sum: conservative against
Eq. 30's max), the largest admissible step is the positive root of Eq. (33),
gamma_1 dt^2 + gamma_0 dt - alpha = 0, capped by the frame time and the explicit elastic limit.
"""

from __future__ import annotations

import math

import numpy as np

from wsim.errors import InvalidParameter


def cfl_gamma(v_star: np.ndarray, spacing: float | np.ndarray) -> float:
    """gamma = sum over axes of max |v*_axis| / spacing_axis for nodal velocities v* (n, 3)."""
    v = np.abs(np.asarray(v_star, dtype=np.float64).reshape(-1, 3))
    if v.size == 0:
        return 0.0
    return float(np.sum(v.max(axis=0) / np.broadcast_to(np.asarray(spacing, dtype=np.float64), (3,))))


def adaptive_dt(v0_star: np.ndarray, v1_star: np.ndarray, spacing: float | np.ndarray, alpha: float,
                dt_max: float) -> float:
    """The root of Eq. (33) for v* = v*_0 + dt v*_1, capped at dt_max [s]."""
    if not (0.0 < alpha < 1.0):
        raise InvalidParameter(f"cfl = {alpha!r} must be in (0, 1)")
    if not (dt_max > 0.0) or not math.isfinite(dt_max):
        raise InvalidParameter(f"dt_max = {dt_max!r} s must be > 0")
    g0, g1 = cfl_gamma(v0_star, spacing), cfl_gamma(v1_star, spacing)
    if g1 > 0.0:
        dt = (-g0 + math.sqrt(g0 * g0 + 4.0 * g1 * alpha)) / (2.0 * g1)
    elif g0 > 0.0:
        dt = alpha / g0
    else:
        dt = dt_max
    return min(dt, dt_max)


def elastic_dt_limit(h: float, material, safety: float = 0.25) -> float:
    """Explicit elasticity's limit: the P wave crosses at most ``safety`` of a cell per step, h / c1."""
    if material.incompressible:
        raise InvalidParameter("explicit EoL elasticity needs a compressible material (nu < 0.5)")
    return safety * h / material.c1
