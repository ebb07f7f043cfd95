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

from wsim.kernels.mesh import query_inside


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


@wp.func
def surface_contact(mesh: wp.uint64, p: wp.vec3, max_dist: float, margin: float, closed: int):
    """Nearest point s of an outward surface mesh to p: (depth = margin - signed distance, s, the
    outward normal n there, the face, the barycentric weights of s on it); inside by
    ``query_inside`` (``closed`` 0: an open, one-sided collider sheet). depth <= 0: no contact
    (also when nothing is within ``max_dist``)."""
    q = query_inside(mesh, p, max_dist, closed)
    if not q.result:
        return -1.0, p, wp.vec3(0.0), int(0), wp.vec3(0.0)
    s = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    d = p - s
    dist = wp.length(d)
    n = wp.mesh_eval_face_normal(mesh, q.face)
    if dist > 1.0e-9:
        n = d / dist * wp.sign(q.sign)
    return margin - dist * wp.sign(q.sign), s, n, q.face, wp.vec3(q.u, q.v, 1.0 - q.u - q.v)


@wp.func
def face_vertices(mesh: wp.uint64, face: int) -> wp.vec3i:
    """The vertex indices of a face of a Warp mesh (read from the mesh's own index buffer)."""
    return wp.vec3i(wp.mesh_get_index(mesh, 3 * face), wp.mesh_get_index(mesh, 3 * face + 1),
                    wp.mesh_get_index(mesh, 3 * face + 2))


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
    closed: int,
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
    depth, s, n, face, bary = surface_contact(mesh, p, max_dist, margin, closed)
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


@wp.kernel
def surface_positions(x_pred: wp.array(dtype=wp.vec3), dx: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec3)):
    """The current positions x_pred + dx of the surface particles (the first len(out)): the points
    of a body's contact mesh, refit after this."""
    i = wp.tid()
    out[i] = x_pred[i] + dx[i]


@wp.kernel
def body_contact(
    x_pred: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    dxc: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    mesh: wp.uint64,
    dx_b: wp.array(dtype=wp.vec3),
    dxc_b: wp.array(dtype=wp.vec3),
    x_prev_b: wp.array(dtype=wp.vec3),
    inv_mass_b: wp.array(dtype=float),
    margin: float,
    max_dist: float,
    mu: float,
    closed: int,
):
    """A surface particle p of body A against the surface of body B (``mesh``: B's current surface
    positions and triangles): the point-triangle contact constraint
    C = n . (p - s) - margin >= 0, s = sum_k b_k q_k the nearest point of B's surface (barycentric
    b_k on the triangle q_0 q_1 q_2) and n the outward normal there ([PBD] §3.5, applied to two
    deformable bodies). With the inverse masses w_p and w_k and W = w_p + sum_k b_k^2 w_k, a violated
    constraint moves p by w_p lambda n and q_k by -b_k w_k lambda n, lambda = -C / W: equal and
    opposite momenta, and the arm p - s along n (no torque error). Coulomb friction as against a
    collider, on the slip of p relative to s over the substep, divided between the bodies the same
    way. One thread per particle of A; B's particles take atomic adds (several of A's particles
    may press on one triangle of B). ``closed``: B's inside test (``wsim.mesh.inside_test``: ray
    parity for one watertight piece, else the winding number)."""
    i = wp.tid()
    w_p = inv_mass[i]
    p = x_pred[i] + dx[i]
    depth, s, n, face, b = surface_contact(mesh, p, max_dist, margin, closed)
    if depth <= 0.0:
        return
    tri = face_vertices(mesh, face)
    w = w_p
    for k in range(3):
        w += b[k] * b[k] * inv_mass_b[tri[k]]
    if w <= 0.0:
        return
    # the slip of p relative to the surface point over the substep, after the normal correction
    s_prev = b[0] * x_prev_b[tri[0]] + b[1] * x_prev_b[tri[1]] + b[2] * x_prev_b[tri[2]]
    rel = (p + n * depth - x_prev[i]) - (s - s_prev)
    c = n * depth + friction_correction(rel, n, depth, mu)  # the change of p - s that is wanted
    dp = c * (w_p / w)
    dx[i] = dx[i] + dp
    dxc[i] = dxc[i] + dp
    for k in range(3):
        dq = -c * (b[k] * inv_mass_b[tri[k]] / w)
        wp.atomic_add(dx_b, tri[k], dq)
        wp.atomic_add(dxc_b, tri[k], dq)


@wp.kernel
def lerp_points(p0: wp.array(dtype=wp.vec3), p1: wp.array(dtype=wp.vec3), s: float, out: wp.array(dtype=wp.vec3)):
    """out = p0 + s (p1 - p0): a moving surface's vertices at a fraction s of the frame."""
    i = wp.tid()
    out[i] = p0[i] + s * (p1[i] - p0[i])


@wp.struct
class Give:
    """How a moving surface yields to a push (coupling across methods, ``PbdBody.set_moving_surfaces``):
    as a body of inverse mass ``inv_mass`` (0: kinematic) in translation, and elastically with the
    plane-wave impedance ``impedance`` = rho c_p of its material (0: not at all), over the column
    of a vertex's patch or, with ``wave_speed`` c_p (0: the column alone), the half-sphere its P
    wave reaches in the interval where that is more (``elastic_give``); ``received``:
    the momentum of the last coupling interval's push, which the partner takes over this one. On
    the device (one element), so that a recorded frame reads each interval's values. Rotation is
    left out: with the free body's rotational give, a 24 kg PBD box set 3 cm off centre on a 4 kg
    BEM cube rang down more slowly (43 mm/s in the sixth half second; 4.4 mm/s without), and its
    98-vertex version rocked harder: the cube rests on something that keeps it from turning about
    its centre."""

    inv_mass: wp.float64
    impedance: wp.float64
    wave_speed: wp.float64
    received: wp.vec3d


@wp.func
def elastic_give(give: Give, area: wp.float64, interval: float) -> wp.float64:
    """1 / (rho c_p A_e T): the velocity a patch of area A takes per unit impulse pushed steadily
    over the coupling interval T, the push engaging the material its P wave reaches in T: a column
    of the patch's area where the wave has not outrun the patch, else a half-sphere of radius
    c_p T, A_e = max(A, 2 pi / 3 (c_p T)^2) (0 where there is none). The World hands c_p only
    where it finds the push implicitly (``wsim.world._wave_speed``): explicitly the column's larger
    give also stands in for the interval's lag."""
    if give.impedance <= wp.float64(0.0) or area <= wp.float64(0.0):
        return wp.float64(0.0)
    reach = give.wave_speed * wp.float64(interval)
    engaged = wp.max(area, wp.float64(2.0943951023931953) * reach * reach)
    return wp.float64(1.0) / (give.impedance * engaged * wp.float64(interval))


@wp.func
def shared_give(give: Give, count: wp.array(dtype=wp.int32)) -> wp.float64:
    """n_c / M: a yielding surface's inverse mass times the contacts n_c of the last iteration
    that push it at once (each particle's projection takes its share of the body)."""
    return wp.float64(wp.max(count[0], 1)) * give.inv_mass


@wp.kernel
def yielding_substep(p0: wp.array(dtype=wp.vec3), p1: wp.array(dtype=wp.vec3), f0: float, f1: float,
                     give: wp.array(dtype=Give), received_v: wp.array(dtype=wp.vec3d),
                     area: wp.array(dtype=wp.float64), share: float, interval: float, h: float,
                     u: wp.array(dtype=wp.vec3d), y: wp.array(dtype=wp.vec3),
                     prev: wp.array(dtype=wp.vec3), cur: wp.array(dtype=wp.vec3)):
    """A yielding surface's vertices at the substep's start (``prev``, fraction f0 of the
    interval) and end (``cur``, f1): their motion p0 -> p1 plus y, how far they have yielded to
    this interval's push so far, y += u h. The yield is the give to the change of the push only:
    the partner takes the last interval's push R (R_v at vertex v) over this one, which its
    motion p0 -> p1 carries already, so each substep the yield velocity loses the give to
    ``share`` = h / T of it, u_v -= share (R / M + R_v e_v), e_v = ``elastic_give`` of v's area;
    ``yielding_iteration`` adds the give to what is pushed now. A resting pusher then pushes what
    the partner already takes, and sees it still (as the EoL rows do,
    ``kernels.eol_contact.partner_yield``)."""
    v = wp.tid()
    g = give[0]
    prev[v] = p0[v] + f0 * (p1[v] - p0[v]) + y[v]
    du = g.inv_mass * g.received + received_v[v] * elastic_give(g, area[v], interval)
    u[v] = u[v] - wp.float64(share) * du
    y[v] = y[v] + wp.vec3(u[v] * wp.float64(h))
    cur[v] = p0[v] + f1 * (p1[v] - p0[v]) + y[v]


@wp.kernel
def yielding_iteration(impulse: wp.array(dtype=wp.vec3d), seen: wp.array(dtype=wp.vec3d),
                       total: wp.array(dtype=wp.vec3d), give: wp.array(dtype=Give),
                       area: wp.array(dtype=wp.float64), interval: float, h: float,
                       count: wp.array(dtype=wp.int32), u: wp.array(dtype=wp.vec3d),
                       y: wp.array(dtype=wp.vec3), cur: wp.array(dtype=wp.vec3)):
    """After a constraint iteration's contacts: the partner yields to what they pushed it with,
    du_v = P / M + dJ_v e_v (``total[0]``: P, the iteration's push; dJ_v = impulse - seen, its
    part at vertex v), and its vertices move by du_v h over the substep. Vertex 0 also keeps the
    iteration's contact count for the next one (``shared_give``)."""
    v = wp.tid()
    g = give[0]
    dJ = impulse[v] - seen[v]
    seen[v] = impulse[v]
    du = g.inv_mass * total[0] + dJ * elastic_give(g, area[v], interval)
    u[v] = u[v] + du
    d = wp.vec3(du * wp.float64(h))
    y[v] = y[v] + d
    cur[v] = cur[v] + d
    if v == 0:
        count[0] = count[1]
        count[1] = 0


@wp.kernel
def moving_surface_contact(
    x_pred: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    dxc: wp.array(dtype=wp.vec3),
    x_prev: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    mesh: wp.uint64,
    v_prev: wp.array(dtype=wp.vec3),
    margin: float,
    max_dist: float,
    mu: float,
    inv_h: float,
    impulse: wp.array(dtype=wp.vec3d),
    closed: int,
    give: wp.array(dtype=Give),
    area: wp.array(dtype=wp.float64),
    interval: float,
    count: wp.array(dtype=wp.int32),
    total: wp.array(dtype=wp.vec3d),
):
    """A particle against another body's surface that moves on its own this frame (``mesh``: its
    vertices at the end of the substep; ``v_prev`` at the start): the collider projection with
    friction relative to the surface's motion, and the momentum the particle received,
    taken from the surface's vertices by their barycentric weights into ``impulse`` [N s]
    (handed to the other body by the World: explicit two-way coupling). ``closed``: the
    surface's inside test (``wsim.mesh.inside_test``).

    A surface that yields (``give``, not kinematic: a BEM body) shares the wanted correction c
    with the particle as a two-body constraint: W = w_p + n_c / M + sum_k b_k^2 e_k
    (``shared_give``, ``elastic_give``); the particle moves by w_p c / W and receives c / (W h),
    and the surface yields to the opposite after the iteration (``yielding_iteration``;
    ``total[0]``: the iteration's push). Taken as kinematic within the interval, a PBD box six
    times heavier than the BEM cube it rested on was handed back the overshoot of each push an
    interval later and rocked off it within 2 s."""
    i = wp.tid()
    w_p = inv_mass[i]
    if w_p == 0.0:
        return
    p = x_pred[i] + dx[i]
    depth, s, n, face, b = surface_contact(mesh, p, max_dist, margin, closed)
    if depth <= 0.0:
        return
    tri = face_vertices(mesh, face)
    s_prev = b[0] * v_prev[tri[0]] + b[1] * v_prev[tri[1]] + b[2] * v_prev[tri[2]]
    rel = (p + n * depth - x_prev[i]) - (s - s_prev)
    c = n * depth + friction_correction(rel, n, depth, mu)
    g = give[0]
    yielding = g.inv_mass > wp.float64(0.0)
    W = wp.float64(w_p)
    if yielding:
        W = W + shared_give(g, count)
        for k in range(3):
            W = W + wp.float64(b[k] * b[k]) * elastic_give(g, area[tri[k]], interval)
    dp = c * float(wp.float64(w_p) / W)
    dx[i] = dx[i] + dp
    dxc[i] = dxc[i] + dp
    J = wp.vec3d(c) * (wp.float64(inv_h) / W)  # the momentum the particle receives
    for k in range(3):
        wp.atomic_sub(impulse, tri[k], wp.float64(b[k]) * J)
    if yielding:
        wp.atomic_sub(total, 0, J)
        wp.atomic_add(count, 1, 1)


@wp.kernel
def moving_points_contact(
    points: wp.array(dtype=wp.vec3),
    points_prev: wp.array(dtype=wp.vec3),
    mesh: wp.uint64,
    x_prev: wp.array(dtype=wp.vec3),
    dx: wp.array(dtype=wp.vec3),
    dxc: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    inv_mass_v: wp.array(dtype=float),
    margin: float,
    max_dist: float,
    mu: float,
    inv_h: float,
    impulse: wp.array(dtype=wp.vec3d),
    closed: int,
    give: wp.array(dtype=Give),
    area: wp.array(dtype=wp.float64),
    interval: float,
    count: wp.array(dtype=wp.int32),
    total: wp.array(dtype=wp.vec3d),
):
    """The other way round from ``moving_surface_contact``: a vertex p of another body's moving
    surface (``points`` at the end of the substep, ``points_prev`` at its start) against this
    body's own current surface (``mesh``: its surface particles' positions x_pred + dx; ``closed``:
    its inside test), so that a corner of the other body cannot pass between this body's
    particles. With s = sum_k b_k q_k the nearest point of this surface and n its outward normal,
    C = n . (p - s) - margin >= 0, and c = n depth + the Coulomb correction of the slip of p
    relative to s over the substep is the wanted change of p - s. As between two PBD bodies
    (``body_contact``) it is shared by inverse mass, W = w_v + sum_k b_k^2 w_k with w_v the
    vertex's (``inv_mass_v``: its lumped share of the other body's mass): the triangle's particles
    move by -b_k w_k / W c now; the vertex's share, c w_v / W, is the momentum c / W handed to it
    (``impulse`` [N s], by the World, one interval late, as for the particles' own contacts), the
    opposite of what this body's free particles took. A vertex treated as immovable (w_v = 0) made
    heavy particles of a coarse body throw a resting light body off. One thread per vertex; the
    particles take atomic adds (several vertices may press on one triangle). A yielding surface
    (``give``) also counts the vertex's push in the iteration's ``total``."""
    j = wp.tid()
    p = points[j]
    depth, s, n, face, b = surface_contact(mesh, p, max_dist, margin, closed)
    if depth <= 0.0:
        return
    tri = face_vertices(mesh, face)
    g = give[0]
    yielding = g.inv_mass > wp.float64(0.0)
    W = inv_mass_v[j]
    if yielding:  # its vertex's give, as in ``moving_surface_contact``
        W = float(shared_give(g, count) + elastic_give(g, area[j], interval))
    free = float(0.0)
    for k in range(3):
        w_k = inv_mass[tri[k]]
        W += b[k] * b[k] * w_k
        if w_k > 0.0:
            free += b[k]
    if free <= 0.0 or W <= 0.0:  # a triangle of pinned or driven particles only: nothing to push
        return
    s_prev = b[0] * x_prev[tri[0]] + b[1] * x_prev[tri[1]] + b[2] * x_prev[tri[2]]
    rel = (p + n * depth - points_prev[j]) - (s - s_prev)
    c = n * depth + friction_correction(rel, n, depth, mu)  # the change of p - s that is wanted
    for k in range(3):
        dq = -c * (b[k] * inv_mass[tri[k]] / W)
        wp.atomic_add(dx, tri[k], dq)
        wp.atomic_add(dxc, tri[k], dq)
    J = wp.vec3d(c * (free * inv_h / W))
    wp.atomic_add(impulse, j, J)
    if yielding:  # the surface yields to it too (``yielding_iteration``)
        wp.atomic_add(total, 0, J)
        wp.atomic_add(count, 1, 1)

