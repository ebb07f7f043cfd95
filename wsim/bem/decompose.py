"""Domain decomposition (paper Sec. 3.4): a body made of closed subdomains joined at their interfaces.

Each subdomain is a closed BEM body of its own, with smaller matrices and a smaller n_max (n_max
grows with the body's size); neighbours are held together by point joints at the vertices their
meshes share (the interface must be triangulated the same way on both sides, so its vertices
coincide). Subdomains of the same shape (up to a translation) share one operator set: it is built
once and held once in memory (the five cubes of the paper's Fig. 9).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from scipy.spatial import cKDTree

from wsim import mesh as wmesh
from wsim.bem.body import BemBody
from wsim.bem.operators import build_operators
from wsim.constraints import PointJoint
from wsim.errors import InvalidMesh, InvalidParameter
from wsim.materials import ElasticMaterial


def decompose(
    pieces: Sequence[Any],
    material: ElasticMaterial,
    dt: float,
    *,
    name: str = "body",
    device: Any = None,
    tol: float = 1e-6,
    build: dict[str, Any] | None = None,
    **body_kw: Any,
) -> tuple[list[BemBody], list[PointJoint]]:
    """BEM bodies for the closed subdomain meshes ``pieces`` (world positions) and the joints
    between every pair that shares vertices. Add the bodies and the joints to a World.

    Args:
        pieces: closed, outward meshes (``trimesh.Trimesh`` or (vertices, faces)) [m] that meet
            along triangulated interfaces with coincident vertices.
        name: bodies are named ``{name}_0``, ``{name}_1``, ...
        device: where the operator sets are built (the World's device).
        tol: vertices closer than ``tol`` times the largest piece's size are one interface point.
        build: keyword arguments of ``build_operators`` (precision, double_nodes, n_max, cache, ...).
        **body_kw: keyword arguments of every ``BemBody`` (frame_update, friction, velocity, ...).
    """
    if len(pieces) < 2:
        raise InvalidParameter(f"decompose '{name}': needs at least two subdomains, got {len(pieces)}")
    build = dict(build or {})
    meshes = [wmesh.surface_arrays(p, f"decompose '{name}': piece {k}") for k, p in enumerate(pieces)]
    size = max(float(np.linalg.norm(v.max(axis=0) - v.min(axis=0))) for v, _ in meshes)
    # one operator set per distinct shape; a piece is placed by translating its shape
    shapes: list[tuple[np.ndarray, np.ndarray, Any]] = []
    bodies = []
    for k, (v, f) in enumerate(meshes):
        centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        local = v - centre
        ops = next((o for sv, sf, o in shapes if sv.shape == local.shape and np.array_equal(sf, f)
                    and np.allclose(sv, local, atol=tol * size)), None)
        if ops is None:
            ops = build_operators((local, f), material, dt, device=device, **build)
            shapes.append((local, f, ops))
        bodies.append(BemBody((local, f), material, dt, operators=ops, name=f"{name}_{k}", position=centre, **body_kw))
    joints = []
    trees = [cKDTree(v) for v, _ in meshes]
    for a in range(len(meshes)):
        for b in range(a + 1, len(meshes)):
            d, j = trees[b].query(meshes[a][0], distance_upper_bound=tol * size)
            ia = np.flatnonzero(np.isfinite(d))
            if len(ia):
                joints.append(PointJoint(bodies[a], ia, bodies[b], j[ia], name=f"{name}_joint_{a}_{b}"))
    # every piece must be joined to the others
    parent = list(range(len(meshes)))

    def find(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for jt in joints:
        parent[find(bodies.index(jt.body_a))] = find(bodies.index(jt.body_b))
    loose = [k for k in range(len(meshes)) if find(k) != find(0)]
    if loose:
        raise InvalidMesh(f"decompose '{name}': piece {loose[0]} shares no vertex with the others (interfaces must "
                          f"have coincident vertices, within {tol} of the size)")
    return bodies, joints
