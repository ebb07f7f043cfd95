"""Warp kernels that find the surface of an EoL body inside a collider (Fan et al. Sec. 3.5, Eqs. 27-28).

The contact constraint of Eq. (27) asks the overlap volume Omega of the body A and a collider B
not to grow: d vol(Omega)/dt = int_{Gamma_A in Omega} v_A . n_A dGamma + int_{Gamma_B in Omega}
v_B . n_B dGamma <= 0. A collider moves rigidly (a divergence-free velocity field), so the flux of
v_B through the closed boundary of Omega vanishes and the collider's term equals
-int_{Gamma_A in Omega} v_B . n_A: the constraint only needs the body's own surface inside the
collider, int_{Gamma_A in Omega} (v_A - v_B) . n_A <= 0. It is integrated with one point per
surface triangle (its centroid, weight its area): this kernel reports, per triangle, whether the
centroid is inside the collider, how deep, the area-weighted outward normal and the collider's
outward normal there. Positions come from the tracked intermediate vertices y and the Lagrangian
map x = F y + T (F = R rigid, A affine). Collider meshes are float32 (Warp BVH).
"""

from __future__ import annotations

import warp as wp


@wp.func
def triangle_world(y: wp.array(dtype=wp.vec3d), tri: wp.vec3i, F: wp.mat33d, T: wp.vec3d):
    x0 = F * y[tri[0]] + T
    x1 = F * y[tri[1]] + T
    x2 = F * y[tri[2]] + T
    third = wp.float64(1.0) / wp.float64(3.0)
    return (x0 + x1 + x2) * third, wp.float64(0.5) * wp.cross(x1 - x0, x2 - x0)


@wp.kernel
def plane_contacts(
    y: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    F: wp.mat33d,
    T: wp.vec3d,
    normal: wp.vec3d,
    height: wp.float64,
    depth: wp.array(dtype=wp.float64),
    centroid: wp.array(dtype=wp.vec3d),
    area_normal: wp.array(dtype=wp.vec3d),
    collider_normal: wp.array(dtype=wp.vec3d),
):
    """Triangles whose centroid lies below the plane normal . x = height (depth > 0)."""
    f = wp.tid()
    xc, an = triangle_world(y, faces[f], F, T)
    centroid[f] = xc
    area_normal[f] = an
    collider_normal[f] = normal
    depth[f] = wp.max(height - wp.dot(normal, xc), wp.float64(0.0))


@wp.kernel
def mesh_contacts(
    y: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    F: wp.mat33d,
    T: wp.vec3d,
    mesh: wp.uint64,
    to_local: wp.mat44d,
    rotation: wp.mat33d,
    max_dist: float,
    depth: wp.array(dtype=wp.float64),
    centroid: wp.array(dtype=wp.vec3d),
    area_normal: wp.array(dtype=wp.vec3d),
    collider_normal: wp.array(dtype=wp.vec3d),
):
    """Triangles whose centroid lies inside a closed collider mesh (winding-sign query; depth > 0)."""
    f = wp.tid()
    xc, an = triangle_world(y, faces[f], F, T)
    centroid[f] = xc
    area_normal[f] = an
    depth[f] = wp.float64(0.0)
    collider_normal[f] = wp.vec3d()
    pl = to_local * wp.vec4d(xc[0], xc[1], xc[2], wp.float64(1.0))
    p = wp.vec3(float(pl[0]), float(pl[1]), float(pl[2]))
    q = wp.mesh_query_point_sign_normal(mesh, p, max_dist)
    if q.result and q.sign < 0.0:
        closest = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        n = wp.mesh_eval_face_normal(mesh, q.face)
        depth[f] = wp.float64(wp.length(closest - p))
        collider_normal[f] = rotation * wp.vec3d(wp.float64(n[0]), wp.float64(n[1]), wp.float64(n[2]))
