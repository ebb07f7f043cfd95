"""Surface input and measures: wsim's array convention for a triangle surface (``surface_arrays``),
mesh files (``load``, ``load_fitted``) and per-face / per-vertex quantities (volume, areas, normals).

See :mod:`wsim.mesh` for the conventions (float64 (N, 3) vertices [m], int32 (M, 3) outward faces,
error messages that start with the object's name).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from wsim.errors import InvalidMesh
from wsim.mesh._common import _corners, _fmt_vec, _positive, _prefix, _scatter_add_rows


def _vertices_array(raw: Any, name: str) -> np.ndarray:
    """Vertices as a C-contiguous float64 (N, 3) copy [m]: N >= 1, all coordinates finite."""
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
    """Faces as int32 (M, 3) indices in [0, n_vertices); (0, 3) for a particle set with no surface."""
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


def surface_arrays(mesh: trimesh.Trimesh | tuple[Any, Any], name: str = "mesh", *,
                   merge_vertices: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Convert a surface to wsim's array convention.

    Args:
        mesh: a ``trimesh.Trimesh`` or a ``(vertices, faces)`` pair of array-likes; vertex
            coordinates in metres.
        name: the object's name, used at the start of error messages (see :mod:`wsim.mesh`).
        merge_vertices: merge vertices at the same position first (``merge_coincident_vertices``:
            a mesh whose faces each have their own corners becomes one surface). Vertex indices
            then refer to the merged vertices: the first of each coincident set, in their order.

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
    if merge_vertices and f.shape[0]:
        v, f, _ = merge_coincident_vertices(v, f)
    return v, f


# Vertices closer than this fraction of the bounding-box diagonal are at "the same position".
_COINCIDENT_FRACTION = 1e-9


def coincident_vertices(vertices: np.ndarray) -> np.ndarray:
    """(N,) for each vertex the index of the first vertex at the same position (itself if none is
    earlier): closer than 1e-9 times the bounding-box diagonal, chained."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, dtype=np.float64)
    n = v.shape[0]
    index = np.arange(n)
    if n < 2:
        return index
    tol = _COINCIDENT_FRACTION * float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    pairs = cKDTree(v).query_pairs(tol, output_type="ndarray")
    if not len(pairs):
        return index
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    first = np.full(int(label.max()) + 1, n)
    np.minimum.at(first, label, index)
    return first[label]


def merge_coincident_vertices(vertices: Any, faces: Any) -> tuple[np.ndarray, np.ndarray, int]:
    """Merge vertices at the same position (``coincident_vertices``), like trimesh's
    ``mesh.merge_vertices()``: returns ``(V, F, n_merged)`` with the first vertex of each coincident
    set kept (in the original order), the faces renumbered onto them (int32) and the number of
    vertices removed."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    rep = coincident_vertices(v)
    keep = rep == np.arange(v.shape[0])
    new_index = np.cumsum(keep) - 1
    return v[keep], new_index[rep][f].astype(np.int32).reshape(-1, 3), int((~keep).sum())


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


def face_normals(vertices: Any, faces: Any) -> np.ndarray:
    """(M, 3) unit outward normals of the triangles (zero for a degenerate one)."""
    a, b, c = _corners(np.asarray(vertices, dtype=np.float64), np.asarray(faces))
    n = np.cross(b - a, c - a)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


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


def load(path: str | os.PathLike, name: str | None = None) -> trimesh.Trimesh:
    """Load a surface mesh file (OBJ, PLY, STL, GLB, ...) as one triangle mesh, or InvalidMesh.
    A USD file (``.usd/.usda/.usdc/.usdz``, optionally ``file.usd:/World/prim``) goes to ``load_usd``.

    Vertices at the same position are merged (``merge_coincident_vertices``), the texture
    coordinates kept per face corner first (``face_uvs``): file formats split a vertex wherever
    its UV or normal changes, which would leave a textured model open (not watertight) for every
    method. Faces keep their order."""
    from wsim.mesh.stage import USD_SUFFIXES, load_usd, split_prim_path  # here: no import cycle

    file, prim = split_prim_path(path)
    if prim is not None or Path(file).suffix.lower() in USD_SUFFIXES:
        return load_usd(file, prim)
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
    uv, color = face_uvs(m), face_colors(m)
    v, f, merged = merge_coincident_vertices(m.vertices, m.faces)
    if merged:
        m = trimesh.Trimesh(v, f, process=False, metadata=dict(m.metadata))
        if uv is not None:
            m.metadata["wsim_face_uv"] = uv
        if color is not None:
            m.metadata["wsim_face_color"] = color
    m.metadata["wsim_source"] = str(p)
    return m


def display_name(mesh: Any, default: str) -> str:
    """The name of a body made from ``mesh`` (its USD prim ``/World/<name>``): the file's stem when
    the mesh came from a file (``load``, ``load_fitted``: a user's ``--mesh bunny.obj`` becomes
    ``bunny``), else ``default`` (a scene's procedural shape)."""
    source = getattr(mesh, "metadata", {}).get("wsim_source") if isinstance(mesh, trimesh.Trimesh) else None
    return Path(source).stem if source else default


def _per_corner(mesh: Any, key: str, per_vertex: Any, width: int) -> np.ndarray | None:
    """(F, 3, width) float32 per face corner: ``mesh.metadata[key]`` if set (kept across ``load``'s
    vertex merge, or set by the USD loader), else the per-vertex array ``per_vertex`` at the
    faces' corners; None when neither fits the mesh."""
    if not isinstance(mesh, trimesh.Trimesh):
        return None
    kept = mesh.metadata.get(key)
    if kept is not None:
        kept = np.asarray(kept, dtype=np.float32)
        return kept if kept.shape == (len(mesh.faces), 3, width) else None
    if per_vertex is None or len(per_vertex) != len(mesh.vertices):
        return None
    return np.asarray(per_vertex, dtype=np.float32)[np.asarray(mesh.faces)]


def face_colors(mesh: Any) -> np.ndarray | None:
    """(F, 3, 3) float32 RGB in [0, 1] at each face's corners, in face order, or None: a mesh file's
    vertex colours (PLY, OBJ with colours, GLB: trimesh's ``visual.vertex_colors`` when its kind is
    "vertex"), or ``metadata["wsim_face_color"]``."""
    visual = getattr(mesh, "visual", None)
    rgb = None
    if getattr(visual, "kind", None) == "vertex":
        rgb = np.asarray(visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0
    return _per_corner(mesh, "wsim_face_color", rgb, 3)


def face_uvs(mesh: Any) -> np.ndarray | None:
    """(F, 3, 2) float32 texture coordinates at each face's corners, in the mesh's face order, or
    None when the mesh has none: ``metadata["wsim_face_uv"]`` (set by the USD loader), else
    trimesh's per-vertex ``visual.uv`` (OBJ, GLB, PLY files with texture coordinates). Per corner,
    so a UV seam survives merging the seam's vertices (``merge_vertices=True``)."""
    return _per_corner(mesh, "wsim_face_uv", getattr(getattr(mesh, "visual", None), "uv", None), 2)


#: ``wsim run --mesh-scale S`` sets this: scenes then use a ``--mesh`` model in its own units times S
#: instead of fitting it to their size (``load_fitted``)
MESH_SCALE_ENV = "WSIM_MESH_SCALE"


def load_fitted(path: str | os.PathLike, size: float, scale: float | None = None) -> trimesh.Trimesh:
    """Load a mesh file and centre its bounding box at the origin (how scenes place a user's
    ``--mesh`` model): its longest side scaled to ``size`` [m], or, with ``scale`` (or
    ``$WSIM_MESH_SCALE``, set by ``wsim run --mesh-scale``), the file's own units times ``scale``.
    Says which on the ``wsim`` logger (the CLI prints it)."""
    import logging

    m = load(path)
    m.apply_translation(-m.bounding_box.centroid)
    env = os.environ.get(MESH_SCALE_ENV)
    if scale is None and env:
        try:
            scale = float(env)
        except ValueError:
            raise InvalidMesh(f"mesh '{Path(path).name}': ${MESH_SCALE_ENV} = {env!r} is not a number") from None
    if scale is not None:
        k = _positive(scale, f"mesh '{Path(path).name}': scale")
        how = f"its own units x {k:g}"
    else:
        k = _positive(size, "fitted mesh size") / max(m.extents)
        how = f"fitted: longest side {size:g} m (x {k:.4g}; --mesh-scale S keeps its own units x S)"
    m.apply_scale(k)
    logging.getLogger("wsim").info("mesh '%s': %s, %s m across", Path(path).name, how,
                                   " x ".join(f"{e:.3g}" for e in m.extents))
    return m
