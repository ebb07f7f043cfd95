"""Meshes from a USD stage: ``load_usd`` reads one ``UsdGeom.Mesh`` prim as a wsim triangle surface.

What is converted (so the result follows :mod:`wsim.mesh`'s conventions):

* ``points`` at a time code (default: the stage's start time code, else the points' first sample,
  else the default value), moved to world by the prim's local-to-world transform (USD matrices act
  on row vectors);
* units: times the stage's ``metersPerUnit`` (``UsdGeom.GetStageMetersPerUnit``; USD's fallback
  when the stage does not author it is 0.01, centimetres);
* axes: a Z-up stage is rotated to wsim's Y-up world, (x, y, z) -> (x, z, -y);
* faces: ``faceVertexCounts`` / ``faceVertexIndices`` polygons fan-triangulated in order (polygon
  k with n corners gives n - 2 triangles (c0, ci, ci+1)); ``orientation = leftHanded`` (or a
  mirroring transform) reverses the winding so faces are counter-clockwise seen from outside;
  holes (``holeIndices``) are refused;
* texture coordinates: the ``st`` primvar (else ``uv`` or ``st0``), any interpolation (vertex,
  varying, faceVarying, uniform, constant), indexed or not, as per-corner UVs (F, 3, 2) float32 in
  the triangles' order in ``metadata["wsim_face_uv"]`` (read by ``wsim.mesh.face_uvs``).

``metadata["wsim_source"]`` makes ``wsim.mesh.display_name`` give the prim's name when a prim
path was given (``"set.usd:/World/table"`` -> ``table``), else the file's stem.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from wsim.errors import InvalidMesh

#: file extensions ``wsim.mesh.load`` hands to ``load_usd``
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")

#: names of the texture-coordinate primvar, in order of preference
UV_PRIMVARS = ("st", "uv", "st0")

# the most mesh prims an error message lists by name
_LIST_MAX = 12


def _tf_reason(exc: BaseException) -> str:
    """One line from a pxr error: the first quoted message of a Tf.ErrorException, else str(exc)."""
    text = str(exc)
    m = re.search(r" : '(.*?)'(?:\n|$)", text, flags=re.S)
    reason = m.group(1) if m else text
    reason = " ".join(re.sub(r"pxrInternal_\w+?__pxrReserved__(::|_)?", "", reason).split())
    return (reason or type(exc).__name__)[:200]


def split_prim_path(path: str | os.PathLike) -> tuple[str | os.PathLike, str | None]:
    """``"set.usd:/World/table"`` -> ``("set.usd", "/World/table")``; anything else -> ``(path, None)``.

    The prim path is the text after the last ':' when it starts with '/' and the text before it is
    a USD file name (so ``C:/models/set.usd`` keeps its drive letter); an existing file whose name
    holds such a colon is taken whole."""
    if not isinstance(path, str):
        return path, None
    head, sep, tail = path.rpartition(":")
    if not sep or not tail.startswith("/") or Path(head).suffix.lower() not in USD_SUFFIXES:
        return path, None
    if Path(path).expanduser().is_file():
        return path, None
    return head, tail


def _time_code(stage: Any, points_attr: Any, time: float | None) -> Any:
    from pxr import Usd

    if time is not None:
        return Usd.TimeCode(float(time))
    if stage.HasAuthoredTimeCodeRange():
        return Usd.TimeCode(stage.GetStartTimeCode())
    samples = points_attr.GetTimeSamples()
    return Usd.TimeCode(samples[0]) if samples else Usd.TimeCode.Default()


def _mesh_prims(stage: Any) -> list[Any]:
    from pxr import UsdGeom

    return [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]


def _listing(prims: list[Any]) -> str:
    names = [str(p.GetPath()) for p in prims[:_LIST_MAX]]
    more = f", ... ({len(prims) - _LIST_MAX} more)" if len(prims) > _LIST_MAX else ""
    return ", ".join(names) + more


def _find_prim(stage: Any, prim: str | None, label: str, file: str) -> Any:
    """The Mesh prim at ``prim``, or the stage's only Mesh prim when ``prim`` is None."""
    from pxr import Sdf, UsdGeom

    if prim is None:
        meshes = _mesh_prims(stage)
        if len(meshes) == 1:
            return meshes[0]
        if not meshes:
            raise InvalidMesh(f"mesh '{label}': '{file}' holds no mesh prims (UsdGeom.Mesh)")
        raise InvalidMesh(
            f"mesh '{label}': '{file}' holds {len(meshes)} mesh prims; say which one "
            f"(load_usd(path, prim) or '{file}:/path/to/prim'): {_listing(meshes)}"
        )
    text = str(prim)
    if not text.startswith("/"):
        text = "/" + text
    if not Sdf.Path.IsValidPathString(text) or not Sdf.Path(text).IsPrimPath():
        raise InvalidMesh(f"mesh '{label}': '{prim}' is not a valid prim path (e.g. /World/bunny)")
    p = stage.GetPrimAtPath(text)
    if not p or not p.IsValid():
        meshes = _mesh_prims(stage)
        hint = f"; mesh prims: {_listing(meshes)}" if meshes else "; the stage holds no mesh prims"
        raise InvalidMesh(f"mesh '{label}': no prim '{text}' in '{file}'{hint}")
    if not p.IsA(UsdGeom.Mesh):
        raise InvalidMesh(
            f"mesh '{label}': prim '{text}' in '{file}' is not a Mesh (UsdGeom.Mesh) but "
            f"{repr(str(p.GetTypeName())) if p.GetTypeName() else 'a typeless prim'}"
        )
    return p


def _triangulate(counts: np.ndarray, indices: np.ndarray, n_points: int, p: str
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Fan triangulation: (T, 3) corner numbers (positions in faceVertexIndices) and (T,) polygon
    of each triangle."""
    if counts.size and counts.min() < 3:
        k = int(np.argmax(counts < 3))
        raise InvalidMesh(f"{p}: face {k} has {int(counts[k])} vertices (faceVertexCounts); at least 3 needed")
    if int(counts.sum()) != len(indices):
        raise InvalidMesh(
            f"{p}: faceVertexCounts add up to {int(counts.sum())} but faceVertexIndices has {len(indices)} entries"
        )
    if len(indices) and (indices.min() < 0 or indices.max() >= n_points):
        k = int(np.argmax((indices < 0) | (indices >= n_points)))
        raise InvalidMesh(
            f"{p}: faceVertexIndices[{k}] = {int(indices[k])} is outside [0, {n_points - 1}] (points)"
        )
    start = np.concatenate(([0], np.cumsum(counts)[:-1])).astype(np.int64)
    n_tri = counts - 2
    poly = np.repeat(np.arange(len(counts)), n_tri)
    # local fan index 1..n-2 of each triangle within its polygon
    first_tri = np.concatenate(([0], np.cumsum(n_tri)[:-1])).astype(np.int64)
    k = np.arange(int(n_tri.sum())) - np.repeat(first_tri, n_tri) + 1
    s = start[poly]
    corners = np.stack([s, s + k, s + k + 1], axis=1)
    return corners, poly


def _face_uvs(prim: Any, tc: Any, corners: np.ndarray, poly: np.ndarray, indices: np.ndarray,
              n_points: int, n_faces: int, p: str) -> np.ndarray | None:
    """(T, 3, 2) float32 UVs at the triangles' corners from the st/uv/st0 primvar, or None."""
    from pxr import UsdGeom

    api = UsdGeom.PrimvarsAPI(prim)
    pv = next((api.GetPrimvar(n) for n in UV_PRIMVARS if api.HasPrimvar(n)), None)
    if pv is None or not pv.HasValue():
        return None
    name = pv.GetPrimvarName()
    raw = pv.ComputeFlattened(tc)
    if raw is None:
        return None
    uv = np.asarray(raw, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] < 2:
        raise InvalidMesh(f"{p}: primvar '{name}' must hold 2-component texture coordinates, got shape {uv.shape}")
    uv = uv[:, :2]
    interp = pv.GetInterpolation()
    if interp in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying):
        need, at = n_points, indices[corners]
    elif interp == UsdGeom.Tokens.faceVarying:
        need, at = len(indices), corners
    elif interp == UsdGeom.Tokens.uniform:
        need, at = n_faces, np.repeat(poly[:, None], 3, axis=1)
    elif interp == UsdGeom.Tokens.constant:
        need, at = 1, np.zeros_like(corners)
    else:
        raise InvalidMesh(f"{p}: primvar '{name}' has unknown interpolation '{interp}'")
    if len(uv) != need:
        raise InvalidMesh(f"{p}: primvar '{name}' ({interp}) has {len(uv)} values, expected {need}")
    return uv[at].astype(np.float32)


def load_usd(path: str | os.PathLike, prim: str | None = None, time: float | None = None) -> trimesh.Trimesh:
    """Read one ``UsdGeom.Mesh`` prim of a USD stage as a triangle mesh in wsim's conventions.

    Args:
        path: a ``.usd``, ``.usda``, ``.usdc`` or ``.usdz`` file.
        prim: the mesh prim's path (``"/World/bunny"``); None takes the stage's only mesh prim
            (an error lists them when there are several).
        time: the time code to read ``points`` and transforms at; None: the stage's start time
            code (else the points' first sample, else their default value).

    Returns:
        A ``trimesh.Trimesh`` (``process=False``: USD's point order kept; polygons fan-triangulated
        in order) in world coordinates: metres, Y up, faces counter-clockwise seen from outside.
        ``metadata["wsim_face_uv"]``: (F, 3, 2) float32 corner UVs when the prim has an
        ``st``/``uv``/``st0`` primvar; ``metadata["wsim_source"]``: see :mod:`wsim.mesh.stage`.

    Raises:
        InvalidMesh: a missing or unreadable file, a missing prim or one that is not a Mesh,
            several meshes and no ``prim``, holes, inconsistent topology or texture coordinates.
    """
    file = Path(path).expanduser()
    label = f"{file.name}:{prim}" if prim is not None else file.name
    if not file.is_file():
        raise InvalidMesh(f"mesh '{label}': file '{file}' not found")
    from pxr import Usd, UsdGeom

    try:
        stage = Usd.Stage.Open(str(file))
    except Exception as exc:  # pxr raises Tf.ErrorException for unreadable layers
        raise InvalidMesh(f"mesh '{label}': cannot read USD file '{file}': {_tf_reason(exc)}") from None
    if stage is None:
        raise InvalidMesh(f"mesh '{label}': cannot read USD file '{file}'")
    found = _find_prim(stage, prim, label, str(file))
    prim_path = str(found.GetPath())
    p = f"mesh '{file.name}:{prim_path}'"
    mesh = UsdGeom.Mesh(found)

    points_attr = mesh.GetPointsAttr()
    tc = _time_code(stage, points_attr, time)
    raw = points_attr.Get(tc)
    points = np.asarray(raw, dtype=np.float64).reshape(-1, 3) if raw is not None else np.zeros((0, 3))
    if len(points) == 0:
        raise InvalidMesh(f"{p}: no points (at time code {tc})")
    holes = mesh.GetHoleIndicesAttr().Get(tc)
    if holes is not None and len(holes):
        raise InvalidMesh(
            f"{p}: {len(holes)} faces are holes (holeIndices, e.g. face {int(holes[0])}); "
            f"wsim needs a surface without holes: remove those faces instead"
        )
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(tc) or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(tc) or [], dtype=np.int64)
    if len(counts) == 0:
        raise InvalidMesh(f"{p}: no faces (faceVertexCounts is empty)")
    corners, poly = _triangulate(counts, indices, len(points), p)
    faces = indices[corners]
    uv = _face_uvs(found, tc, corners, poly, indices, len(points), len(counts), p)

    # to world: USD matrices act on row vectors, x' = [x, 1] M
    m = np.array(UsdGeom.XformCache(tc).GetLocalToWorldTransform(found), dtype=np.float64)
    v = points @ m[:3, :3] + m[3, :3]
    v *= float(UsdGeom.GetStageMetersPerUnit(stage))
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z:
        v = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)  # a proper rotation: winding unchanged
    left = mesh.GetOrientationAttr().Get(tc) == UsdGeom.Tokens.leftHanded
    if left != (np.linalg.det(m[:3, :3]) < 0):  # clockwise faces, or a mirroring transform
        faces = faces[:, [0, 2, 1]]
        if uv is not None:
            uv = uv[:, [0, 2, 1]]
    if not np.isfinite(v).all():
        raise InvalidMesh(f"{p}: non-finite point coordinates")

    out = trimesh.Trimesh(vertices=v, faces=faces.astype(np.int64), process=False)
    out.metadata["wsim_source"] = f"{file}:{prim_path}" if prim is not None else str(file)
    out.metadata["wsim_usd_prim"] = prim_path
    if uv is not None:
        out.metadata["wsim_face_uv"] = np.ascontiguousarray(uv, dtype=np.float32)
    return out
