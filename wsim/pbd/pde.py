"""Closed-form solutions of the dynamic beam PDE used to fit keyframe curves (Fang et al. 2021).

The paper models each coordinate w (x, y or z) of a curve by a separated solution of a dynamic
fourth-order PDE (its Eqs. 4-8, Appendix B). We use the textbook sign of the dynamic
Euler-Bernoulli beam,

    m w_tt + D w_uuuu = 0,   m > 0, D > 0,                                            (1)

(the paper writes m w_tt = D w_uuuu, which makes its own Eqs. (6), (7) need D/m < 0). Separating
w = W(u) T(t) with W'''' = lam W and T'' = -(D/m) lam T, the two physically consistent families are

    lam = +D0^4 (paper Eq. 7): space {e^{D0 u}, e^{-D0 u}, cos D0 u, sin D0 u}, time {cos m0 t, sin m0 t}
    lam = -D0^4 (paper Eq. 6): space {e^{+-a u} cos a u, e^{+-a u} sin a u} (a = D0 / sqrt 2),
                               time {cosh m0 t, sinh m0 t}

with m0^2 = (D/m) D0^4; every (D0, m0) pair is consistent for some D/m > 0.

Numerically stable bases spanning the same spaces:

- space, D0 <= D_SWITCH: the four fundamental solutions of W'''' = lam W (Krylov functions),
  F_k(u; lam) = sum_n lam^n u^(4n+k) / (4n+k)!,  k = 0..3, with F_k^(j)(0) = delta_jk. As lam -> 0
  they become exactly 1, u, u^2/2, u^3/6: the PDE basis tends to the cubic polynomials.
- space, D0 > D_SWITCH: the Krylov functions all grow like e^(D0 u) and become nearly collinear,
  so the same span is written with bounded functions: {e^(-D0 u), e^(-D0 (1-u)), cos D0 u,
  sin D0 u} for lam > 0, {e^(-a u) cos a u, e^(-a u) sin a u, e^(-a (1-u)) cos a u,
  e^(-a (1-u)) sin a u} for lam < 0. Coefficients are stored in the basis their D0 selects.
- time: {C(m t), S(m t) / m} with (C, S) = (cos, sin) or (cosh, sinh); {1, t} as m -> 0.

A segment between two keyframes at t = 0 and t = 1 holds the paper's 8 coefficients per
coordinate. Fitting them to the two keyframes is exactly a 4-term spatial fit per keyframe (the
2x2 time matrix is invertible), and the closed form then reads

    w(u, t) = W0(u) S(m (1 - t)) / S(m) + W1(u) S(m t) / S(m),                          (2)

a blend of the two keyframe curves; m -> 0 gives linear interpolation. All evaluation is float64.
"""

from __future__ import annotations

import math

import numpy as np

#: below this |D0 u| the Krylov functions use their power series (the closed forms cancel)
SERIES_LIMIT = 1.0
_SERIES_TERMS = 8
#: above this D0 the spatial basis is the bounded exponential/trigonometric one
D_SWITCH = 4.0


def spatial_constant(lam: float) -> float:
    """D0 = |lam|^(1/4) [1/u]."""
    return abs(float(lam)) ** 0.25


def krylov(u: np.ndarray, lam: float) -> np.ndarray:
    """The four fundamental solutions F_0..F_3 of W'''' = lam W at parameters u: shape (..., 4).

    Closed forms for |D0 u| > SERIES_LIMIT, power series below (float64 throughout).
    """
    u = np.asarray(u, dtype=np.float64)
    out = np.empty(u.shape + (4,))
    d0 = spatial_constant(lam)
    z = d0 * np.abs(u)
    small = z <= SERIES_LIMIT
    if np.any(small):
        us = u[small]
        acc = np.zeros(us.shape + (4,))
        u4 = us**4
        for k in range(4):
            term = us**k / math.factorial(k)
            total = term.copy()
            for n in range(1, _SERIES_TERMS):
                term = term * lam * u4 / ((4 * n + k) * (4 * n + k - 1) * (4 * n + k - 2) * (4 * n + k - 3))
                total = total + term
            acc[..., k] = total
        out[small] = acc
    big = ~small
    if np.any(big):
        ub = u[big]
        if lam > 0.0:
            x = d0 * ub
            ch, sh, c, s = np.cosh(x), np.sinh(x), np.cos(x), np.sin(x)
            out[big] = np.stack(
                [0.5 * (ch + c), 0.5 * (sh + s) / d0, 0.5 * (ch - c) / d0**2, 0.5 * (sh - s) / d0**3], axis=-1
            )
        else:
            a = d0 / math.sqrt(2.0)
            x = a * ub
            ch, sh, c, s = np.cosh(x), np.sinh(x), np.cos(x), np.sin(x)
            out[big] = np.stack(
                [ch * c, 0.5 * (ch * s + sh * c) / a, 0.5 * sh * s / a**2, 0.25 * (ch * s - sh * c) / a**3], axis=-1
            )
    return out


def scaled_exponential(u: np.ndarray, lam: float) -> np.ndarray:
    """The bounded basis of the same span as ``krylov`` for large D0 (module docstring): (..., 4)."""
    u = np.asarray(u, dtype=np.float64)
    d0 = spatial_constant(lam)
    if lam > 0.0:
        x = d0 * u
        return np.stack([np.exp(-x), np.exp(-d0 * (1.0 - u)), np.cos(x), np.sin(x)], axis=-1)
    a = d0 / math.sqrt(2.0)
    x = a * u
    e0, e1, c, s = np.exp(-x), np.exp(-a * (1.0 - u)), np.cos(x), np.sin(x)
    return np.stack([e0 * c, e0 * s, e1 * c, e1 * s], axis=-1)


def spatial_basis(u: np.ndarray, lam: float) -> np.ndarray:
    """The PDE spatial basis at u for constant lam: Krylov for D0 <= D_SWITCH, else scaled exponentials."""
    return krylov(u, lam) if spatial_constant(lam) <= D_SWITCH else scaled_exponential(u, lam)


def time_basis(t: np.ndarray, m0: float, lam: float) -> np.ndarray:
    """{C(m0 t), S(m0 t) / m0} at times t, shape (..., 2): cos/sin for lam >= 0, cosh/sinh for lam < 0.

    {1, t} for m0 = 0 (the common limit).
    """
    t = np.asarray(t, dtype=np.float64)
    if m0 == 0.0:
        return np.stack([np.ones_like(t), t], axis=-1)
    x = m0 * t
    if lam >= 0.0:
        return np.stack([np.cos(x), np.sin(x) / m0], axis=-1)
    return np.stack([np.cosh(x), np.sinh(x) / m0], axis=-1)


def blend_weights(t: np.ndarray, m0: float, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """Weights (a, b) of Eq. (2): w(t) = a(t) W0 + b(t) W1, exact at t = 0 and 1.

    S = sin for lam >= 0 (needs m0 < pi), sinh for lam < 0; linear (1 - t, t) for m0 = 0.
    """
    t = np.asarray(t, dtype=np.float64)
    if m0 == 0.0:
        return 1.0 - t, t
    S = np.sin if lam >= 0.0 else np.sinh
    s1 = S(m0)
    return S(m0 * (1.0 - t)) / s1, S(m0 * t) / s1


def closed_form(u: np.ndarray, t: np.ndarray, coeffs: np.ndarray, lam: float, m0: float) -> np.ndarray:
    """w(u, t) = sum_a sum_k c[a, k] T_a(t) F_k(u) (the paper's Eqs. 5-8 in the stable bases).

    ``coeffs`` is (2, 4); u and t broadcast against each other.
    """
    F = spatial_basis(u, lam)
    T = time_basis(t, m0, lam)
    return np.einsum("...a,...k,ak->...", T, F, coeffs)


def segment_coefficients(W0: np.ndarray, W1: np.ndarray, lam: float, m0: float) -> np.ndarray:
    """The paper's 8 coefficients (2, 4) of the segment whose keyframe curves have
    spatial-basis coefficients W0, W1 (4,) at t = 0 and t = 1 (Eq. 2 solved for the time
    coefficients)."""
    T1 = time_basis(np.array(1.0), m0, lam)
    c0 = np.asarray(W0, dtype=np.float64)
    c1 = (np.asarray(W1, dtype=np.float64) - T1[0] * c0) / T1[1]
    return np.stack([c0, c1])


def pde_residual_ratio(u: np.ndarray, t: np.ndarray, coeffs: np.ndarray, lam: float, m0: float, h: float = 1e-3) -> float:
    """max |m w_tt + D w_uuuu| / max(|m w_tt|, |D w_uuuu|) by central finite differences, with
    m = 1 and D = m0^2 / D0^4 taken from the consistent-sign relation (validation helper)."""
    d0 = spatial_constant(lam)
    D = m0**2 / d0**4 if d0 > 0 else 0.0
    w = lambda uu, tt: closed_form(uu, tt, coeffs, lam, m0)  # noqa: E731
    w_tt = (w(u, t + h) - 2 * w(u, t) + w(u, t - h)) / h**2
    w_uuuu = (w(u + 2 * h, t) - 4 * w(u + h, t) + 6 * w(u, t) - 4 * w(u - h, t) + w(u - 2 * h, t)) / h**4
    scale = max(np.abs(w_tt).max(), np.abs(D * w_uuuu).max(), 1e-300)
    return float(np.abs(w_tt + D * w_uuuu).max() / scale)
