"""Laplace-domain fundamental solutions of 3D elastodynamics (Sugimoto et al., Appendix A), numpy float64.

The reference implementation the Warp kernels (``kernels/bem_kernels.py``) are tested against.
With r = y - x, r = |r|, d = r / r, n the unit normal at y and the inverse wave speeds
a1 = 1/c1, a2 = 1/c2 (a1 = 0 in the incompressible limit nu = 0.5, where c1 = inf), every kernel
is written through

    E_k = exp(-s r a_k),   z_k = s r a_k,
    phi(z) = ((1 + z) e^-z - 1) / z^2 = -1/2 + z/3 - z^2/8 + ...   (series for small |z|),
    Phi = a1^2 phi(z1) - a2^2 phi(z2) = [(1 + z1) E1 - (1 + z2) E2] / (s r)^2
          (the first form for small |z2|, the second for large: each is free of cancellation there),

because the paper's 1/s^2 brackets are exactly [(1 + z1) E1 - (1 + z2) E2] / s^2 = r^2 Phi: the
closed forms cancel catastrophically for small |s r / c|, phi does not, and a1 = 0 is exact.

- (16) u_ij = 1/(4 pi rho r) { delta_ij [a2^2 E2 - Phi] + d_i d_j [3 Phi + a1^2 E1 - a2^2 E2] }
- (17) p_ij = 1/(4 pi r^2) { C1 delta_ij (d.n) + C2 d_i d_j (d.n) + C3 d_i n_j + C4 d_j n_i }, with
  kappa = a1^2/a2^2 = mu/(lambda + 2 mu),
      C1 = 6 Phi/a2^2 + 2 kappa E1 - 3 E2 - s r a2 E2
      C2 = -30 Phi/a2^2 - 12 kappa E1 + 12 E2 - 2 kappa s r a1 E1 + 2 s r a2 E2
      C3 = 6 Phi/a2^2 + 4 kappa E1 - E1 - 2 E2 - s r a1 E1 + 2 kappa s r a1 E1
      C4 = 6 Phi/a2^2 + 2 kappa E1 - 3 E2 - s r a2 E2
  (the first term of the paper's Eq. 17 has a + sign; read as "-" it would not reduce to the
  Kelvin traction at s = 0). i is the direction of the point load, j the traction component.
- (19) d_ij = 1/(4 pi) { d_i n_j Phi + delta_ij (d.n) a2^2 phi(z2) }   (bounded as r -> 0)
- (21) l_ij = 1/(4 pi) { r d_i (d x n)_j Phi - [n]x_ij a2 E2 / s },  [n]x v = n x v
- (20) q = l + d [x - x_bar]x^T

At s -> 0, u and p become the Kelvin elastostatic kernels (``kelvin_u``, ``kelvin_p``).
"""

from __future__ import annotations

import numpy as np

from wsim.rigid import cross_matrix

#: below this |z| phi(z) uses its Taylor series (relative error < 1e-16 with 16 terms)
PHI_SERIES_LIMIT = 0.5
_PHI_TERMS = 16


def phi(z: np.ndarray) -> np.ndarray:
    """phi(z) = ((1 + z) e^-z - 1) / z^2 for complex z, by series where |z| is small."""
    z = np.asarray(z, dtype=np.complex128)
    out = np.empty_like(z)
    small = np.abs(z) < PHI_SERIES_LIMIT
    if np.any(small):
        zs = z[small]
        # sum_{n>=2} (-1)^n (1 - n) z^(n-2) / n!
        term = np.full_like(zs, 1.0 / 2.0)  # z^0 / 2!
        total = -term
        for n in range(3, 2 + _PHI_TERMS):
            term = term * zs / n  # z^(n-2) / n!
            total = total + (-1.0) ** n * (1 - n) * term
        out[small] = total
    big = ~small
    if np.any(big):
        zb = z[big]
        out[big] = ((1.0 + zb) * np.exp(-zb) - 1.0) / zb**2
    return out


def inverse_speeds(material) -> tuple[float, float]:
    """(a1, a2) = (1/c1, 1/c2); a1 = 0 for an incompressible material."""
    a1 = 0.0 if material.incompressible else 1.0 / material.c1
    return a1, 1.0 / material.c2


def _geometry(x: np.ndarray, y: np.ndarray):
    r = np.asarray(y, dtype=np.float64) - np.asarray(x, dtype=np.float64)
    rr = np.linalg.norm(r, axis=-1)
    return r / rr[..., None], rr


def _scalars(rr: np.ndarray, s: complex, a1: float, a2: float):
    """E1, E2, phi(z2) and Phi. Phi = a1^2 phi(z1) - a2^2 phi(z2) = [(1 + z1) E1 - (1 + z2) E2]/(s r)^2
    exactly; the first form (series) is used while |z2| < PHI_SERIES_LIMIT (then |z1| <= |z2|), the
    second beyond, where the first would subtract two ~-1/(s r)^2 terms to get an exponentially
    small difference."""
    z1, z2 = s * rr * a1, s * rr * a2
    E1, E2 = np.exp(-z1), np.exp(-z2)
    p2 = phi(z2)
    small = np.abs(z2) < PHI_SERIES_LIMIT
    Phi = np.empty(np.shape(z2), dtype=np.complex128)
    Phi[small] = a1**2 * phi(z1[small]) - a2**2 * p2[small]
    big = ~small
    Phi[big] = ((1 + z1[big]) * E1[big] - (1 + z2[big]) * E2[big]) / (s * rr[big]) ** 2
    return E1, E2, p2, Phi


def u_hat(x: np.ndarray, y: np.ndarray, s: complex, material) -> np.ndarray:
    """Eq. (16): (..., 3, 3) complex displacement kernel."""
    a1, a2 = inverse_speeds(material)
    d, rr = _geometry(x, y)
    E1, E2, _, Phi = _scalars(rr, s, a1, a2)
    eye = np.eye(3)
    dd = d[..., :, None] * d[..., None, :]
    A = a2**2 * E2 - Phi
    B = 3.0 * Phi + a1**2 * E1 - a2**2 * E2
    return (A[..., None, None] * eye + B[..., None, None] * dd) / (4.0 * np.pi * material.rho * rr[..., None, None])


def p_hat(x: np.ndarray, y: np.ndarray, n: np.ndarray, s: complex, material) -> np.ndarray:
    """Eq. (17): (..., 3, 3) complex traction kernel (load direction i, traction component j)."""
    a1, a2 = inverse_speeds(material)
    kappa = (a1 / a2) ** 2
    d, rr = _geometry(x, y)
    n = np.asarray(n, dtype=np.float64)
    E1, E2, _, Phi = _scalars(rr, s, a1, a2)
    srr = s * rr
    F = 6.0 * Phi / a2**2
    C1 = F + 2 * kappa * E1 - 3 * E2 - srr * a2 * E2
    C2 = -5.0 * F - 12 * kappa * E1 + 12 * E2 - 2 * kappa * srr * a1 * E1 + 2 * srr * a2 * E2
    C3 = F + 4 * kappa * E1 - E1 - 2 * E2 - srr * a1 * E1 + 2 * kappa * srr * a1 * E1
    C4 = C1
    dn = np.einsum("...i,...i->...", d, n)
    eye = np.eye(3)
    T1 = dn[..., None, None] * eye
    T2 = dn[..., None, None] * d[..., :, None] * d[..., None, :]
    T3 = d[..., :, None] * n[..., None, :]
    T4 = n[..., :, None] * d[..., None, :]
    out = C1[..., None, None] * T1 + C2[..., None, None] * T2 + C3[..., None, None] * T3 + C4[..., None, None] * T4
    return out / (4.0 * np.pi * rr[..., None, None] ** 2)


def d_hat(x: np.ndarray, y: np.ndarray, n: np.ndarray, s: complex, material) -> np.ndarray:
    """Eq. (19): (..., 3, 3) complex translational fictitious-force kernel (bounded as r -> 0)."""
    a1, a2 = inverse_speeds(material)
    d, rr = _geometry(x, y)
    n = np.asarray(n, dtype=np.float64)
    _, _, p2, Phi = _scalars(rr, s, a1, a2)
    dn = np.einsum("...i,...i->...", d, n)
    out = Phi[..., None, None] * d[..., :, None] * n[..., None, :] + (dn * a2**2 * p2)[..., None, None] * np.eye(3)
    return out / (4.0 * np.pi)


def q_hat(x: np.ndarray, y: np.ndarray, n: np.ndarray, s: complex, material, x_bar: np.ndarray) -> np.ndarray:
    """Eqs. (20)-(21): (..., 3, 3) complex Euler-force kernel q = l + d [x - x_bar]x^T."""
    a1, a2 = inverse_speeds(material)
    d, rr = _geometry(x, y)
    n = np.asarray(n, dtype=np.float64)
    E1, E2, _, Phi = _scalars(rr, s, a1, a2)
    dxn = np.cross(d, n)
    l = (rr * Phi)[..., None, None] * d[..., :, None] * dxn[..., None, :] - (a2 * E2 / s)[..., None, None] * cross_matrix(n)
    l = l / (4.0 * np.pi)
    lever = np.asarray(x, dtype=np.float64) - np.asarray(x_bar, dtype=np.float64)
    return l + d_hat(x, y, n, s, material) @ np.swapaxes(cross_matrix(np.broadcast_to(lever, d.shape)), -1, -2)


def kelvin_u(x: np.ndarray, y: np.ndarray, material) -> np.ndarray:
    """Kelvin's elastostatic displacement kernel 1/(8 pi mu r) [(l + 3 mu)/(l + 2 mu) delta + (l + mu)/(l + 2 mu) d d]."""
    d, rr = _geometry(x, y)
    mu = material.mu
    k = 0.0 if material.incompressible else mu / (material.lam + 2 * mu)  # mu / (lambda + 2 mu)
    A = 1.0 + k  # (lambda + 3 mu) / (lambda + 2 mu)
    B = 1.0 - k  # (lambda + mu) / (lambda + 2 mu)
    dd = d[..., :, None] * d[..., None, :]
    return (A * np.eye(3) + B * dd) / (8.0 * np.pi * mu * rr[..., None, None])


def kelvin_p(x: np.ndarray, y: np.ndarray, n: np.ndarray, material) -> np.ndarray:
    """Kelvin's traction kernel -1/(8 pi (1 - nu) r^2) {(d.n)[(1 - 2nu) delta + 3 d d] - (1 - 2nu)(d n^T - n d^T)}."""
    d, rr = _geometry(x, y)
    n = np.asarray(n, dtype=np.float64)
    nu = material.nu
    dn = np.einsum("...i,...i->...", d, n)[..., None, None]
    dd = d[..., :, None] * d[..., None, :]
    dnT = d[..., :, None] * n[..., None, :]
    out = dn * ((1 - 2 * nu) * np.eye(3) + 3 * dd) - (1 - 2 * nu) * (dnT - np.swapaxes(dnT, -1, -2))
    return -out / (8.0 * np.pi * (1 - nu) * rr[..., None, None] ** 2)
