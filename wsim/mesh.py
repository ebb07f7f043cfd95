"""Surface meshes for wsim: input, validation, procedural shapes and tetrahedralization.

Conventions used throughout this module (and expected by every caller):

* vertices are ``float64`` arrays of shape ``(N, 3)``, in metres;
* faces are ``int32`` arrays of shape ``(M, 3)``, listed counter-clockwise when seen from outside,
  so the right-hand-rule normals point outwards and the signed volume is positive;
* every problem with a mesh raises :class:`wsim.errors.InvalidMesh` whose message starts with
  the object's name -- ``"mesh '<name>': "`` for a bare name, or the caller's own label verbatim
  when it is already quoted (``name="body 'horse'"`` gives ``"body 'horse': "``) -- and names the
  offending quantity together with an example index, so a scene script can be fixed from the
  message alone.

Everything here is plain vectorized numpy/scipy (no Python loop over faces or vertices), so
validating a 100k-face surface takes a fraction of a second.
"""

from __future__ import annotations

import itertools
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError, cKDTree

from wsim.errors import InvalidMesh, InvalidParameter

__all__ = [
    "surface_arrays",
    "signed_volume",
    "vertex_areas",
    "check_surface",
    "edges",
    "hinges",
    "bumpy_sphere",
    "fish",
    "neck_body",
    "beam",
    "torus",
    "bumpy_cube",
    "tetrahedralize",
    "winding_number",
]

# Faces whose area is at most this fraction of the squared bounding-box diagonal count as degenerate.
_DEGENERATE_AREA_FRACTION = 1e-12
# Number of (point, face) pairs evaluated at once by the brute-force winding number; bounds the
# temporaries to a few tens of MB whatever the mesh or query size.
_WINDING_CHUNK_PAIRS = 1 << 18
# Number of query points whose candidate faces are processed at once by the inside/outside oracle.
_ORACLE_CHUNK_POINTS = 20_000
# Highest icosphere subdivision level accepted (level 7 already has 163,842 vertices).
_MAX_SUBDIVISIONS = 7


# ----------------------------------------------------------------------------------------------
# small helpers
# ----------------------------------------------------------------------------------------------


def _prefix(name: str) -> str:
    """Start of every error message: a bare name becomes ``mesh 'name'``; a label the caller has
    already formatted (it contains a quote, e.g. ``body 'horse'``) is used as is."""
    name = str(name)
    return name if ("'" in name or '"' in name) else f"mesh '{name}'"


def _fmt_vec(v: np.ndarray) -> str:
    return "[" + ", ".join(f"{x:.6g}" for x in np.asarray(v, dtype=np.float64)) + "]"


def _check_int(value: Any, what: str, minimum: int, maximum: int | None = None) -> int:
    """Validate an integer shape parameter (bools are rejected: ``True`` is not a resolution)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InvalidParameter(f"{what} must be an integer, got {value!r}")
    value = int(value)
    if value < minimum or (maximum is not None and value > maximum):
        upper = "" if maximum is None else f" and <= {maximum}"
        raise InvalidParameter(f"{what} must be >= {minimum}{upper}, got {value}")
    return value


def _check_positive(value: Any, what: str) -> float:
    """Validate a strictly positive, finite length [m] or other real parameter."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InvalidParameter(f"{what} must be a real number, got {value!r}") from None
    if not math.isfinite(x) or x <= 0.0:
        raise InvalidParameter(f"{what} must be positive and finite, got {value!r}")
    return x


def _check_range(value: Any, what: str, lo: float, hi: float) -> float:
    """Validate a real parameter in the half-open interval [lo, hi)."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InvalidParameter(f"{what} must be a real number, got {value!r}") from None
    if not (math.isfinite(x) and lo <= x < hi):
        raise InvalidParameter(f"{what} must lie in [{lo:g}, {hi:g}), got {value!r}")
    return x


def _corners(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]


def _scatter_add_rows(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum the rows of ``values`` (K, 3) into ``n`` bins; bincount is much faster than np.add.at."""
    out = np.empty((n, 3), dtype=np.float64)
    for k in range(3):
        out[:, k] = np.bincount(index, weights=values[:, k], minlength=n)
    return out


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


# ----------------------------------------------------------------------------------------------
# input and basic quantities
# ----------------------------------------------------------------------------------------------


def _vertices_array(raw: Any, name: str) -> np.ndarray:
    p = _prefix(name)
    try:
        v = np.array(raw, dtype=np.float64, order="C", copy=True)
    except (TypeError, ValueError) as exc:
        raise InvalidMesh(f"{p}: vertices are not a numeric array ({exc})") from None
    if v.ndim != 2 or v.shape[1] != 3:
        raise InvalidMesh(f"{p}: vertices must have shape (N, 3), got {v.shape}")
    if v.shape[0] == 0:
        raise InvalidMesh(f"{p}: no vertices (vertices has shape {v.shape})")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise InvalidMesh(
            f"{p}: non-finite vertex coordinates: {int(bad.sum())} vertices "
            f"(e.g. vertex {i} = {_fmt_vec(v[i])})"
        )
    return v


def _faces_array(raw: Any, n_vertices: int, name: str) -> np.ndarray:
    p = _prefix(name)
    try:
        f = np.asarray(raw)
    except (TypeError, ValueError) as exc:
        raise InvalidMesh(f"{p}: faces are not an integer array ({exc})") from None
    if f.size == 0 and (f.ndim == 1 or (f.ndim == 2 and f.shape[1] == 3)):
        # A particle set with no surface is legal input.
        return np.zeros((0, 3), dtype=np.int32)
    if f.ndim != 2 or f.shape[1] != 3:
        raise InvalidMesh(f"{p}: faces must have shape (M, 3), got {f.shape}")
    if f.dtype.kind == "f":
        # Index arrays read from text files often arrive as floats; accept them only if exact.
        ok = np.isfinite(f) & (f == np.round(f))
        if not ok.all():
            bad = int(np.argmax(~ok.all(axis=1)))
            raise InvalidMesh(f"{p}: face indices must be integers (e.g. face {bad} = {f[bad].tolist()})")
        f = f.astype(np.int64)
    elif f.dtype.kind not in "iu":
        raise InvalidMesh(f"{p}: face indices must be integers, got dtype {f.dtype}")
    f = f.astype(np.int64, copy=False)
    neg = (f < 0).any(axis=1)
    if neg.any():
        i = int(np.argmax(neg))
        raise InvalidMesh(
            f"{p}: negative face index in {int(neg.sum())} faces (e.g. face {i} = {f[i].tolist()})"
        )
    oob = (f >= n_vertices).any(axis=1)
    if oob.any():
        i = int(np.argmax(oob))
        raise InvalidMesh(
            f"{p}: face index out of range: {int(oob.sum())} faces refer to vertices outside "
            f"[0, {n_vertices - 1}] (e.g. face {i} = {f[i].tolist()})"
        )
    return np.ascontiguousarray(f, dtype=np.int32)


def surface_arrays(mesh: trimesh.Trimesh | tuple[Any, Any], name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Convert a surface to wsim's array convention.

    Args:
        mesh: a ``trimesh.Trimesh`` or a ``(vertices, faces)`` pair of array-likes; vertex
            coordinates in metres.
        name: the object's name, used at the start of error messages (see the module docstring).

    Returns:
        ``(V, F)``: ``V`` a C-contiguous float64 (N, 3) copy of the vertices [m], ``F`` int32
        (M, 3) faces. ``F`` may be empty, shape (0, 3), for a particle set with no surface.

    Raises:
        InvalidMesh: wrong shapes, no vertices, non-finite coordinates, non-integer, negative or
            out-of-range face indices.
    """
    if isinstance(mesh, trimesh.Trimesh):
        raw_v, raw_f = mesh.vertices, mesh.faces
    elif isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        raw_v, raw_f = mesh
    else:
        raise InvalidMesh(
            f"{_prefix(name)}: expected a trimesh.Trimesh or a (vertices, faces) pair, "
            f"got {type(mesh).__name__}"
        )
    v = _vertices_array(raw_v, name)
    f = _faces_array(raw_f, v.shape[0], name)
    return v, f


def signed_volume(vertices: Any, faces: Any) -> float:
    """Signed volume [m^3] enclosed by a closed surface: (1/6) sum over faces of v0 . (v1 x v2).

    Positive when the faces are oriented outwards. For an open surface the value depends on the
    origin and is only the signed volume of the cone from the origin over the faces.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if f.size == 0:
        return 0.0
    a, b, c = _corners(v, f)
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def face_areas(vertices: Any, faces: Any) -> np.ndarray:
    """Area [m^2] of each triangle, shape (M,)."""
    a, b, c = _corners(np.asarray(vertices, dtype=np.float64), np.asarray(faces))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def vertex_normals(vertices: Any, faces: Any) -> np.ndarray:
    """(V, 3) unit area-weighted vertex normals (the sum of the adjacent faces' area vectors)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    a, b, c = _corners(v, f)
    n = _scatter_add_rows(f.reshape(-1), np.repeat(np.cross(b - a, c - a), 3, axis=0), v.shape[0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def vertex_areas(vertices: Any, faces: Any) -> np.ndarray:
    """Lumped area [m^2] of each vertex: one third of the area of every incident face, shape (N,)."""
    n = np.asarray(vertices).shape[0]
    f = np.asarray(faces)
    if f.size == 0:
        return np.zeros(n, dtype=np.float64)
    third = face_areas(vertices, f) / 3.0
    return np.bincount(f.reshape(-1), weights=np.repeat(third, 3), minlength=n)


# ----------------------------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------------------------


def _check_degenerate(v: np.ndarray, f: np.ndarray, p: str) -> None:
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


def has_boundary(faces: Any) -> bool:
    """True when some edge is used by only one face (an open surface)."""
    f = _faces_only(faces)
    if len(f) == 0:
        return True
    n = int(f.max()) + 1
    keys = _edge_keys(f.reshape(-1), f[:, [1, 2, 0]].reshape(-1), n)
    _, counts = np.unique(keys, return_counts=True)
    return bool(np.any(counts == 1))


def load(path: str | os.PathLike, name: str | None = None) -> trimesh.Trimesh:
    """Load a surface mesh file (OBJ, PLY, STL, GLB, ...) as one triangle mesh, or InvalidMesh."""
    p = Path(path).expanduser()
    label = name or p.name
    if not p.is_file():
        raise InvalidMesh(f"mesh '{label}': file '{p}' not found")
    try:
        m = trimesh.load(str(p), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InvalidMesh(f"mesh '{label}': cannot read '{p}': {exc}") from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise InvalidMesh(f"mesh '{label}': '{p}' holds no triangles")
    return m


def load_fitted(path: str | os.PathLike, size: float) -> trimesh.Trimesh:
    """Load a mesh file, centre its bounding box at the origin and scale its longest side to ``size`` [m]
    (how scenes place a user's ``--mesh`` model)."""
    m = load(path)
    m.apply_translation(-m.bounding_box.centroid)
    m.apply_scale(_check_positive(size, "fitted mesh size") / max(m.extents))
    return m


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


# ----------------------------------------------------------------------------------------------
# topology
# ----------------------------------------------------------------------------------------------


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


# ----------------------------------------------------------------------------------------------
# procedural shapes
# ----------------------------------------------------------------------------------------------


def _finish(vertices: np.ndarray, faces: np.ndarray, name: str) -> trimesh.Trimesh:
    """Wrap generated arrays in a Trimesh after a self-check, so a bad parameter combination
    fails here with a clear message rather than later inside a solver."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int32)
    check_surface(v, f, name, closed=True)
    return trimesh.Trimesh(vertices=v, faces=f, process=False)


def _unit_icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere vertices (on the unit sphere) and outward faces."""
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = np.array(ico.vertices, dtype=np.float64)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    f = np.array(ico.faces, dtype=np.int32)
    if signed_volume(v, f) < 0.0:  # do not rely on the library's winding convention
        f = f[:, ::-1].copy()
    return v, f


def bumpy_sphere(
    radius: float = 0.5, subdivisions: int = 3, amplitude: float = 0.1, lobes: int = 4, seed: int = 0
) -> trimesh.Trimesh:
    """An icosphere whose radius is modulated by a smooth random field; centred at the origin.

    The radius along unit direction u is ``radius * (1 + amplitude * g(u))`` where
    ``g(u) = sum_k w_k T_lobes(d_k . u)`` is a weighted sum of three Chebyshev polynomials of degree
    ``lobes`` in the cosine of the angle to random axes ``d_k`` (zonal, spherical-harmonic-like
    patterns with about ``lobes`` bands each), with ``sum |w_k| = 1`` so ``|g| <= 1``. Polynomials in
    ``d . u`` are smooth everywhere on the sphere, including at the axes.

    Args:
        radius: mean radius [m].
        subdivisions: icosphere level; 10 * 4**s + 2 vertices (s = 3: 642, s = 6: 40,962).
        amplitude: relative radial amplitude, in [0, 1).
        lobes: polynomial degree of the field (>= 1); higher means more, smaller bumps.
        seed: random seed; the mesh is a deterministic function of all arguments.
    """
    radius = _check_positive(radius, "bumpy_sphere radius")
    subdivisions = _check_int(subdivisions, "bumpy_sphere subdivisions", 0, _MAX_SUBDIVISIONS)
    amplitude = _check_range(amplitude, "bumpy_sphere amplitude", 0.0, 1.0)
    lobes = _check_int(lobes, "bumpy_sphere lobes", 1)
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(3, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    weights = rng.uniform(0.5, 1.0, size=3) * rng.choice([-1.0, 1.0], size=3)
    weights /= np.abs(weights).sum()

    u, f = _unit_icosphere(subdivisions)
    cosines = np.clip(u @ axes.T, -1.0, 1.0)
    field = (np.cos(lobes * np.arccos(cosines)) * weights).sum(axis=1)
    v = u * (radius * (1.0 + amplitude * field))[:, None]
    return _finish(v, f, "bumpy_sphere")


def fish(length: float = 1.0, subdivisions: int = 3) -> trimesh.Trimesh:
    """A fish-like body along +x (head at +x), centred at the origin, spanning x in [-L/2, L/2].

    Built by mapping a unit icosphere point (x, y, z) to
    ``(L/2 * x, y * gy(x), z * gz(x))``: the profile functions are smooth and positive, so the map
    has a positive Jacobian (orientation and closedness are preserved) and no face degenerates.
    The body is laterally flattened (z thinner than y), narrows into a peduncle and flares into a
    thin, tall tail fin near x = -L/2.

    Args:
        length: nose-to-tail length L [m].
        subdivisions: icosphere level (s = 3: 642 vertices).
    """
    length = _check_positive(length, "fish length")
    subdivisions = _check_int(subdivisions, "fish subdivisions", 0, _MAX_SUBDIVISIONS)
    u, f = _unit_icosphere(subdivisions)
    s = u[:, 0]
    # Height (y) factor: body bulge slightly ahead of the middle plus a fin bump near the tail.
    gy = length * (0.03 + 0.15 * np.exp(-(((s - 0.15) / 0.55) ** 2)) + 0.28 * np.exp(-(((s + 0.9) / 0.13) ** 2)))
    # Width (z) factor: about half the body height and very thin at the fin.
    gz = length * (0.012 + 0.085 * np.exp(-(((s - 0.2) / 0.6) ** 2)))
    v = np.stack([0.5 * length * s, u[:, 1] * gy, u[:, 2] * gz], axis=1)
    return _finish(v, f, "fish")


def _neck_profile(
    x: np.ndarray, length: float, torso_radius: float, neck_radius: float, head_radius: float
) -> np.ndarray:
    """Radius [m] of the neck_body surface of revolution at axial positions x [m]."""
    u = x / length
    # Torso plateau for u < 0.3, cosine taper into the neck by u = 0.55 (C1 at both ends).
    t = np.clip((u - 0.3) / 0.25, 0.0, 1.0)
    taper = 0.5 * (1.0 + np.cos(np.pi * t))
    body = neck_radius + (torso_radius - neck_radius) * taper
    # sqrt-like rounded caps make the radius go to zero at both poles with a vertical tangent,
    # so the surface is smooth at the pole vertices.
    a0 = min(torso_radius, 0.3 * length)
    c0 = np.sqrt(np.clip(1.0 - (1.0 - np.clip(x / a0, 0.0, 1.0)) ** 2, 0.0, 1.0))
    a1 = min(neck_radius, 0.05 * length)
    c1 = np.sqrt(np.clip(1.0 - (1.0 - np.clip((length - x) / a1, 0.0, 1.0)) ** 2, 0.0, 1.0))
    body = body * c0 * c1
    # Head bulb: an ellipsoid touching the far pole, slightly elongated along the axis.
    ah = 1.25 * head_radius
    xh = length - ah
    head = head_radius * np.sqrt(np.clip(1.0 - ((x - xh) / ah) ** 2, 0.0, None))
    # Smooth maximum of neck and head (an 8-norm): no kink where the bulb emerges from the neck.
    p = 8.0
    return (body**p + head**p) ** (1.0 / p)


def _ring_sector_counts(radius: np.ndarray, spacing: float, sectors: int) -> np.ndarray:
    """Sectors of each ring: the smallest of sectors, sectors/2, sectors/4, ... (>= 3) whose arc
    2 pi r / m is no longer than the ring spacing, with neighbouring rings differing by at most 2x.

    Why: a single pole vertex joined to a full ring has valence ``sectors``; halving the ring size
    towards the poles keeps every valence <= 12, which bounds the number of constraint colours
    (one GPU launch each) and keeps the triangles near the poles from becoming needles.
    """
    allowed = [sectors]
    while allowed[-1] % 2 == 0 and allowed[-1] // 2 >= 3:
        allowed.append(allowed[-1] // 2)
    allowed_arr = np.array(allowed[::-1])  # ascending
    idx = np.minimum(np.searchsorted(allowed_arr, 2.0 * np.pi * radius / spacing), len(allowed_arr) - 1)
    for _ in range(len(allowed_arr)):  # at most one halving between neighbours, from either side
        idx[1:] = np.maximum(idx[1:], idx[:-1] - 1)
        idx[:-1] = np.maximum(idx[:-1], idx[1:] - 1)
    return allowed_arr[idx]


def _ring_strip(a0: int, m0: int, a1: int, m1: int) -> np.ndarray:
    """Triangles joining ring (first vertex a0, m0 vertices) to the next ring along +x (a1, m1).

    m1 is m0, 2 m0 or m0 / 2; vertex j of a ring of m sits at angle 2 pi j / m, so the rings of a
    halving share the angles of every other vertex. Walked +phi first, then +x: outward normals.
    """
    if m1 == m0:
        j = np.arange(m0)
        jn = (j + 1) % m0
        return np.concatenate([np.stack([a0 + j, a0 + jn, a1 + jn], 1), np.stack([a0 + j, a1 + jn, a1 + j], 1)])
    if m1 == 2 * m0:
        i = np.arange(m0)
        s0, s1 = a0 + i, a0 + (i + 1) % m0
        l0, l1, l2 = a1 + 2 * i, a1 + 2 * i + 1, a1 + (2 * i + 2) % m1
        return np.concatenate([np.stack([s0, s1, l1], 1), np.stack([s0, l1, l0], 1), np.stack([s1, l2, l1], 1)])
    # halving: the doubling strip seen from the other side, with the walk reversed
    return _ring_strip(a1, m1, a0, m0)[:, ::-1]


def neck_body(
    length: float = 1.6,
    torso_radius: float = 0.2,
    neck_radius: float = 0.07,
    head_radius: float = 0.12,
    rings: int = 64,
    sectors: int = 24,
) -> trimesh.Trimesh:
    """An elongated creature along +x, from x = 0 to x = length: torso, thin neck, head bulb.

    A surface of revolution about the x axis whose radius profile is a wide torso over the first
    ~40 % of the length, a smooth (cosine) narrowing into a neck of ``neck_radius`` and an
    ellipsoidal head bulb at the far end. ``rings`` rings are spaced uniformly in arc length of
    the profile; a ring has ``sectors`` vertices, halved (24, 12, 6, ...) near the poles where its
    circumference is short, so no vertex has more than 12 neighbours and no face degenerates
    (use a ``sectors`` with factors of 2 for the smallest pole rings). Each end is closed by one
    pole vertex: vertex 0 at x = 0, the last vertex at x = length.

    Args:
        length: total length [m].
        torso_radius, neck_radius, head_radius: radii [m] of the three parts.
        rings: number of vertex rings (>= 2).
        sectors: vertices of a full ring (>= 3).

    Returns a mesh with at most ``rings * sectors + 2`` vertices.
    """
    length = _check_positive(length, "neck_body length")
    torso_radius = _check_positive(torso_radius, "neck_body torso_radius")
    neck_radius = _check_positive(neck_radius, "neck_body neck_radius")
    head_radius = _check_positive(head_radius, "neck_body head_radius")
    rings = _check_int(rings, "neck_body rings", 2)
    sectors = _check_int(sectors, "neck_body sectors", 3)
    if 2.5 * head_radius > 0.4 * length:
        raise InvalidParameter(
            f"neck_body head_radius {head_radius:g} m is too large for length {length:g} m "
            f"(need 2.5 * head_radius <= 0.4 * length)"
        )

    # Arc-length parametrization of the profile curve (x, r(x)); the dense samples are clustered
    # towards the poles (cosine spacing) where the sqrt caps make r(x) steep.
    dense = 0.5 * length * (1.0 - np.cos(np.linspace(0.0, np.pi, 8001)))
    r_dense = _neck_profile(dense, length, torso_radius, neck_radius, head_radius)
    arc = np.r_[0.0, np.cumsum(np.hypot(np.diff(dense), np.diff(r_dense)))]
    spacing = arc[-1] / (rings + 1)
    xr = np.interp(spacing * np.arange(1, rings + 1), arc, dense)
    rr = _neck_profile(xr, length, torso_radius, neck_radius, head_radius)
    counts = _ring_sector_counts(rr, spacing, sectors)
    starts = 1 + np.concatenate([[0], np.cumsum(counts)[:-1]])

    pts = [np.zeros((1, 3))]
    for x, r, m in zip(xr, rr, counts):
        phi = 2.0 * np.pi * np.arange(m) / m
        pts.append(np.stack([np.full(m, x), r * np.cos(phi), r * np.sin(phi)], axis=1))
    last_pole = 1 + int(counts.sum())
    pts.append(np.array([[length, 0.0, 0.0]]))
    v = np.vstack(pts)

    j0 = np.arange(counts[0])
    faces = [np.stack([np.zeros(counts[0], dtype=np.int64), starts[0] + (j0 + 1) % counts[0], starts[0] + j0], axis=1)]
    for i in range(rings - 1):
        faces.append(_ring_strip(int(starts[i]), int(counts[i]), int(starts[i + 1]), int(counts[i + 1])))
    j1 = np.arange(counts[-1])
    faces.append(np.stack([np.full(counts[-1], last_pole), starts[-1] + j1, starts[-1] + (j1 + 1) % counts[-1]], axis=1))
    return _finish(v, np.concatenate(faces), "neck_body")


def _box_surface(lo: np.ndarray, hi: np.ndarray, divisions: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Surface of the box [lo, hi] on a (nx, ny, nz) lattice: shared vertices, outward triangles."""
    dims = np.asarray(divisions, dtype=np.int64)
    axes_coords = [np.linspace(lo[k], hi[k], dims[k] + 1) for k in range(3)]
    grid = np.stack(np.meshgrid(*[np.arange(d + 1) for d in dims], indexing="ij"), axis=-1)
    on_surface = ((grid == 0) | (grid == dims)).any(axis=-1)
    index = np.full(on_surface.shape, -1, dtype=np.int64)
    index[on_surface] = np.arange(int(on_surface.sum()))
    ijk = grid[on_surface]
    v = np.stack([axes_coords[k][ijk[:, k]] for k in range(3)], axis=1)

    tris = []
    for axis in range(3):
        u_ax, w_ax = [k for k in range(3) if k != axis]
        iu, iw = np.meshgrid(np.arange(dims[u_ax]), np.arange(dims[w_ax]), indexing="ij")
        iu, iw = iu.reshape(-1), iw.reshape(-1)
        for side, level in ((-1.0, 0), (1.0, int(dims[axis]))):

            def corner(du: int, dw: int) -> np.ndarray:
                idx = [None, None, None]
                idx[axis] = np.full(iu.shape, level)
                idx[u_ax] = iu + du
                idx[w_ax] = iw + dw
                return index[idx[0], idx[1], idx[2]]

            q00, q10, q11, q01 = corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)
            t = np.concatenate([np.stack([q00, q10, q11], axis=1), np.stack([q00, q11, q01], axis=1)])
            a, b, c = _corners(v, t)
            wrong = np.cross(b - a, c - a)[:, axis] * side < 0.0
            t[wrong] = t[wrong][:, [0, 2, 1]]
            tris.append(t)
    return v, np.concatenate(tris)


def beam(
    length: float = 1.0, width: float = 0.2, height: float = 0.2, divisions: tuple[int, int, int] = (10, 2, 2)
) -> trimesh.Trimesh:
    """A box-shaped beam x in [0, length], y in [-width/2, width/2], z in [-height/2, height/2] [m].

    Every side is a grid of ``divisions = (nx, ny, nz)`` cells per axis, each quad split into two
    triangles, with vertices shared between sides (``(nx+1)(ny+1)(nz+1) - (nx-1)(ny-1)(nz-1)``
    vertices). The root face x = 0 is a natural place to clamp a cantilever.
    """
    length = _check_positive(length, "beam length")
    width = _check_positive(width, "beam width")
    height = _check_positive(height, "beam height")
    if not isinstance(divisions, (tuple, list)) or len(divisions) != 3:
        raise InvalidParameter(f"beam divisions must be a triple (nx, ny, nz), got {divisions!r}")
    div = tuple(_check_int(d, f"beam divisions[{k}]", 1) for k, d in enumerate(divisions))
    lo = np.array([0.0, -0.5 * width, -0.5 * height])
    hi = np.array([length, 0.5 * width, 0.5 * height])
    v, f = _box_surface(lo, hi, div)
    return _finish(v, f, "beam")


def torus(
    major_radius: float = 0.4, minor_radius: float = 0.15, major_sections: int = 48, minor_sections: int = 16
) -> trimesh.Trimesh:
    """A torus centred at the origin with the z axis as its axis of revolution.

    Vertices lie exactly on the analytic torus, so the polyhedral volume is
    ``2 pi^2 R r^2 * [M sin(2 pi/M) / 2 pi] * [m sin(2 pi/m) / 2 pi]`` (about 2.8 % below the analytic
    value at the default 48 x 16 sections, 0.7 % at 96 x 32).

    Args:
        major_radius: distance R [m] from the axis to the tube centre.
        minor_radius: tube radius r [m], r < R.
        major_sections: vertex rings around the axis (>= 3).
        minor_sections: vertices per ring (>= 3).
    """
    major_radius = _check_positive(major_radius, "torus major_radius")
    minor_radius = _check_positive(minor_radius, "torus minor_radius")
    if minor_radius >= major_radius:
        raise InvalidParameter(
            f"torus minor_radius {minor_radius:g} m must be smaller than major_radius {major_radius:g} m"
        )
    nu = _check_int(major_sections, "torus major_sections", 3)
    nv = _check_int(minor_sections, "torus minor_sections", 3)
    u = 2.0 * np.pi * np.arange(nu) / nu
    w = 2.0 * np.pi * np.arange(nv) / nv
    uu, ww = np.meshgrid(u, w, indexing="ij")
    rho = major_radius + minor_radius * np.cos(ww)
    v = np.stack([rho * np.cos(uu), rho * np.sin(uu), minor_radius * np.sin(ww)], axis=-1).reshape(-1, 3)
    i = np.arange(nu)[:, None]
    j = np.arange(nv)[None, :]
    ip, jp = (i + 1) % nu, (j + 1) % nv
    p00 = (i * nv + j).reshape(-1)
    p10 = (ip * nv + j).reshape(-1)
    p11 = (ip * nv + jp).reshape(-1)
    p01 = (i * nv + jp).reshape(-1)
    # d/du x d/dv points outwards (at u = v = 0 it is y x z = +x), so walk u first, then v.
    f = np.concatenate([np.stack([p00, p10, p11], axis=1), np.stack([p00, p11, p01], axis=1)])
    return _finish(v, f, "torus")


def bumpy_cube(size: float = 1.0, divisions: int = 8, amplitude: float = 0.05, seed: int = 0) -> trimesh.Trimesh:
    """A subdivided cube centred at the origin, displaced along its vertex normals by a smooth field.

    The cube (side ``size`` [m], ``divisions`` cells per edge, two triangles per cell) has every
    vertex moved by ``amplitude * size * g(x)`` along its area-weighted vertex normal, where ``g`` is a
    weighted sum of three plane waves of one to two wavelengths across the cube with random
    directions and phases, normalized so ``|g| <= 1``. Deterministic for a seed.

    Args:
        size: edge length [m].
        divisions: cells per cube edge (>= 1); 6 * divisions**2 + 2 vertices.
        amplitude: displacement relative to ``size``, in [0, 0.2).
        seed: random seed.
    """
    size = _check_positive(size, "bumpy_cube size")
    divisions = _check_int(divisions, "bumpy_cube divisions", 1)
    amplitude = _check_range(amplitude, "bumpy_cube amplitude", 0.0, 0.2)
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(3, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    wavenumbers = 2.0 * np.pi * rng.uniform(1.0, 2.0, size=3) / size  # [1/m]
    phases = rng.uniform(0.0, 2.0 * np.pi, size=3)
    weights = rng.uniform(0.5, 1.0, size=3)
    weights /= weights.sum()

    half = 0.5 * size
    v, f = _box_surface(np.full(3, -half), np.full(3, half), (divisions,) * 3)
    normals = vertex_normals(v, f)
    field = (np.cos((v @ dirs.T) * wavenumbers + phases) * weights).sum(axis=1)
    v = v + (amplitude * size * field)[:, None] * normals
    return _finish(v, f, "bumpy_cube")


# ----------------------------------------------------------------------------------------------
# winding number and inside/outside classification
# ----------------------------------------------------------------------------------------------


def _winding_number_arrays(v: np.ndarray, f: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Brute-force generalized winding number, chunked over points to bound memory."""
    q = points.shape[0]
    out = np.zeros(q, dtype=np.float64)
    m = f.shape[0]
    if q == 0 or m == 0:
        return out
    a, b, c = _corners(v, f)
    step = max(1, _WINDING_CHUNK_PAIRS // m)
    for start in range(0, q, step):
        pts = points[start : start + step]
        # Per-component (chunk, M) arrays: vectors from the query point to the three corners.
        ax, ay, az = (a[None, :, k] - pts[:, k, None] for k in range(3))
        bx, by, bz = (b[None, :, k] - pts[:, k, None] for k in range(3))
        cx, cy, cz = (c[None, :, k] - pts[:, k, None] for k in range(3))
        la = np.sqrt(ax * ax + ay * ay + az * az)
        lb = np.sqrt(bx * bx + by * by + bz * bz)
        lc = np.sqrt(cx * cx + cy * cy + cz * cz)
        det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        den = la * lb * lc
        den += (ax * bx + ay * by + az * bz) * lc
        den += (bx * cx + by * cy + bz * cz) * la
        den += (cx * ax + cy * ay + cz * az) * lb
        # van Oosterom & Strackee: tan(omega / 2) = det / den; atan2 keeps the correct branch.
        out[start : start + step] = np.arctan2(det, den).sum(axis=1)
    return out * (2.0 / (4.0 * np.pi))


def winding_number(vertices: Any, faces: Any, points: Any) -> np.ndarray:
    """Generalized winding number of a triangle surface at each query point, shape (Q,).

    Sum over faces of the signed solid angle (van Oosterom-Strackee formula) divided by 4 pi: about 1
    inside and 0 outside a closed outward-oriented surface, fractional for open surfaces. Cost is
    O(Q * M); the evaluation is chunked so memory stays bounded (about 40 MB) for any Q and M.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim == 1 and p.shape[0] == 3:
        p = p[None, :]
    if v.ndim != 2 or v.shape[1] != 3:
        raise InvalidMesh(f"{_prefix('mesh')}: vertices must have shape (N, 3), got {v.shape}")
    if f.size and (f.ndim != 2 or f.shape[1] != 3):
        raise InvalidMesh(f"{_prefix('mesh')}: faces must have shape (M, 3), got {f.shape}")
    if p.ndim != 2 or p.shape[1] != 3:
        raise InvalidParameter(f"winding_number points must have shape (Q, 3), got {p.shape}")
    return _winding_number_arrays(v, f.reshape(-1, 3).astype(np.int64), p)


def _closest_points_on_triangles(
    p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closest point on each triangle (a, b, c) to the matching p, all (K, 3).

    Returns ``(x, region)``; region says which feature holds the closest point: 0 = a, 1 = b,
    2 = edge ab, 3 = c, 4 = edge ac, 5 = edge bc, 6 = interior. The Voronoi-region tests follow the
    usual barycentric derivation, checked in the order a, b, ab, c, ac, bc, interior; only the
    (K,) barycentric weights are selected per region, so the cost stays a few passes over K.
    """

    def dot(u: np.ndarray, w: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", u, w)

    ab, ac = b - a, c - a
    ap = p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    # (p - b) . e = (p - a) . e - ab . e and (p - c) . e = (p - a) . e - ac . e
    ab_ab, ab_ac, ac_ac = dot(ab, ab), dot(ab, ac), dot(ac, ac)
    d3, d4 = d1 - ab_ab, d2 - ab_ac
    d5, d6 = d1 - ab_ac, d2 - ac_ac
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    conditions = [
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
    ]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        denom = va + vb + vc
        zero = np.zeros_like(d1)
        one = np.ones_like(d1)
        # x = a + v * ab + w * ac
        v = np.select(conditions, [zero, one, t_ab, zero, zero, 1.0 - t_bc], vb / denom)
        w = np.select(conditions, [zero, zero, zero, one, t_ac, t_bc], vc / denom)
    region = np.select(conditions, [0, 1, 2, 3, 4, 5], 6).astype(np.int8)
    x = a + ab * v[:, None] + ac * w[:, None]
    return x, region


def _linked_components(points: np.ndarray, link: float, k: int = 8) -> np.ndarray:
    """Label groups of points that are chained together by steps shorter than ``link`` [m].

    Points sharing a cell of side ``link / 2`` (diagonal 0.87 link) are merged directly; one point
    per cell is then joined to those of its k nearest cell representatives closer than ``link``.
    Looking at only k neighbours may split a group in two (costing one more winding-number
    evaluation), but never joins points farther apart than ``link``.
    """
    ijk = np.floor((points - points.min(axis=0)) / (0.5 * link)).astype(np.int64)
    _, first, cell_of = np.unique(ijk, axis=0, return_index=True, return_inverse=True)
    reps = points[first]
    m = reps.shape[0]
    kk = min(k + 1, m)
    dd, ii = cKDTree(reps).query(reps, k=kk, distance_upper_bound=link)
    dd = dd.reshape(m, kk)
    ii = ii.reshape(m, kk)
    ok = dd < link  # missing neighbours come back as inf / index m
    rows = np.repeat(np.arange(m), kk)[ok.reshape(-1)]
    cols = ii[ok]
    graph = coo_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)), shape=(m, m))
    _, labels = connected_components(graph, directed=False)
    return labels[cell_of.reshape(-1)]


class _InsideOracle:
    """Exact inside/outside classification of many points against one closed, consistently
    oriented surface, much faster than the brute-force winding number.

    For a closed surface the winding number is an integer, constant on each connected component of
    the complement, so it need not be summed over all faces for every point:

    * a point whose nearest face lies within a few edge lengths gets the sign of
      ``(p - x) . n`` where x is its closest surface point and n the angle-weighted pseudonormal of
      the feature (face, edge or vertex) holding x -- exact for closed manifold surfaces
      (Baerentzen & Aanaes); points with a vanishing sign fall back to the winding number;
    * points farther than ``rho`` from the surface are grouped into clusters whose surface-free
      balls overlap (same inside/outside state) and one winding number is evaluated per cluster.
    """

    def __init__(self, v: np.ndarray, f: np.ndarray) -> None:
        self.v = v
        self.f = f.astype(np.int64)
        a, b, c = _corners(v, self.f)
        self.a, self.b, self.c = a, b, c
        centroids = (a + b + c) / 3.0
        # Bounding radius of every face about its centroid: any surface point is within it of
        # some centroid, which gives exact distance bounds from a KD-tree over the centroids.
        self.centroids = centroids
        self.radii = np.sqrt(
            np.maximum.reduce([((corner - centroids) ** 2).sum(axis=1) for corner in (a, b, c)])
        )
        self.face_radius = float(self.radii.max())
        self.tree = cKDTree(centroids)
        self.scale = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))

        n_raw = np.cross(b - a, c - a)
        fn = n_raw / np.linalg.norm(n_raw, axis=1, keepdims=True)
        self.face_normal = fn
        n = v.shape[0]
        src = self.f.reshape(-1)
        dst = self.f[:, [1, 2, 0]].reshape(-1)
        _, edge_id = np.unique(_edge_keys(src, dst, n), return_inverse=True)
        edge_id = edge_id.reshape(-1)
        # Edge pseudonormal: sum of the two adjacent unit face normals.
        self.edge_normal = _scatter_add_rows(edge_id, np.repeat(fn, 3, axis=0), int(edge_id.max()) + 1)
        self.face_edges = edge_id.reshape(-1, 3)  # columns: ab, bc, ca
        # Vertex pseudonormal: face normals weighted by the incident angle.
        corners = (a, b, c)
        angles = np.empty((self.f.shape[0], 3))
        for k in range(3):
            e1 = corners[(k + 1) % 3] - corners[k]
            e2 = corners[(k + 2) % 3] - corners[k]
            angles[:, k] = np.arctan2(np.linalg.norm(np.cross(e1, e2), axis=1), np.einsum("ij,ij->i", e1, e2))
        weighted = (angles[:, :, None] * fn[:, None, :]).reshape(-1, 3)
        self.vertex_normal = _scatter_add_rows(src, weighted, n)

    def _nearest(self, pts: np.ndarray, owner: np.ndarray, cand: np.ndarray, n: int) -> tuple[np.ndarray, ...]:
        """Closest candidate face of each of n points; ``owner`` (sorted) says which point each
        candidate face ``cand`` belongs to, and every point has at least one candidate.

        Returns per point: squared distance [m^2], closest point [m], region code, face index.
        """
        po = pts[owner]
        x, region = _closest_points_on_triangles(po, self.a[cand], self.b[cand], self.c[cand])
        d2 = ((po - x) ** 2).sum(axis=1)
        # owner is sorted (candidates are generated point by point): segment minima, then the
        # first pair of each point that attains its minimum.
        starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
        d2min = np.minimum.reduceat(d2, starts)
        hit = np.flatnonzero(d2 == d2min[owner])
        best = hit[np.r_[True, owner[hit][1:] != owner[hit][:-1]]]
        return d2[best], x[best], region[best], cand[best]

    def classify(self, points: np.ndarray, rho: float) -> tuple[np.ndarray, np.ndarray]:
        """Return ``(inside, dist)``: inside flags and the distance [m] to the surface, exact for
        points near it and ``rho`` (a lower bound) for points farther than ``rho``."""
        q = points.shape[0]
        inside = np.zeros(q, dtype=bool)
        dist = np.full(q, rho, dtype=np.float64)
        far = np.zeros(q, dtype=bool)
        ambiguous = np.zeros(q, dtype=bool)
        k = min(32, self.f.shape[0])
        k_first = min(4, k)
        bound = rho + self.face_radius
        slack = 1e-9 * self.scale + 1e-300
        for start in range(0, q, _ORACLE_CHUNK_POINTS):
            pts = points[start : start + _ORACLE_CHUNK_POINTS]
            m = pts.shape[0]
            # k nearest face centroids within rho + face_radius. Bounding the search keeps deep
            # interior points cheap (near the centre of a sphere every face is almost equally
            # near, the KD-tree's worst case); no centroid in range means farther than rho.
            dk, ik = self.tree.query(pts, k=k, distance_upper_bound=bound)
            dk = dk.reshape(m, k)
            ik = ik.reshape(m, k)
            near = np.isfinite(dk[:, 0])
            far[start : start + m] = ~near
            sel = np.flatnonzero(near)
            if sel.size == 0:
                continue
            p_near = pts[sel]
            dk, ik = dk[sel], ik[sel]
            # Upper bound u on the distance from the few nearest faces, then only faces whose
            # bounding ball reaches within u (|p - centroid| - radius <= u) can hold the closest
            # point: this removes most candidate pairs before the exact computation.
            valid = np.isfinite(dk[:, :k_first])
            owner = np.nonzero(valid)[0]
            d2, _, _, _ = self._nearest(p_near, owner, ik[:, :k_first][valid], sel.size)
            u = np.sqrt(d2)
            valid = np.isfinite(dk)
            valid[valid] = dk[valid] - self.radii[ik[valid]] <= (u[:, None] + slack).repeat(k, axis=1)[valid]
            owner = np.nonzero(valid)[0]
            d2, x, reg, fi = self._nearest(p_near, owner, ik[valid], sel.size)
            u = np.sqrt(d2)
            # Exact unless a face beyond the k nearest centroids could still be closer: its
            # centroid would lie within u + face_radius, beyond the k-th (or beyond the search
            # bound when fewer than k were in range).
            kth = dk[:, -1]
            enough = np.where(np.isfinite(kth), kth > u + self.face_radius + slack, u + slack <= rho)
            redo = np.flatnonzero(~enough)
            if redo.size:
                lists = self.tree.query_ball_point(
                    p_near[redo], u[redo] + self.face_radius + slack, return_sorted=False
                )
                counts = np.fromiter(map(len, lists), dtype=np.int64, count=redo.size)
                cand2 = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(counts.sum()))
                owner2 = np.repeat(np.arange(redo.size), counts)
                reach = np.linalg.norm(p_near[redo][owner2] - self.centroids[cand2], axis=1) - self.radii[cand2]
                keep = reach <= u[redo][owner2] + slack
                d2r, xr, regr, fir = self._nearest(p_near[redo], owner2[keep], cand2[keep], redo.size)
                d2[redo], x[redo], reg[redo], fi[redo] = d2r, xr, regr, fir

            # Sign of (p - x) . pseudonormal of the feature holding x.
            fv = self.f[fi]
            fe = self.face_edges[fi]
            options = np.stack(
                [
                    self.vertex_normal[fv[:, 0]],  # region 0: vertex a
                    self.vertex_normal[fv[:, 1]],  # 1: vertex b
                    self.edge_normal[fe[:, 0]],  # 2: edge ab
                    self.vertex_normal[fv[:, 2]],  # 3: vertex c
                    self.edge_normal[fe[:, 2]],  # 4: edge ca
                    self.edge_normal[fe[:, 1]],  # 5: edge bc
                    self.face_normal[fi],  # 6: interior
                ],
                axis=1,
            )
            pn = options[np.arange(sel.size), reg]
            pn_len = np.linalg.norm(pn, axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.einsum("ij,ij->i", p_near - x, pn) / pn_len
            gi = start + sel
            dist[gi] = np.sqrt(d2)
            inside[gi] = s < 0.0
            ambiguous[gi] = ~(np.abs(s) > 1e-12 * self.scale)

        amb = np.flatnonzero(ambiguous)
        if amb.size:
            inside[amb] = _winding_number_arrays(self.v, self.f, points[amb]) > 0.5

        far_idx = np.flatnonzero(far)
        if far_idx.size:
            # Each far point has a surface-free ball of radius > rho, so two far points less than
            # 2 rho apart have overlapping balls and are on the same side of the surface.
            labels = _linked_components(points[far_idx], 2.0 * rho)
            # Representative of each cluster: any member (all are more than rho from the surface).
            order = np.argsort(labels, kind="stable")
            first = order[np.r_[True, labels[order][1:] != labels[order][:-1]]]
            w = _winding_number_arrays(self.v, self.f, points[far_idx[first]])
            state = np.zeros(int(labels.max()) + 1, dtype=bool)
            state[labels[first]] = w > 0.5
            inside[far_idx] = state[labels]
        return inside, dist


# ----------------------------------------------------------------------------------------------
# tetrahedralization
# ----------------------------------------------------------------------------------------------


def _grid_candidates(v: np.ndarray, spacing: float) -> np.ndarray:
    """Body-centred cubic lattice with one point per spacing^3 [m^3], centred in the bounding box
    shrunk by spacing/2 (points outside that box cannot be inside the surface and spacing/2 away
    from it).

    A simple cubic grid has eight co-spherical points in every cell, so its Delaunay
    tetrahedralization is degenerate: Qhull is several times slower on it and emits thousands of
    zero-volume tets whose removal leaves neighbouring tets with mismatched faces. The BCC lattice
    (cube corners plus cube centres, cube edge spacing * 2^(1/3)) has a unique Delaunay
    tetrahedralization of congruent, well-shaped tets (edges 1.09 and 1.26 spacing).
    """
    a = spacing * 2.0 ** (1.0 / 3.0)
    lo = v.min(axis=0) + 0.5 * spacing
    hi = v.max(axis=0) - 0.5 * spacing
    ext = hi - lo
    if (ext < 0).any():
        return np.zeros((0, 3))
    counts = np.floor(ext / a + 1e-9).astype(np.int64) + 1
    total = 2 * int(np.prod(counts + 1))
    if total > 50_000_000:
        raise InvalidParameter(
            f"tetrahedralize spacing {spacing:g} m would need {total} grid candidates; use a larger spacing"
        )
    start = 0.5 * (lo + hi) - 0.5 * (counts - 1) * a
    corner_axes = [start[k] + a * np.arange(counts[k]) for k in range(3)]
    centre_axes = [start[k] + a * (np.arange(counts[k] + 1) - 0.5) for k in range(3)]
    corners = np.stack(np.meshgrid(*corner_axes, indexing="ij"), axis=-1).reshape(-1, 3)
    centres = np.stack(np.meshgrid(*centre_axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return np.vstack([corners, centres])


def tetrahedralize(
    vertices: Any, faces: Any, spacing: float | None = None, name: str = "mesh"
) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedral volume mesh of a closed surface.

    Points are the surface vertices (``points[:N]`` equals the input vertices exactly, in the same
    order) followed by the nodes of a regular body-centred cubic grid with one node per
    ``spacing^3`` (cube edge ``spacing * 2^(1/3)``, nearest nodes ``1.09 * spacing`` apart) that lie
    inside the surface and at least ``0.5 * spacing`` [m] from it; BCC rather than simple cubic
    because the latter's co-spherical cells make the Delaunay step degenerate (see
    :func:`_grid_candidates`). Tets are the Delaunay tetrahedralization of all points,
    keeping those with volume > 1e-10 * spacing^3 whose centroid is inside the surface (generalized
    winding number > 0.5); every returned tet has a positive determinant (vertices reordered where
    needed).

    The inside tests use the exact classification of :class:`_InsideOracle`, which equals the
    winding-number test for the closed, consistently oriented surfaces that ``check_surface``
    admits, evaluating the brute-force winding number only where the surface leaves it undecided.

    Args:
        vertices, faces: the surface (see :func:`surface_arrays`); must pass
            ``check_surface(closed=True)``.
        spacing: interior grid spacing [m]; default the mean surface edge length.
        name: the object's name, used at the start of error messages (see the module docstring).

    Returns:
        ``(points, tets)``: float64 (P, 3) [m] and int32 (T, 4).
    """
    check_surface(vertices, faces, name, closed=True)
    v, f = surface_arrays((vertices, faces), name)
    e = edges(f)
    mean_edge = float(np.linalg.norm(v[e[:, 1]] - v[e[:, 0]], axis=1).mean())
    h = mean_edge if spacing is None else _check_positive(spacing, "tetrahedralize spacing")

    oracle = _InsideOracle(v, f)
    # Points within rho of the surface are classified locally; rho >= h/2 also guarantees that
    # every grid point left unmeasured is at least h/2 from the surface.
    rho = max(h, mean_edge)
    grid = _grid_candidates(v, h)
    grid_dist = np.zeros(0)
    if grid.shape[0]:
        inside, dist = oracle.classify(grid, rho)
        keep = inside & (dist >= 0.5 * h)
        grid, grid_dist = grid[keep], dist[keep]
    points = np.vstack([v, grid])
    # Radius of a surface-free ball around every point (0 for surface vertices).
    clearance = np.concatenate([np.zeros(v.shape[0]), grid_dist])

    try:
        tets = Delaunay(points).simplices.astype(np.int64)
    except QhullError as exc:
        raise InvalidMesh(f"{_prefix(name)}: Delaunay tetrahedralization failed: {exc}") from None
    p0 = points[tets[:, 0]]
    det = np.einsum(
        "ij,ij->i", points[tets[:, 1]] - p0, np.cross(points[tets[:, 2]] - p0, points[tets[:, 3]] - p0)
    )
    flip = det < 0.0
    tets[flip] = tets[flip][:, [0, 1, 3, 2]]
    tets = tets[np.abs(det) > 6.0 * 1e-10 * h**3]  # det = 6 * volume
    if tets.shape[0]:
        corners = points[tets]
        centroids = corners.mean(axis=1)
        # A centroid within the surface-free ball of one of its tet's interior grid points is
        # inside (the ball lies inside); only the others need the oracle.
        covered = (np.linalg.norm(corners - centroids[:, None, :], axis=2) < clearance[tets]).any(axis=1)
        inside = covered.copy()
        rest = np.flatnonzero(~covered)
        if rest.size:
            inside[rest] = oracle.classify(centroids[rest], rho)[0]
        tets = tets[inside]
    if tets.shape[0] == 0:
        raise InvalidMesh(
            f"{_prefix(name)}: tetrahedralization produced no tetrahedra inside the surface "
            f"(spacing {h:.3g} m)"
        )
    return points, np.ascontiguousarray(tets, dtype=np.int32)
