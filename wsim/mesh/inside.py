"""The point-in-mesh test of wsim: which points lie inside a closed surface.

One test for every caller (the EoL grid's material samples, the tetrahedralizer, anything else
that needs inside/outside): the generalized winding number w(p) of the surface (Jacobson et al.
2013, "Robust inside-outside segmentation using generalized winding numbers") thresholded at 1/2,
evaluated by Warp's BVH query ``mesh_query_point_sign_winding_number`` (Barill et al. 2018, "Fast
winding numbers": exact triangle solid angles near the point, a dipole expansion of far BVH
clusters). On a closed surface w is 0 or 1 away from the surface, so the 1/2 threshold is robust
to the approximation. The same query returns the closest surface point, so the distance to the
surface comes with it at no extra traversal.

``winding_number`` gives the value of w itself (fractional for open surfaces) by the exact direct
sum over all faces, O(points x faces): a reference and a field, not the inside test.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from wsim.device import resolve_device
from wsim.errors import InvalidMesh, InvalidParameter
from wsim.kernels import mesh as km
from wsim.mesh._common import _prefix

class SurfaceQuery:
    """A closed surface's Warp BVH, built once and queried for any number of point sets.

    Coordinates go to float32 relative to the centre of the surface's bounding box, so a body far
    from the origin keeps its resolution (about 1e-7 of its size).
    """

    def __init__(self, vertices: Any, faces: Any, device: str | wp.Device | None = None) -> None:
        v = np.asarray(vertices, dtype=np.float64)
        self.device = resolve_device(device)
        self.centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        self._mesh = wp.Mesh(
            points=wp.array((v - self.centre).astype(np.float32), dtype=wp.vec3, device=self.device),
            indices=wp.array(np.asarray(faces).ravel().astype(np.int32), dtype=wp.int32, device=self.device),
            support_winding_number=True,
        )

    def classify(self, points: Any) -> tuple[np.ndarray, np.ndarray]:
        """``(inside, distance)`` for points (Q, 3) [m]: the boolean point-in-mesh mask (winding
        number > 1/2) and the float64 distance [m] to the closest surface point (float32-accurate)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(p) == 0:
            return np.zeros(0, dtype=bool), np.zeros(0)
        pts = wp.array((p - self.centre).astype(np.float32), dtype=wp.vec3, device=self.device)
        inside = wp.empty(len(p), dtype=wp.int32, device=self.device)
        distance = wp.empty(len(p), dtype=wp.float32, device=self.device)
        wp.launch(km.classify, dim=len(p), inputs=[self._mesh.id, pts], outputs=[inside, distance], device=self.device)
        return inside.numpy().astype(bool), distance.numpy().astype(np.float64)

    def inside(self, points: Any) -> np.ndarray:
        """Boolean mask (Q,) of the points strictly inside the surface (winding number > 1/2)."""
        return self.classify(points)[0]


def inside_test(faces: Any) -> int:
    """The contact kernels' inside test for a closed surface (``closed`` of
    ``wsim.kernels.mesh.query_inside``): ray parity (``WATERTIGHT``) for one watertight piece,
    where a ray from a point off the surface crosses it an odd number of times exactly when the
    point is inside; the winding number (1) otherwise, as for several pieces that may overlap or
    nest, where a point inside two of them has winding number 2 but crosses an even number of
    faces. Topology only: a piece folded through itself is not seen."""
    from wsim.mesh.topology import pieces, watertight

    return km.WATERTIGHT if watertight(faces) and pieces(faces)[0] == 1 else 1


def inside_surface(vertices: Any, faces: Any, points: Any, device: str | wp.Device | None = None) -> np.ndarray:
    """Boolean mask of the points (Q, 3) [m] inside a closed surface (generalized winding number > 1/2),
    by a Warp BVH query on ``device`` (default: ``wsim.device.resolve_device(None)``).

    On one CPU thread, 30k points in the box of a 1280-face sphere take about 0.18 s (BVH build
    included): 7x faster than the direct float64 sum of :func:`winding_number` and 16x faster than
    a numpy one. Build a :class:`SurfaceQuery` to query one surface several times.
    """
    return SurfaceQuery(vertices, faces, device).inside(points)


def winding_number(vertices: Any, faces: Any, points: Any, device: str | wp.Device | None = None) -> np.ndarray:
    """Generalized winding number of a triangle surface at each query point, float64 shape (Q,).

    Sum over faces of the signed solid angle divided by 4 pi: 1 inside and 0 outside a closed
    outward-oriented surface (to roundoff), -1 inside an inward one, fractional for open surfaces.
    Exact direct sum in float64, O(Q * M) (a Warp kernel on ``device``); for inside/outside of a
    closed surface use :func:`inside_surface`, which is much faster.
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
    if len(p) == 0 or f.size == 0:
        return np.zeros(len(p), dtype=np.float64)
    dev = resolve_device(device)
    out = wp.empty(len(p), dtype=wp.float64, device=dev)
    wp.launch(
        km.winding_number_direct,
        dim=len(p),
        inputs=[
            wp.array(v, dtype=wp.vec3d, device=dev),
            wp.array(f.reshape(-1, 3).astype(np.int32), dtype=wp.vec3i, device=dev),
            wp.array(p, dtype=wp.vec3d, device=dev),
        ],
        outputs=[out],
        device=dev,
    )
    return out.numpy()
