"""Point constraints solved against a dense linear response: the seam between a body's dynamics
and its contacts, fixed points and joints (Sugimoto et al. 2022, Sec. 3.4).

A body that takes part (a ``Participant``: today ``BemBody``) opens its step with
``constraint_begin``, which predicts the unconstrained step and returns its own constrained points
(fixed, driven, in contact). ``solve_group`` adds the ``PointJoint`` s between participants, asks each
for the linear response K of its points (V(f) = V0 + K f, world forces f [N] held over the step),
assembles the constraints' response from the blocks (``wsim.kernels.pgs.assemble_delassus``), runs
projected Gauss-Seidel on the device and hands each participant its points' forces
(``constraint_end``). Nothing here knows which method produced K, so bodies of other methods can
join the same solve by implementing the four methods of ``Participant``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, Sequence

import numpy as np
import warp as wp

from wsim.errors import InvalidParameter
from wsim.kernels import pgs

CONTACT = 0
FIXED = 1


@dataclass
class PointSet:
    """The constraints of m points (``wsim.kernels.pgs``'s kinds and data), host arrays.

    Attributes:
        kind: (m,) CONTACT or FIXED.
        normal, height: (m, 3), (m,) the half-space n . x >= height of a CONTACT point (world) [m].
        target: (m, 3) a FIXED point's target, or a CONTACT point's no-slip position [m].
        mu: (m,) Coulomb friction coefficient of a CONTACT point.
    """

    kind: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    height: np.ndarray = field(default_factory=lambda: np.zeros(0))
    target: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    mu: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    def add(self, kind: int, normal: np.ndarray, height: np.ndarray, target: np.ndarray, mu: np.ndarray) -> None:
        """Append points (arrays of one length)."""
        k = len(np.atleast_1d(height))
        self.kind = np.concatenate([self.kind, np.full(k, kind, dtype=np.int32)])
        self.normal = np.concatenate([self.normal, np.asarray(normal, dtype=np.float64).reshape(k, 3)])
        self.height = np.concatenate([self.height, np.asarray(height, dtype=np.float64).reshape(k)])
        self.target = np.concatenate([self.target, np.asarray(target, dtype=np.float64).reshape(k, 3)])
        self.mu = np.concatenate([self.mu, np.broadcast_to(np.asarray(mu, dtype=np.float64), (k,))])


@dataclass(frozen=True)
class PointRefs:
    """Points of one body as weighted sums of up to three of its nodes: a node is (n, n, n) with
    weights (1, 0, 0); a point inside a face is the face's nodes with barycentric weights (a
    collider corner pressing on the face). Forces spread to the nodes with the same weights.

    Attributes:
        ids: (m, 3) int64 node indices.  w: (m, 3) float64 weights (each row sums to 1).
    """

    ids: np.ndarray
    w: np.ndarray

    @staticmethod
    def nodes(nodes: np.ndarray) -> PointRefs:
        n = np.asarray(nodes, dtype=np.int64).reshape(-1)
        w = np.zeros((len(n), 3))
        w[:, 0] = 1.0
        return PointRefs(np.repeat(n[:, None], 3, axis=1), w)

    @staticmethod
    def empty() -> PointRefs:
        return PointRefs(np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3)))

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def __getitem__(self, index) -> PointRefs:
        return PointRefs(self.ids[index], self.w[index])

    def concat(self, other: PointRefs) -> PointRefs:
        return PointRefs(np.concatenate([self.ids, other.ids]), np.concatenate([self.w, other.w]))

    @property
    def is_node(self) -> np.ndarray:
        """(m,) whether each point is a plain node."""
        return self.w[:, 0] == 1.0

    def positions(self, V: np.ndarray) -> np.ndarray:
        """(m, 3) positions from the nodes' positions V (N, 3)."""
        return np.einsum("mk,mkd->md", self.w, V[self.ids])

    def spread(self, forces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(nodes, node forces): the distinct nodes the points touch and the forces (k, 3) the
        point forces (m, 3) put on them."""
        used, inverse = np.unique(self.ids, return_inverse=True)
        out = np.zeros((len(used), 3))
        np.add.at(out, inverse.reshape(self.ids.shape), self.w[:, :, None] * forces[:, None, :])
        return used, out


@dataclass(frozen=True)
class SolveRecord:
    """One constraint solve: the step, its points (contacts among them), the Gauss-Seidel sweeps,
    the last sweep's residual [m] (the largest position change it made) and whether it reached the
    tolerance."""

    step: int
    points: int
    contacts: int
    sweeps: int
    residual: float
    converged: bool


def _views(buf: wp.array, sizes: Sequence[tuple[int, Any]]) -> list[wp.array]:
    """Consecutive typed views into one float64 device buffer (one transfer instead of several)."""
    out, offset = [], 0
    for n, dtype in sizes:
        width = 3 if dtype is wp.vec3d else 1
        out.append(wp.array(ptr=buf.ptr + 8 * offset, shape=(n,), dtype=dtype, device=buf.device, copy=False))
        offset += width * n
    return out


def solve_points(K: wp.array, Kt: wp.array | None, V0: np.ndarray, points: PointSet, f0: np.ndarray, tol: float,
                 max_iter: int, device: wp.Device) -> tuple[np.ndarray, np.ndarray, int, float]:
    """Forces (m, 3) [N] from projected Gauss-Seidel started at ``f0``; also the linear model's
    positions V0 + K f (m, 3) [m], the sweeps and the last sweep's residual [m]. With ``Kt`` (K^T)
    one block runs the sweeps (``pgs_block``; on the CPU a block is one lane), else one thread
    (``pgs_points``, the reference): the same sweeps in the same order. The inputs go to the
    device in one buffer and the results come back in one (each transfer costs ~20 us)."""
    m = len(V0)
    pack = np.concatenate([np.ravel(V0), np.ravel(points.normal), np.ravel(points.target), points.height, points.mu])
    inp = wp.array(pack.astype(np.float64), dtype=wp.float64, device=device)
    V0_d, normal, target, height, mu = _views(inp, [(m, wp.vec3d), (m, wp.vec3d), (m, wp.vec3d), (m, wp.float64),
                                                  (m, wp.float64)])
    res = np.zeros(6 * m + 2)
    res[: 3 * m] = np.ravel(f0)
    out = wp.array(res, dtype=wp.float64, device=device)
    f, V, stats = _views(out, [(m, wp.vec3d), (m, wp.vec3d), (2, wp.float64)])
    kind = wp.array(points.kind.astype(np.int32), dtype=wp.int32, device=device)
    data = [V0_d, kind, normal, height, target, mu, int(max_iter), wp.float64(tol), f, stats]
    if Kt is not None:
        wp.launch_tiled(pgs.pgs_block, dim=1, block_dim=pgs.PGS_BLOCK, device=device, inputs=[K, Kt, *data, V])
    else:
        wp.launch(pgs.pgs_points, dim=1, device=device, inputs=[K, *data, V])
    r = out.numpy()
    return r[: 3 * m].reshape(m, 3), r[3 * m: 6 * m].reshape(m, 3), int(r[6 * m]), float(r[6 * m + 1])


class Participant(Protocol):
    """A body whose step can be constrained at surface points (the seam of ``solve_group``)."""

    name: str
    dt: float
    steps: int
    constraint_tolerance: float
    constraint_iterations: int
    failed: bool

    def joint_points(self, vertex_ids: np.ndarray) -> PointRefs:
        """The points a joint holds at these mesh vertices."""

    def constraint_begin(self) -> tuple[PointRefs, PointSet, np.ndarray]:
        """Predict the coming step; returns (points, constraints on them, predicted world positions of
        every node of the body (N, 3))."""

    def contact_surface(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float | None, int]:
        """(predicted node positions, faces, node positions at the step start, friction, the faces'
        inside test ``wsim.mesh.inside_test``) of the opened step, for contact between bodies
        (``wsim.contact``)."""

    def constraint_response(self, points: PointRefs) -> tuple[wp.array, wp.array]:
        """K (3m, 3m) [m/N] of ``points`` on the device (V = V0 + K f) and its transpose."""

    def constraint_positions(self, points: PointRefs, forces: np.ndarray) -> np.ndarray:
        """True end-of-step world positions of ``points`` with world forces (m, 3) [N] applied there."""

    def constraint_nonlinearity(self, points: PointRefs, forces: np.ndarray) -> float:
        """An upper bound [m] on how far the true positions of these forces can be from V0 + K f."""

    def constraint_warm(self, points: PointRefs, kind: np.ndarray) -> np.ndarray:
        """The forces (m, 3) [N] the points carried last step in constraints of the same kind
        (CONTACT, FIXED, JOINT), to start the solve from (zeros if none)."""

    def constraint_end(self, points: PointRefs, forces: np.ndarray, kind: np.ndarray, record: SolveRecord) -> None:
        """Apply the forces and finish the step; ``kind`` (m,) says what each force came from:
        CONTACT, FIXED or JOINT (for the body's impulse read-outs)."""


JOINT = 2


@dataclass(frozen=True)
class PointJoint:
    """Vertices of two bodies held together: equal positions, equal and opposite forces (paper Sec.
    3.4, point joints). ``vertices_a[k]`` of ``body_a`` is joined to ``vertices_b[k]`` of ``body_b``.
    Add it with ``World.add_joint``; both bodies must be in that World and step with one dt."""

    body_a: Any
    vertices_a: np.ndarray
    body_b: Any
    vertices_b: np.ndarray
    name: str = "joint"

    def __post_init__(self) -> None:
        a = np.asarray(self.vertices_a)
        b = np.asarray(self.vertices_b)
        for what, v in (("vertices_a", a), ("vertices_b", b)):
            if v.ndim != 1 or v.size == 0 or not np.issubdtype(v.dtype, np.integer):
                raise InvalidParameter(f"joint '{self.name}': {what} must be a non-empty 1-D list of vertex ids")
        if a.shape != b.shape:
            raise InvalidParameter(f"joint '{self.name}': {len(a)} vertices of '{self.body_a.name}' against "
                                   f"{len(b)} of '{self.body_b.name}'; they pair one to one")
        if self.body_a is self.body_b:
            raise InvalidParameter(f"joint '{self.name}': joins body '{self.body_a.name}' to itself")
        object.__setattr__(self, "vertices_a", a.astype(np.int64))
        object.__setattr__(self, "vertices_b", b.astype(np.int64))


@dataclass
class _Side:
    """One participant's share of a group solve."""

    body: Any
    own: PointRefs  # own constrained points
    own_set: PointSet
    V: np.ndarray  # predicted positions of all its nodes
    points: PointRefs = field(default_factory=PointRefs.empty)  # own + joint points


def solve_group(bodies: Sequence[Any], joints: Sequence[tuple[Any, PointRefs, Any, PointRefs]], device: wp.Device,
                tol: float, max_iter: int, step: int, refinements: int = 3, contact_margin: float | None = None) -> None:
    """One constrained step of ``bodies`` (participants) coupled by ``joints`` ((body_a, points_a,
    body_b, points_b)) and, with ``contact_margin`` [m], by contact between them (``wsim.contact``).
    See the module docstring.

    The linear model is refined by the true positions of the solved forces (``constraint_positions``)
    up to ``refinements`` times, until it misses them by less than ``tol``.
    """
    sides = [_Side(b, *b.constraint_begin()) for b in bodies]
    pairs = [(ja, pa, jb, pb, None) for ja, pa, jb, pb in joints]
    if contact_margin is not None and len(sides) > 1:
        from wsim.contact import body_contacts

        # jointed bodies (the pieces of a decomposed body) do not collide: their interfaces touch
        skip = {frozenset((id(a), id(b))) for a, _, b, _ in joints}
        found = body_contacts([(s.body, *s.body.contact_surface()) for s in sides], contact_margin, device, skip)
        pairs += [(c.body_a, c.refs_a, c.body_b, c.refs_b, c) for c in found]
    # bodies no joint or contact links this step are solved apart (each on its own K, with no
    # zero blocks between them in the sweeps)
    parent = list(range(len(sides)))
    slot = {id(s.body): k for k, s in enumerate(sides)}

    def find(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for pair in pairs:
        parent[find(slot[id(pair[0])])] = find(slot[id(pair[2])])
    free = []  # bodies nothing holds or touches this step: a free step, finished together below
    for root in sorted({find(k) for k in range(len(sides))}):
        members = [s for k, s in enumerate(sides) if find(k) == root]
        linked = [p for p in pairs if find(slot[id(p[0])]) == root]
        if not linked and len(members) == 1 and not len(members[0].own):
            free.append(members[0])
            continue
        _solve_component(members, linked, device, tol, max_iter, step, refinements)
    _end_free(free)


def _end_free(sides: list[_Side]) -> None:
    """``constraint_end`` with no points for ``sides``; a body type with ``constraint_end_free``
    ends its bodies together (BEM bodies on one operator set correct as one stack)."""
    by_type: dict[type, list[_Side]] = {}
    for s in sides:
        by_type.setdefault(type(s.body), []).append(s)
    for cls, group in by_type.items():
        together = getattr(cls, "constraint_end_free", None)
        if together is not None:
            together([s.body for s in group], [s.own for s in group])
            continue
        for s in group:
            s.body.constraint_end(s.own, np.zeros((0, 3)), np.zeros(0, dtype=np.int32), None)


def _solve_component(sides: list[_Side], pairs: list, device: wp.Device, tol: float, max_iter: int, step: int,
                     refinements: int) -> None:
    """``solve_group`` for bodies linked by joints or contacts (or one body)."""
    index = {id(s.body): k for k, s in enumerate(sides)}
    # constraints: own points first (one side), then joints and contacts between bodies (two sides)
    side_body, side_point, side_sign, side_kind = [], [], [], []
    V0c, kinds, normal, height, target, mu = [], [], [], [], [], []
    for k, s in enumerate(sides):
        n_own = len(s.own)
        s.points = s.own
        for i in range(n_own):
            side_body.append((k, 0))
            side_point.append((i, 0))
            side_sign.append((1.0, 0.0))
        side_kind.extend(s.own_set.kind.tolist())
        V0c.append(s.own.positions(s.V))
        kinds.append(s.own_set.kind)
        normal.append(s.own_set.normal)
        height.append(s.own_set.height)
        target.append(s.own_set.target)
        mu.append(s.own_set.mu)
    for body_a, pa, body_b, pb, touch in pairs:
        ka, kb = index[id(body_a)], index[id(body_b)]
        sa, sb = sides[ka], sides[kb]
        ia = len(sa.points) + np.arange(len(pa))
        ib = len(sb.points) + np.arange(len(pb))
        sa.points = sa.points.concat(pa)
        sb.points = sb.points.concat(pb)
        for i, j in zip(ia, ib):
            side_body.append((ka, kb))
            side_point.append((int(i), int(j)))
            side_sign.append((1.0, -1.0))
        V0c.append(pa.positions(sa.V) - pb.positions(sb.V))
        m = len(pa)
        if touch is None:  # a joint: the two points coincide
            kinds.append(np.full(m, FIXED, dtype=np.int32))
            normal.append(np.zeros((m, 3)))
            target.append(np.zeros((m, 3)))
            mu.append(np.zeros(m))
        else:  # contact: n . (P_a - P_b) >= 0, friction on the relative slip
            kinds.append(np.full(m, CONTACT, dtype=np.int32))
            normal.append(touch.normal)
            target.append(touch.slip_ref)
            mu.append(touch.mu)
        height.append(np.zeros(m))
        side_kind.extend([JOINT if touch is None else CONTACT] * m)
    C = len(side_body)
    if C == 0:
        for s in sides:
            s.body.constraint_end(s.points, np.zeros((0, 3)), np.zeros(0, dtype=np.int32), None)
        return
    cons = PointSet(np.concatenate(kinds).astype(np.int32), np.concatenate(normal), np.concatenate(height),
                    np.concatenate(target), np.concatenate(mu))
    V0 = np.concatenate(V0c)
    side_body_a = np.array(side_body, dtype=np.int32)
    side_point_a = np.array(side_point, dtype=np.int32)
    side_sign_a = np.array(side_sign, dtype=np.float64)
    # responses of every side's points: one body without joints solves on its own K (and K^T);
    # otherwise the blocks go into one flat device array and the constraints' response is assembled
    blocks = [s.body.constraint_response(s.points) if len(s.points) else None for s in sides]
    if len(sides) == 1 and not pairs:
        D, Dt = blocks[0]
    else:
        rows = np.array([3 * len(s.points) for s in sides], dtype=np.int32)
        offsets = np.concatenate([[0], np.cumsum(rows.astype(np.int64) ** 2)])
        flat = wp.empty(max(int(offsets[-1]), 1), dtype=wp.float64, device=device)
        for k, blk in enumerate(blocks):
            if blk is not None:
                wp.copy(flat, blk[0].flatten(), dest_offset=int(offsets[k]), count=int(rows[k]) ** 2)
        D = wp.empty((3 * C, 3 * C), dtype=wp.float64, device=device)
        Dt = wp.empty((3 * C, 3 * C), dtype=wp.float64, device=device)
        wp.launch(pgs.assemble_delassus, dim=(C, C), device=device,
                  inputs=[flat, wp.array(offsets[:-1].astype(np.int32), dtype=wp.int32, device=device),
                          wp.array(rows, dtype=wp.int32, device=device),
                          wp.array(side_body_a, dtype=wp.int32, device=device),
                          wp.array(side_point_a, dtype=wp.int32, device=device),
                          wp.array(side_sign_a, dtype=wp.float64, device=device), D, Dt])
    # warm start: each participant's last forces on the same points
    side_kind_a = np.array(side_kind, dtype=np.int32)
    lam0 = np.zeros((C, 3))
    for k, s in enumerate(sides):
        first = np.flatnonzero(side_body_a[:, 0] == k)
        if len(first):
            lam0[first] = s.body.constraint_warm(s.points[side_point_a[first, 0]], side_kind_a[first])
    shift = np.zeros_like(V0)
    sweeps_total = 0
    for _ in range(refinements):
        lam, V_lin, sweeps, residual = solve_points(D, Dt, V0 + shift, cons, lam0, tol, max_iter, device)
        sweeps_total += sweeps
        forces = [np.zeros((len(s.points), 3)) for s in sides]
        for side in range(2):
            for k in range(len(sides)):
                on = np.flatnonzero((side_sign_a[:, side] != 0.0) & (side_body_a[:, side] == k))
                np.add.at(forces[k], side_point_a[on, side], side_sign_a[on, side, None] * lam[on])
        if sum(s.body.constraint_nonlinearity(s.points, f) for s, f in zip(sides, forces)) <= 0.5 * tol:
            break  # the linear model is exact to well within tol: no need for the true positions
        true = [s.body.constraint_positions(s.points, f) if len(s.points) else np.zeros((0, 3))
                for s, f in zip(sides, forces)]
        value = np.zeros_like(V0)
        for side in range(2):
            for k in range(len(sides)):
                on = np.flatnonzero((side_sign_a[:, side] != 0.0) & (side_body_a[:, side] == k))
                value[on] += side_sign_a[on, side, None] * true[k][side_point_a[on, side]]
        miss = value - V_lin
        if np.abs(miss).max() <= tol:
            break
        shift = shift + miss
        lam0 = lam
    record = SolveRecord(step=step, points=C, contacts=int(np.sum(cons.kind == CONTACT)), sweeps=sweeps_total,
                         residual=residual, converged=residual <= tol)
    for k, s in enumerate(sides):
        kind = np.zeros(len(s.points), dtype=np.int32)
        for side in range(2):
            on = np.flatnonzero((side_sign_a[:, side] != 0.0) & (side_body_a[:, side] == k))
            kind[side_point_a[on, side]] = side_kind_a[on]
        s.body.constraint_end(s.points, forces[k], kind, record)
