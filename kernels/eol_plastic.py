"""Warp kernel of EoL plastic flow at material points (Fan et al. Sec. 3.7, Eqs. 34-37; Bargteil et al. 2007).

F_p^-1 is stored per material quadrature point, in the material domain, so advection never
touches it (no smearing, no remeshing). After each step, at the point's tracked intermediate
position y_i: F = F_L G^-1 (total deformation gradient, Eq. 34 with G = grad_y z), the elastic part
F_e = F F_p^-1 = U Sigma V^T (Eq. 36), and

    Delta F_p^-1 = V (Sigma / det(Sigma)^(1/3))^(-gamma) V^T           (Eq. 37, det = 1: volume kept)
    F_p^-1 <- F_p^-1 Delta F_p^-1                                       (Eq. 35)

gamma = clamp(flow_rate dt (|tau| - yield) / |tau|, 0, 1), with |tau| the Frobenius norm of the
deviatoric principal Kirchhoff stress of Neo-Hookean, tau_k = mu (sigma_k^2 - 1) + lam ln J
(the paper's ||sigma||; a rate [1/s] times dt so that the flow does not depend on the step size).
"""

from __future__ import annotations

import warp as wp

from wsim.kernels.eol_grid import Grid, sample_gradient


@wp.kernel
def plastic_flow(
    z: wp.array3d(dtype=wp.vec3d),
    grid: Grid,
    y: wp.array(dtype=wp.vec3d),
    F_L: wp.mat33d,
    mu: wp.float64,
    lam: wp.float64,
    yield_stress: wp.float64,
    flow: wp.float64,
    Fp_inv: wp.array(dtype=wp.mat33d),
    flowing: wp.array(dtype=wp.int32),
):
    """One thread per material point: Eqs. (35-37); ``flowing`` counts the points above yield."""
    i = wp.tid()
    F = F_L * wp.inverse(sample_gradient(z, y[i], grid))
    Fe = F * Fp_inv[i]
    U = wp.mat33d()
    sig = wp.vec3d()
    V = wp.mat33d()
    wp.svd3(Fe, U, sig, V)
    tiny = wp.float64(1.0e-12)
    s0 = wp.max(wp.abs(sig[0]), tiny)
    s1 = wp.max(wp.abs(sig[1]), tiny)
    s2 = wp.max(wp.abs(sig[2]), tiny)
    logJ = wp.log(s0 * s1 * s2)
    t0 = mu * (s0 * s0 - wp.float64(1.0)) + lam * logJ
    t1 = mu * (s1 * s1 - wp.float64(1.0)) + lam * logJ
    t2 = mu * (s2 * s2 - wp.float64(1.0)) + lam * logJ
    mean = (t0 + t1 + t2) / wp.float64(3.0)
    norm = wp.sqrt((t0 - mean) * (t0 - mean) + (t1 - mean) * (t1 - mean) + (t2 - mean) * (t2 - mean))
    if norm <= yield_stress:
        return
    gamma = wp.min(flow * (norm - yield_stress) / norm, wp.float64(1.0))
    cbrt = wp.exp(logJ / wp.float64(3.0))
    d = wp.vec3d(wp.pow(s0 / cbrt, -gamma), wp.pow(s1 / cbrt, -gamma), wp.pow(s2 / cbrt, -gamma))
    dFp_inv = V * wp.diag(d) * wp.transpose(V)
    Fp_inv[i] = Fp_inv[i] * dFp_inv
    wp.atomic_add(flowing, 0, 1)
