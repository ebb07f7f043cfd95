"""Validation of triangle surfaces: ``check_surface`` raises :class:`wsim.errors.InvalidMesh`
naming the first defect (shapes, non-finite coordinates, degenerate, duplicate or unreferenced
elements and, for closed surfaces, boundary / non-manifold edges, flipped faces, inward normals;
for a body, several separate pieces), with an example index, so a scene script can be fixed from
the message alone. When vertices split at the same position are the cause (a file whose faces
each have their own corners), the message says so and how to merge them.

Plain vectorized numpy (no Python loop over faces or vertices): validating a 100k-face surface
takes a fraction of a second.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from wsim.errors import InvalidMesh
from wsim.mesh._common import _corners, _fmt_vec, _prefix
from wsim.mesh.surface import merge_coincident_vertices, signed_volume, surface_arrays
from wsim.mesh.topology import _edge_keys, pieces

# Faces whose area is at most this fraction of the squared bounding-box diagonal count as degenerate.
_DEGENERATE_AREA_FRACTION = 1e-12


def _check_degenerate(v: np.ndarray, f: np.ndarray, p: str) -> None:
    """Faces that repeat a vertex index or have area <= 1e-12 * bbox_diag^2 [m^2]."""
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    if repeated.any():
        i = int(np.argmax(repeated))
        raise InvalidMesh(
            f"{p}: {int(repeated.sum())} degenerate faces repeat a vertex index "
            f"(e.g. face {i} = {f[i].tolist()})"
        )
    a, b, c = _corners(v, f)
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    tol = _DEGENERATE_AREA_FRACTION * diag * diag
    small = area <= tol
    if small.any():
        i = int(np.argmax(small))
        raise InvalidMesh(
            f"{p}: {int(small.sum())} degenerate faces with area <= 1e-12 * bbox_diag^2 = {tol:.3g} m^2 "
            f"(e.g. face {i} = {f[i].tolist()}, area {area[i]:.3g} m^2)"
        )


def _check_duplicates(f: np.ndarray, p: str) -> None:
    """Faces using the same vertex set as an earlier face (found by sorting, not pairwise)."""
    s = np.sort(f, axis=1)
    order = np.lexsort((s[:, 2], s[:, 1], s[:, 0]))
    ss = s[order]
    same = (ss[1:] == ss[:-1]).all(axis=1)
    if same.any():
        k = int(np.argmax(same))
        i, j = sorted((int(order[k]), int(order[k + 1])))
        raise InvalidMesh(
            f"{p}: {int(same.sum())} duplicate faces (e.g. face {j} = {f[j].tolist()} uses the same "
            f"vertices as face {i} = {f[i].tolist()})"
        )


def _merge_hint(fixes: Sequence[str]) -> str:
    """How to merge vertices at the same position: the caller's keyword if it has one."""
    how = "merge them (trimesh: mesh.merge_vertices())"
    return f"pass merge_vertices=True or {how}" if "merge_vertices" in fixes else how


def _duplicates_note(v: np.ndarray, f: np.ndarray, merged_is_fine: Callable[[np.ndarray], bool], result: str,
                     fixes: Sequence[str]) -> str:
    """``; 28 of its 36 vertices are duplicates at the same position (merged, <result>): pass
    merge_vertices=True or ...`` when merging the vertices at the same position cures the defect
    (``merged_is_fine(merged faces)``), else ''. Only called on the error path (a k-d tree)."""
    _, mf, n_merged = merge_coincident_vertices(v, f)
    if n_merged == 0 or not merged_is_fine(mf):
        return ""
    return (f"; {n_merged} of its {v.shape[0]} vertices are duplicates at the same position (merged, {result}): "
            f"{_merge_hint(fixes)}")


def _edge_uses(f: np.ndarray, n: int) -> np.ndarray:
    """How many faces use each undirected edge (one count per distinct edge)."""
    keys = _edge_keys(f.reshape(-1), f[:, [1, 2, 0]].reshape(-1), n)
    return np.unique(keys, return_counts=True)[1]


def _check_pieces(v: np.ndarray, f: np.ndarray, p: str, closed: bool, fixes: Sequence[str]) -> None:
    """One connected piece, or InvalidMesh with the count and how to split (or allow) them; when the
    pieces are only vertices split at the same position, how to merge them instead."""
    count, _ = pieces(f)
    if count <= 1:
        return

    def whole(mf: np.ndarray) -> bool:  # one manifold piece (closed if it must be) once merged
        uses = _edge_uses(mf, v.shape[0])
        return pieces(mf)[0] == 1 and uses.max() <= 2 and (not closed or uses.min() == 2)

    note = _duplicates_note(v, f, whole, "it is one piece", fixes)
    if note:
        raise InvalidMesh(f"{p}: the mesh has {count} separate pieces{note}")
    allow = " or pass allow_pieces=True to simulate them as one body" if "allow_pieces" in fixes else ""
    raise InvalidMesh(
        f"{p}: the mesh has {count} separate pieces; make one body per piece (trimesh: mesh.split()){allow}"
    )


def _check_fans(v: np.ndarray, f: np.ndarray, p: str, n: int, directed: np.ndarray) -> None:
    """Every vertex of a closed, edge-manifold, consistently oriented surface is surrounded by one
    fan of faces: two sheets that touch at a single vertex (two spheres sharing one point) pass
    the edge tests, but the surface has no one normal there and the shared vertex belongs to both.
    Around vertex i the corner of face f at i is followed by the corner of the face across the
    edge from i to f's next vertex (it runs that edge back to i); the corners at i form one cycle
    for a fan, several for a pinch."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    m = f.shape[0]
    corner_vertex = f.reshape(-1).astype(np.int64)
    nxt = f[:, [1, 2, 0]].reshape(-1).astype(np.int64)
    order = np.argsort(directed)
    face_of_edge = order // 3  # faces by sorted directed edge
    back = np.searchsorted(directed[order], nxt * n + corner_vertex)  # the edge next -> i, run back
    g = face_of_edge[back]
    # the corner of face g at vertex i: the slot of g holding i
    slot = np.argmax(f[g] == corner_vertex[:, None], axis=1)
    follow = 3 * g + slot
    count, label = connected_components(coo_matrix((np.ones(3 * m), (np.arange(3 * m), follow)), shape=(3 * m, 3 * m)),
                                         directed=False)
    if count <= n:  # one cycle of corners per (referenced) vertex: no pinch (the fans only on the error path)
        return
    fans = np.bincount(np.unique(np.stack([corner_vertex, label], axis=1), axis=0)[:, 0], minlength=n)
    pinched = np.flatnonzero(fans > 1)
    if pinched.size:
        i = int(pinched[0])
        raise InvalidMesh(
            f"{p}: non-manifold vertex: {pinched.size} vertices join sheets of the surface that touch only "
            f"there (e.g. vertex {i} = {_fmt_vec(v[i])}, where {int(fans[i])} fans of faces meet); split the "
            f"vertex into one per sheet (then each sheet is its own piece)"
        )


def _check_closed(v: np.ndarray, f: np.ndarray, p: str, fixes: Sequence[str] = ()) -> None:
    """Watertight, manifold, consistently oriented and outward (positive signed volume)."""
    n = v.shape[0]
    src = f.reshape(-1).astype(np.int64)
    dst = f[:, [1, 2, 0]].reshape(-1).astype(np.int64)

    # Watertight and manifold: every undirected edge is used by exactly two faces.
    keys = _edge_keys(src, dst, n)
    uniq, counts = np.unique(keys, return_counts=True)
    problems = []
    boundary = counts == 1
    if boundary.any():
        k = int(uniq[np.argmax(boundary)])
        problems.append(
            f"not watertight: {int(boundary.sum())} boundary edges used by only one face "
            f"(e.g. vertices {k // n}-{k % n})"
            + _duplicates_note(v, f, lambda mf: bool(np.all(_edge_uses(mf, n) == 2)), "it is watertight", fixes)
        )
    nonmanifold = counts > 2
    if nonmanifold.any():
        j = int(np.argmax(nonmanifold))
        k = int(uniq[j])
        problems.append(
            f"non-manifold: {int(nonmanifold.sum())} edges shared by more than two faces "
            f"(e.g. vertices {k // n}-{k % n}, shared by {int(counts[j])} faces)"
        )
    if problems:
        raise InvalidMesh(f"{p}: " + "; ".join(problems))

    # Consistent orientation: neighbours traverse their shared edge in opposite directions, so
    # each directed edge occurs once.
    directed = src * n + dst
    order = np.argsort(directed, kind="stable")
    sd = directed[order]
    rep = np.flatnonzero(sd[1:] == sd[:-1])
    if rep.size:
        face_a = order[rep] // 3
        face_b = order[rep + 1] // 3
        # The face involved in most clashes is the one that is flipped (a single flipped face
        # clashes with all three neighbours, each neighbour only with it).
        clash = np.bincount(np.concatenate([face_a, face_b]))
        bad = int(np.argmax(clash))
        k = int(np.flatnonzero((face_a == bad) | (face_b == bad))[0])
        other = int(face_b[k] if face_a[k] == bad else face_a[k])
        e = int(sd[rep[k]])
        raise InvalidMesh(
            f"{p}: inconsistent orientation: {rep.size} edges are traversed in the same direction by "
            f"both of their faces (e.g. face {bad} = {f[bad].tolist()} is flipped relative to its "
            f"neighbour face {other} = {f[other].tolist()}: both traverse edge {e // n}->{e % n})"
        )

    _check_fans(v, f, p, n, directed)

    vol = signed_volume(v, f)
    if not vol > 0.0:
        raise InvalidMesh(
            f"{p}: normals point inwards: signed volume {vol:.6g} m^3 is not positive; flip the faces "
            f"(reverse the vertex order of every face, e.g. faces[:, ::-1])"
        )



def check_surface(vertices: Any, faces: Any, name: str = "mesh", *, closed: bool = True, one_piece: bool = False,
                  fixes: Sequence[str] = ()) -> None:
    """Validate a triangle surface; raise :class:`InvalidMesh` naming the first problem found.

    Always checked: array shapes and finite coordinates (as :func:`surface_arrays`), degenerate
    faces (a repeated vertex index, or area <= 1e-12 * bbox_diag^2 [m^2]), duplicate faces (same
    vertex set) and, when there are faces, vertices referenced by no face.

    With ``closed=True`` additionally: there is at least one face; every undirected edge is shared
    by exactly two faces (boundary and non-manifold edges are reported separately); orientation is
    consistent (each directed edge appears at most once); and the signed volume is positive
    (outward normals).

    With ``one_piece=True`` (a body): the faces form one connected piece (``topology.pieces``);
    the message gives the count and says to make one body per piece.

    Where vertices split at the same position are the cause (not watertight, or many pieces, but
    watertight, or one manifold piece, once they are merged), the message says so and how to merge
    them (only on this error path is a k-d tree of the vertices built).
    ``fixes``: the caller's keyword arguments that cure a defect, named in the hints:
    ``"merge_vertices"`` (merge them first), ``"allow_pieces"`` (accept several pieces).
    """
    v, f = surface_arrays((vertices, faces), name)
    p = _prefix(name)
    if f.shape[0]:
        _check_degenerate(v, f, p)
        _check_duplicates(f, p)
        used = np.zeros(v.shape[0], dtype=bool)
        used[f.reshape(-1)] = True
        if not used.all():
            i = int(np.argmax(~used))
            raise InvalidMesh(
                f"{p}: {int((~used).sum())} unreferenced vertices are used by no face "
                f"(e.g. vertex {i} = {_fmt_vec(v[i])})"
            )
    if closed:
        if f.shape[0] == 0:
            raise InvalidMesh(f"{p}: has no faces; a closed surface needs at least 4")
        _check_closed(v, f, p, fixes)
    if one_piece:
        _check_pieces(v, f, p, closed, fixes)
