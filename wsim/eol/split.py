"""Least-squares momentum distribution (Fan et al., Sec. 3.4, Eqs. 18-25).

The EoL decomposition is redundant: M_1 = M_12 M_2^-1 M_12^T (Eq. 20), so every solution of
Eq. (17b), v* = M_2^-1 (p_2 - M_12^T q1_dot), also satisfies (17a). Among them the paper picks
the smallest Eulerian velocity in the 2-norm (Eq. 23), which keeps the advection CFL limit and
its dissipation small:

    q1_dot = argmin || V - M_C q1_dot ||_2,   v* = V - M_C q1_dot,   M_C = M_2^-1 M_12^T,

with V = M_2^-1 p_2 = O v (Eq. 25: the object's part of the spatial velocity, in y). v* is the
residual of a linear least-squares problem: orthogonal to the columns of M_C (the Lagrangian
modes) and linear in V (which Eq. 32b relies on). n1 unknowns (6 or 12): the normal equations
are solved directly (``momentum_split``, the matrix form).

``EolBody`` solves the same problem from moments: per node J_L(y_s) q1_dot = L y_s + c (rigid:
L = [omega]x, c = nu; affine: L = A_dot, c = b_dot), so the normal equations only need
C = sum_s k_s yb_s yb_s^T and B = sum_s k_s w_s yb_s^T with yb = (y, 1) and node weights k_s (1:
the paper's 2-norm; m_s: the mass norm). ``split_on_device`` reduces them and solves for (L, c)
on the device (kernels ``velocity_moments``, ``split_fields``: the step reads the fields back
with its velocity maxima, one synchronization); ``lagrangian_fields`` is the same solve on the
host; ``fields_of`` turns a ``momentum_split`` q1_dot into the same (L, c), so the forms can be
compared.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.kernels import eol_step as ks
from wsim.kernels.eol_grid import Grid
from wsim.launch import Launcher, launch_on
from wsim.rigid import cross_matrix


def momentum_split(M_C: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(q1_dot, v*) for intermediate nodal velocities V (3 n_active,) and M_C (3 n_active, n1)."""
    normal = M_C.T @ M_C
    q1_dot = np.linalg.solve(normal, M_C.T @ V)
    return q1_dot, V - M_C @ q1_dot


def lagrangian_fields(kind: str, C: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(L, c) of the least-squares split from the moments C (4, 4) and B (3, 4) (see the module
    docstring): the q1_dot of ``momentum_split`` with the node weights of the moments, as a field
    L y + c. ``kind``: "rigid" or "affine"."""
    if kind == "affine":  # x_dot = Q (y, 1): Q = B C^-1 whatever the metric A^-T A^-1
        Q = np.linalg.solve(C.T, B.T).T
        return Q[:, :3], Q[:, 3]
    if kind != "rigid":
        raise ValueError(f"lagrangian_fields: kind = {kind!r} must be 'rigid' or 'affine'")
    # normal equations of J_L = [-[y], I] from the same moments
    Syy, sy, cnt = C[:3, :3], C[:3, 3], C[3, 3]
    N = np.zeros((6, 6))
    N[:3, :3] = np.trace(Syy) * np.eye(3) - Syy
    N[:3, 3:] = cross_matrix(sy)
    N[3:, :3] = -cross_matrix(sy)
    N[3:, 3:] = cnt * np.eye(3)
    rhs = np.concatenate([[B[2, 1] - B[1, 2], B[0, 2] - B[2, 0], B[1, 0] - B[0, 1]], B[:, 3]])
    q = np.linalg.solve(N, rhs)
    return cross_matrix(q[:3]), q[3:]


def fields_of(kind: str, q1_dot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(L, c) with J_L(y) q1_dot = L y + c (``wsim.eol.lagrangian.lagrangian_jacobian``'s ordering)."""
    q = np.asarray(q1_dot, dtype=np.float64)
    if kind == "rigid":
        return cross_matrix(q[:3]), q[3:6].copy()
    if kind == "affine":
        return np.column_stack([q[0:3], q[3:6], q[6:9]]), q[9:12].copy()
    raise ValueError(f"fields_of: kind = {kind!r} must be 'rigid' or 'affine'")


def moments(y: np.ndarray, w: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Host form of the moments: C (4, 4) and B (3, 4) of velocities w (n, 3) at nodes y (n, 3)."""
    yb = np.column_stack([y, np.ones(len(y))])
    k = np.asarray(weights, dtype=np.float64)
    return (k[:, None] * yb).T @ yb, (k[:, None] * w).T @ yb


def split_on_device(grid: Grid, w0: wp.array, w1: wp.array, mass: wp.array, weighted: bool,
                    moments: wp.array, kind: str, fields: wp.array, device, launcher: Launcher | None = None) -> None:
    """The split of w0 and w1 (``lagrangian_fields`` of their moments) into ``fields`` (layout
    ``kernels.eol_step.FIELDS``), on the device: no read-back. ``kind``: "rigid" or "affine".
    ``moments`` (40,) must be zero (``split_fields`` leaves it so)."""
    blocks = ks.reduce_blocks(mass.shape[0], device)
    launch_on(device, launcher, ks.velocity_moments, blocks, [w0, w1, mass, grid, int(bool(weighted)), blocks, moments],
              block_dim=ks.REDUCE_BLOCK)
    launch_on(device, launcher, ks.split_fields, 1, [moments, 1 if kind == "affine" else 0, fields])


def unpack_fields(fields: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray], float]:
    """((L_0, c_0), (L_1, c_1), total weight) from ``split_on_device``'s fields read back."""
    f = np.asarray(fields, dtype=np.float64)
    return (f[0:9].reshape(3, 3), f[9:12].copy()), (f[12:21].reshape(3, 3), f[21:24].copy()), float(f[24])
