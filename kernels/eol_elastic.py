"""Warp kernel of EoL elastic forces from the reference map (Fan et al. Sec. 3.3; Levin et al. 2011).

The grid stores material coordinates z_s at its nodes (z = y - u). At a quadrature point y in the
intermediate domain G = grad_y z = sum_s z_s grad Phi_s(y)^T, and the deformation gradient is
F = G^-1. The elastic energy of the material is V = int_z W(F) dz = int_y W(F) det(G) dy, so per
point (weight w, intermediate volume)

    dV/dG = w det(G) (W F^T - F^T P F^T)      (P = dW/dF; dF = -F dG F, d det G = det G G^-T : dG)
    f_s  = -dV/du_s = +dV/dz_s = (dV/dG) grad Phi_s(y)

Constitutive law: compressible Neo-Hookean, W = mu/2 (tr F^T F - 3) - mu ln J + lam/2 (ln J)^2,
P = mu (F - F^-T) + lam ln J F^-T: zero energy and stress for any rotation, so rigid motion of
the reference map costs nothing. Float64 throughout: G is a difference of nearby absolute
coordinates (z_s - z_t ~ h), where float32 would lose the strain to cancellation.
"""

from __future__ import annotations

import warp as wp

from wsim.kernels.eol_grid import corner_gradient


@wp.kernel
def neo_hookean_forces(
    z: wp.array(dtype=wp.vec3d),
    point_nodes: wp.array2d(dtype=wp.int32),
    point_local: wp.array(dtype=wp.vec3d),
    point_weight: wp.array(dtype=wp.float64),
    h: wp.float64,
    mu: wp.float64,
    lam: wp.float64,
    forces: wp.array(dtype=wp.vec3d),
    energy: wp.array(dtype=wp.float64),
):
    """One thread per quadrature point: add f_s = (dV/dG) grad Phi_s to its 8 nodes and W det G w to energy."""
    q = wp.tid()
    t = point_local[q]
    G = wp.mat33d()
    for c in range(8):
        G += wp.outer(z[point_nodes[q, c]], corner_gradient(c, t, h))
    detG = wp.determinant(G)
    F = wp.inverse(G)
    J = wp.float64(1.0) / detG
    F_invT = wp.transpose(G)  # F^-T = G^T
    logJ = wp.log(J)
    half = wp.float64(0.5)
    W = half * mu * (wp.ddot(F, F) - wp.float64(3.0)) - mu * logJ + half * lam * logJ * logJ
    P = mu * (F - F_invT) + lam * logJ * F_invT
    Ft = wp.transpose(F)
    dVdG = point_weight[q] * detG * (W * Ft - Ft * P * Ft)
    for c in range(8):
        wp.atomic_add(forces, point_nodes[q, c], dVdG * corner_gradient(c, t, h))
    wp.atomic_add(energy, 0, point_weight[q] * detG * W)
