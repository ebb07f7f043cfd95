"""Baseline curve bases of the PBD-reconstruction paper: cubic Bezier and uniform cubic B-spline.

Each keyframe curve is fitted on its own by least squares (the paper's Eqs. 18 and 22, solved as
a least-squares problem rather than through the normal equations), with the same parameters u as
the PDE fit; in-between frames interpolate the fitted control points linearly in time.

With 4 control points a uniform cubic B-spline is a single polynomial segment, so it spans
exactly the cubic polynomials on its domain, like the cubic Bezier: the two fits give the same
curve (the paper's identical Bezier and B-spline table rows), with different control points.
"""

from __future__ import annotations

from math import comb

import numpy as np


def bernstein(u: np.ndarray, degree: int = 3) -> np.ndarray:
    """Bernstein polynomials B_i^k(u) = C(k, i) u^i (1 - u)^(k - i), i = 0..k (Eq. 17): (..., k + 1)."""
    u = np.asarray(u, dtype=np.float64)[..., None]
    i = np.arange(degree + 1)
    return np.array([comb(degree, j) for j in i], dtype=np.float64) * u**i * (1.0 - u) ** (degree - i)


def cox_de_boor(x: np.ndarray, knots: np.ndarray, degree: int) -> np.ndarray:
    """B-spline basis N_{i,q}(x) of ``degree`` over ``knots`` by the Cox-de Boor recursion (Eqs. 20-21).

    The zeroth-degree functions use half-open intervals [t_i, t_{i+1}), except that the last
    non-empty interval is closed so the basis sums to one at the end of the domain. Returns
    (..., len(knots) - degree - 1).
    """
    x = np.asarray(x, dtype=np.float64)[..., None]
    t = np.asarray(knots, dtype=np.float64)
    N = ((t[:-1] <= x) & (x < t[1:])).astype(np.float64)
    last = np.flatnonzero(t[1:] > t[:-1])[-1]
    N[..., last] = np.where(x[..., 0] == t[last + 1], 1.0, N[..., last])
    for q in range(1, degree + 1):
        left_den = t[q:-1] - t[: -q - 1]
        right_den = t[q + 1 :] - t[1:-q]
        left = np.divide(x - t[: -q - 1], left_den, out=np.zeros(np.broadcast_shapes(x.shape, left_den.shape)), where=left_den > 0)
        right = np.divide(t[q + 1 :] - x, right_den, out=np.zeros(np.broadcast_shapes(x.shape, right_den.shape)), where=right_den > 0)
        N = left * N[..., :-1] + right * N[..., 1:]
    return N


#: uniform knots of a cubic B-spline with 4 control points; its domain is [t_3, t_4] = [3, 4]
UNIFORM_CUBIC_KNOTS = np.arange(8, dtype=np.float64)


def uniform_cubic_bspline(u: np.ndarray) -> np.ndarray:
    """Uniform cubic B-spline basis with 4 control points at u in [0, 1] (mapped onto [t_3, t_4]): (..., 4)."""
    return cox_de_boor(3.0 + np.asarray(u, dtype=np.float64), UNIFORM_CUBIC_KNOTS, 3)


def uniform_cubic_bspline_closed(u: np.ndarray) -> np.ndarray:
    """The same four functions in closed form ((1-u)^3, 3u^3 - 6u^2 + 4, ...)/6, for the GPU kernel."""
    u = np.asarray(u, dtype=np.float64)
    return np.stack(
        [(1 - u) ** 3, 3 * u**3 - 6 * u**2 + 4, -3 * u**3 + 3 * u**2 + 3 * u + 1, u**3], axis=-1
    ) / 6.0
