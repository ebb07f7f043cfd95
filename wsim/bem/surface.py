"""The BEM surface: collocation nodes, triangles, double nodes and the free term at shared nodes.

Collocation is at the mesh vertices with piecewise-linear displacement and traction (paper
Eq. 7). Where the traction is discontinuous (sharp edges and corners, paper Sec. 4 "double
nodes" [BTW84]), a vertex is split into one node per smooth sector of its incident faces: the
copies sit at the same point, share the displacement (the equations enforce it, because their
H rows differ exactly by the free term on their own columns) and carry independent tractions.
Copies are indexed right after their original vertex, as the paper does for compression.

``free_term`` gives c(x) in closed form for the interior solid-angle cone of a vertex; it is
needed only where a vertex has several nodes (elsewhere the assembly's rigid-body identity
yields c plus the principal value together).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from wsim import mesh as wmesh
from wsim.bem.quadrature import subdivided_rule
from wsim.errors import InvalidParameter


@dataclass(frozen=True)
class BemSurface:
    """Nodes and triangles of one closed BEM surface (immutable, shared by every solve on it).

    Attributes:
        nodes: (N, 3) float64 collocation node positions [m] (double-node copies repeat a point).
        faces: (M, 3) int32 node indices, outward (counter-clockwise) orientation.
        vertex: (N,) int32 index of the input mesh vertex each node sits on.
        normals: (M, 3) float64 unit face normals.
        areas: (M,) float64 face areas [m^2].
        longest_edge: (M,) float64 longest edge of each face [m].
    """

    nodes: np.ndarray
    faces: np.ndarray
    vertex: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    longest_edge: np.ndarray

    @property
    def n_nodes(self) -> int:
        return int(self.nodes.shape[0])

    def node_areas(self) -> np.ndarray:
        """int_Gamma N_v dA per node [m^2]."""
        return wmesh.vertex_areas(self.nodes, self.faces)

    def first_node(self) -> np.ndarray:
        """(N,) int32: the first node at the same vertex as each node."""
        _, first = np.unique(self.vertex, return_index=True)  # every vertex has a node
        return first[self.vertex].astype(np.int32)


def _sectors(faces: np.ndarray, normals: np.ndarray, cos_limit: float) -> np.ndarray:
    """(M, 3) sector label per face corner: corners of one vertex joined through smooth edges share it."""
    m = faces.shape[0]
    parent = np.arange(3 * m)  # union-find over face corners 3 f + k

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    # the two faces of each undirected edge: directed edge (a, b) in one, (b, a) in the other
    corner_of = {}
    for f in range(m):
        for k in range(3):
            corner_of[(int(faces[f, k]), int(faces[f, (k + 1) % 3]))] = (f, k)
    for (a, b), (f, k) in corner_of.items():
        g, kk = corner_of[(b, a)]
        if f > g or float(normals[f] @ normals[g]) < cos_limit:
            continue  # each edge once; sharp edges do not join sectors
        # vertex a is corner k of f and corner (kk + 1) % 3 of g; vertex b likewise
        for cf, cg in ((3 * f + k, 3 * g + (kk + 1) % 3), (3 * f + (k + 1) % 3, 3 * g + kk)):
            ra, rb = find(cf), find(cg)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    return np.array([find(c) for c in range(3 * m)]).reshape(m, 3)


def prepare_surface(vertices, faces, *, double_nodes: float | None = None, name: str = "mesh",
                    fixes: Sequence[str] = ()) -> BemSurface:
    """Validate a closed mesh of one piece (``InvalidMesh`` before any assembly) and build its BEM surface.

    Args:
        vertices, faces: the triangle mesh (closed, consistently outward-oriented, no degenerate faces).
        double_nodes: None for one node per vertex; else a crease angle [deg] in (0, 180): edges whose
            faces' normals differ by more than it carry a traction discontinuity, and their vertices
            get one node per smooth sector.
        name: mesh name for error messages.
        fixes: the caller's keyword arguments named in the hints of ``check_surface`` (``BemBody``:
            ``("merge_vertices",)``).
    """
    wmesh.check_surface(vertices, faces, name, closed=True, one_piece=True, fixes=fixes)
    v, f = wmesh.surface_arrays((vertices, faces), name)
    v = v.astype(np.float64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    norm = np.linalg.norm(cross, axis=1)
    normals = cross / norm[:, None]
    if double_nodes is None:
        nodes, new_faces, vertex = v, f.astype(np.int32), np.arange(v.shape[0], dtype=np.int32)
    else:
        angle = float(double_nodes)
        if not (0.0 < angle < 180.0):
            raise InvalidParameter(f"double_nodes = {double_nodes!r} must be a crease angle in (0, 180) degrees or None")
        label = _sectors(f, normals, float(np.cos(np.radians(angle))))
        # one node per (vertex, sector), copies right after the first node of their vertex
        keys = np.stack([f.reshape(-1), label.reshape(-1)], axis=1)
        uniq, inverse = np.unique(keys, axis=0, return_inverse=True)  # sorted by vertex, then sector
        nodes = v[uniq[:, 0]]
        vertex = uniq[:, 0].astype(np.int32)
        new_faces = inverse.reshape(-1, 3).astype(np.int32)
    edges = np.stack([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1)], axis=1)
    return BemSurface(nodes=np.ascontiguousarray(nodes), faces=new_faces, vertex=vertex, normals=normals,
                      areas=0.5 * norm, longest_edge=edges.max(axis=1))


def _ring_edges(node_faces: np.ndarray, centre: int) -> list[tuple[int, int]]:
    """Directed ring edges (a, b) of the faces (centre, a, b) around a vertex; the signed fan of
    ``solid_angle_moments`` needs their orientation, not their order."""
    ring = []
    for tri in node_faces:
        k = int(np.flatnonzero(tri == centre)[0])
        ring.append((int(tri[(k + 1) % 3]), int(tri[(k + 2) % 3])))
    return ring


def solid_angle_moments(x: np.ndarray, ring_points: list[tuple[np.ndarray, np.ndarray]], inward: np.ndarray,
                        order: int = 10, subdivision: int = 4) -> tuple[float, np.ndarray]:
    """Interior solid angle Omega and M = int d d^T d(omega) over the interior cone at x.

    The cone is bounded by the triangles (x, a, b) of ``ring_points`` (outward orientation). Each
    spherical triangle (p, a, b) about a pole p (``inward``) is the central projection of the flat
    triangle p, a, b (unit vectors), with d(omega) = det[p, a, b] / |y|^3 dA; their signed sum is
    minus the interior measure (mod the full sphere, restored by the sign of Omega).
    """
    bary, w = subdivided_rule(order, subdivision)
    p = inward / np.linalg.norm(inward)
    omega = 0.0
    M = np.zeros((3, 3))
    for pa, pb in ring_points:
        ea = (pa - x) / np.linalg.norm(pa - x)
        eb = (pb - x) / np.linalg.norm(pb - x)
        y = bary @ np.stack([p, ea, eb])
        ry = np.linalg.norm(y, axis=1)
        det = float(np.linalg.det(np.stack([p, ea, eb])))
        # area of the flat reference triangle is 1/2 in (xi, eta); weights sum to 1
        dw = 0.5 * w * det / ry**3
        d = y / ry[:, None]
        omega -= float(dw.sum())
        M -= np.einsum("q,qi,qj->ij", dw, d, d)
    if omega <= 0.0:
        omega += 4.0 * np.pi
        M += (4.0 * np.pi / 3.0) * np.eye(3)
    return omega, M


def free_term(surface: BemSurface, node_list: np.ndarray, kappa: float) -> np.ndarray:
    """c(x) at the given nodes: (K, 3, 3). For the interior cone of solid angle Omega at x,

        c = [kappa Omega I + 3 (1 - kappa) M] / (4 pi),   M = int_cone d d^T d(omega),

    kappa = mu / (lambda + 2 mu). Derivation: the rigid-body identity c + int p0 = 0 on the cone
    truncated by a sphere of radius R; on the flat faces d.n = 0 and the Kelvin traction is
    kappa (d n^T - n d^T) / (4 pi r^2), whose angular integrals telescope to zero around the vertex,
    so only the spherical cap (n = d) remains. A smooth point gives c = I / 2.
    """
    out = np.zeros((len(node_list), 3, 3))
    for k, node in enumerate(node_list):
        vtx = surface.vertex[node]
        at_vertex = np.flatnonzero(surface.vertex == vtx)
        mask = np.isin(surface.faces, at_vertex).any(axis=1)
        faces = surface.faces[mask]
        # rename the copies of this vertex to one id so the ring is one loop
        faces = np.where(np.isin(faces, at_vertex), -1, faces)
        ring = _ring_edges(faces, -1)
        x = surface.nodes[node]
        pts = [(surface.nodes[a], surface.nodes[b]) for a, b in ring]
        inward = -(surface.normals[mask] * surface.areas[mask, None]).sum(axis=0)
        omega, M = solid_angle_moments(x, pts, inward)
        out[k] = (kappa * omega * np.eye(3) + 3.0 * (1.0 - kappa) * M) / (4.0 * np.pi)
    return out
