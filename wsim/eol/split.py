"""Least-squares momentum distribution (Fan et al., Sec. 3.4, Eqs. 18-25).

The EoL decomposition is redundant: M_1 = M_12 M_2^-1 M_12^T (Eq. 20), so every solution of
Eq. (17b), v* = M_2^-1 (p_2 - M_12^T q1_dot), also satisfies (17a). Among them the paper picks
the smallest Eulerian velocity in the 2-norm (Eq. 23), which keeps the advection CFL limit and
its dissipation small:

    q1_dot = argmin || V - M_C q1_dot ||_2,   v* = V - M_C q1_dot,   M_C = M_2^-1 M_12^T,

with V = M_2^-1 p_2 = O v (Eq. 25: the object's part of the spatial velocity, in y). v* is the
residual of a linear least-squares problem: orthogonal to the columns of M_C (the Lagrangian
modes) and linear in V (which Eq. 32b relies on). n1 unknowns (6 or 12): the normal equations
are solved directly.
"""

from __future__ import annotations

import numpy as np


def momentum_split(M_C: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(q1_dot, v*) for intermediate nodal velocities V (3 n_active,) and M_C (3 n_active, n1)."""
    normal = M_C.T @ M_C
    q1_dot = np.linalg.solve(normal, M_C.T @ V)
    return q1_dot, V - M_C @ q1_dot
