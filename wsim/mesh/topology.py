"""Topology of triangle lists: unique edges, bending hinges (pairs of faces sharing an edge),
whether a surface has a boundary and its connected pieces. Only the face indices are read, never the
vertex positions (so vertices split at the same position count as separate: see
``wsim.mesh.surface.merge_coincident_vertices``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from wsim.errors import InvalidMesh
from wsim.mesh._common import _prefix


def _edge_keys(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """Undirected edge keys ``min*n + max``; int64 cannot overflow because n < 2**31."""
    a = a.astype(np.int64)
    b = b.astype(np.int64)
    return np.minimum(a, b) * n + np.maximum(a, b)


def _faces_only(faces: Any, what: str = "mesh") -> np.ndarray:
    """Faces array for the topology-only functions (edges, hinges): (M, 3) non-negative ints."""
    f = np.asarray(faces)
    if f.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise InvalidMesh(f"{_prefix(what)}: faces must have shape (M, 3), got {f.shape}")
    if f.dtype.kind not in "iu":
        raise InvalidMesh(f"{_prefix(what)}: face indices must be integers, got dtype {f.dtype}")
    if f.min() < 0:
        bad = int(np.argmax((f < 0).any(axis=1)))
        raise InvalidMesh(f"{_prefix(what)}: negative face index (e.g. face {bad} = {f[bad].tolist()})")
    return f.astype(np.int64)


def has_boundary(faces: Any) -> bool:
    """True when some edge is used by only one face (an open surface)."""
    f = _faces_only(faces)
    if len(f) == 0:
        return True
    n = int(f.max()) + 1
    keys = _edge_keys(f.reshape(-1), f[:, [1, 2, 0]].reshape(-1), n)
    _, counts = np.unique(keys, return_counts=True)
    return bool(np.any(counts == 1))


def watertight(faces: Any) -> bool:
    """True when every edge joins exactly two faces that run it in opposite directions (a closed,
    consistently oriented, edge-manifold surface): a ray from any point then crosses it an odd
    number of times exactly when the point is inside, so ray parity can stand in for the winding
    number (``wsim.kernels.mesh.query_inside``)."""
    f = _faces_only(faces)
    if len(f) == 0:
        return False
    n = int(f.max()) + 1
    a, b = f.reshape(-1), f[:, [1, 2, 0]].reshape(-1)
    if np.any(a == b):
        return False
    directed = a * n + b
    if len(np.unique(directed)) != len(directed):  # an edge run twice the same way
        return False
    return bool(np.all(np.isin(b * n + a, directed)))


def edges(faces: Any) -> np.ndarray:
    """Unique undirected edges of a triangle list: (E, 2) int32 with i < j, sorted lexicographically."""
    f = _faces_only(faces)
    if f.shape[0] == 0:
        return np.zeros((0, 2), dtype=np.int32)
    n = int(f.max()) + 1
    keys = np.unique(_edge_keys(f.reshape(-1), f[:, [1, 2, 0]].reshape(-1), n))
    keys = keys[keys // n != keys % n]  # a face with a repeated index has a zero-length "edge"
    return np.stack([keys // n, keys % n], axis=1).astype(np.int32)


def hinges(faces: Any) -> np.ndarray:
    """Bending hinges: one row per interior edge shared by exactly two faces.

    Returns an (H, 4) int32 array ``[w1, w2, e0, e1]``: ``(e0, e1)`` is the shared edge oriented as
    in the first face (the one with the lower face index), so that face is ``(e0, e1, w1)`` up to a
    cyclic rotation; ``w1`` and ``w2`` are the vertices of face 1 and face 2 opposite the edge.
    Rows are sorted by the undirected edge (min, max) vertex pair. Edges used by one face or by
    more than two faces get no hinge.
    """
    f = _faces_only(faces)
    if f.shape[0] == 0:
        return np.zeros((0, 4), dtype=np.int32)
    n = int(f.max()) + 1
    # Directed edge k of face i is (f[i,k], f[i,k+1]) with wing f[i,k+2]; flattened face-major so
    # that a stable sort keeps the lower face index first within each edge.
    src = f.reshape(-1)
    dst = f[:, [1, 2, 0]].reshape(-1)
    wing = f[:, [2, 0, 1]].reshape(-1)
    keys = _edge_keys(src, dst, n)
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    starts = np.flatnonzero(np.r_[True, sk[1:] != sk[:-1]])
    counts = np.diff(np.r_[starts, sk.size])
    pair = starts[counts == 2]
    first = order[pair]
    second = order[pair + 1]
    ok = (first // 3 != second // 3) & (src[first] != dst[first])
    first, second = first[ok], second[ok]
    return np.stack([wing[first], wing[second], src[first], dst[first]], axis=1).astype(np.int32)


def pieces(faces: Any) -> tuple[int, np.ndarray]:
    """Connected pieces of a triangle list: faces that share a vertex index, directly or through
    other faces, are one piece.

    Returns ``(count, label)``: the number of pieces and each face's piece, numbered 0, 1, ... in
    the order of each piece's first face; ``(0, empty)`` without faces.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = _faces_only(faces)
    m = f.shape[0]
    if m == 0:
        return 0, np.zeros(0, dtype=np.int64)
    n = int(f.max()) + 1
    # bipartite graph: face i (node i) -- its three vertices (nodes m + v)
    rows = np.repeat(np.arange(m, dtype=np.int64), 3)
    graph = coo_matrix((np.ones(3 * m, dtype=np.int8), (rows, m + f.reshape(-1))), shape=(m + n, m + n))
    _, label = connected_components(graph, directed=False)
    _, first, inverse = np.unique(label[:m], return_index=True, return_inverse=True)
    rank = np.empty(first.size, dtype=np.int64)
    rank[np.argsort(first)] = np.arange(first.size)
    return int(first.size), rank[inverse.reshape(-1)]

