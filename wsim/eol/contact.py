"""Contact of an EoL body with the World's colliders: constraint rows (Eq. 28) and the QP (Eq. 29).

Each surface triangle inside a collider contributes (int Phi_s n dGamma) . w_s to a row, for the 8
nodes of the grid cell holding its centroid (one-point quadrature, area-weighted outward normal n).
Rows are one per (collider, collision cell): triangles are binned by the spatial collision grid
of Sec. 3.5, so the overlap is resolved locally rather than as one total volume. The row's right
side is the collider's own flux (kinematic colliders), minus a relaxation of the overlap that
already exists (vol / tau, so a penetration made during a step is pushed out over a few steps
instead of being kept forever).

QP (Eq. 29): minimize 1/2 (w - w_hat)^T M (w - w_hat) subject to J w <= b, M the diagonal lumped
mass. Its dual is the small dense LCP: lambda >= 0, S lambda - r >= 0, complementary, with
S = J M^-1 J^T (m x m) and r = J w_hat - b; solved by the primal-dual active-set method of Ito and
Kunisch (2008), the paper's choice: finite, exact, O(m^3) with m the number of rows (tens to a
few hundred per body), with projected Gauss-Seidel as a fallback should the active set cycle.
With the final active set frozen the solution is linear in w_hat = w + dt a and b, which gives the
split v = v_0 + dt v_1 of Eq. (31) used by the adaptive step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True)
class ContactRows:
    """J (m x 3 n_nodes, CSR), the right side b (m,), each row's collider index and overlap volume [m^3]."""

    J: sp.csr_matrix
    b: np.ndarray
    collider: np.ndarray
    overlap: np.ndarray

    @property
    def m(self) -> int:
        return len(self.b)


def assemble_rows(keys: np.ndarray, nodes: np.ndarray, phi: np.ndarray, coeff: np.ndarray, rhs: np.ndarray,
                  overlap: np.ndarray, n_nodes: int) -> ContactRows:
    """Rows from K contact triangles: ``keys`` (K, 4) int (collider, collision cell), ``nodes``/``phi``
    (K, 8) of the centroid's cell, ``coeff`` (K, 3) area normal in the velocity axes, ``rhs`` (K,)
    the collider-flux part of b, ``overlap`` (K,) the triangle's overlap volume."""
    uniq, row = np.unique(keys, axis=0, return_inverse=True)
    row = row.ravel()
    m = len(uniq)
    r = np.repeat(row, 24)
    cols = (3 * nodes[:, :, None] + np.arange(3)[None, None, :]).reshape(len(row), 24).ravel()
    vals = (phi[:, :, None] * coeff[:, None, :]).reshape(len(row), 24).ravel()
    J = sp.csr_matrix((vals, (r, cols)), shape=(m, 3 * n_nodes))
    J.sum_duplicates()
    return ContactRows(J=J, b=np.bincount(row, rhs, minlength=m), collider=uniq[:, 0],
                       overlap=np.bincount(row, overlap, minlength=m))


def solve_lcp(S: np.ndarray, r: np.ndarray, max_iter: int = 50) -> tuple[np.ndarray, int]:
    """lambda >= 0 with S lambda - r >= 0 and lambda . (S lambda - r) = 0: primal-dual active set
    (Ito & Kunisch 2008); projected Gauss-Seidel if the active set does not settle."""
    m = len(r)
    lam = np.zeros(m)
    c = 1.0 / max(float(np.mean(np.diag(S))), 1e-300)
    active = r > 0.0
    for it in range(1, max_iter + 1):
        lam = np.zeros(m)
        if active.any():
            idx = np.flatnonzero(active)
            lam[idx] = np.linalg.lstsq(S[np.ix_(idx, idx)], r[idx], rcond=None)[0]
        mu = S @ lam - r
        new = lam - c * mu > 0.0
        if np.array_equal(new, active):
            scale = max(float(np.abs(r).max()), 1e-300)
            if lam.min() >= -1e-10 * scale and mu.min() >= -1e-8 * scale:
                return lam, it
            break
        active = new
    lam = np.maximum(lam, 0.0)
    d = np.diag(S).copy()
    for it in range(max_iter + 1, max_iter + 2001):
        prev = lam.copy()
        for i in range(m):
            if d[i] > 0.0:
                lam[i] = max(0.0, lam[i] - (S[i] @ lam - r[i]) / d[i])
        if np.abs(lam - prev).max() <= 1e-12 * max(np.abs(lam).max(), 1e-300):
            break
    return lam, it


@dataclass(frozen=True)
class ContactSolution:
    """w = w0 + dt w1 and lambda = lambda0 + dt lambda1 on the frozen active set (Eq. 31)."""

    w0: np.ndarray
    w1: np.ndarray
    lam0: np.ndarray
    lam1: np.ndarray
    active: np.ndarray
    iterations: int


def contact_qp(rows: ContactRows, inv_mass: np.ndarray, w: np.ndarray, a: np.ndarray, dt_guess: float) -> ContactSolution:
    """Solve Eq. (29) at w_hat = w + dt_guess a (flat 3 n_nodes arrays; ``inv_mass`` per component,
    zero where a node has no mass), then split the solution on its active set into the parts
    independent of and proportional to dt."""
    J = rows.J
    JM = J.multiply(inv_mass[None, :]).tocsr()
    S = (JM @ J.T).toarray()
    lam, iters = solve_lcp(S, J @ (w + dt_guess * a) - rows.b)
    active = lam > 0.0
    idx = np.flatnonzero(active)
    lam0 = np.zeros(rows.m)
    lam1 = np.zeros(rows.m)
    if len(idx):
        Saa = S[np.ix_(idx, idx)]
        Ja = J[idx]
        lam0[idx] = np.linalg.lstsq(Saa, Ja @ w - rows.b[idx], rcond=None)[0]
        lam1[idx] = np.linalg.lstsq(Saa, Ja @ a, rcond=None)[0]
    w0 = w - JM.T @ lam0
    w1 = a - JM.T @ lam1
    return ContactSolution(w0=w0, w1=w1, lam0=lam0, lam1=lam1, active=active, iterations=iters)
