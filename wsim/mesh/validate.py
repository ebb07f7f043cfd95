"""Validation of triangle surfaces: ``check_surface`` raises :class:`wsim.errors.InvalidMesh`
naming the first defect (shapes, non-finite coordinates, degenerate, duplicate or unreferenced
elements and, for closed surfaces, boundary / non-manifold edges, flipped faces, inward normals),
with an example index, so a scene script can be fixed from the message alone.

Plain vectorized numpy (no Python loop over faces or vertices): validating a 100k-face surface
takes a fraction of a second.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from wsim.errors import InvalidMesh
from wsim.mesh._common import _corners, _fmt_vec, _prefix
from wsim.mesh.surface import signed_volume, surface_arrays
from wsim.mesh.topology import _edge_keys

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


def _check_closed(v: np.ndarray, f: np.ndarray, p: str) -> None:
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

    vol = signed_volume(v, f)
    if not vol > 0.0:
        raise InvalidMesh(
            f"{p}: normals point inwards: signed volume {vol:.6g} m^3 is not positive; flip the faces "
            f"(reverse the vertex order of every face, e.g. faces[:, ::-1])"
        )



def check_surface(vertices: Any, faces: Any, name: str = "mesh", *, closed: bool = True) -> None:
    """Validate a triangle surface; raise :class:`InvalidMesh` naming the first problem found.

    Always checked: array shapes and finite coordinates (as :func:`surface_arrays`), degenerate
    faces (a repeated vertex index, or area <= 1e-12 * bbox_diag^2 [m^2]), duplicate faces (same
    vertex set) and, when there are faces, vertices referenced by no face.

    With ``closed=True`` additionally: there is at least one face; every undirected edge is shared
    by exactly two faces (boundary and non-manifold edges are reported separately); orientation is
    consistent (each directed edge appears at most once); and the signed volume is positive
    (outward normals).
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
    if not closed:
        return
    if f.shape[0] == 0:
        raise InvalidMesh(f"{p}: has no faces; a closed surface needs at least 4")
    _check_closed(v, f, p)
