"""Laplace-domain elastodynamic kernels in float64 complex arithmetic (Sugimoto et al., Appendix A).

Complex numbers are ``wp.vec2d`` (re, im) with the small helpers below. The kernels are written
exactly as in ``wsim.bem.fundamental`` (whose docstring derives the forms): every 1/s^2 bracket
of the paper's Eqs. (16), (17), (19), (21) goes through phi(z) = ((1 + z) e^-z - 1)/z^2, with a
Taylor series for |z| < 0.5 where the closed form cancels, and the inverse wave speeds a1 = 1/c1,
a2 = 1/c2 make the incompressible limit (a1 = 0) exact. Each kernel is a few complex
coefficients times real geometric tensors; the functions return the coefficients so that an
assembly loop can multiply them by shape functions and accumulate real and imaginary parts.
"""

from __future__ import annotations

import warp as wp

_PI4 = wp.constant(wp.float64(12.566370614359172))  # 4 pi
_PHI_SERIES_LIMIT = wp.constant(wp.float64(0.5))


@wp.func
def cmul(a: wp.vec2d, b: wp.vec2d) -> wp.vec2d:
    return wp.vec2d(a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0])


@wp.func
def cdiv(a: wp.vec2d, b: wp.vec2d) -> wp.vec2d:
    den = b[0] * b[0] + b[1] * b[1]
    return wp.vec2d((a[0] * b[0] + a[1] * b[1]) / den, (a[1] * b[0] - a[0] * b[1]) / den)


@wp.func
def cexp(a: wp.vec2d) -> wp.vec2d:
    m = wp.exp(a[0])
    return wp.vec2d(m * wp.cos(a[1]), m * wp.sin(a[1]))


@wp.func
def creal(x: wp.float64) -> wp.vec2d:
    return wp.vec2d(x, wp.float64(0.0))


@wp.func
def phi_series(z: wp.vec2d) -> wp.vec2d:
    """sum_{n>=2} (-1)^n (1 - n) z^(n-2) / n!: phi to round-off for |z| < 0.5 (16 terms)."""
    term = creal(wp.float64(0.5))
    total = -term
    sign = wp.float64(-1.0)
    for n in range(3, 18):
        nf = wp.float64(n)
        term = cmul(term, z) / nf
        total = total + term * (sign * (wp.float64(1.0) - nf))
        sign = -sign
    return total


@wp.func
def phi(z: wp.vec2d) -> wp.vec2d:
    """((1 + z) e^-z - 1) / z^2; the series for |z| < 0.5, where the closed form cancels."""
    if wp.sqrt(z[0] * z[0] + z[1] * z[1]) < _PHI_SERIES_LIMIT:
        return phi_series(z)
    one = creal(wp.float64(1.0))
    return cdiv(cmul(one + z, cexp(-z)) - one, cmul(z, z))


@wp.func
def kernel_scalars(r: wp.float64, s: wp.vec2d, a1: wp.float64, a2: wp.float64):
    """E1 = e^(-s r a1), E2 = e^(-s r a2), phi(z2) and Phi = a1^2 phi(z1) - a2^2 phi(z2)
    = [(1 + z1) E1 - (1 + z2) E2] / (s r)^2 (series form for small |z2|, direct form beyond,
    reusing E1 and E2: two complex exponentials per point in all)."""
    z1 = s * (r * a1)
    z2 = s * (r * a2)
    E1 = cexp(-z1)
    E2 = cexp(-z2)
    one = creal(wp.float64(1.0))
    p2 = wp.vec2d()
    Phi = wp.vec2d()
    if wp.sqrt(z2[0] * z2[0] + z2[1] * z2[1]) < _PHI_SERIES_LIMIT:
        p2 = phi_series(z2)
        Phi = phi_series(z1) * (a1 * a1) - p2 * (a2 * a2)  # |z1| <= |z2| small: the series cancels nothing
    else:
        w2 = cmul(one + z2, E2)
        p2 = cdiv(w2 - one, cmul(z2, z2))
        sr = s * r
        Phi = cdiv(cmul(one + z1, E1) - w2, cmul(sr, sr))  # the -1's cancel analytically
    return E1, E2, p2, Phi


@wp.func
def u_from(r: wp.float64, E1: wp.vec2d, E2: wp.vec2d, Phi: wp.vec2d, a1: wp.float64, a2: wp.float64, rho: wp.float64):
    """Eq. (16) from the shared scalars: u = A delta + B d d^T."""
    f = wp.float64(1.0) / (_PI4 * rho * r)
    A = (E2 * (a2 * a2) - Phi) * f
    B = (Phi * wp.float64(3.0) + E1 * (a1 * a1) - E2 * (a2 * a2)) * f
    return A, B


@wp.func
def p_from(r: wp.float64, s: wp.vec2d, E1: wp.vec2d, E2: wp.vec2d, Phi: wp.vec2d, a1: wp.float64, a2: wp.float64):
    """Eq. (17) from the shared scalars: p = C1 (d.n) delta + C2 (d.n) d d^T + C3 d n^T + C1 n d^T
    (module docstring of wsim.bem.fundamental; load direction i = row, traction component j = column)."""
    kappa = (a1 * a1) / (a2 * a2)
    F = Phi * (wp.float64(6.0) / (a2 * a2))
    sr = s * r
    sE1 = cmul(sr, E1)
    sE2 = cmul(sr, E2)
    C1 = F + E1 * (wp.float64(2.0) * kappa) - E2 * wp.float64(3.0) - sE2 * a2
    C2 = -F * wp.float64(5.0) - E1 * (wp.float64(12.0) * kappa) + E2 * wp.float64(12.0) - sE1 * (wp.float64(2.0) * kappa * a1) + sE2 * (wp.float64(2.0) * a2)
    C3 = F + E1 * (wp.float64(4.0) * kappa - wp.float64(1.0)) - E2 * wp.float64(2.0) - sE1 * a1 + sE1 * (wp.float64(2.0) * kappa * a1)
    f = wp.float64(1.0) / (_PI4 * r * r)
    return C1 * f, C2 * f, C3 * f


@wp.func
def d_from(p2: wp.vec2d, Phi: wp.vec2d, a2: wp.float64):
    """Eq. (19) from the shared scalars: d = Dn d n^T + Dd (d.n) delta (bounded as r -> 0)."""
    return Phi / _PI4, p2 * (a2 * a2) / _PI4


@wp.func
def l_from(r: wp.float64, s: wp.vec2d, E2: wp.vec2d, Phi: wp.vec2d, a2: wp.float64):
    """Eq. (21) from the shared scalars: l = L1 d (d x n)^T + L2 [n]x, L1 = r Phi / 4 pi, L2 = -a2 E2 / (4 pi s)."""
    return Phi * (r / _PI4), -cdiv(E2 * a2, s) / _PI4


@wp.func
def u_coeffs(r: wp.float64, s: wp.vec2d, a1: wp.float64, a2: wp.float64, rho: wp.float64):
    """Eq. (16): u = A delta + B d d^T."""
    E1, E2, p2, Phi = kernel_scalars(r, s, a1, a2)
    return u_from(r, E1, E2, Phi, a1, a2, rho)


@wp.func
def p_coeffs(r: wp.float64, s: wp.vec2d, a1: wp.float64, a2: wp.float64):
    """Eq. (17): see ``p_from``."""
    E1, E2, p2, Phi = kernel_scalars(r, s, a1, a2)
    return p_from(r, s, E1, E2, Phi, a1, a2)


@wp.func
def d_coeffs(r: wp.float64, s: wp.vec2d, a1: wp.float64, a2: wp.float64):
    """Eq. (19): see ``d_from``."""
    E1, E2, p2, Phi = kernel_scalars(r, s, a1, a2)
    return d_from(p2, Phi, a2)


@wp.func
def l_coeffs(r: wp.float64, s: wp.vec2d, a1: wp.float64, a2: wp.float64):
    """Eq. (21): see ``l_from``."""
    E1, E2, p2, Phi = kernel_scalars(r, s, a1, a2)
    return l_from(r, s, E2, Phi, a2)


@wp.func
def outer(a: wp.vec3d, b: wp.vec3d) -> wp.mat33d:
    return wp.outer(a, b)


@wp.func
def cross_matrix(v: wp.vec3d) -> wp.mat33d:
    z = wp.float64(0.0)
    return wp.mat33d(z, -v[2], v[1], v[2], z, -v[0], -v[1], v[0], z)


@wp.kernel
def evaluate_kernels(
    x: wp.array(dtype=wp.vec3d),
    y: wp.array(dtype=wp.vec3d),
    n: wp.array(dtype=wp.vec3d),
    s: wp.vec2d,
    a1: wp.float64,
    a2: wp.float64,
    rho: wp.float64,
    x_bar: wp.vec3d,
    out_re: wp.array(dtype=wp.mat33d, ndim=2),
    out_im: wp.array(dtype=wp.mat33d, ndim=2),
):
    """u, p, d, q (rows 0..3 of the outputs) at point pairs, for testing the functions above."""
    i = wp.tid()
    rv = y[i] - x[i]
    r = wp.length(rv)
    d = rv / r
    nn = n[i]
    dn = wp.dot(d, nn)
    eye = wp.identity(n=3, dtype=wp.float64)
    A, B = u_coeffs(r, s, a1, a2, rho)
    out_re[0, i] = eye * A[0] + outer(d, d) * B[0]
    out_im[0, i] = eye * A[1] + outer(d, d) * B[1]
    C1, C2, C3 = p_coeffs(r, s, a1, a2)
    T1 = eye * dn
    T2 = outer(d, d) * dn
    T3 = outer(d, nn)
    T4 = outer(nn, d)
    out_re[1, i] = T1 * C1[0] + T2 * C2[0] + T3 * C3[0] + T4 * C1[0]
    out_im[1, i] = T1 * C1[1] + T2 * C2[1] + T3 * C3[1] + T4 * C1[1]
    Dn, Dd = d_coeffs(r, s, a1, a2)
    dre = T3 * Dn[0] + T1 * Dd[0]
    dim = T3 * Dn[1] + T1 * Dd[1]
    out_re[2, i] = dre
    out_im[2, i] = dim
    L1, L2 = l_coeffs(r, s, a1, a2)
    lever = wp.transpose(cross_matrix(x[i] - x_bar))
    dxn = outer(d, wp.cross(d, nn))
    nx = cross_matrix(nn)
    out_re[3, i] = dxn * L1[0] + nx * L2[0] + dre * lever
    out_im[3, i] = dxn * L1[1] + nx * L2[1] + dim * lever
