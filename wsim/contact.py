"""Contact between bodies: which surface points of one body are inside (or within a margin of)
another's predicted surface, and the two-sided contact constraints that keep them out.

Detection lives here, outside the methods: a body taking part exposes its predicted surface
(``Participant.contact_surface``: node positions at the end of the coming step, their faces, the
positions at its start, its friction) and the constraint solve (``wsim.constraints.solve_group``)
takes the contacts like joints, as constraints between two bodies: n . (P_a - P_b) >= 0 for a node
P_a of one body and the nearest point P_b of the other's face (a barycentric combination of three
nodes), with n the face's outward normal, equal and opposite forces and Coulomb friction on the
relative slip. Both ways (the nodes of each body against the faces of the other), so a corner of
either cannot pass through a face of the other. Broad phase: the predicted bounding boxes, grown
by the margin.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import warp as wp

from wsim.constraints import PointRefs
from wsim.mesh.surface import face_normals, vertex_normals
from wsim.kernels import mesh as km

#: friction of a body that gives none, for contact between bodies (the larger of the two is used)
DEFAULT_FRICTION = 0.5


def pair_friction(a: float | None, b: float | None) -> float:
    """Coulomb friction between two bodies of frictions a and b (None: ``DEFAULT_FRICTION``): the larger."""
    return max(DEFAULT_FRICTION if a is None else a, DEFAULT_FRICTION if b is None else b)


def collider_friction(collider: float, body: float | None) -> float:
    """Coulomb friction between a collider and a body of friction ``body`` (every method; None:
    the collider's alone): the larger, as between two bodies (``pair_friction``) and MuJoCo's
    rule. A body given friction for contact with other bodies cannot have less on a collider, so
    a frictionless collider needs bodies that set none (or zero)."""
    return collider if body is None else max(collider, body)


@dataclass(frozen=True)
class PairContacts:
    """Two-sided contacts between bodies a and b (k of them): ``refs_a`` and ``refs_b`` are the
    touching points, ``normal`` (k, 3) points from b's surface towards a, ``slip_ref`` (k, 3) is
    the relative position P_a - P_b at the step start (no slip keeps it), ``mu`` (k,) the friction."""

    body_a: Any
    refs_a: PointRefs
    body_b: Any
    refs_b: PointRefs
    normal: np.ndarray
    slip_ref: np.ndarray
    mu: np.ndarray


def nearest_faces(mesh: wp.Mesh, points: np.ndarray, reach: float, margin: float,
                  device: wp.Device, closed: bool | int = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Indices of ``points`` (in the mesh's coordinates) inside the closed, outward ``mesh`` or
    within ``margin`` of it (searched up to ``reach``), their nearest faces, the barycentric
    weights of the nearest points on them and the faces' outward normals. ``closed``: the
    inside test of ``wsim.kernels.mesh.query_inside`` (False: one-sided; True: winding number;
    ``WATERTIGHT``: ray parity)."""
    k = len(points)
    if not k:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int32), np.zeros((0, 3)), np.zeros((0, 3))
    face = wp.empty(k, dtype=wp.int32, device=device)
    both = wp.zeros(2 * k, dtype=wp.vec3d, device=device)  # weights, then normals: one read-back
    wp.launch(km.nearest_face_points, dim=k, device=device,
              inputs=[mesh.id, wp.array(np.ascontiguousarray(points), dtype=wp.vec3d, device=device), float(reach),
                      float(margin), int(closed), face, both[:k], both[k:]])
    f = face.numpy()
    hit = np.flatnonzero(f >= 0)
    if not len(hit):
        return hit, f[hit], np.zeros((0, 3)), np.zeros((0, 3))
    values = both.numpy()
    return hit, f[hit], values[:k][hit], values[k:][hit]


HOST_QUERY_POINTS = 64  # see ``query_device``


def query_device(device: wp.Device | str, points: int) -> wp.Device:
    """Where a query of ``points`` points runs: the CPU for fewer than ``HOST_QUERY_POINTS``. Each
    point is one thread's serial walk of a BVH, so a GPU launch costs its latency whatever the
    count (H100, a 1408-face bowl: 0.37-0.55 ms for 10-42 points by ray parity, 1.0-1.6 ms by the
    winding number) while the host walks one point in ~5 us (0.27-0.38 ms; 0.41-0.80) and keeps
    the points and results where they are, on the host."""
    device = wp.get_device(device)
    return device if device.is_cpu or points >= HOST_QUERY_POINTS else wp.get_device("cpu")


def points_inside(points: np.ndarray, V: np.ndarray, faces: np.ndarray, margin: float,
                  device: wp.Device, closed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``nearest_faces`` on the closed surface (V, faces) built for the query (a body's predicted
    surface changes every step), by the inside test ``closed`` (``wsim.mesh.inside_test``), on
    ``query_device``."""
    device = query_device(device, len(points))
    mesh = wp.Mesh(points=wp.array(V.astype(np.float32), dtype=wp.vec3, device=device),
                   indices=wp.array(faces.astype(np.int32).ravel(), dtype=wp.int32, device=device),
                   support_winding_number=closed == 1)
    reach = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    return nearest_faces(mesh, points, reach, margin, device, closed=closed)


#: a point's nearest face is re-examined when its normal faces the point's own by less than this
#: (cosine of the angle between the face's normal and the opposite of the point's own)
FACING_COS = 0.0
#: how much more a neighbouring face must face the point's own surface to be taken instead
FACING_MARGIN = 0.1


def _barycentric(q: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(n, 3) barycentric weights of points q (n, 3) (or one, (3,)) projected on triangles (n, 3, 3)."""
    e0, e1, d = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], q - tri[:, 0]
    d00, d01, d11 = (e0 * e0).sum(1), (e0 * e1).sum(1), (e1 * e1).sum(1)
    d20, d21 = (d * e0).sum(1), (d * e1).sum(1)
    den = np.maximum(d00 * d11 - d01 * d01, 1e-300)
    w1 = (d11 * d20 - d01 * d21) / den
    w2 = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - w1 - w2, w1, w2], axis=1)


def facing_faces(points: np.ndarray, face: np.ndarray, bary: np.ndarray, normal: np.ndarray, V: np.ndarray,
                 F: np.ndarray, own: np.ndarray, reach: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(face, bary, normal) of ``points`` inside the surface (V, F), each moved from its nearest face
    to a face around it (sharing a vertex) that faces the point's own surface better: one whose
    outward normal is more opposed to the point's own outward normal ``own`` (k, 3), by more than
    FACING_MARGIN, among those whose plane the point is behind by at most ``reach`` (k,) [m] (how
    far it can have gone in this step). Only points whose nearest face's normal is less opposed
    than FACING_COS are re-examined.

    Near an edge the nearest face is not the one a point came through: two cubes of one mesh
    meeting face to face have every node of the touching faces but the centre on the other's
    face edges; pressed a little into it, half of them were nearer a side face than the face they
    pressed on, and took its normal, across the blow. Their friction on that normal then held
    the faces together as they sprang apart (the cubes stopped dead). A corner coming down onto an
    edge, whose own normal is opposed to both faces, keeps the nearest."""
    todo = np.flatnonzero(np.einsum("ij,ij->i", normal, own) > -FACING_COS)
    if not len(todo):
        return face, bary, normal
    face, bary, normal = face.copy(), bary.copy(), normal.copy()
    unit = face_normals(V, F)
    for i in todo:
        around = np.flatnonzero(np.isin(F, F[face[i]]).any(axis=1))
        behind = -np.einsum("ij,ij->i", unit[around], points[i] - V[F[around, 0]])  # depth behind each plane
        # the point's projection on each face's plane in that face's barycentric weights: only a face
        # that holds it is a candidate (a point off the face it pushes on would carry the pair a net
        # moment, (P_a - P_b) x f)
        w = _barycentric(points[i] + behind[:, None] * unit[around], V[F[around]])
        ok = (behind >= 0.0) & (behind <= reach[i]) & (w.min(axis=1) >= -1e-6)
        if not ok.any():
            continue
        around, w = around[ok], w[ok]
        score = unit[around] @ own[i]
        k = int(np.argmin(score))
        if score[k] >= float(normal[i] @ own[i]) - FACING_MARGIN:
            continue
        face[i], bary[i], normal[i] = around[k], np.maximum(w[k], 0.0) / np.maximum(w[k], 0.0).sum(), unit[around[k]]
    return face, bary, normal


def body_contacts(surfaces: Sequence[tuple[Any, np.ndarray, np.ndarray, np.ndarray, float | None, int]], margin: float,
                  device: wp.Device, skip: set | frozenset = frozenset()) -> list[PairContacts]:
    """Contacts between every pair of ``surfaces`` ((body, predicted node positions (N, 3), faces
    (M, 3) into the nodes, node positions at the step start (N, 3), friction or None, the faces'
    inside test ``wsim.mesh.inside_test``)), except the pairs in ``skip`` (frozensets of the two
    bodies' ids).

    The points of a surface that press on another are its nodes and, on a coarse surface, its
    faces' centroids (``surface_points``, ``centroid_faces``): with nodes alone, two coarse
    surfaces touch only where a node of one lies over a face of the other, and two 8-node cubes
    (``trimesh.creation.box``) stacked corner over corner slid down each other's edges (on the
    edge planes, no face held them) until the top one lay on the ground inside the other, and
    stacked 2 cm off had two supports on a diagonal and tipped into it. Each surface is queried once (one mesh built, one launch) with the
    points of every partner near it: a point's answer does not depend on the others queried
    with it, so the contacts are those of one query per pair and direction, in the same order
    (per pair: the nodes, then the centroids)."""
    boxes = [(V.min(axis=0) - margin, V.max(axis=0) + margin) for _, V, *_ in surfaces]
    points = [surface_points(V, F, X) for _, V, F, X, *_ in surfaces]
    queries: dict[int, list[tuple[int, np.ndarray]]] = {}  # face surface -> (point surface, its near points)
    order: list[tuple[int, int, float]] = []  # (points, faces, friction) in the output's order
    for i in range(len(surfaces)):
        for j in range(i + 1, len(surfaces)):
            if frozenset((id(surfaces[i][0]), id(surfaces[j][0]))) in skip:
                continue
            (lo_i, hi_i), (lo_j, hi_j) = boxes[i], boxes[j]
            if np.any(hi_i < lo_j) or np.any(hi_j < lo_i):
                continue
            mu = pair_friction(surfaces[i][4], surfaces[j][4])
            for p, f in ((i, j), (j, i)):
                lo, hi = boxes[f]
                P = points[p].V
                near = np.flatnonzero(np.all((P >= lo) & (P <= hi), axis=1))
                if len(near):
                    queries.setdefault(f, []).append((p, near))
                    order.append((p, f, mu))
    found: dict[tuple[int, int], tuple] = {}
    for f, asked in queries.items():
        _, V_f, F_f, _, _, test = surfaces[f]
        hit, face, bary, normal = points_inside(np.concatenate([points[p].V[near] for p, near in asked]),
                                                V_f, F_f, margin, device, test)
        start = 0
        for p, near in asked:
            mine = (hit >= start) & (hit < start + len(near))
            idx, fc, bc, nc = near[hit[mine] - start], face[mine], bary[mine], normal[mine]
            if len(idx):
                sp_ = points[p]
                # how deep a point can be behind a face it came through: its own and the face's
                # motion over the step (both bounded by the two surfaces' largest), and the margin
                reach = (np.linalg.norm(sp_.V[idx] - sp_.X[idx], axis=1)
                         + float(np.linalg.norm(V_f - surfaces[f][3], axis=1).max()) + 2.0 * margin)
                fc, bc, nc = facing_faces(sp_.V[idx], fc, bc, nc, V_f, F_f, sp_.normals()[idx], reach)
            found[(p, f)] = (idx, fc, bc, nc)
            start += len(near)
    out = []
    for p, f, mu in order:
        idx, face, bary, normal = found[(p, f)]
        if not len(idx):
            continue
        body_p = surfaces[p][0]
        body_f, _, F_f, X_f, *_ = surfaces[f]
        refs_f = PointRefs(F_f[face].astype(np.int64), bary)
        refs_p = points[p].refs(idx)
        slip = points[p].X[idx] - refs_f.positions(X_f)
        out.append(PairContacts(body_p, refs_p, body_f, refs_f, normal, slip, np.full(len(idx), mu)))
    return out


@dataclass
class SurfacePoints:
    """The points of a surface that press on others (``body_contacts``): its N nodes, then the
    centroids of its faces ``sampled`` (``centroid_faces``), at the predicted positions ``V`` and
    at the step start ``X``, with their outward normals (vertex normals, then face normals; made
    on demand) and as ``PointRefs``."""

    nodes: int
    faces: np.ndarray
    sampled: np.ndarray
    V: np.ndarray
    X: np.ndarray
    _normals: np.ndarray | None = None

    def normals(self) -> np.ndarray:
        if self._normals is None:
            V = self.V[: self.nodes]
            self._normals = np.concatenate([vertex_normals(V, self.faces), face_normals(V, self.sampled)])
        return self._normals

    def refs(self, idx: np.ndarray) -> PointRefs:
        """The points ``idx`` as weighted nodes: a node itself, a centroid its face's corners by thirds."""
        node = idx < self.nodes
        if node.all():
            return PointRefs.nodes(idx)
        ids = np.where(node[:, None], idx[:, None], self.sampled[np.where(node, 0, idx - self.nodes)]).astype(np.int64)
        w = np.where(node[:, None], [1.0, 0.0, 0.0], 1.0 / 3.0)
        return PointRefs(ids, w)


#: surfaces of fewer faces press on others with their faces' centroids too (``centroid_faces``)
CENTROID_FACES = 48


def centroid_faces(F: np.ndarray) -> np.ndarray:
    """The faces of a surface whose centroids press on other bodies and on mesh colliders besides
    its nodes (``body_contacts``, ``BemBody``'s collider contact): all of them if it has fewer than
    ``CENTROID_FACES`` (an 8-node box has 12; a box subdivided once, 48, rests on another by its
    nodes alone), else none."""
    F = np.asarray(F)
    return F if len(F) < CENTROID_FACES else F[:0]


def surface_points(V: np.ndarray, F: np.ndarray, X: np.ndarray) -> SurfacePoints:
    """``SurfacePoints`` of a surface of nodes V (predicted), X (step start) and faces F."""
    F = np.asarray(F)
    S = centroid_faces(F)
    if not len(S):
        return SurfacePoints(nodes=len(V), faces=F, sampled=S, V=V, X=X)
    return SurfacePoints(nodes=len(V), faces=F, sampled=S, V=np.concatenate([V, V[S].mean(axis=1)]),
                         X=np.concatenate([X, X[S].mean(axis=1)]))
