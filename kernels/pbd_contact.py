"""Particle contact with the World's colliders: ground planes and (kinematic) triangle meshes.

Contact is a position projection after each constraint iteration ([PBD] §3.5, collision
constraints as inequality constraints with infinite stiffness). Overlap that already existed at
the start of the substep (a body placed inside the contact margin, a collider that moved into
it) is resolved without adding velocity: x_prev and x_pred move with x by that part of the
correction (pre-stabilization, Macklin et al. 2014 §4.4), so only penetration created during the
substep turns into a velocity change. Then position-based Coulomb friction (Macklin et al., "Unified Particle Physics for Real-Time Applications",
SIGGRAPH 2014, Eq. 24): with d the penetration depth just resolved and dx_t the tangential
displacement of the particle relative to the collider over the substep,

    dx_t removed entirely         if |dx_t| <  mu d     (static friction: the particle sticks)
    dx_t scaled by mu d / |dx_t|  otherwise             (kinetic friction)

Positions are x = x_pred + dx (see ``wsim.kernels.pbd``): the correction is added to dx, and
also to dxc, the substep's contact corrections, whose angular impulse
``wsim.kernels.pbd.restore_angular_momentum`` keeps apart from that of the internal constraints.
Positions are float32; each thread touches one particle, so there are no races.
"""

from __future__ import annotations

import warp as wp


@wp.func
def friction_correction(dx: wp.vec3, n: wp.vec3, depth: float, mu: float) -> wp.vec3:
    """Displacement that applies Coulomb friction to the relative displacement dx (see module docstring)."""
    dx_t = dx - n * wp.dot(dx, n)
    t_len = wp.length(dx_t)
    if t_len <= 0.0:
        return wp.vec3(0.0)
    limit = mu * depth
    if t_len < limit:
        return -dx_t
    return -dx_t * (limit / t_len)


@wp.func
def resolve_overlap(
    x_prev: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    i: int,
    n: wp.vec3,
    depth: float,
    depth_prev: float,
) -> float:
    """Move x_prev and x_pred along n by the part of the correction that was already overlap at
    the start of the substep (pre-stabilization: it changes positions, not velocities); returns
    that shift [m]."""
    shift = wp.min(depth, wp.max(depth_prev, 0.0))
    if shift > 0.0:
        x_prev[i] = x_prev[i] + n * shift
        x_pred[i] = x_pred[i] + n * shift
        return shift
    return 0.0


@wp.kernel
def ground_contact(
    dx: wp.array(dtype=wp.vec3),
    dxc: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    normal: wp.vec3,
    height: float,
    margin: float,
    mu: float,
):
    """Half-space {p : p.n >= height}: push a particle within ``margin`` of the plane out to it, then friction."""
    i = wp.tid()
    if inv_mass[i] == 0.0:
        return
    p = x_pred[i] + dx[i]
    depth = height + margin - wp.dot(p, normal)
    if depth <= 0.0:
        return
    shift = resolve_overlap(x_prev, x_pred, i, normal, depth, height + margin - wp.dot(x_prev[i], normal))
    p = p + normal * depth
    c = normal * (depth - shift) + friction_correction(p - x_prev[i], normal, depth, mu)
    dx[i] = dx[i] + c
    dxc[i] = dxc[i] + c


@wp.kernel
def mesh_contact(
    dx: wp.array(dtype=wp.vec3),
    dxc: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    mesh: wp.uint64,
    transforms: wp.array(dtype=wp.mat44),
    inverses: wp.array(dtype=wp.mat44),
    step: int,
    margin: float,
    max_dist: float,
    mu: float,
):
    """Triangle-mesh collider posed by transforms[step] (local -> world; transforms[step - 1] at the substep start).

    The particle is taken to the collider's local frame, the closest surface point is found with
    its inside/outside sign (angle-weighted pseudo-normal, exact for closed meshes), and a particle
    inside or within ``margin`` is moved to the surface point plus ``margin`` along the outward
    normal. Friction uses the displacement relative to the collider surface point, so a moving
    collider drags what it touches.
    """
    i = wp.tid()
    if inv_mass[i] == 0.0:
        return
    M = transforms[step]
    Minv = inverses[step]
    p_world = x_pred[i] + dx[i]
    p = wp.transform_point(Minv, p_world)
    q = wp.mesh_query_point_sign_normal(mesh, p, max_dist)
    if not q.result:
        return
    s = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    d = p - s
    dist = wp.length(d)
    n = wp.mesh_eval_face_normal(mesh, q.face)
    if dist > 1.0e-9:
        n = d / dist * wp.sign(q.sign)
    signed = dist * wp.sign(q.sign)
    depth = margin - signed
    if depth <= 0.0:
        return
    target = wp.transform_point(M, s + n * margin)
    n_world = wp.normalize(wp.transform_vector(M, n))
    # how far the collider surface point moved over this substep
    s_prev = wp.transform_point(transforms[step - 1], s)
    s_now = wp.transform_point(M, s)
    # overlap at the substep start, against the tangent plane of the contact point then
    depth_prev = margin - wp.dot(x_prev[i] - s_prev, wp.normalize(wp.transform_vector(transforms[step - 1], n)))
    resolve_overlap(x_prev, x_pred, i, n_world, depth, depth_prev)
    dx_rel = (target - x_prev[i]) - (s_now - s_prev)
    c = (target - x_pred[i]) + friction_correction(dx_rel, n_world, depth, mu) - dx[i]
    dx[i] = dx[i] + c
    dxc[i] = dxc[i] + c
