"""Contact of an EoL body with the World's colliders: constraint rows (Eq. 28) and the QP (Eq. 29).

Each surface sample inside a collider contributes (int Phi_s n dGamma) . w_s to a row, for the 8
nodes of the grid cell holding it (its share of the triangle's area-weighted outward normal n).
Samples are the triangle centroids, or for a triangle wider than ``spacing`` the centroids of its
k x k subdivision (``surface_samples``): one point per triangle misses a contact that falls
between the centroids of a coarse mesh, which then sinks through the collider.
Rows are one per (collider, collision cell): samples are binned by the collision grid of Sec. 3.5
(blocks of the body's grid cells, see ``wsim.kernels.eol_contact``), so the overlap is resolved
locally rather than as one total volume. The rows are assembled on the device; the row's right
side is the collider's own flux (kinematic colliders), minus a relaxation of the overlap that
already exists (vol / tau, so a penetration made during a step is pushed out over a few steps
instead of being kept forever).

QP (Eq. 29): minimize 1/2 (w - w_hat)^T M (w - w_hat) subject to J w <= b, M the diagonal lumped
mass. Its dual is the small dense LCP: lambda >= 0, S lambda - r >= 0, complementary, with
S = J M^-1 J^T (m x m) and r = J w_hat - b; solved by the primal-dual active-set method of Ito and
Kunisch (2008), the paper's choice: finite, exact, O(m^3) with m the number of rows (tens to a
few hundred per body), with non-negative least squares (Lawson-Hanson) as a fallback should the active set cycle.
``EolBody`` forms the dual on the device (``ContactSystem``: S, J w, J a from the packed rows,
``wsim.kernels.eol_contact``), so only m-sized data reach the host and the cost does not grow
with the grid; ``contact_qp`` is the same QP from primal data (J on the touched nodes), the host
reference the tests compare with.
With the final active set frozen the solution is linear in w_hat = w + dt a and b, which gives the
split v = v_0 + dt v_1 of Eq. (31) used by the adaptive step.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.linalg as sla
import scipy.optimize as sopt
import scipy.sparse as sp
import scipy.sparse.linalg as spla


def surface_samples(vertices: np.ndarray, faces: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contact quadrature of a triangle surface: (face (P,) int32, barycentric (P, 3), area share (P,)).

    A triangle whose longest edge is l gets k = ceil(l / spacing) subdivisions per edge and one
    sample at the centroid of each of its k^2 congruent sub-triangles (share 1 / k^2): the
    midpoint rule on the subdivision, exact for linear integrands on each piece."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    e = v[f[:, [1, 2, 0]]] - v[f]
    k = np.maximum(np.ceil(np.linalg.norm(e, axis=2).max(axis=1) / spacing - 1e-9).astype(np.int64), 1)
    face, bary, share = [], [], []
    for kk in np.unique(k):
        idx = np.flatnonzero(k == kk)
        i, j = np.meshgrid(np.arange(kk), np.arange(kk), indexing="ij")
        up = i + j <= kk - 1  # sub-triangles (i, j), (i+1, j), (i, j+1)
        down = i + j <= kk - 2  # and (i+1, j), (i, j+1), (i+1, j+1)
        uv = np.concatenate([np.column_stack([i[up] + 1 / 3, j[up] + 1 / 3]),
                             np.column_stack([i[down] + 2 / 3, j[down] + 2 / 3])]) / kk
        b = np.column_stack([1.0 - uv.sum(axis=1), uv])
        face.append(np.repeat(idx, len(b)))
        bary.append(np.tile(b, (len(idx), 1)))
        share.append(np.full(len(idx) * len(b), 1.0 / kk**2))
    return np.concatenate(face).astype(np.int32), np.concatenate(bary), np.concatenate(share)


@dataclass(frozen=True)
class ContactRows:
    """J (m x 3 n, scipy CSR: a row touches the (block + 1)^3 nodes of its collision cell) on the
    n touched ``nodes`` (global grid indices; column 3 i + d is component d of nodes[i]), the right side b (m,), each row's collider index, overlap volume
    [m^3] and ``ids`` (m,) int: the row's slot (collider and collision cell), its identity from
    step to step."""

    J: sp.csr_matrix
    b: np.ndarray
    collider: np.ndarray
    overlap: np.ndarray
    nodes: np.ndarray
    ids: np.ndarray

    @property
    def m(self) -> int:
        return len(self.b)


def block_nodes(node_shape: tuple[int, int, int], block: int, ccells: tuple[int, int, int],
                ids: np.ndarray) -> np.ndarray:
    """(m, (block + 1)^3) global node indices of the rows' collision cells, in the kernels' slot
    order (-1 past the grid's last node: a block at the far edge of a grid not divisible by it)."""
    cc = np.stack(np.unravel_index(ids % int(np.prod(ccells)), ccells), axis=1)
    r = np.arange(block + 1)
    loc = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
    ijk = block * cc[:, None, :] + loc[None, :, :]
    inside = np.all(ijk < np.asarray(node_shape), axis=2)
    flat = (ijk[..., 0] * node_shape[1] + ijk[..., 1]) * node_shape[2] + ijk[..., 2]
    return np.where(inside, flat, -1)


def rows_from_blocks(ids: np.ndarray, packed: np.ndarray, nodes: np.ndarray, n_cells_per_collider: int) -> ContactRows:
    """ContactRows from the kernels' packed rows: ``packed`` (m, 3 (block + 1)^3 + 2) = J block,
    b, overlap; ``nodes`` (m, (block + 1)^3) from ``block_nodes``. Rows are sorted by id (the
    atomic counter hands out slots in no set order) and J is restricted to the nodes with a
    nonzero coefficient."""
    order = np.argsort(ids, kind="stable")
    ids, packed, nodes = ids[order], packed[order], nodes[order]
    m, nb = nodes.shape
    coeff = packed[:, : 3 * nb].reshape(m, nb, 3)
    used = (nodes >= 0) & np.any(coeff != 0.0, axis=2)
    touched, local = np.unique(nodes[used], return_inverse=True)
    # CSR straight from the blocks: a dense J (m x 3 n, ~0.5 M entries at 260 rows) and its
    # conversion cost milliseconds per step on the host
    row = np.repeat(np.nonzero(used)[0], 3)
    col = (3 * local.reshape(-1, 1) + np.arange(3)).ravel()
    J = sp.csr_matrix((coeff[used].ravel(), (row, col)), shape=(m, 3 * len(touched)))
    return ContactRows(J=J, b=packed[:, -2].copy(), collider=ids // n_cells_per_collider,
                       overlap=packed[:, -1].copy(), nodes=touched, ids=ids)


class ActiveSolver:
    """Solves S[idx, idx] x = rhs for active sets idx of one S, keeping the last factorization
    (the QP's final split reuses the one its active-set iteration ended on).

    Cholesky: S = J M^-1 J^T is a Gram matrix, positive definite when the active rows are
    independent; least squares (the minimum-norm multipliers) when it is not (dependent rows, a
    row on massless nodes only). Cholesky is ~30x cheaper than lstsq's SVD at the hundred-odd
    rows of a body resting on the ground. A sparse S (the QP of many touching bodies, whose rows
    share nodes only with their neighbours': ``wsim.eol.pairs.joint_system``) is factorized by
    sparse LU (SuperLU): a dense Cholesky of the thousands of rows of a pile is O(m^3)."""

    def __init__(self, S: np.ndarray | sp.spmatrix) -> None:
        self.S = S.tocsr() if sp.issparse(S) else S
        self._key: bytes | None = None
        self._factor: Any = None

    def solve(self, idx: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        key = idx.tobytes()
        if key != self._key:
            if sp.issparse(self.S):
                Saa = self.S[idx][:, idx].tocsc()
                try:
                    self._factor = ("lu", spla.splu(Saa, permc_spec="MMD_AT_PLUS_A"))
                except RuntimeError:  # exactly singular: dependent rows
                    self._factor = ("lstsq", Saa.toarray())
            else:
                Saa = self.S[np.ix_(idx, idx)]
                try:
                    self._factor = ("chol", sla.cho_factor(Saa, check_finite=False))
                    if not np.all(np.isfinite(self._factor[1][0])):
                        raise np.linalg.LinAlgError
                except (np.linalg.LinAlgError, ValueError):
                    self._factor = ("lstsq", Saa)
            self._key = key
        kind, f = self._factor
        if kind == "chol":
            return sla.cho_solve(f, rhs, check_finite=False)
        if kind == "lu":
            x = f.solve(np.asarray(rhs, dtype=np.float64))
            if np.all(np.isfinite(x)):
                return x
            self._factor = kind, f = ("lstsq", self.S[idx][:, idx].toarray())
        return np.linalg.lstsq(f, rhs, rcond=None)[0]


def solve_lcp(S: np.ndarray, r: np.ndarray, max_iter: int = 50, active: np.ndarray | None = None,
              solver: ActiveSolver | None = None) -> tuple[np.ndarray, int]:
    """lambda >= 0 with S lambda - r >= 0 and lambda . (S lambda - r) = 0: primal-dual active set
    (Ito & Kunisch 2008), started from ``active`` (a guess such as the last step's active rows;
    default: the rows violated at lambda = 0); ``nnls_lcp`` if the active set does not settle
    (then the iteration count returned is max_iter + 1)."""
    m = len(r)
    solver = solver or ActiveSolver(S)
    lam = np.zeros(m)
    c = 1.0 / max(float(np.mean(S.diagonal())), 1e-300)
    active = (r > 0.0) if active is None else np.asarray(active, dtype=bool)
    for it in range(1, max_iter + 1):
        lam = np.zeros(m)
        if active.any():
            idx = np.flatnonzero(active)
            lam[idx] = solver.solve(idx, r[idx])
        mu = S @ lam - r
        new = lam - c * mu > 0.0
        if np.array_equal(new, active):
            scale = max(float(np.abs(r).max()), 1e-300)
            if lam.min() >= -1e-10 * scale and mu.min() >= -1e-8 * scale:
                return lam, it
            break
        active = new
    return nnls_lcp(S, r), max_iter + 1


def nnls_lcp(S: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The LCP as the bound-constrained QP min 1/2 l^T S l - r^T l, l >= 0, rewritten with S = L L^T
    as the non-negative least-squares problem min |L^T l - L^-1 r|, l >= 0 (Lawson-Hanson, scipy:
    finite and robust where the active-set iteration cycles on nearly dependent rows). A
    semidefinite S (dependent rows) gets a 1e-12 relative diagonal shift first."""
    m = len(r)
    S = S.toarray() if sp.issparse(S) else S
    shift = 1e-12 * max(float(np.max(np.diag(S))), 1e-300)
    L = sla.cholesky(S + shift * np.eye(m), lower=True, check_finite=False)
    lam, _ = sopt.nnls(L.T, sla.solve_triangular(L, r, lower=True, check_finite=False), maxiter=50 * m)
    return lam


@dataclass(frozen=True)
class ContactSystem:
    """The QP of Eq. (29) in its dual form, all an active-set solve needs (m rows, sorted by id):
    S = J M^-1 J^T (m x m), J w and J a (the rows' rates at the unconstrained velocity w and
    acceleration a), b, the rows' ``ids`` and ``overlap`` [m^3], and ``jsum`` (m, 3) =
    sum_s J_s over nodes with mass (row i's impulse lambda_i changes the momentum by
    -lambda_i jsum_i). ``EolBody`` assembles it on the device, so only m-sized data reach the host;
    S is a scipy sparse matrix for the large joint QPs of touching bodies (``wsim.eol.pairs``)."""

    S: np.ndarray | sp.spmatrix
    Jw: np.ndarray
    Ja: np.ndarray
    b: np.ndarray
    ids: np.ndarray
    overlap: np.ndarray
    jsum: np.ndarray

    @property
    def m(self) -> int:
        return len(self.b)


@dataclass(frozen=True)
class ContactSolution:
    """lambda = lambda0 + dt lambda1 on the frozen active set (Eq. 31); ``contact_qp`` adds the
    velocities w = w0 + dt w1."""

    lam0: np.ndarray
    lam1: np.ndarray
    active: np.ndarray
    iterations: int
    w0: np.ndarray | None = None
    w1: np.ndarray | None = None


def solve_contact(system: ContactSystem, dt_guess: float, active: np.ndarray | None = None) -> ContactSolution:
    """The multipliers of Eq. (29) at w_hat = w + dt_guess a (``active``: an optional guess of the
    active rows), split on the final active set into the parts independent of and proportional
    to dt (one more solve with the factorization the iteration ended on)."""
    solver = ActiveSolver(system.S)
    lam, iters = solve_lcp(system.S, system.Jw + dt_guess * system.Ja - system.b, active=active, solver=solver)
    active = lam > 0.0
    idx = np.flatnonzero(active)
    lam0 = np.zeros(system.m)
    lam1 = np.zeros(system.m)
    if len(idx):
        both = solver.solve(idx, np.column_stack([system.Jw[idx] - system.b[idx], system.Ja[idx]]))
        lam0[idx], lam1[idx] = both[:, 0], both[:, 1]
    return ContactSolution(lam0=lam0, lam1=lam1, active=active, iterations=iters)


def contact_qp(rows: ContactRows, inv_mass: np.ndarray, w: np.ndarray, a: np.ndarray, dt_guess: float,
               active: np.ndarray | None = None) -> ContactSolution:
    """Eq. (29) from the primal data, on the host: J on ``rows.nodes``, w and a flat 3 n arrays
    there, ``inv_mass`` per component (zero where a node has no mass). The reference for the
    device assembly of ``ContactSystem`` (tests, and rows read back with ``EolBody.contact_rows``)."""
    J = rows.J if sp.issparse(rows.J) else sp.csr_matrix(rows.J)
    JMinv = J @ sp.diags(inv_mass)
    system = ContactSystem(S=(JMinv @ J.T).toarray(), Jw=J @ w, Ja=J @ a, b=rows.b, ids=rows.ids,
                           overlap=rows.overlap,
                           jsum=(J @ sp.diags((inv_mass > 0.0).astype(float))).toarray().reshape(rows.m, -1, 3).sum(axis=1))
    sol = solve_contact(system, dt_guess, active)
    return replace(sol, w0=w - JMinv.T @ sol.lam0, w1=a - JMinv.T @ sol.lam1)
