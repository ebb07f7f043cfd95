"""Error correction (paper Sec. 3.2.1): move the rigid drift left in u_n into the frame's pose.

At the end of step n, with u_n from Eq. (12):

1. translation error t = weighted centroid of u_n (weights w below); u' = u_n - 1 (x) t;
2. rotation error R_e: shape matching [MHTG05] of x + u' against x with the paper's weights
   w_i = int_Gamma (y . n) N_i dGamma (each node's share of 3 V, the volume-integral analogue);
3. u'' = R_e^T (x + u' - c_0) + c_0 - x is stored as u_n, and the frame moves to R R_e,
   T + R (c_0 + t - R_e c_0): every point x + u stays where it is (``BemBody._finish_step``).

The paper hands the drift to the frame's accelerations instead (da, dalpha: the least-squares
solutions of Eq. (9) with u''). That makes momentum no load applied: a load's impulse ended 5 %
larger in the frame of a 26-node cube (2 % at 98 nodes), with swings of the size of the impulse
itself while the load acts. Moved to the pose, the drift leaves the frame's velocities to the
loads alone (Eq. 10: exact), and the points do not jump. What made the drift of a loaded body
grow without bound is the discrete operators' own resultant of a traction, which is not
exactly Eq. (10)'s; ``load_balance`` gives the BEM the frame terms that balance it (the step adds
them to u and to the B ring, not to the frame), so what is left of the drift is transient.

All float64, O(N) per step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from wsim.rigid import cross_matrix, nearest_rotation
from wsim.bem.surface import BemSurface

def volume_weights(surface: BemSurface, origin: np.ndarray) -> np.ndarray:
    """w_i = int_Gamma ((y - origin) . n) N_i dGamma per node; sum_i w_i = 3 V.

    On a flat triangle (i, j, k): int y N_i dA = A (2 y_i + y_j + y_k) / 12.
    """
    y = surface.nodes - origin
    f = surface.faces
    w = np.zeros(surface.n_nodes)
    for k in range(3):
        own = y[f[:, k]]
        others = y[f[:, (k + 1) % 3]] + y[f[:, (k + 2) % 3]]
        share = surface.areas * np.einsum("ij,ij->i", (2.0 * own + others) / 12.0, surface.normals)
        np.add.at(w, f[:, k], share)
    return w


@dataclass(frozen=True)
class Correction:
    """Precomputed pieces of the error correction (immutable, shared by bodies on one operator set).

    Attributes:
        x: (N, 3) rest node positions in the frame (centre of mass at the origin) [m].
        w: (N,) volume weights; c0: (3,) weighted rest centroid.
    """

    x: np.ndarray
    w: np.ndarray
    c0: np.ndarray

    def __post_init__(self) -> None:  # derived once: q = x - c0, w q, sum w
        object.__setattr__(self, "q", self.x - self.c0)
        object.__setattr__(self, "wq", self.w[:, None] * (self.x - self.c0))
        object.__setattr__(self, "w_sum", float(self.w.sum()))

    @classmethod
    def from_operators(cls, ops) -> Correction:
        """The pieces for ``ops``."""
        x = ops.surface.nodes - ops.com
        w = volume_weights(ops.surface, ops.com)
        return cls(x=x, w=w, c0=(w @ x) / w.sum())

    def drift(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t, R_e, u'') with x + u = R_e (x + u'' - c0) + c0 + t, so a frame moved to R R_e,
        T + R (c0 + t) - R R_e c0 keeps every point where it is. ``u`` (3N,) or a stack (K, 3N) of
        bodies on these operators (then t (K, 3), R_e (K, 3, 3), u'' (K, 3N))."""
        n = self.x.shape[0]
        u3 = u.reshape(*u.shape[:-1], n, 3)
        t = np.einsum("n,...nc->...c", self.w, u3) / self.w_sum
        p = self.q + u3 - t[..., None, :]
        R_e = nearest_rotation(np.swapaxes(p, -1, -2) @ self.wq)
        return t, R_e, (p @ R_e + self.c0 - self.x).reshape(u.shape)


def load_balance(ops, correction: Correction) -> np.ndarray:
    """(6, 3N) X: X p is the [b; alpha] (b = a - g', frame axes) that tractions p need on top of
    (A p, C p) for the BEM to carry them without rigid drift, in the static limit.

    A load p accelerates the frame by exactly A p and C p (Eq. 10). The discrete operators' own
    resultant of p is not that: at s = 0 (the CQ weights' generating functions at zeta = 1,
    H_s = sum_k H_k and likewise G_s, [D_s Q_s]) the equation H_s u = G_s p + [D_s Q_s] beta has a
    drift-free solution u (W u = 0, W the correction's rigid functionals: the weighted centroid
    and the linearized shape-matching rotation theta = J^-1 sum_i w_i q_i x u_i) only for
    beta = M p = -(Y^T [D_s Q_s])^-1 Y^T G_s p, Y = H_s^-T W^T. A uniform traction on a 26-node
    cube's bottom face has M p 4.7 % above A p (2.1 % at 98 nodes: discretization error). Fed the
    frame's A p alone, the BEM drifts at the difference for as long as the load acts. The step
    gives the BEM X p = M p - (A p, C p) (in u and the B ring), not the frame."""
    n = ops.n_nodes
    n3 = 3 * n
    q, w = correction.q, correction.w
    W = np.zeros((6, n, 3))
    W[:3] = (w / w.sum())[None, :, None] * np.eye(3)[:, None, :]
    J = np.einsum("n,nab->ab", w, (q * q).sum(axis=1)[:, None, None] * np.eye(3) - q[:, :, None] * q[:, None, :])
    qx = cross_matrix(q)  # (N, 3, 3): qx[i] u_i = q_i x u_i
    W[3:] = np.linalg.solve(J, np.einsum("n,nab->anb", w, qx).reshape(3, -1)).reshape(3, n, 3)
    W = W.reshape(6, n3)
    Hs = np.zeros((n3, n3))
    for Hk in ops.H:
        Hs += Hk
    Y = scipy.linalg.solve(Hs.T, W.T, overwrite_a=True, check_finite=False)  # (3N, 6)
    del Hs
    YG = np.zeros((6, n3))
    for Gk in ops.G:
        YG += Y.T @ np.asarray(Gk, dtype=np.float64)
    YDQ = Y.T @ np.concatenate([ops.D.sum(axis=0), ops.Q.sum(axis=0)], axis=1)
    return -np.linalg.solve(YDQ, YG) - np.vstack([ops.A, ops.C])
