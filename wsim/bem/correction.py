"""Error correction of paper Sec. 3.2.1: move the rigid drift left in u_n into the frame.

At the end of step n, with u_n from Eq. (12) and the accelerations a_n, alpha_n it used:

1. translation error t = weighted centroid of u_n (weights w below); u' = u_n - 1 (x) t;
2. a_n <- least-squares solution of Eq. (9) with u'. Because u_n solved (9) exactly with the old
   a_n, the residual with u' and a is r(a) = -H_0 (1 (x) t) - D_0 (a - a_old), so
   da = -(D_0^T D_0)^-1 D_0^T H_0 (1 (x) t) = -K_a t with the 3 x 3 matrix K_a precomputed;
3. rotation error R_e: shape matching [MHTG05] of x + u' against x with the paper's weights
   w_i = int_Gamma (y . n) N_i dGamma (each node's share of 3 V, the volume-integral analogue);
4. u'' = R_e^T (x + u' - c_0) + c_0 - x;
5. alpha_n <- least-squares solution of (9) with u'' and the new a_n:
   dalpha = P_Q (r_1 + H_0 (u'' - u')), P_Q = (Q_0^T Q_0)^-1 Q_0^T, r_1 = r(a_new); P_Q H_0 is a
   precomputed 3 x 3N matrix, so no extra dense product is needed;
6. u_n <- solution of (9) with the new a_n, alpha_n: u_n + H_0^-1 D_0 da + H_0^-1 Q_0 dalpha.
7. (the caller) the frame update of Eq. (11) uses the new accelerations.

Every step is exact (no linearization): the least-squares problems have 3 unknowns and their
normal matrices are precomputed from D_0, Q_0 and H_0. All float64, O(N) per step.

Free steps hand the drift to the accelerations (``apply``, the paper's); constrained steps move it
to the frame's pose (``drift``; ``BemBody``). A load's drift is systematic: the discrete
operators' own resultant of a traction is not Eq. (10)'s, and ``apply`` turned the difference
into momentum no load applied (5-18 % of a vertex load's impulse on 26-node boxes).
``load_balance`` gives the BEM the frame terms that balance a load in the static limit, so the
drift it leaves is a transient that nearly sums to zero (1e-4 to 2e-3 of the impulse is left
once the body has rung down, where ``apply`` alone left 2-18 %). Moving every free step's drift
to the pose instead (tried: exact momentum at every step) let free, elongated boxes at
nu >= 0.4 ring up after a load (|u| 2.4x every 300 steps) where ``apply`` rings down.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg

from wsim.rigid import cross_matrix, nearest_rotation
from wsim.bem.surface import BemSurface

_CHUNK = 2048  # columns of H_0 promoted to float64 at a time


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
        H0_T: (3N, 3) H_0 (1 (x) I), the image of unit translations.
        K_a: (3, 3) (D_0^T D_0)^-1 D_0^T H0_T.
        P_Q: (3, 3N) (Q_0^T Q_0)^-1 Q_0^T;  P_Q_H0: (3, 3N) P_Q H_0.
        D0: (3N, 3).  E: (3N, 6) [H_0^-1 D_0, H_0^-1 Q_0] (float64 LU solve).
    """

    x: np.ndarray
    w: np.ndarray
    c0: np.ndarray
    H0_T: np.ndarray
    K_a: np.ndarray
    P_Q: np.ndarray
    P_Q_H0: np.ndarray
    D0: np.ndarray
    E: np.ndarray

    def __post_init__(self) -> None:  # derived once: q = x - c0, w q, sum w
        object.__setattr__(self, "q", self.x - self.c0)
        object.__setattr__(self, "wq", self.w[:, None] * (self.x - self.c0))
        object.__setattr__(self, "w_sum", float(self.w.sum()))

    @classmethod
    def from_operators(cls, ops, E: np.ndarray) -> Correction:
        """The pieces for ``ops``; E = [H_0^-1 D_0, H_0^-1 Q_0] as the step already holds it."""
        n = ops.n_nodes
        x = ops.surface.nodes - ops.com
        w = volume_weights(ops.surface, ops.com)
        H0 = ops.H[0]
        D0, Q0 = ops.D[0], ops.Q[0]
        H0_T = np.asarray(H0, dtype=np.float64).reshape(3 * n, n, 3).sum(axis=1)
        K_a = np.linalg.solve(D0.T @ D0, D0.T @ H0_T)
        P_Q = np.linalg.solve(Q0.T @ Q0, Q0.T)
        P_Q_H0 = np.empty((3, 3 * n))
        for c in range(0, 3 * n, _CHUNK):
            P_Q_H0[:, c : c + _CHUNK] = P_Q @ np.asarray(H0[:, c : c + _CHUNK], dtype=np.float64)
        return cls(x=x, w=w, c0=(w @ x) / w.sum(), H0_T=H0_T, K_a=K_a, P_Q=P_Q, P_Q_H0=P_Q_H0, D0=D0, E=E)

    def drift(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Steps 1, 3 and 4 alone: (t, R_e, u'') with x + u = R_e (x + u'' - c0) + c0 + t, so a
        frame moved to R R_e, T + R (c0 + t) - R R_e c0 keeps every point where it is. Used on
        constrained steps (``BemBody``), where the drift goes to the frame's pose, not its
        acceleration: a held or resting body must not feel a correction force. ``u`` (3N,) or a
        stack (K, 3N) of bodies on these operators (then t (K, 3), R_e (K, 3, 3), u'' (K, 3N))."""
        n = self.x.shape[0]
        u3 = u.reshape(*u.shape[:-1], n, 3)
        t = np.einsum("n,...nc->...c", self.w, u3) / self.w_sum
        p = self.q + u3 - t[..., None, :]
        R_e = nearest_rotation(np.swapaxes(p, -1, -2) @ self.wq)
        return t, R_e, (p @ R_e + self.c0 - self.x).reshape(u.shape)

    def apply(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Steps 1-6 for the (3N,) displacement u, or a stack (K, 3N): returns (da, dalpha,
        corrected u), each with u's leading axis."""
        n = self.x.shape[0]
        t, _, u2 = self.drift(u)  # steps 1, 3, 4
        da = -t @ self.K_a.T
        du = u2 - (u.reshape(*u.shape[:-1], n, 3) - t[..., None, :]).reshape(u.shape)  # u'' - u'
        r1 = -t @ self.H0_T.T - da @ self.D0.T
        dalpha = r1 @ self.P_Q.T + du @ self.P_Q_H0.T
        return da, dalpha, u + np.concatenate([da, dalpha], axis=-1) @ self.E.T


def load_balance(ops, correction: Correction, cp: Any = None) -> np.ndarray:
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
    gives the BEM X p = M p - (A p, C p) (in u and the B ring), not the frame.

    ``cp``: CuPy (the ``gpu`` extra), to sum and solve on the current CUDA device (the host's
    dense solve grows as N^3: 1.2 s at N = 642 on two cores); the result is the host's to
    round-off."""
    n = ops.n_nodes
    n3 = 3 * n
    q, w = correction.q, correction.w
    W = np.zeros((6, n, 3))
    W[:3] = (w / w.sum())[None, :, None] * np.eye(3)[:, None, :]
    J = np.einsum("n,nab->ab", w, (q * q).sum(axis=1)[:, None, None] * np.eye(3) - q[:, :, None] * q[:, None, :])
    qx = cross_matrix(q)  # (N, 3, 3): qx[i] u_i = q_i x u_i
    W[3:] = np.linalg.solve(J, np.einsum("n,nab->anb", w, qx).reshape(3, -1)).reshape(3, n, 3)
    W = W.reshape(6, n3)
    if cp is not None:
        Hs = cp.zeros((n3, n3), dtype=cp.float64)
        for Hk in ops.H:
            Hs += cp.asarray(Hk)
        Yd = cp.linalg.solve(Hs.T, cp.asarray(W.T))
        del Hs
        YGd = cp.zeros((6, n3), dtype=cp.float64)
        for Gk in ops.G:
            YGd += Yd.T @ cp.asarray(Gk).astype(cp.float64)
        Y, YG = cp.asnumpy(Yd), cp.asnumpy(YGd)
    else:
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
