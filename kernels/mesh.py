"""Warp kernels of point-in-mesh queries on closed triangle surfaces (used by ``wsim.mesh.inside``).

``classify``: inside/outside by the generalized winding number (Jacobson et al. 2013) through
Warp's BVH fast-winding-number query (Barill et al. 2018), with the distance to the surface.
``winding_number_direct``: the exact winding number by the direct sum of triangle solid angles.
"""

from __future__ import annotations

import math

import warp as wp

# Barill et al.'s accuracy parameter beta: a BVH cluster farther than beta times its radius is
# replaced by its dipole. 2 keeps the far-field error far below the 1/2 margin of a closed surface.
_WINDING_ACCURACY = wp.constant(2.0)
# w = sum over faces of 2 atan2(...) / (4 pi) = sum of atan2(...) / (2 pi).
_TWO_PI = wp.constant(wp.float64(2.0 * math.pi))


@wp.kernel
def classify(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    inside: wp.array(dtype=wp.int32),
    distance: wp.array(dtype=wp.float32),
):
    """inside[i] = 1 where the generalized winding number at points[i] exceeds 1/2 (Warp's fast
    winding number, accuracy ``_WINDING_ACCURACY``); distance[i] = |points[i] - closest surface point|."""
    i = wp.tid()
    p = points[i]
    q = wp.mesh_query_point_sign_winding_number(mesh, p, 1.0e30, _WINDING_ACCURACY, 0.5)
    inside[i] = wp.where(q.result and q.sign < 0.0, 1, 0)
    distance[i] = wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v))


@wp.kernel
def winding_number_direct(
    vertices: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    points: wp.array(dtype=wp.vec3d),
    out: wp.array(dtype=wp.float64),
):
    """out[i] = sum over faces of the signed solid angle at points[i] / 4 pi, each solid angle by van
    Oosterom & Strackee (1983): tan(Omega / 2) = a . (b x c) / (|a||b||c| + (a.b)|c| + (b.c)|a| + (c.a)|b|)
    with a, b, c the corners relative to the point; atan2 keeps the correct branch."""
    i = wp.tid()
    p = points[i]
    total = wp.float64(0.0)
    for k in range(faces.shape[0]):
        t = faces[k]
        a = vertices[t[0]] - p
        b = vertices[t[1]] - p
        c = vertices[t[2]] - p
        la = wp.length(a)
        lb = wp.length(b)
        lc = wp.length(c)
        den = la * lb * lc + wp.dot(a, b) * lc + wp.dot(b, c) * la + wp.dot(c, a) * lb
        total += wp.atan2(wp.dot(a, wp.cross(b, c)), den)
    out[i] = total / _TWO_PI
