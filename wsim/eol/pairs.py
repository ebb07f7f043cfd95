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

The samples' records stay on the device: each becomes one entry of its row and one entry per
corner of each body's cell (``kernels.eol_contact.pair_entries``), and the entries are summed
per key there (``entries_device``: a sort, one thread per key, ``wsim.segments``). The host gets
one row of sums per row and per (body, row, node), and makes each body's sparse matrices over the
rows and nodes it touches from them (``rows_from_entries``; the records of two 32-cell spheres in
contact were ~5,000 of 53 numbers, and their numpy assembly ~11 ms a step on an H100's host).
``entries_host`` is the same sum in numpy, the tests' reference. The joint QP's dual matrix is
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
import warp as wp

from wsim.eol.contact import ContactSystem
from wsim.kernels import eol_contact as kc
from wsim.kernels.eol_contact import PAIR_RECORD
from wsim.segments import KeySums

#: warm-start ids of rows between bodies, kept in body A's ``active_rows`` beside its own rows'
#: (< 2**31): PAIR_ID (1 + B's key) + A's collision cell
PAIR_ID = 1 << 32
FRICTION_SWEEPS = 30
SPARSE_ROWS = 400  # past this many rows the joint QP (``joint_system``) and the friction's K (``row_friction``) are sparse
FRICTION_TOLERANCE = 1e-6  # the sweeps stop once no row's impulse changes by more than this of the largest bound


def corner_offsets(node_shape: tuple[int, int, int]) -> np.ndarray:
    """(8,) flat offsets of a cell's corners from its first node, in the kernels' corner order
    c = 4 i + 2 j + k."""
    ny, nz = node_shape[1], node_shape[2]
    return np.array([(c // 4) * ny * nz + ((c // 2) % 2) * nz + c % 2 for c in range(8)], dtype=np.int64)


@dataclass(frozen=True)
class BodyInfo:
    """What the assembly needs of a body in the group: its grid (nodes per axis, origin, h), its
    Lagrangian map x = F y + T, Q (velocity axes -> world), 1 / tau of its overlap relaxation, its
    key in the World (warm-start ids) and its collision cells per axis."""

    node_shape: tuple[int, int, int]
    origin: np.ndarray
    h: float
    F: np.ndarray
    T: np.ndarray
    Q: np.ndarray
    inv_tau: float
    key: int
    ccells: tuple[int, int, int]

    def node_positions(self, nodes: np.ndarray) -> np.ndarray:
        """(n, 3) world positions of flat grid nodes."""
        ny, nz = self.node_shape[1], self.node_shape[2]
        ijk = np.stack([nodes // (ny * nz), (nodes // nz) % ny, nodes % nz], axis=1)
        return (self.origin + self.h * ijk) @ self.F.T + self.T


@dataclass
class Side:
    """One body's part of the rows between bodies: the ``rows`` it has a part in (indices of the
    ``PairRows``), the touched ``nodes`` (sorted flat ids) with their inverse masses and world
    positions ``x``, J (len(rows) x 3 n, CSR, velocity axes: the rows' coefficients) and G
    (len(rows) x n, CSR: each row's sampling weights of the body's velocity in the relative slip
    v_A - v_B, negative for B), Q (velocity axes -> world) and ``lut`` (flat node id -> its
    position in ``nodes``, -1 where untouched)."""

    rows: np.ndarray
    nodes: np.ndarray
    inv_mass: np.ndarray
    x: np.ndarray
    J: sp.csr_matrix
    G: sp.csr_matrix
    Q: np.ndarray
    lut: np.ndarray

    def JMinv(self) -> sp.csr_matrix:
        """J M^-1 (the same pattern, each column over its node's mass)."""
        out = self.J.copy()
        out.data = out.data * np.repeat(self.inv_mass, 3)[out.indices]
        return out


@dataclass
class PairRows:
    """The rows between bodies of one step (m of them): their warm-start ``ids`` and the body
    (group index) that keeps them (``owner``: A), the pair of bodies (A, B) of each, J w, J a, b
    and overlap as in ``ContactSystem``, D = sum_s sigma_s c_s (world: A's normal impulse per unit
    multiplier is -D), the relative slip before contact from w and from a (area-weighted mean of
    v_A - v_B, world), each row's friction coefficient, and each body's ``Side``."""

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
    _cache: dict = field(default_factory=dict, repr=False)  # K and the couples' regions, made once a step

    @property
    def m(self) -> int:
        return len(self.b)

    def take(self, idx: np.ndarray) -> PairRows:
        """The rows ``idx`` (sorted; those of one QP), with the sides of the bodies they touch."""
        if len(idx) == self.m:
            return self
        new = np.full(self.m, -1)
        new[idx] = np.arange(len(idx))
        sides = {}
        for b, s in self.sides.items():
            keep = new[s.rows] >= 0
            if keep.any():
                sides[b] = Side(rows=new[s.rows[keep]], nodes=s.nodes, inv_mass=s.inv_mass, x=s.x, J=s.J[keep],
                                G=s.G[keep], Q=s.Q, lut=s.lut)
        return PairRows(ids=self.ids[idx], owner=self.owner[idx], bodies=self.bodies[idx], Jw=self.Jw[idx],
                        Ja=self.Ja[idx], b=self.b[idx], overlap=self.overlap[idx], D=self.D[idx],
                        slip_w=self.slip_w[idx], slip_a=self.slip_a[idx], mu=self.mu[idx], sides=sides)


@dataclass(frozen=True)
class Entries:
    """The rows between bodies summed per key (``kernels.eol_contact.pair_entries``; on the device
    by ``entries_device``, on the host by ``entries_host``): ``row_keys`` (m,) ascending (pair p,
    A's collision cell k: p ``row_stride`` + k) with their sums ``row_values`` (m,
    ``PAIR_ROW_VALUES``), and ``node_keys`` (E,) ascending ((X ``rows`` + row key) ``nodes`` + node:
    body X's grid node n in the row) with their sums ``node_values`` (E, ``PAIR_NODE_VALUES``) and
    each node's mass."""

    row_keys: np.ndarray
    row_values: np.ndarray
    node_keys: np.ndarray
    node_values: np.ndarray
    node_mass: np.ndarray
    row_stride: int
    rows: int
    nodes: int


def key_strides(pairs: list[tuple[int, int, float]], bodies: list[BodyInfo]) -> tuple[int, int, int]:
    """(row_stride, rows, nodes) of the entries' keys: the collision cells of any body, all row
    keys, the nodes of any grid."""
    row_stride = max(int(np.prod(b.ccells)) for b in bodies)
    rows = len(pairs) * row_stride
    nodes = max(int(np.prod(b.node_shape)) for b in bodies)
    if len(bodies) * rows * nodes >= 2**62:  # ~1e18: thousands of bodies of 10^6 nodes
        raise ValueError(f"contact between {len(bodies)} EoL bodies: {len(pairs)} pairs of grids up to {nodes} nodes "
                         "do not fit the rows' 63-bit keys")
    return row_stride, rows, nodes


def entries_host(records: list[tuple[int, np.ndarray, np.ndarray]], pairs: list[tuple[int, int, float]],
                 bodies: list[BodyInfo], strides: tuple[int, int, int]) -> Entries:
    """``Entries`` from the samples' records on the host: ``kernels.eol_contact.pair_entries`` in
    numpy (the reference for the device path, and its fallback)."""
    row_stride, n_rows, n_nodes = strides
    own = np.concatenate([np.full(len(ri), b, dtype=np.int64) for b, ri, _ in records])
    ri = np.concatenate([r for _, r, _ in records]).astype(np.int64)
    rf = np.concatenate([f for _, _, f in records]).reshape(-1, PAIR_RECORD)
    pair_ab = np.array([(a, b) for a, b, _ in pairs], dtype=np.int64).reshape(-1, 2)
    pair, own_is_a = ri[:, 0], ri[:, 1] != 0
    other = np.where(own_is_a, pair_ab[pair, 1], pair_ab[pair, 0])
    row = pair * row_stride + ri[:, 4]
    c, vol = rf[:, 32:35], rf[:, 35]
    sigma = np.where(own_is_a, 1.0, -1.0)
    rel_w = rf[:, 36:39] - rf[:, 42:45]  # own - other, world
    rel_a = rf[:, 39:42] - rf[:, 45:48]
    area = np.linalg.norm(c, axis=1)
    inv_tau = np.array([b.inv_tau for b in bodies])[own]
    row_values = np.column_stack([np.einsum("ij,ij->i", c, rel_w), np.einsum("ij,ij->i", c, rel_a), vol * inv_tau, vol,
                                  sigma[:, None] * c, (sigma * area)[:, None] * rel_w,
                                  (sigma * area)[:, None] * rel_a, area])
    keys, vals, mass = [], [], []
    for side, body, sign in ((0, own, 1.0), (1, other, -1.0)):
        Q = np.stack([bodies[b].Q for b in range(len(bodies))])[body]  # (N, 3, 3)
        cq = sign * np.einsum("nij,ni->nj", Q, c)  # Q^T c
        shape = np.array([b.node_shape for b in bodies], dtype=np.int64)[body]
        k = np.arange(8)
        node = (ri[:, 2 + side][:, None] + ((k // 4) * shape[:, 1:2] + (k // 2) % 2) * shape[:, 2:3] + k % 2)
        w = rf[:, 8 * side:8 * side + 8]
        keys.append((body[:, None] * n_rows + row[:, None]) * n_nodes + node)
        vals.append(np.concatenate([w[:, :, None] * cq[:, None, :], (w * (sign * sigma * area)[:, None])[:, :, None],
                                    w[:, :, None]], axis=2))
        mass.append(rf[:, 16 + 8 * side:24 + 8 * side])
    # entry order as the device's (16 per record, own side first) so the sums are the same
    keys_ = np.stack(keys, axis=1).reshape(-1)
    vals_ = np.stack(vals, axis=1).reshape(-1, vals[0].shape[2])
    mass_ = np.stack(mass, axis=1).reshape(-1)
    uk, first, inv = np.unique(keys_, return_index=True, return_inverse=True)
    ur, rinv = np.unique(row, return_inverse=True)

    def summed(v: np.ndarray, idx: np.ndarray, n: int) -> np.ndarray:
        return np.stack([np.bincount(idx.reshape(-1), v[:, q], minlength=n) for q in range(v.shape[1])], axis=1)

    return Entries(row_keys=ur, row_values=summed(row_values, rinv, len(ur)), node_keys=uk,
                   node_values=summed(vals_, inv, len(uk)), node_mass=mass_[first], row_stride=row_stride,
                   rows=n_rows, nodes=n_nodes)


def rows_from_entries(entries: Entries, pairs: list[tuple[int, int, float]], bodies: list[BodyInfo]) -> PairRows:
    """``PairRows`` from the summed entries: the rows' sums, and each body's side as CSR matrices
    over the nodes its entries touch (entries with no material, zero weight, dropped)."""
    e = entries
    pair_ab = np.array([(a, b) for a, b, _ in pairs], dtype=np.int64).reshape(-1, 2)
    row_pair, cell = e.row_keys // e.row_stride, e.row_keys % e.row_stride
    total = e.row_values[:, 13]
    per_area = 1.0 / np.where(total > 0.0, total, 1.0)  # a sample's share of its row: |c| / the row's sum
    out = PairRows(
        ids=PAIR_ID * (1 + np.array([bodies[b].key for b in pair_ab[row_pair, 1]], dtype=np.int64)) + cell,
        owner=pair_ab[row_pair, 0], bodies=pair_ab[row_pair], Jw=e.row_values[:, 0].copy(),
        Ja=e.row_values[:, 1].copy(), b=-e.row_values[:, 2], overlap=e.row_values[:, 3].copy(),
        D=e.row_values[:, 4:7].copy(), slip_w=e.row_values[:, 7:10] * per_area[:, None],
        slip_a=e.row_values[:, 10:13] * per_area[:, None], mu=np.array([pairs[p][2] for p in row_pair]))
    keep = e.node_values[:, 4] > 0.0  # a corner without material
    key, vals, mass = e.node_keys[keep], e.node_values[keep], e.node_mass[keep]
    node, rest = key % e.nodes, key // e.nodes
    body, row = rest // e.rows, np.searchsorted(e.row_keys, rest % e.rows)
    m = out.m
    # entries are sorted by body, row, node: each body's a contiguous block in CSR order
    for b in np.unique(body):
        lo, hi = np.searchsorted(body, [b, b + 1])
        info = bodies[b]
        rows_, nodes_ = row[lo:hi], node[lo:hi]
        touched = np.unique(nodes_)
        lut = np.full(int(np.prod(info.node_shape)), -1, dtype=np.int64)
        lut[touched] = np.arange(len(touched))
        local = lut[nodes_]
        used = np.bincount(rows_, minlength=m) > 0
        side_rows = np.flatnonzero(used)
        ms, n = len(side_rows), len(touched)
        inv_mass = np.zeros(n)
        inv_mass[local] = 1.0 / mass[lo:hi]
        # int32 indices: scipy checks (and would otherwise convert) int64 ones on every construction
        ptr = np.concatenate([[0], np.cumsum(np.bincount(rows_, minlength=m)[side_rows])]).astype(np.int32)
        local32 = local.astype(np.int32)
        J = sp.csr_matrix((vals[lo:hi, :3].ravel(), (3 * local32[:, None] + np.arange(3, dtype=np.int32)).ravel(),
                           3 * ptr), shape=(ms, 3 * n))
        G = sp.csr_matrix((vals[lo:hi, 3] * per_area[rows_], local32, ptr), shape=(ms, n))
        out.sides[int(b)] = Side(rows=side_rows, nodes=touched, inv_mass=inv_mass, x=info.node_positions(touched),
                                 J=J, G=G, Q=info.Q, lut=lut)
    return out


class PairScratch:
    """Device arrays of ``entries_device`` (grown on demand), its two ``KeySums`` and the small
    per-body tables it last uploaded (uploaded again only when they change)."""

    def __init__(self, device: wp.Device) -> None:
        self.device = device
        self.row_sums = KeySums(device)
        self.node_sums = KeySums(device)
        self._records = 0
        self._tables: dict[str, tuple[np.ndarray, wp.array]] = {}
        self._bodies = 0

    def per_body(self, bodies: int) -> tuple[wp.array, wp.array]:
        """The group's surface bounds (bodies x 6, float32: min then max, reset to +inf, -inf)
        and a host buffer for the bodies' record counts (page-locked on a GPU)."""
        if bodies > self._bodies:
            self.bounds = wp.empty((bodies, 6), dtype=wp.float32, device=self.device)
            self.counts = wp.zeros(bodies, dtype=wp.int32, device="cpu", pinned=self.device.is_cuda)
            self._bodies = bodies
        init = np.tile(np.array([np.inf] * 3 + [-np.inf] * 3, dtype=np.float32), (self._bodies, 1))
        self.bounds.assign(init)
        return self.bounds, self.counts

    def ensure(self, records: int) -> None:
        if records <= self._records:
            return
        n, d = max(records, 2 * self._records, 64), self.device
        self.row_keys = wp.empty(n, dtype=wp.int64, device=d)
        self.row_values = wp.empty((n, kc.PAIR_ROW_VALUES), dtype=wp.float64, device=d)
        self.node_keys = wp.empty(16 * n, dtype=wp.int64, device=d)
        self.node_values = wp.empty((16 * n, kc.PAIR_NODE_VALUES), dtype=wp.float64, device=d)
        self.node_mass = wp.empty(16 * n, dtype=wp.float64, device=d)
        self._records = n

    def table(self, name: str, values: np.ndarray, dtype) -> wp.array:
        """``values`` on the device, uploaded only if they differ from the last upload of ``name``."""
        last = self._tables.get(name)
        if last is None or last[0].shape != values.shape or not np.array_equal(last[0], values):
            last = (values.copy(), wp.array(values, dtype=dtype, device=self.device))
            self._tables[name] = last
        return last[1]


def entries_device(buffers: list[tuple[int, wp.array, wp.array, int]], pairs: list[tuple[int, int, float]],
                   bodies: list[BodyInfo], scratch: PairScratch) -> Entries:
    """``Entries`` on the device from the records the bodies' ``pair_samples`` launches left there:
    (group index, rec_i, rec_f, count) per body. Only the sums reach the host: one row per row
    and per (body, row, node), instead of every record (``entries_host`` is the same in numpy)."""
    row_stride, n_rows, n_nodes = key_strides(pairs, bodies)
    total = sum(n for *_, n in buffers)
    scratch.ensure(total)
    d = scratch.device
    pair_ab = np.array([(a, b) for a, b, _ in pairs], dtype=np.int32).reshape(-1, 2)
    pair_a = scratch.table("pair_a", np.ascontiguousarray(pair_ab[:, 0]), wp.int32)
    pair_b = scratch.table("pair_b", np.ascontiguousarray(pair_ab[:, 1]), wp.int32)
    axes = scratch.table("axes", np.stack([b.Q for b in bodies]), wp.mat33d)
    shapes = scratch.table("shapes", np.array([b.node_shape for b in bodies], dtype=np.int32), wp.vec3i)
    inv_tau = scratch.table("inv_tau", np.array([b.inv_tau for b in bodies], dtype=np.float64), wp.float64)
    offset = 0
    for own, rec_i, rec_f, n in buffers:
        if n:
            wp.launch(kc.pair_entries, n, [rec_i, rec_f, own, pair_a, pair_b, axes, shapes, inv_tau,
                                           wp.int64(row_stride), wp.int64(n_rows), wp.int64(n_nodes), offset,
                                           scratch.node_keys, scratch.node_values, scratch.node_mass,
                                           scratch.row_keys, scratch.row_values], device=d)
        offset += n
    scratch.row_sums.launch(scratch.row_keys, scratch.row_values, None, total, key_bound=n_rows)
    scratch.node_sums.launch(scratch.node_keys, scratch.node_values, scratch.node_mass, 16 * total,
                             key_bound=len(bodies) * n_rows * n_nodes)
    (row_keys, row_values, _), (node_keys, node_values, node_mass) = KeySums.fetch_all([scratch.row_sums,
                                                                                        scratch.node_sums])
    return Entries(row_keys=row_keys, row_values=row_values, node_keys=node_keys, node_values=node_values,
                   node_mass=node_mass, row_stride=row_stride, rows=n_rows, nodes=n_nodes)


def own_rows_at(side: Side, packed: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """A body's own rows (the device's packed blocks: ``packed`` (m, 3 nb + 2) with their block
    ``nodes`` (m, nb), ``wsim.eol.contact.block_nodes``, -1 past the grid) at the nodes the rows
    between bodies touch: (m, 3 n) over ``side.nodes``, dense."""
    m, nb = nodes.shape
    pos = np.where(nodes >= 0, side.lut[np.maximum(nodes, 0)], -1)
    k = np.nonzero(pos >= 0)
    out = np.zeros((m, len(side.nodes), 3))
    out[k[0], pos[k]] = packed[:, : 3 * nb].reshape(m, nb, 3)[k]
    return out.reshape(m, -1)


def joint_system(own: list[ContactSystem | None], own_at: list[np.ndarray | None], bodies: list[int],
                 rows: PairRows) -> ContactSystem:
    """One QP for touching bodies: the rows of each body in ``bodies`` (its ``own`` system, sorted
    by id, and those rows at the shared nodes ``own_at``), then the rows between them. S gets each
    body's block, the rows between bodies' sum_b J_b M_b^-1 J_b^T and the cross terms between a
    body's own rows and them at the nodes both touch. Past ``SPARSE_ROWS`` rows S is sparse
    (scipy CSR; ``ActiveSolver`` then factorizes by sparse LU): a row shares nodes only with the
    rows of neighbouring collision cells."""
    sizes = [0 if s is None else s.m for s in own]
    start = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    n_own, m = int(start[-1]), rows.m
    n = n_own + m
    sparse = n > SPARSE_ROWS
    coo: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (row ids, column ids, values) when sparse
    S = None if sparse else np.zeros((n, n))

    def add(r: np.ndarray, c: np.ndarray, B: np.ndarray | sp.spmatrix) -> None:
        if not sparse:
            S[np.ix_(r, c)] += B.toarray() if sp.issparse(B) else B
        elif sp.issparse(B):
            B = B.tocoo()
            coo.append((r[B.row], c[B.col], B.data))
        else:
            i, j = np.nonzero(B)
            coo.append((r[i], c[j], B[i, j]))

    for k, b in enumerate(bodies):
        side = rows.sides.get(b)
        JMinv = None if side is None else side.JMinv()
        if JMinv is not None:
            r = n_own + side.rows
            add(r, r, JMinv @ side.J.T)
        if own[k] is None:
            continue
        sl = np.arange(start[k], start[k + 1])
        add(sl, sl, own[k].S)
        if JMinv is not None and own_at[k] is not None:
            C = (JMinv @ own_at[k].T).T
            add(sl, n_own + side.rows, C)
            add(n_own + side.rows, sl, C.T)
    if sparse:
        S = sp.csr_matrix((np.concatenate([v for _, _, v in coo]),
                           (np.concatenate([i for i, _, _ in coo]), np.concatenate([j for _, j, _ in coo]))), shape=(n, n))
    parts = [s for s in own if s is not None]

    def cat(name: str, pair: np.ndarray) -> np.ndarray:
        return np.concatenate([getattr(s, name) for s in parts] + [pair])

    return ContactSystem(S=S, Jw=cat("Jw", rows.Jw), Ja=cat("Ja", rows.Ja), b=cat("b", rows.b),
                         ids=cat("ids", rows.ids), overlap=cat("overlap", rows.overlap),
                         jsum=np.concatenate([s.jsum for s in parts] + [np.zeros((m, 3))]))


def node_changes(rows: PairRows, b: int, lam: np.ndarray) -> np.ndarray:
    """(n, 3) velocity change of body b's touched nodes (velocity axes) from multipliers ``lam``
    of the rows between bodies: -M^-1 J^T lambda."""
    side = rows.sides[b]
    return -side.inv_mass[:, None] * (side.J.T @ lam[side.rows]).reshape(-1, 3)


def own_changes(rows: PairRows, b: int, own_at: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """(n, 3) velocity change of body b's nodes touched by the rows between bodies (velocity axes)
    from the multipliers ``lam`` of its own rows (``own_rows_at``): -M^-1 J_own^T lambda there."""
    return -rows.sides[b].inv_mass[:, None] * (lam @ own_at).reshape(-1, 3)


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
    if "K" not in rows._cache:
        blocks = []
        for s in rows.sides.values():
            GMinv = s.G.copy()  # G M^-1: each entry over its node's mass (``multiply`` goes through COO)
            GMinv.data *= s.inv_mass[GMinv.indices]
            blocks.append((s.rows, (GMinv @ s.G.T).tocoo()))
        if m > SPARSE_ROWS:  # a row's slip shares nodes with its neighbours' only: K @ P sparse
            K = sp.csr_matrix((np.concatenate([B.data for _, B in blocks]),
                               (np.concatenate([r[B.row] for r, B in blocks]),
                                np.concatenate([r[B.col] for r, B in blocks]))), shape=(m, m))
            diag, total = K.diagonal(), np.asarray(abs(K).sum(axis=1)).ravel()
        else:
            K = np.zeros((m, m))
            for r, B in blocks:
                K[np.ix_(r, r)] += B.toarray()
            diag, total = np.diag(K).copy(), np.abs(K).sum(axis=1)
        rows._cache["K"] = (K, diag, 1.0 / np.maximum(total, 1e-300))
    K, diag, step = rows._cache["K"]

    tol = FRICTION_TOLERANCE * float(bound.max())
    step = step[:, None]
    for _ in range(FRICTION_SWEEPS):
        u = slip + K @ P
        u -= np.einsum("ij,ij->i", u, n)[:, None] * n  # tangential: P stays tangential, and so the update
        new = P - step * u
        size = np.sqrt(np.einsum("ij,ij->i", new, new))
        new *= np.minimum(1.0, bound / np.maximum(size, 1e-300))[:, None]
        done = float(np.abs(new - P).max()) <= tol
        P = new
        if done:
            break
    P[diag <= 0.0] = 0.0
    return P


def friction_changes(rows: PairRows, b: int, P: np.ndarray) -> np.ndarray:
    """(n, 3) velocity change of body b's touched nodes (velocity axes) from the friction impulses
    P of the rows between bodies: M^-1 G^T P, turned into the body's axes."""
    side = rows.sides[b]
    return side.inv_mass[:, None] * ((side.G.T @ P[side.rows]) @ side.Q)


def moment_couples(rows: PairRows, changes: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """Velocity changes (n, 3 per body, velocity axes) that keep each pair's angular momentum:
    a row's impulse acts on each body at the mass centroid of the cell its sample lies in (the
    mass-weighted weights that keep nodes holding a sliver of material from being flung), which
    differ between the two bodies by a fraction of a cell, so the equal and opposite impulses
    ``changes`` (from ``node_changes`` and ``friction_changes``) carry a net moment tau. Each pair
    gets the couple -tau, as rigid rotations omega x (x - xbar_b) of the nodes its rows touch in
    either body (about each region's mass centroid xbar_b): no net force, the least kinetic energy
    for that moment (one omega, (I_A + I_B) omega = -tau with I_b the regions' inertia tensors).
    With the centroids left uncorrected a frictionless glancing blow of two 6-cell spheres gained
    4.9 % of |L|; weights moved onto the sample instead put the push back on light nodes.
    ``changes`` may carry a leading stack axis ((..., n, 3): dv0 and dv1 of a step at once),
    each slice getting its own couple; the pairs are summed in one pass per body."""
    if "couples" not in rows._cache:
        rows._cache["couples"] = _couple_regions(rows)
    inverse, parts = rows._cache["couples"]
    lead = next(iter(changes.values())).shape[:-2]  # a stack of changes (dv0, dv1) gets a couple each
    tau = np.zeros(lead + (len(inverse), 3))
    for k, p in parts.items():
        dv = changes[k][..., p.nodes, :] @ rows.sides[k].Q.T  # world
        moment = np.moveaxis(p.m[:, None] * np.cross(p.x, dv), -2, 0)  # (E, ..., 3)
        tau += np.moveaxis((p.onehot @ moment.reshape(len(p.m), -1)).reshape((p.onehot.shape[0],) + lead + (3,)), 0, -2)
    omega = -np.einsum("rij,...rj->...ri", inverse, tau)
    out = {}
    for k, p in parts.items():
        dv = np.cross(omega[..., p.region, :], p.r) @ rows.sides[k].Q  # world -> velocity axes, (..., E, 3)
        flat = np.moveaxis(dv, -2, 0).reshape(dv.shape[-2], -1)
        # a node in several regions (a body touching two others there) gets the sum of their couples
        out[k] = np.moveaxis((p.spread @ flat).reshape((p.spread.shape[0],) + lead + (3,)), 0, -2)
    return {k: out[k] if k in out else np.zeros_like(dv) for k, dv in changes.items()}


@dataclass(frozen=True)
class CoupleParts:
    """One body's parts of the couples' regions, concatenated (E entries): its touched ``nodes``
    (indices into its side's nodes), ``region`` of each, ``onehot`` (R x E) and ``spread``
    (n x E), sparse, that sum entries per region and per node, mass ``m``, world position ``x`` and
    ``r`` = x - the part's mass centroid."""

    nodes: np.ndarray
    region: np.ndarray
    onehot: sp.csr_matrix
    spread: sp.csr_matrix
    m: np.ndarray
    x: np.ndarray
    r: np.ndarray


def _region_sums(region: np.ndarray, values: np.ndarray, R: int) -> np.ndarray:
    """(R, q) sums of values (E, q) per region (E,): one bincount over region-major bins."""
    q = values.shape[1]
    bins = (region[:, None] * q + np.arange(q)).ravel()
    return np.bincount(bins, values.ravel(), minlength=R * q).reshape(R, q)


def _couple_regions(rows: PairRows) -> tuple[np.ndarray, dict[int, CoupleParts]]:
    """The couples' regions, made once a step: per pair (sorted), the nodes its rows touch in each
    body about each part's mass centroid, and the inverse (R, 3, 3) of each pair's summed inertia;
    per body its ``CoupleParts``, found for all its pairs at once (entries in region, then node
    order)."""
    pair_keys = np.unique(rows.bodies[:, 0] * (int(rows.bodies.max()) + 1) + rows.bodies[:, 1])
    region_of_row = np.searchsorted(pair_keys, rows.bodies[:, 0] * (int(rows.bodies.max()) + 1) + rows.bodies[:, 1])
    R = len(pair_keys)
    inertia = np.zeros((R, 3, 3))
    parts = {}
    eye = np.eye(3)
    for k in sorted(rows.sides):
        side = rows.sides[k]
        G, n = side.G, len(side.nodes)
        nz = G.data != 0.0
        row = np.repeat(np.arange(G.shape[0]), np.diff(G.indptr))[nz]
        key = np.unique(region_of_row[side.rows[row]] * n + G.indices[nz])
        region, nodes = key // n, key % n
        m = 1.0 / side.inv_mass[nodes]
        x = side.x[nodes]
        msum = np.bincount(region, m, minlength=R)
        centroid = _region_sums(region, m[:, None] * x, R) / np.where(msum > 0.0, msum, 1.0)[:, None]
        r = x - centroid[region]
        # sum over the part of m ((r . r) I - r r^T), per region
        outer = m[:, None, None] * ((r * r).sum(axis=1)[:, None, None] * eye - r[:, :, None] * r[:, None, :])
        inertia += _region_sums(region, outer.reshape(-1, 9), R).reshape(R, 3, 3)
        e, ones = np.arange(len(nodes)), np.ones(len(nodes))
        onehot = sp.csr_matrix((ones, (region, e)), shape=(R, len(nodes)))
        spread = sp.csr_matrix((ones, (nodes, e)), shape=(n, len(nodes)))
        parts[k] = CoupleParts(nodes=nodes, region=region, onehot=onehot, spread=spread, m=m, x=x, r=r)
    return np.linalg.pinv(inertia, rcond=1e-12), parts


def slip_change(rows: PairRows, changes: dict[int, np.ndarray]) -> np.ndarray:
    """(m, 3) change of the rows' relative slip v_A - v_B (world) from velocity changes of the
    bodies' touched nodes (velocity axes), sum_b G_b (dv_b Q_b^T)."""
    out = np.zeros((rows.m, 3))
    for b, dv in changes.items():
        side = rows.sides[b]
        out[side.rows] += side.G @ (dv @ side.Q.T)
    return out
