"""Reconstruction kernels: every vertex of a keyframe-curve reconstruction at one time.

One thread per vertex: the vertex's curve c and parameters u (one per coordinate) select the
fitted coefficients of the two keyframes around the time, the spatial basis is evaluated at u
and the two keyframe curves are blended (``wsim.pbd.pde`` Eq. (2) for the PDE basis, linear
for the Bezier and B-spline baselines). Everything is float64 (the Krylov series and the
exponentials need it); positions are written as float32 for export.

The basis functions mirror ``wsim.pbd.pde.spatial_basis``, ``wsim.pbd.baselines.bernstein``
and ``uniform_cubic_bspline_closed``; tests compare them with the numpy versions.
"""

from __future__ import annotations

import warp as wp

#: basis selector of ``reconstruct_curves``
BASIS_PDE = 0
BASIS_BEZIER = 1
BASIS_BSPLINE = 2

_SERIES_LIMIT = wp.constant(wp.float64(1.0))
_D_SWITCH = wp.constant(wp.float64(4.0))


@wp.func
def krylov(u: wp.float64, lam: wp.float64, d0: wp.float64) -> wp.vec4d:
    """F_0..F_3 of W'''' = lam W (``wsim.pbd.pde.krylov``): series for d0 |u| <= 1, closed forms above."""
    one = wp.float64(1.0)
    half = wp.float64(0.5)
    if d0 * wp.abs(u) <= _SERIES_LIMIT:
        u4 = u * u * u * u
        out = wp.vec4d()
        term0 = one
        for k in range(4):
            term = term0
            total = term
            for n in range(1, 8):
                q = wp.float64(4 * n + k)
                term = term * lam * u4 / (q * (q - one) * (q - wp.float64(2.0)) * (q - wp.float64(3.0)))
                total = total + term
            out[k] = total
            term0 = term0 * u / wp.float64(k + 1)
        return out
    if lam > wp.float64(0.0):
        x = d0 * u
        ch = wp.cosh(x)
        sh = wp.sinh(x)
        c = wp.cos(x)
        s = wp.sin(x)
        return wp.vec4d(half * (ch + c), half * (sh + s) / d0, half * (ch - c) / (d0 * d0), half * (sh - s) / (d0 * d0 * d0))
    a = d0 / wp.sqrt(wp.float64(2.0))
    x = a * u
    ch = wp.cosh(x)
    sh = wp.sinh(x)
    c = wp.cos(x)
    s = wp.sin(x)
    return wp.vec4d(ch * c, half * (ch * s + sh * c) / a, half * sh * s / (a * a), wp.float64(0.25) * (ch * s - sh * c) / (a * a * a))


@wp.func
def pde_basis(u: wp.float64, lam: wp.float64) -> wp.vec4d:
    """``wsim.pbd.pde.spatial_basis``: Krylov functions for D0 <= 4, bounded exponentials above."""
    d0 = wp.pow(wp.abs(lam), wp.float64(0.25))
    if d0 <= _D_SWITCH:
        return krylov(u, lam, d0)
    if lam > wp.float64(0.0):
        x = d0 * u
        return wp.vec4d(wp.exp(-x), wp.exp(-d0 * (wp.float64(1.0) - u)), wp.cos(x), wp.sin(x))
    a = d0 / wp.sqrt(wp.float64(2.0))
    x = a * u
    e0 = wp.exp(-x)
    e1 = wp.exp(-a * (wp.float64(1.0) - u))
    c = wp.cos(x)
    s = wp.sin(x)
    return wp.vec4d(e0 * c, e0 * s, e1 * c, e1 * s)


@wp.func
def poly_basis(u: wp.float64, kind: int) -> wp.vec4d:
    """Cubic Bernstein polynomials (Eq. 17) or the uniform cubic B-spline functions (Eq. 19)."""
    v = wp.float64(1.0) - u
    if kind == BASIS_BEZIER:
        return wp.vec4d(v * v * v, wp.float64(3.0) * u * v * v, wp.float64(3.0) * u * u * v, u * u * u)
    sixth = wp.float64(1.0) / wp.float64(6.0)
    u2 = u * u
    u3 = u2 * u
    return wp.vec4d(
        v * v * v * sixth,
        (wp.float64(3.0) * u3 - wp.float64(6.0) * u2 + wp.float64(4.0)) * sixth,
        (-wp.float64(3.0) * u3 + wp.float64(3.0) * u2 + wp.float64(3.0) * u + wp.float64(1.0)) * sixth,
        u3 * sixth,
    )


@wp.func
def blend(tau: wp.float64, m0: wp.float64, lam: wp.float64) -> wp.vec2d:
    """Weights (a, b) of Eq. (2): S(m0 (1 - tau)) / S(m0), S(m0 tau) / S(m0); S = sin (lam >= 0) or
    sinh (lam < 0); linear for m0 = 0."""
    if m0 == wp.float64(0.0):
        return wp.vec2d(wp.float64(1.0) - tau, tau)
    if lam >= wp.float64(0.0):
        s1 = wp.sin(m0)
        return wp.vec2d(wp.sin(m0 * (wp.float64(1.0) - tau)) / s1, wp.sin(m0 * tau) / s1)
    s1 = wp.sinh(m0)
    return wp.vec2d(wp.sinh(m0 * (wp.float64(1.0) - tau)) / s1, wp.sinh(m0 * tau) / s1)


@wp.kernel
def reconstruct_curves(
    vertex_curve: wp.array(dtype=int),
    vertex_u: wp.array(dtype=wp.vec3d),
    rest: wp.array(dtype=wp.vec3d),
    coef: wp.array(dtype=wp.vec4d, ndim=3),  # (keyframes, curves, 3)
    lam: wp.array(dtype=wp.vec3d),  # (curves,)
    m: wp.array(dtype=wp.vec3d, ndim=2),  # (segments, curves)
    segment: int,
    tau: wp.float64,
    kind: int,
    displacement: int,
    out: wp.array(dtype=wp.vec3),
):
    """x_v(tau) in segment ``segment``: blend of the two keyframe curves at the vertex's parameters."""
    v = wp.tid()
    c = vertex_curve[v]
    uv = vertex_u[v]
    res = wp.vec3d()
    for w in range(3):
        if kind == BASIS_PDE:
            lw = lam[c][w]
            basis = pde_basis(uv[w], lw)
            ab = blend(tau, m[segment, c][w], lw)
        else:
            basis = poly_basis(uv[w], kind)
            ab = wp.vec2d(wp.float64(1.0) - tau, tau)
        res[w] = ab[0] * wp.dot(coef[segment, c, w], basis) + ab[1] * wp.dot(coef[segment + 1, c, w], basis)
    if displacement != 0:
        res = res + rest[v]
    out[v] = wp.vec3(float(res[0]), float(res[1]), float(res[2]))


@wp.kernel
def reconstruct_linear(
    keys: wp.array(dtype=wp.vec3d, ndim=2),  # (keyframes, vertices)
    segment: int,
    tau: wp.float64,
    out: wp.array(dtype=wp.vec3),
):
    """Naive baseline: keyframe positions interpolated linearly in time."""
    v = wp.tid()
    p = keys[segment, v] * (wp.float64(1.0) - tau) + keys[segment + 1, v] * tau
    out[v] = wp.vec3(float(p[0]), float(p[1]), float(p[2]))


@wp.kernel
def check_finite_points(out: wp.array(dtype=wp.vec3), flag: wp.array(dtype=int)):
    """flag[0] = 1 if any reconstructed position is NaN/Inf."""
    i = wp.tid()
    p = out[i]
    if not (wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2])):
        flag[0] = 1
