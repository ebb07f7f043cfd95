"""Contact between EoL bodies in one QP (the paper's Eq. 29 across objects; issue 18).

Touching EoL bodies step together with one dt, and their contact rows join one QP: the rows of
each body against the World's colliders and other methods' surfaces (``EolBody``'s own rows,
assembled on the device), and the rows between the bodies. A row between bodies A and B is one
collision cell of A's grid (Sec. 3.5's collision grid, carried by A's Lagrangian map) and holds
every sample of either surface inside the other there (``kernels.eol_contact.pair_samples``):

    sum_s c_s . (v_own(x_s) - v_other(x_s)) <= -sum_s vol_s / tau

with c_s = -|n_s dGamma . n_other| n_other (the sample's area pushed into the other body, as for
a collider) and each body's velocity at x_s the mass-weighted mean of its cell's nodes. The own
and the other body's velocities are the unknowns: its multiplier pushes the two bodies apart
with equal and opposite impulses at the same points (the pair's linear momentum is exact), and
vertex-face contact holds both ways (a corner of either body cannot pass through a face of the
other). There is no lag: the explicit exchange these rows replace, where the lighter body kept
itself out of the other's surface and handed it the push one coupling interval later, rang on
fine grids (16 bodies at 32 cells reached 7.6e5 m/s).

Rows are assembled here on the host from the samples' records (only samples inside another body
travel), sparse per body over the nodes they touch. The joint QP's dual matrix is
S = sum_bodies J_b M_b^-1 J_b^T over all rows of the touching bodies: each body's own rows keep
the block its device assembly made, the rows between bodies add theirs and the cross terms with
the own rows at the nodes both touch.

Coulomb friction between the bodies acts per row after the normal solve, on the relative slip at
the row's samples (area-weighted mean of v_A - v_B, tangential to the row's normal), bounded by
mu times the row's normal impulse, by a Jacobi iteration on the rows' coupled tangential response
(``row_friction``): equal and opposite at the same points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from wsim.eol.contact import ContactSystem
from wsim.kernels.eol_contact import PAIR_RECORD

#: warm-start ids of rows between bodies, kept in body A's ``active_rows`` beside its own rows'
#: (< 2**31): PAIR_ID (1 + B's key) + A's collision cell
PAIR_ID = 1 << 32
FRICTION_SWEEPS = 30


def corner_offsets(node_shape: tuple[int, int, int]) -> np.ndarray:
    """(8,) flat offsets of a cell's corners from its first node, in the kernels' corner order
    c = 4 i + 2 j + k."""
    ny, nz = node_shape[1], node_shape[2]
    return np.array([(c // 4) * ny * nz + ((c // 2) % 2) * nz + c % 2 for c in range(8)], dtype=np.int64)


@dataclass(frozen=True)
class BodyInfo:
    """What the assembly needs of a body in the group: its grid's nodes per axis, Q (velocity axes
    -> world), 1 / tau of its overlap relaxation, its key in the World (warm-start ids)."""

    node_shape: tuple[int, int, int]
    Q: np.ndarray
    inv_tau: float
    key: int


@dataclass
class Side:
    """One body's part of the rows between bodies: the touched ``nodes`` (sorted flat ids), their
    inverse masses, J (m x 3 n, velocity axes: the rows' coefficients) and G (m x n: each row's
    sampling weights of the body's velocity in the relative slip v_A - v_B, negative for B)."""

    nodes: np.ndarray
    inv_mass: np.ndarray
    J: sp.csr_matrix
    G: sp.csr_matrix
    Q: np.ndarray

    def local(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(positions in ``self.nodes``, mask of the given flat ids that are touched)."""
        pos = np.minimum(np.searchsorted(self.nodes, nodes), len(self.nodes) - 1)
        return pos, self.nodes[pos] == nodes


@dataclass
class PairRows:
    """The rows between bodies of one step (m of them): their warm-start ``ids`` and the body
    (group index) that keeps them (``owner``: A), the pair of bodies (A, B) of each, J w, J a, b and overlap as in ``ContactSystem``,
    D = sum_s sigma_s c_s (world: A's normal impulse per unit multiplier is -D), the relative slip
    before contact from w and from a (area-weighted mean of v_A - v_B, world), each row's friction
    coefficient, and each body's ``Side``."""

    ids: np.ndarray
    owner: np.ndarray
    bodies: np.ndarray
    Jw: np.ndarray
    Ja: np.ndarray
    b: np.ndarray
    overlap: np.ndarray
    D: np.ndarray
    slip_w: np.ndarray
    slip_a: np.ndarray
    mu: np.ndarray
    sides: dict[int, Side] = field(default_factory=dict)

    @property
    def m(self) -> int:
        return len(self.b)

    def take(self, idx: np.ndarray) -> PairRows:
        """The rows ``idx`` (those of one QP), with the sides of the bodies they touch."""
        sides = {}
        for b, s in self.sides.items():
            J, G = s.J[idx], s.G[idx]
            if J.nnz:
                sides[b] = Side(nodes=s.nodes, inv_mass=s.inv_mass, J=J, G=G, Q=s.Q)
        return PairRows(ids=self.ids[idx], owner=self.owner[idx], bodies=self.bodies[idx], Jw=self.Jw[idx],
                        Ja=self.Ja[idx], b=self.b[idx], overlap=self.overlap[idx], D=self.D[idx],
                        slip_w=self.slip_w[idx], slip_a=self.slip_a[idx], mu=self.mu[idx], sides=sides)


def assemble(records: list[tuple[int, np.ndarray, np.ndarray]], pairs: list[tuple[int, int, float]],
             bodies: list[BodyInfo]) -> PairRows | None:
    """The rows between bodies from the samples' records: (own body's group index, rec_i (N, 5),
    rec_f (N, ``PAIR_RECORD``)) per body (``kernels.eol_contact.pair_samples``); ``pairs`` (A, B,
    friction) by pair index. None when no sample is inside another body."""
    own = np.concatenate([np.full(len(ri), b, dtype=np.int64) for b, ri, _ in records]) if records else np.zeros(0, np.int64)
    if len(own) == 0:
        return None
    ri = np.concatenate([r for _, r, _ in records]).astype(np.int64)
    rf = np.concatenate([f for _, _, f in records]).reshape(-1, PAIR_RECORD)
    pair_ab = np.array([(a, b) for a, b, _ in pairs], dtype=np.int64).reshape(-1, 2)
    pair, own_is_a = ri[:, 0], ri[:, 1] != 0
    other = np.where(own_is_a, pair_ab[pair, 1], pair_ab[pair, 0])
    cells = int(ri[:, 4].max()) + 1
    keys, row = np.unique(pair * cells + ri[:, 4], return_inverse=True)
    row = row.reshape(-1)
    m = len(keys)
    c = rf[:, 32:35]
    vol = rf[:, 35]
    sigma = np.where(own_is_a, 1.0, -1.0)
    rel_w = rf[:, 36:39] - rf[:, 42:45]  # own - other, world
    rel_a = rf[:, 39:42] - rf[:, 45:48]
    inv_tau = np.array([bodies[b].inv_tau for b in own])

    def per_row(v: np.ndarray) -> np.ndarray:
        if v.ndim == 1:
            return np.bincount(row, v, minlength=m)
        return np.stack([np.bincount(row, v[:, d], minlength=m) for d in range(v.shape[1])], axis=1)

    area = np.linalg.norm(c, axis=1)
    share = area / per_row(area)[row]  # the sample's share of its row's slip and friction
    row_pair = pair[np.unique(row, return_index=True)[1]]
    a_of_row = pair_ab[row_pair, 0]
    out = PairRows(
        ids=PAIR_ID * (1 + np.array([bodies[b].key for b in pair_ab[row_pair, 1]], dtype=np.int64)) + keys % cells,
        owner=a_of_row,
        bodies=pair_ab[row_pair],
        Jw=per_row(np.einsum("ij,ij->i", c, rel_w)),
        Ja=per_row(np.einsum("ij,ij->i", c, rel_a)),
        b=-per_row(vol * inv_tau),
        overlap=per_row(vol),
        D=per_row(sigma[:, None] * c),
        slip_w=per_row((share * sigma)[:, None] * rel_w),
        slip_a=per_row((share * sigma)[:, None] * rel_a),
        mu=np.array([pairs[p][2] for p in row_pair]),
    )
    # each body's side: its own samples (+c, sampling sign sigma) and the other's inside it (-c, -sigma)
    for b in np.unique(np.concatenate([own, other])):
        parts = []
        for mine, col, sign in ((own == b, 0, 1.0), (other == b, 1, -1.0)):
            if mine.any():
                parts.append((np.flatnonzero(mine), col, sign))
        info = bodies[b]
        offsets = corner_offsets(info.node_shape)
        rows, nodes, weight, mass, coeff, slip = [], [], [], [], [], []
        for idx, col, sign in parts:
            base = ri[idx, 2 + col]
            wts = rf[idx, 8 * col:8 * col + 8]
            on = wts > 0.0
            k = np.nonzero(on)
            rows.append(row[idx][k[0]])
            nodes.append((base[:, None] + offsets[None, :])[k])
            weight.append(wts[k])
            mass.append(rf[idx, 16 + 8 * col:24 + 8 * col][k])
            coeff.append(sign * (c[idx] @ info.Q)[k[0]])  # world -> velocity axes: Q^T c
            slip.append(sign * (sigma[idx] * share[idx])[k[0]])
        rows_, nodes_ = np.concatenate(rows), np.concatenate(nodes)
        weight_, mass_ = np.concatenate(weight), np.concatenate(mass)
        touched, local = np.unique(nodes_, return_inverse=True)
        local = local.reshape(-1)
        inv_mass = np.zeros(len(touched))
        inv_mass[local] = 1.0 / mass_
        vals = weight_[:, None] * np.concatenate(coeff)
        J = sp.csr_matrix((vals.ravel(), (np.repeat(rows_, 3), (3 * local[:, None] + np.arange(3)).ravel())),
                          shape=(m, 3 * len(touched)))
        G = sp.csr_matrix((weight_ * np.concatenate(slip), (rows_, local)), shape=(m, len(touched)))
        out.sides[int(b)] = Side(nodes=touched, inv_mass=inv_mass, J=J, G=G, Q=info.Q)
    return out


def own_rows_at(side: Side, packed: np.ndarray, nodes: np.ndarray) -> sp.csr_matrix:
    """A body's own rows (the device's packed blocks: ``packed`` (m, 3 nb + 2) with their block
    ``nodes`` (m, nb), ``wsim.eol.contact.block_nodes``) restricted to the nodes the rows between
    bodies touch: (m, 3 n) over ``side.nodes``."""
    m, nb = nodes.shape
    pos, hit = side.local(np.where(nodes >= 0, nodes, 0))
    hit &= nodes >= 0
    k = np.nonzero(hit)
    coeff = packed[:, : 3 * nb].reshape(m, nb, 3)[k]
    return sp.csr_matrix((coeff.ravel(), (np.repeat(k[0], 3), (3 * pos[k][:, None] + np.arange(3)).ravel())),
                         shape=(m, 3 * len(side.nodes)))


def joint_system(own: list[ContactSystem | None], own_at: list[sp.csr_matrix | None], bodies: list[int],
                 rows: PairRows) -> ContactSystem:
    """One QP for touching bodies: the rows of each body in ``bodies`` (its ``own`` system, sorted
    by id, and those rows at the shared nodes ``own_at``), then the rows between them. S gets each
    body's block, the rows between bodies' sum_b J_b M_b^-1 J_b^T and the cross terms between a
    body's own rows and them at the nodes both touch."""
    sizes = [0 if s is None else s.m for s in own]
    start = np.concatenate([[0], np.cumsum(sizes)])
    n_own, m = int(start[-1]), rows.m
    S = np.zeros((n_own + m, n_own + m))
    for k, b in enumerate(bodies):
        side = rows.sides.get(b)
        JMinv = None if side is None else side.J.multiply(np.repeat(side.inv_mass, 3)[None, :]).tocsr()
        if JMinv is not None:
            S[n_own:, n_own:] += (JMinv @ side.J.T).toarray()
        if own[k] is None:
            continue
        sl = slice(start[k], start[k + 1])
        S[sl, sl] = own[k].S
        if JMinv is not None and own_at[k] is not None:
            C = (own_at[k] @ JMinv.T).toarray()
            S[sl, n_own:] = C
            S[n_own:, sl] = C.T
    parts = [s for s in own if s is not None]

    def cat(name: str, pair: np.ndarray) -> np.ndarray:
        return np.concatenate([getattr(s, name) for s in parts] + [pair])

    return ContactSystem(S=S, Jw=cat("Jw", rows.Jw), Ja=cat("Ja", rows.Ja), b=cat("b", rows.b),
                         ids=cat("ids", rows.ids), collider=cat("collider", np.full(m, -1)),
                         overlap=cat("overlap", rows.overlap), jsum=np.concatenate([s.jsum for s in parts]
                                                                                    + [np.zeros((m, 3))]))


def node_changes(rows: PairRows, b: int, lam: np.ndarray) -> np.ndarray:
    """(n, 3) velocity change of body b's touched nodes (velocity axes) from multipliers ``lam``
    of the rows between bodies: -M^-1 J^T lambda."""
    side = rows.sides[b]
    return -side.inv_mass[:, None] * (side.J.T @ lam).reshape(-1, 3)


def own_changes(rows: PairRows, b: int, own_at: sp.csr_matrix, lam: np.ndarray) -> np.ndarray:
    """(n, 3) velocity change of body b's nodes touched by the rows between bodies (velocity axes)
    from the multipliers ``lam`` of its own rows (``own_rows_at``): -M^-1 J_own^T lambda there."""
    return -rows.sides[b].inv_mass[:, None] * (own_at.T @ lam).reshape(-1, 3)


def row_friction(rows: PairRows, lam: np.ndarray, slip: np.ndarray) -> np.ndarray:
    """Coulomb friction impulses P (m, 3) (world, on A; -P on B) of the rows between bodies: slip
    (m, 3) is each row's relative velocity v_A - v_B after the normal impulses (at the QP's dt),
    lam the rows' normal multipliers (A's normal impulse is lam |D|). P is tangential to the row's
    normal D / |D|, at most mu lam |D|, and removes as much of the tangential slip as that allows:
    projected Jacobi sweeps on the rows' coupled tangential response K = sum_b G_b M_b^-1 G_b^T
    (the slip of row i changes by K_ij P_j), each row's step scaled by K_ii / sum_j |K_ij| so the
    sweeps cannot overshoot where rows share nodes."""
    m = rows.m
    P = np.zeros((m, 3))
    bound = rows.mu * np.maximum(lam, 0.0) * np.linalg.norm(rows.D, axis=1)
    if not np.any(bound > 0.0):
        return P
    n = rows.D / np.maximum(np.linalg.norm(rows.D, axis=1), 1e-300)[:, None]
    K = sum(s.G.multiply(s.inv_mass[None, :]) @ s.G.T for s in rows.sides.values()).tocsr()
    diag = K.diagonal()
    step = 1.0 / np.maximum(np.asarray(abs(K).sum(axis=1)).ravel(), 1e-300)

    def tangential(v: np.ndarray) -> np.ndarray:
        return v - np.einsum("ij,ij->i", v, n)[:, None] * n

    for _ in range(FRICTION_SWEEPS):
        u = tangential(slip + K @ P)
        P = tangential(P - step[:, None] * u)
        size = np.linalg.norm(P, axis=1)
        P *= np.minimum(1.0, bound / np.maximum(size, 1e-300))[:, None]
    P[diag <= 0.0] = 0.0
    return P


def friction_changes(rows: PairRows, b: int, P: np.ndarray) -> np.ndarray:
    """(n, 3) velocity change of body b's touched nodes (velocity axes) from the friction impulses
    P of the rows between bodies: M^-1 G^T P, turned into the body's axes."""
    side = rows.sides[b]
    return side.inv_mass[:, None] * ((side.G.T @ P) @ side.Q)


def slip_change(rows: PairRows, changes: dict[int, np.ndarray]) -> np.ndarray:
    """(m, 3) change of the rows' relative slip v_A - v_B (world) from velocity changes of the
    bodies' touched nodes (velocity axes), sum_b G_b (dv_b Q_b^T)."""
    out = np.zeros((rows.m, 3))
    for b, dv in changes.items():
        side = rows.sides[b]
        out += side.G @ (dv @ side.Q.T)
    return out
