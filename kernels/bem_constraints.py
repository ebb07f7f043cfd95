"""Warp kernels of the BEM constraint response (Sugimoto et al. 2022, Sec. 3.4, Eqs. 13-14).

A world force f_j [N] at node j, held over the step, is the traction p_j = R_{k-1}^T f_j / a_j on
the node (a_j = int_Gamma N_j dGamma, the node's share of the area, the same weights as A of
Eq. 10, so the tractions' resultant is exactly f_j). With u_k = u* + W p (W = H_0^-1 G', Eq. 12)
and the frame update of Eq. (11) linear in a = A p and alpha = C p, node i's world position
V_i = R_k (x_i + u_i) + T_k (Eq. 13) is, to first order in p,

    V_i = V*_i + sum_j K_ij f_j,
    K_ij = R*_k W_ij R_{k-1}^T / a_j + (dt^2 / m) I - dt^2 [r_i]x R_{k-1} (C_j / a_j) R_{k-1}^T,

with r_i = R*_k (x_i + u*_i) (starred: the unconstrained step). The last term is Eq. (14)'s
rotation increment dt dw x (x + u) with dw = dt R_{k-1} C p: dw is a world vector, so the lever arm
is taken in world axes, R*_k (x + u). The paper prints dt dw x (x + u) in frame axes, which is the
same only while the frame has not turned.
"""

from __future__ import annotations

from typing import Any

import warp as wp


@wp.func
def w_block(W: wp.array2d(dtype=Any), a: int, b: int) -> wp.mat33d:
    """The 3 x 3 block of W at rows 3a.., columns 3b.. in float64."""
    r = 3 * a
    c = 3 * b
    return wp.mat33d(
        wp.float64(W[r, c]), wp.float64(W[r, c + 1]), wp.float64(W[r, c + 2]),
        wp.float64(W[r + 1, c]), wp.float64(W[r + 1, c + 1]), wp.float64(W[r + 1, c + 2]),
        wp.float64(W[r + 2, c]), wp.float64(W[r + 2, c + 1]), wp.float64(W[r + 2, c + 2]))


@wp.kernel
def response_blocks(
    W: wp.array2d(dtype=Any),
    row_of: wp.array(dtype=wp.int32),
    ids: wp.array(dtype=wp.vec3i),
    weights: wp.array(dtype=wp.vec3d),
    Rk: wp.mat33d,
    R1: wp.mat33d,
    inv_area: wp.array(dtype=wp.float64),
    torque: wp.array(dtype=wp.mat33d),
    lin_a: wp.array(dtype=wp.mat33d),
    lin_c: wp.array(dtype=wp.mat33d),
    inv_mass: wp.float64,
    K: wp.array2d(dtype=wp.float64),
    Kt: wp.array2d(dtype=wp.float64),
):
    """Block K_ij (and K^T for ``wsim.kernels.pgs.pgs_block``) of points i, j, each a weighted sum of up to three nodes (``wsim.constraints.PointRefs``;
    a node has weights (1, 0, 0)): with the force on point j spread to its nodes n_jb by w_jb,

        K_ij = sum_a sum_b w_ia w_jb R*_k W(n_ia, n_jb) R_{k-1}^T / a(n_jb)
               + lin_a_i / m + lin_c_i R_{k-1} T_j R_{k-1}^T

    (the weights of a point sum to 1). With the frame update lin_a_i = dt^2 I,
    lin_c_i = -dt^2 [r_i]x (module docstring, r_i the point's lever arm) and T_j = I^-1 [l_j]x, the
    frame's angular acceleration per unit force at point j (l_j its lever in frame axes); without
    it (a fixed frame, Eq. 9 with a = alpha = 0) they remove the D_0 A + Q_0 C part of G':
    lin_a_i = -R E_D,i R^T, lin_c_i = -R E_Q,i R^T with E = [H_0^-1 D_0, H_0^-1 Q_0] at the point
    and T_j = sum_b w_jb C(n_jb) / a(n_jb) (``wsim.bem.constraints.point_torques``). W(n, c) is read at
    rows 3 row_of[n].. of ``W`` (all rows of W, or only those of the points' nodes). Launch with
    dim = (m, m)."""
    i, j = wp.tid()
    wi = weights[i]
    wj = weights[j]
    ni = ids[i]
    nj = ids[j]
    Wsum = wp.mat33d()
    for b in range(3):
        if wj[b] != wp.float64(0.0):
            col = nj[b]
            for a in range(3):
                if wi[a] != wp.float64(0.0):
                    Wsum += (wi[a] * wj[b] * inv_area[col]) * w_block(W, int(row_of[ni[a]]), col)
    blk = Rk * Wsum * wp.transpose(R1) + lin_a[i] * inv_mass + lin_c[i] * (R1 * torque[j] * wp.transpose(R1))
    for p in range(3):
        for q in range(3):
            K[3 * i + p, 3 * j + q] = blk[p, q]
            Kt[3 * j + q, 3 * i + p] = blk[p, q]


@wp.kernel
def point_rows(
    W: wp.array2d(dtype=Any),
    row_of: wp.array(dtype=wp.int32),
    rows: wp.array(dtype=int),
    nodes: wp.array(dtype=int),
    p: wp.array(dtype=wp.vec3d),
    out: wp.array(dtype=wp.vec3d),
):
    """out_i = sum_j W[node rows_i, node nodes_j] p_j: the displacement of the point tractions p at
    the nodes ``rows`` only (the constraint points), not the whole surface; node n's rows of W are
    3 row_of[n].. of ``W``."""
    i = wp.tid()
    a = 3 * int(row_of[rows[i]])
    s = wp.vec3d()
    for j in range(nodes.shape[0]):
        b = 3 * nodes[j]
        pj = p[j]
        for q in range(3):
            s[0] += wp.float64(W[a, b + q]) * pj[q]
            s[1] += wp.float64(W[a + 1, b + q]) * pj[q]
            s[2] += wp.float64(W[a + 2, b + q]) * pj[q]
    out[i] = s

