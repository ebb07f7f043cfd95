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
one row of sums per row and per (body, row, node), and keeps each body's entries over the nodes it
touches (``rows_from_entries``; the records of two 32-cell spheres in contact were ~5,000 of 53
numbers, and their numpy assembly ~11 ms a step on an H100's host). ``entries_host`` is the same
sum in numpy, the tests' reference. The joint QP's dual matrix is S = sum_bodies J_b M_b^-1 J_b^T
over all rows of the touching bodies: each body's own rows keep the block its device assembly
made, the rows between bodies add theirs and the cross terms with the own rows at the nodes both
touch.

The solve works on all bodies at once (``PairRows.stacked``): their touched nodes in one list,
over which J = [J_A J_B ...] and G are one sparse matrix each, so that the rows' block
J M^-1 J^T of S, the friction's K = G M^-1 G^T, the velocity changes M^-1 J^T lambda and the slip
G v are one product each (tens to hundreds of rows: the cost of a step's host work is the number
of numpy and scipy calls, tens of microseconds for each sparse matrix made, more than their
arithmetic).

Coulomb friction between the bodies acts per row after the normal solve, on the relative slip at
the row's samples (area-weighted mean of v_A - v_B, tangential to the row's normal), bounded by
mu times the row's normal impulse, by a Jacobi iteration on the rows' coupled tangential response
(``row_friction``): equal and opposite at the same points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

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
        i, rest = np.divmod(nodes, ny * nz)
        j, k = np.divmod(rest, nz)
        return (self.origin + self.h * np.column_stack([i, j, k])) @ self.F.T + self.T


@dataclass
class Side:
    """One body's part of the rows between bodies: the ``rows`` it has a part in (indices of the
    ``PairRows``), the touched ``nodes`` (sorted flat ids) with their inverse masses and world
    positions ``x``, Q (velocity axes -> world) and ``lut`` (flat node id -> its position in
    ``nodes``, -1 where untouched). Its entries (one per row and touched node, sorted by row then
    node): the row (index of the ``PairRows``), the node (position in ``nodes``), the row's
    coefficients ``entry_j`` (velocity axes) and ``entry_g``, the node's sampling weight in the
    row's relative slip v_A - v_B (negative for B). ``J`` and ``G`` are the same as CSR matrices
    over the side's rows (made on demand: the solve uses all bodies' entries at once,
    ``PairRows.stacked``)."""

    rows: np.ndarray
    nodes: np.ndarray
    inv_mass: np.ndarray
    x: np.ndarray
    Q: np.ndarray
    lut: np.ndarray
    entry_row: np.ndarray
    entry_node: np.ndarray
    entry_j: np.ndarray
    entry_g: np.ndarray

    def _ptr(self) -> np.ndarray:
        """CSR row pointer of the entries over ``rows`` (int32: scipy checks, and would otherwise
        convert, int64 indices on every construction)."""
        return np.append(np.searchsorted(self.entry_row, self.rows), len(self.entry_row)).astype(np.int32)

    @cached_property
    def J(self) -> sp.csr_matrix:
        """J (len(rows) x 3 n, CSR, velocity axes: the rows' coefficients)."""
        cols = 3 * self.entry_node.astype(np.int32)[:, None] + np.arange(3, dtype=np.int32)
        return sp.csr_matrix((self.entry_j.ravel(), cols.ravel(), 3 * self._ptr()), shape=(len(self.rows), 3 * len(self.nodes)))

    @cached_property
    def G(self) -> sp.csr_matrix:
        """G (len(rows) x n, CSR: each row's sampling weights of the body's velocity in the slip)."""
        return sp.csr_matrix((self.entry_g, self.entry_node.astype(np.int32), self._ptr()),
                             shape=(len(self.rows), len(self.nodes)))

    def JMinv(self) -> sp.csr_matrix:
        """J M^-1 (the same pattern, each column over its node's mass)."""
        out = self.J.copy()
        out.data = out.data * np.repeat(self.inv_mass, 3)[out.indices]
        return out


@dataclass(frozen=True)
class Stacked:
    """All sides of a ``PairRows`` at once: the touched nodes of every body in one list (bodies in
    key order, body ``keys[i]``'s nodes at ``start[i]:start[i + 1]``, ``slices``), their inverse
    masses and world positions, and the bodies' entries over them in row order (bodies in key
    order within a row, then nodes: ``row``, ``col`` the node and ``g`` the slip weight) as
    J = [J_A J_B ...] (m x 3 N, the block row of the bodies' coefficients, so that
    sum_b J_b M_b^-1 J_b^T = J M^-1 J^T) and G (m x N), CSR, each kept scaled by M^-1/2 (``root``
    per node): Jr = J M^-1/2 and Gr = G M^-1/2 make the Gram products J M^-1 J^T = Jr Jr^T and
    G M^-1 G^T = Gr Gr^T, and M^-1 J^T = M^-1/2 Jr^T, G = Gr M^1/2, so that one sparse matrix
    each serves every product of the step."""

    keys: tuple[int, ...]
    start: np.ndarray
    slices: dict[int, slice]
    inv_mass: np.ndarray
    root: np.ndarray
    x: np.ndarray
    Q: np.ndarray  # (bodies, 3, 3)
    row: np.ndarray
    col: np.ndarray
    g: np.ndarray
    Jr: sp.csr_matrix
    Gr: sp.csr_matrix

    @property
    def n(self) -> int:
        return int(self.start[-1])


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
    # made once a step and reused by its solves: the stacked sides, K and the couples' operators
    _cache: dict = field(default_factory=dict, repr=False)

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
            rows = new[s.rows]
            if (rows >= 0).any():
                row = new[s.entry_row]
                keep = row >= 0
                sides[b] = Side(rows=rows[rows >= 0], nodes=s.nodes, inv_mass=s.inv_mass, x=s.x, Q=s.Q, lut=s.lut,
                                entry_row=row[keep], entry_node=s.entry_node[keep], entry_j=s.entry_j[keep],
                                entry_g=s.entry_g[keep])
        return PairRows(ids=self.ids[idx], owner=self.owner[idx], bodies=self.bodies[idx], Jw=self.Jw[idx],
                        Ja=self.Ja[idx], b=self.b[idx], overlap=self.overlap[idx], D=self.D[idx],
                        slip_w=self.slip_w[idx], slip_a=self.slip_a[idx], mu=self.mu[idx], sides=sides)

    def stacked(self) -> Stacked:
        """The sides stacked (``Stacked``), made once."""
        if "stacked" not in self._cache:
            self._cache["stacked"] = _stack(self)
        return self._cache["stacked"]


def _stack(rows: PairRows) -> Stacked:
    """``Stacked`` from the sides: their entries merged into row order (a stable sort of the
    sides' runs of rows), and the CSR matrices J M^-1/2 and G M^-1/2."""
    keys = tuple(sorted(rows.sides))
    sides = [rows.sides[k] for k in keys]
    start = np.concatenate([[0], np.cumsum([len(s.nodes) for s in sides])]).astype(np.int64)
    n = int(start[-1])
    inv_mass = np.concatenate([s.inv_mass for s in sides])
    root = np.sqrt(inv_mass)
    row = np.concatenate([s.entry_row for s in sides])
    order = np.argsort(row, kind="stable")  # merges the sides' runs of rows
    row = np.take(row, order)
    # np.take: a fancy index of rows of a 2-D array costs several times more
    col = np.take(np.concatenate([s.entry_node + start[i] for i, s in enumerate(sides)]), order)
    g = np.take(np.concatenate([s.entry_g for s in sides]), order)
    w = np.take(root, col)
    col32 = col.astype(np.int32)
    ptr = np.concatenate([[0], np.cumsum(np.bincount(row, minlength=rows.m))]).astype(np.int32)
    cols = np.empty((len(col), 3), dtype=np.int32)  # node n's components: columns 3 n, 3 n + 1, 3 n + 2
    for c in range(3):
        np.add(3 * col32, c, out=cols[:, c])
    Jr = np.take(np.concatenate([s.entry_j for s in sides]), order, axis=0) * w[:, None]
    return Stacked(keys=keys, start=start, slices={k: slice(int(start[i]), int(start[i + 1])) for i, k in enumerate(keys)},
                   inv_mass=inv_mass, root=root, x=np.concatenate([s.x for s in sides]),
                   Q=np.stack([s.Q for s in sides]) if sides else np.zeros((0, 3, 3)), row=row, col=col, g=g,
                   Jr=sp.csr_matrix((Jr.ravel(), cols.ravel(), 3 * ptr), shape=(rows.m, 3 * n)),
                   Gr=sp.csr_matrix((g * w, col32, ptr), shape=(rows.m, n)))


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
    """``PairRows`` from the summed entries: the rows' sums, and each body's side over the nodes
    its entries touch (entries with no material, zero weight, dropped)."""
    e = entries
    pair_ab = np.array([(a, b) for a, b, _ in pairs], dtype=np.int64).reshape(-1, 2)
    pair_mu = np.array([mu for *_, mu in pairs], dtype=np.float64)
    keys = np.array([b.key for b in bodies], dtype=np.int64)
    row_pair, cell = np.divmod(e.row_keys, e.row_stride)
    total = e.row_values[:, 13]
    per_area = 1.0 / np.where(total > 0.0, total, 1.0)  # a sample's share of its row: |c| / the row's sum
    out = PairRows(
        ids=PAIR_ID * (1 + keys[pair_ab[row_pair, 1]]) + cell,
        owner=pair_ab[row_pair, 0], bodies=pair_ab[row_pair], Jw=e.row_values[:, 0].copy(),
        Ja=e.row_values[:, 1].copy(), b=-e.row_values[:, 2], overlap=e.row_values[:, 3].copy(),
        D=e.row_values[:, 4:7].copy(), slip_w=e.row_values[:, 7:10] * per_area[:, None],
        slip_a=e.row_values[:, 10:13] * per_area[:, None], mu=pair_mu[row_pair])
    keep = e.node_values[:, 4] > 0.0  # a corner without material
    # np.compress: a boolean index of the (E, 5) sums costs several times more
    key, vals, mass = np.compress(keep, e.node_keys), np.compress(keep, e.node_values, axis=0), np.compress(keep, e.node_mass)
    rest, node = np.divmod(key, e.nodes)
    body, row = np.divmod(rest, e.rows)
    row = np.searchsorted(e.row_keys, row)
    g = vals[:, 3] * per_area[row]
    # entries are sorted by body, row, node: each body's a contiguous block, in CSR order
    count = np.bincount(body, minlength=len(bodies))
    end = np.cumsum(count)
    for b in np.flatnonzero(count):
        sl = slice(int(end[b] - count[b]), int(end[b]))
        out.sides[int(b)] = _side(bodies[b], row[sl], node[sl], mass[sl], vals[sl, :3], g[sl])
    return out


def _side(info: BodyInfo, row: np.ndarray, node: np.ndarray, mass: np.ndarray, j: np.ndarray, g: np.ndarray) -> Side:
    """A body's ``Side`` from its entries (sorted by row, then node): their rows, grid nodes and
    the nodes' masses, coefficients j and slip weights g."""
    size = math.prod(info.node_shape)
    touched = np.zeros(size, dtype=bool)  # the touched nodes, sorted (a mark per grid node: no sort)
    touched[node] = True
    touched = np.flatnonzero(touched)
    lut = np.full(size, -1, dtype=np.int32)  # int32: half the memory to fill (grids of < 2^31 nodes)
    lut[touched] = np.arange(len(touched))
    local = lut[node]
    inv_mass = np.zeros(len(touched))
    inv_mass[local] = 1.0 / mass
    first = np.ones(len(row), dtype=bool)  # the rows of the side: each run's first entry
    np.not_equal(row[1:], row[:-1], out=first[1:])
    return Side(rows=row[first], nodes=touched, inv_mass=inv_mass, x=info.node_positions(touched), Q=info.Q, lut=lut,
                entry_row=row, entry_node=local, entry_j=j, entry_g=g)


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
        self._streams: list[wp.Stream] = []

    def streams(self, n: int) -> list[wp.Stream]:
        """n CUDA streams of the device (made once, kept): the bodies' sample launches run on them
        side by side."""
        while len(self._streams) < n:
            self._streams.append(wp.Stream(self.device))
        return self._streams[:n]

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


def own_rows_at(side: Side, packed: np.ndarray, nodes: np.ndarray) -> sp.csr_matrix:
    """A body's own rows (the device's packed blocks: ``packed`` (m, 3 nb + 2) with their block
    ``nodes`` (m, nb), ``wsim.eol.contact.block_nodes``, -1 past the grid) at the nodes the rows
    between bodies touch: (m, 3 n) over ``side.nodes``, CSR (a row's block holds a few dozen
    of the thousands of nodes the rows between bodies touch: dense, the products with it and
    its making cost milliseconds a step in a pile)."""
    m, nb = nodes.shape
    pos = np.where(nodes >= 0, side.lut[np.maximum(nodes, 0)], -1)
    row, slot = np.nonzero(pos >= 0)
    cols = (3 * pos[row, slot])[:, None] + np.arange(3)
    return sp.csr_matrix((packed[:, : 3 * nb].reshape(m, nb, 3)[row, slot].ravel(), (np.repeat(row, 3), cols.ravel())),
                         shape=(m, 3 * len(side.nodes)))


def joint_system(own: list[ContactSystem | None], own_at: list[np.ndarray | None], bodies: list[int],
                 rows: PairRows) -> ContactSystem:
    """One QP for touching bodies: the rows of each body in ``bodies`` (its ``own`` system, sorted
    by id, and those rows at the shared nodes ``own_at``), then the rows between them. S gets each
    body's block, the rows between bodies' sum_b J_b M_b^-1 J_b^T (= J M^-1 J^T with J the
    bodies' coefficients side by side, ``PairRows.stacked``: one sparse product) and the cross
    terms between a body's own rows and them at the nodes both touch. Past ``SPARSE_ROWS`` rows S
    is sparse (scipy CSR; ``ActiveSolver`` then factorizes by sparse LU): a row shares nodes only
    with the rows of neighbouring collision cells."""
    sizes = [0 if s is None else s.m for s in own]
    start = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    n_own, m = int(start[-1]), rows.m
    n = n_own + m
    sparse = n > SPARSE_ROWS
    coo: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (row ids, column ids, values) when sparse
    st = rows.stacked()
    between = st.Jr @ st.Jr.T  # the rows between bodies' block, sum_b J_b M_b^-1 J_b^T = Jr Jr^T
    if sparse:
        S = None
        between = between.tocoo()
        coo.append((n_own + between.row, n_own + between.col, between.data))
    elif n_own:
        S = np.zeros((n, n))
        S[n_own:, n_own:] = between.toarray()
    else:
        S = between.toarray()

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
        if own[k] is None:
            continue
        sl = np.arange(start[k], start[k + 1])
        add(sl, sl, own[k].S)
        side = rows.sides.get(b)
        if side is not None and own_at[k] is not None and own_at[k].nnz:  # (own rows far from the others share no node)
            C = own_at[k] @ side.JMinv().T  # (own rows, the side's rows): J_own M^-1 J_b^T
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


def node_changes(rows: PairRows, lam: np.ndarray) -> np.ndarray:
    """(..., N, 3) velocity change of the touched nodes of every body (``PairRows.stacked``,
    velocity axes) from multipliers ``lam`` (..., m) of the rows between bodies: -M^-1 J^T lambda
    = -M^-1/2 Jr^T lambda (a stack of multipliers, such as lambda_0 and lambda_1, in one
    product)."""
    st = rows.stacked()
    flat = st.Jr.T @ lam.reshape(-1, rows.m).T  # (3 N, k)
    dv = flat.T.reshape(lam.shape[:-1] + (st.n, 3))
    dv *= -st.root[:, None]
    return dv


def own_changes(rows: PairRows, b: int, own_at: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """(n, 3) velocity change of body b's nodes touched by the rows between bodies (velocity axes)
    from the multipliers ``lam`` of its own rows (``own_rows_at``): -M^-1 J_own^T lambda there."""
    return -rows.sides[b].inv_mass[:, None] * (own_at.T @ lam).reshape(-1, 3)


def _friction_matrix(rows: PairRows) -> tuple[np.ndarray | sp.csr_matrix, np.ndarray, np.ndarray]:
    """The friction's K = G M^-1 G^T (G: the bodies' slip weights side by side,
    ``PairRows.stacked``), dense up to ``SPARSE_ROWS`` rows, as (diag(s) K, K's diagonal, s) with
    s_i = 1 / sum_j |K_ij| each row's step; made once a step."""
    if "K" not in rows._cache:
        st = rows.stacked()
        K = (st.Gr @ st.Gr.T).tocsr()
        row = np.repeat(np.arange(rows.m), np.diff(K.indptr))
        step = 1.0 / np.maximum(np.bincount(row, np.abs(K.data), minlength=rows.m), 1e-300)
        if rows.m > SPARSE_ROWS:  # a row's slip shares nodes with its neighbours' only: K @ P sparse
            scaled = sp.csr_matrix((K.data * step[row], K.indices, K.indptr), shape=K.shape)
        else:
            scaled = K.toarray()
            scaled *= step[:, None]
        rows._cache["K"] = (scaled, K.diagonal(), step)
    return rows._cache["K"]


def row_friction(rows: PairRows, lam: np.ndarray, slip: np.ndarray) -> np.ndarray:
    """Coulomb friction impulses P (m, 3) (world, on A; -P on B) of the rows between bodies: slip
    (m, 3) is each row's relative velocity v_A - v_B after the normal impulses (at the QP's dt),
    lam the rows' normal multipliers (A's normal impulse is lam |D|). P is tangential to the row's
    normal D / |D|, at most mu lam |D|, and removes as much of the tangential slip as that allows:
    the minimum of 1/2 P.K P + slip.P over those discs, K = sum_b G_b M_b^-1 G_b^T the rows'
    coupled tangential response (the slip of row i changes by K_ij P_j), whose minimum is
    Coulomb's law per row (stick where the slip can be removed inside the disc, else slide at the
    bound against the remaining slip).

    Solved by accelerated projected gradient (FISTA, Beck & Teboulle 2009, with the adaptive
    restart of O'Donoghue & Candes 2015), each row's step s_i = 1 / sum_j |K_ij| (a diagonal
    metric that bounds K, so the step cannot overshoot where rows share nodes): Y the
    extrapolated point, P <- clamp(Y - s (I - n n^T)(K Y + slip)), Y <- P + (t_k - 1) / t_{k+1}
    (P - P_prev), restarted (Y = P) where the step turns back against the last change. The
    sweeps stop after the first that changes no component of P by more than
    ``FRICTION_TOLERANCE`` of the largest bound, or after ``FRICTION_SWEEPS``. On the rows of a
    16-object pile the plain projected sweeps it replaced were never done within the 30 sweeps,
    their impulses 2-20 % of the largest bound from the minimum's; these are 0.01-7 % from it
    after as many, as the plain sweeps are after 100-300."""
    m = rows.m
    size = np.linalg.norm(rows.D, axis=1)
    bound = rows.mu * np.maximum(lam, 0.0) * size
    if not np.any(bound > 0.0):
        return np.zeros((m, 3))
    n = (rows.D / np.maximum(size, 1e-300)[:, None]).T  # (3, m)
    sK, diag, step = _friction_matrix(rows)
    tol = FRICTION_TOLERANCE * float(bound.max())
    # At tens to hundreds of rows each numpy call's overhead, not its arithmetic, is a sweep's
    # cost, so the sweeps make few calls: contiguous (3, m) arrays (a component per row) in
    # buffers made once, the step folded into K and the slip (diag(s) K, s slip: the projection
    # commutes with a row's scale).
    s_slip = (step[:, None] * slip).T
    dense = not sp.issparse(sK)
    sKT = sK.T
    P, new, Y = np.zeros((3, m)), np.empty((3, m)), np.zeros((3, m))
    u, d = np.empty((3, m)), np.empty((3, m))
    un = np.empty(m)
    t = 1.0
    for _ in range(FRICTION_SWEEPS):
        if dense:
            np.matmul(Y, sKT, out=u)  # (diag(s) K Y)^T
        else:
            u[...] = (sK @ Y.T).T
        u += s_slip
        np.multiply(u, n, out=d)
        np.add.reduce(d, axis=0, out=un)
        np.multiply(n, un, out=d)
        u -= d  # tangential: P and Y stay tangential, and so the update
        np.subtract(Y, u, out=new)
        np.multiply(new, new, out=d)
        np.add.reduce(d, axis=0, out=un)
        np.sqrt(un, out=un)
        np.maximum(un, 1e-300, out=un)
        np.divide(bound, un, out=un)
        np.minimum(un, 1.0, out=un)
        new *= un
        np.subtract(new, P, out=d)  # the change
        if np.abs(d).max() <= tol:
            P, new = new, P
            break
        np.subtract(Y, new, out=u)
        t_next = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
        if np.vdot(u, d) > 0.0:  # the step went back against the last change: restart
            Y[...] = new
            t_next = 1.0
        else:
            np.multiply(d, (t - 1.0) / t_next, out=Y)
            Y += new
        t = t_next
        P, new = new, P
    P = np.ascontiguousarray(P.T)
    P[diag <= 0.0] = 0.0
    return P


def friction_changes(rows: PairRows, P: np.ndarray) -> np.ndarray:
    """(N, 3) velocity change of the touched nodes of every body (``PairRows.stacked``, velocity
    axes) from the friction impulses P of the rows between bodies: M^-1 G^T P = M^-1/2 Gr^T P,
    each body's turned into its axes."""
    st = rows.stacked()
    out = st.Gr.T @ P  # world
    for i, sl in enumerate(st.slices.values()):
        out[sl] = out[sl] @ st.Q[i]
    out *= st.root[:, None]
    return out


def slip_change(rows: PairRows, dv: np.ndarray) -> np.ndarray:
    """(m, 3) change of the rows' relative slip v_A - v_B (world) from velocity changes dv (N, 3)
    of the touched nodes of every body (``PairRows.stacked``, velocity axes),
    sum_b G_b (dv_b Q_b^T) = Gr M^1/2 (dv Q^T)."""
    st = rows.stacked()
    world = np.empty_like(dv)
    for i, sl in enumerate(st.slices.values()):
        world[sl] = dv[sl] @ st.Q[i].T
    world /= st.root[:, None]
    return st.Gr @ world


def moment_couples(rows: PairRows, changes: np.ndarray) -> np.ndarray:
    """Velocity changes (..., N, 3) of the touched nodes of every body (``PairRows.stacked``,
    velocity axes) that keep each pair's angular momentum: a row's impulse acts on each body at
    the mass centroid of the cell its sample lies in (the mass-weighted weights that keep nodes
    holding a sliver of material from being flung), which differ between the two bodies by a
    fraction of a cell, so the equal and opposite impulses ``changes`` (..., N, 3) (from
    ``node_changes`` and ``friction_changes``) carry a net moment tau. Each pair gets the couple
    -tau, as rigid rotations omega x (x - xbar_b) of the nodes its rows touch in either body
    (about each region's mass centroid xbar_b): no net force, the least kinetic energy for that
    moment (one omega, (I_A + I_B) omega = -tau with I_b the regions' inertia tensors). With the
    centroids left uncorrected a frictionless glancing blow of two 6-cell spheres gained 4.9 % of
    |L|; weights moved onto the sample instead put the push back on light nodes.

    Both steps are linear and fixed within a step (``_couple_operators``, made once): tau = C dv,
    C holding the blocks m_k [x_k]_x Q_b of each region's nodes (x_k world, [x]_x a = x x a),
    and the couple W (I_A + I_B)^-1 tau, W holding the blocks Q_b^T [r_k]_x (r_k = x_k - xbar_b;
    a node in several regions, a body touching two others there, gets the sum of their
    couples). A leading stack axis ((..., N, 3): dv0 and dv1 of a step at once) gives each slice
    its own couple."""
    if "couples" not in rows._cache:
        rows._cache["couples"] = _couple_operators(rows)
    C, inverse, W = rows._cache["couples"]
    lead, n = changes.shape[:-2], changes.shape[-2]
    flat = changes.reshape(-1, 3 * n).T  # (3 N, k)
    tau = (C @ flat).reshape(len(inverse), 3, -1)  # (R, 3, k)
    return (W @ (inverse @ tau).reshape(-1, flat.shape[1])).T.reshape(lead + (n, 3))


def _levi_civita() -> np.ndarray:
    """(3, 3, 3) eps_ijk: (a x b)_i = eps_ijk a_j b_k."""
    eps = np.zeros((3, 3, 3))
    eps[0, 1, 2] = eps[1, 2, 0] = eps[2, 0, 1] = 1.0
    eps[0, 2, 1] = eps[2, 1, 0] = eps[1, 0, 2] = -1.0
    return eps


def _couple_operators(rows: PairRows) -> tuple[sp.bsr_matrix, np.ndarray, sp.bsr_matrix]:
    """The couples' C (3 R x 3 N, block sparse), the inverses (R, 3, 3) of the regions' summed
    inertia and W (3 N x 3 R, block sparse) of ``moment_couples`` (R regions: the pairs, sorted):
    per region the nodes its rows weight (nonzero G) in either body, each body's part about its
    mass centroid (pseudo-inverse: a region of one node has no inertia about some axis)."""
    st = rows.stacked()
    N, nb = st.n, len(st.keys)
    pair = rows.bodies[:, 0] * (int(rows.bodies.max()) + 1) + rows.bodies[:, 1]
    pair_keys = np.unique(pair)
    R = len(pair_keys)
    nz = st.g != 0.0
    mark = np.zeros(N * R, dtype=bool)  # (node, region) keys, node-major: a mark each, no sort
    mark[st.col[nz] * R + np.searchsorted(pair_keys, pair)[st.row[nz]]] = True
    node, region = np.divmod(np.flatnonzero(mark), R)
    body = np.searchsorted(st.start, node, side="right") - 1
    m = 1.0 / st.inv_mass[node]
    x = np.take(st.x, node, axis=0)
    mx = m[:, None] * x
    # the sums per region and per part (a region's nodes in one body) over contiguous runs:
    # region-major order (none needed for one region), in which the parts ascend too (nodes are
    # body-major)
    order = np.argsort(region, kind="stable") if R > 1 else None

    def by_region(a: np.ndarray) -> np.ndarray:
        return a if order is None else np.take(a, order, axis=0)

    part = by_region(region * nb + body)
    first = np.flatnonzero(np.concatenate([[True], part[1:] != part[:-1]]))
    msum = np.add.reduceat(by_region(m), first)
    centroid = np.zeros((R * nb, 3))
    centroid[part[first]] = np.add.reduceat(by_region(mx), first) / np.where(msum > 0.0, msum, 1.0)[:, None]
    r = x - np.take(centroid, region * nb + body, axis=0)
    # inertia: the sum over the region of m ((r . r) I - r r^T), from the sums of m r r^T (a
    # (3, n) @ (n, 3) product per region)
    mr, rr = by_region(m[:, None] * r), by_region(r)
    bounds = np.searchsorted(by_region(region), np.arange(R + 1))
    second = np.stack([mr[bounds[q]:bounds[q + 1]].T @ rr[bounds[q]:bounds[q + 1]] for q in range(R)])
    inertia = np.trace(second, axis1=1, axis2=2)[:, None, None] * np.eye(3) - second
    # the blocks m [x]_x Q_b of C and Q_b^T [r]_x of W, a body at a time (nodes are body-major),
    # each a (n, 3) @ (3, 9) product (numpy's stacked 3 x 3 products cost ~50 ns a matrix): with
    # [v]_x[i, k] = eps_ijk v_j, (m [x]_x Q)[i, c] = (m x)_j eps_ijk Q_kc and
    # (Q^T [r]_x)[i, c] = r_j Q_ki eps_kjc
    eps = _levi_civita()
    left = np.einsum("ijk,bkc->bjic", eps, st.Q).reshape(nb, 3, 9)
    right = np.einsum("bki,kjc->bjic", st.Q, eps).reshape(nb, 3, 9)
    cb, wb = np.empty((len(node), 9)), np.empty((len(node), 9))
    lo = np.searchsorted(body, np.arange(nb + 1))
    for i in range(nb):
        np.matmul(mx[lo[i]:lo[i + 1]], left[i], out=cb[lo[i]:lo[i + 1]])
        np.matmul(r[lo[i]:lo[i + 1]], right[i], out=wb[lo[i]:lo[i + 1]])
    C = sp.bsr_matrix((by_region(cb).reshape(-1, 3, 3), by_region(node).astype(np.int32),  # block rows: regions
                       np.concatenate([[0], np.cumsum(np.bincount(region, minlength=R))]).astype(np.int32)),
                      shape=(3 * R, 3 * N))
    W = sp.bsr_matrix((wb.reshape(-1, 3, 3), region.astype(np.int32),  # block rows: nodes
                       np.concatenate([[0], np.cumsum(np.bincount(node, minlength=N))]).astype(np.int32)),
                      shape=(3 * N, 3 * R))
    return C, np.linalg.pinv(inertia, rcond=1e-12), W
