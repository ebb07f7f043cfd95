"""Warp kernels that assemble the contact rows of an EoL body against a collider (Fan et al. Sec. 3.5, Eqs. 27-28).

The contact constraint of Eq. (27) asks the overlap volume Omega of the body A and a collider B
not to grow: d vol(Omega)/dt = int_{Gamma_A in Omega} v_A . n_A dGamma + int_{Gamma_B in Omega}
v_B . n_B dGamma <= 0. A collider moves rigidly (a divergence-free velocity field), so the flux of
v_B through the closed boundary of Omega vanishes and the collider's term equals
-int_{Gamma_A in Omega} v_B . n_A: the constraint only needs the body's own surface inside the
collider, int_{Gamma_A in Omega} (v_A - v_B) . n_A <= 0.

It is integrated with surface samples: points of the surface triangles given by barycentric
coordinates, each with a share of its triangle's area (one centroid per triangle, or the centroids
of a k x k subdivision of a triangle wider than a grid cell). Rows (Eq. 28) are one per collider
and collision cell: a block of ``block``^3 cells of the body's grid (the collision grid of Sec.
3.5; against rigid colliders the intermediate grid is the spatial grid carried by the Lagrangian
map). A row's support is then the (block + 1)^3 nodes of its block, so the kernels accumulate each
row's J coefficients, right side and overlap into a fixed slot per row with atomics, and
``compact_rows`` packs the rows that received samples (clearing their slots for the next step):
only those travel to the host. Per row:

    J: 3 (block + 1)^3 coefficients  -int_{Gamma_A in Omega, block} Phi_s |n_A . n_B| n_B dGamma  (velocity axes)
    b: sum of -|n_A . n_B| n_B . v_B - overlap / tau  (collider flux minus relaxation of existing overlap)
    overlap volume: sum of |n_A . n_B| depth dGamma

Frictionless contact pushes along the collider's normal n_B only. The exact flux n_A . v_A of Eq.
(27) is kept for the rate of the overlap of the whole intersection (by the divergence theorem,
sum n_A dGamma over the body's surface inside a plane is -n_B times the area of the cut, so a
normal-only and the exact gradient agree for every rigid translation), but per collision cell the
body's own normal n_A has a tangential part (the sides of the cap below a plane tilt outwards):
the rows' impulses J^T lambda then push sideways wherever neighbouring cells' multipliers differ,
a net tangential impulse of 0.02-0.2 % of the normal one that slid a ball resting on a
frictionless plane by 7.6 cm in 3 s (issue 16). Each sample's coefficient is therefore n_A
projected on the collider's normal, (n_A . n_B) n_B dGamma (the projected area of the sample
along n_B): the same constraint on normal motion, no constraint on, and no impulse along, the
collider's tangent plane.

Where the body's surface inside the collider faces into it (n_A . n_B < 0: the cap of a convex
body below a plane, a face landing flat) that is -|n_A . n_B| n_B dGamma. A thin part that crosses
the collider also has faces looking out of it (n_A . n_B > 0: a fin's upper face, below the ground),
whose exact flux is the opposite: moving them out grows the overlap. In a row that holds both faces
they cancel (J ~ 0 while b = -overlap / tau < 0: an infeasible row, and the QP fell back to NNLS on
nearly dependent rows); in a row that holds the upper face alone, the multiplier pulls the fin into
the ground. An independent check saw sub-cell fins 2-6 cells deep and the body's momentum off its
impulses by up to 186 kg m/s in a frame (issue 16). Every sample inside therefore asks its surface
to move out, -|n_A . n_B| n_B dGamma whichever way it faces: identical to Eq. (27) wherever the
body's surface inside faces the collider, and a row's impulse -J^T lambda (lambda >= 0) can only
push the body out of the collider.

The velocity of the body at a sample is the mass-weighted mean of its cell's nodes,
sum_s Phi_s m_s w_s / sum_s Phi_s m_s (Phi_s m_s / sum Phi m is the row's weight of node s, in
place of Phi_s). With plain Phi_s the QP, which minimizes sum m |w - w_hat|^2, satisfies a row most
cheaply by changing the nodes of least mass: a node holding a sliver of material (at the
``mass_floor``, 2 % of a full node) next to a flat face took the impulse of the whole face and
was flung at 10-20 m/s on the first contact of a landing box, until its material left the grid
(issue 16). Mass-weighted, an impulse changes the cell's nodes by the same velocity whatever
their masses (as particle-to-grid transfers do); for a uniform velocity the two agree.

Positions come from the tracked intermediate vertices y and the Lagrangian map x = F y + T
(F = R rigid, A affine). Collider meshes are float32 (Warp BVH); everything else is float64.
"""

from __future__ import annotations

import warp as wp

from wsim.kernels.eol_grid import Grid, corner_weight, node_position
from wsim.kernels.mesh import query_inside


@wp.struct
class ContactSurface:
    """The body's contact samples and where their rows go: the tracked intermediate vertices y and
    faces, the samples (face, barycentric, area share), the Lagrangian map x = F y + T, the world
    -> velocity-axes rotation, 1 / tau, the body's grid (a ``Grid``: nodes per axis, origin, h) and
    the collision grid (``block`` cells per collision cell, ``ccells`` collision cells per axis)."""

    y: wp.array(dtype=wp.vec3d)
    faces: wp.array(dtype=wp.vec3i)
    sample_face: wp.array(dtype=wp.int32)
    sample_bary: wp.array(dtype=wp.vec3d)
    sample_share: wp.array(dtype=wp.float64)
    F: wp.mat33d
    T: wp.vec3d
    to_axes: wp.mat33d
    inv_tau: wp.float64
    grid: Grid
    block: int
    ccells: wp.vec3i
    mass: wp.array(dtype=wp.float64)


@wp.func
def sample_world(surf: ContactSurface, i: int):
    """Sample i's intermediate point, world point and area-weighted normal (its share of the triangle)."""
    tri = surf.faces[surf.sample_face[i]]
    bary = surf.sample_bary[i]
    y0 = surf.y[tri[0]]
    y1 = surf.y[tri[1]]
    y2 = surf.y[tri[2]]
    yp = bary[0] * y0 + bary[1] * y1 + bary[2] * y2
    F = surf.F
    T = surf.T
    x0 = F * y0 + T
    an = wp.float64(0.5) * surf.sample_share[i] * wp.cross(F * y1 + T - x0, F * y2 + T - x0)
    return yp, F * yp + T, an


@wp.func
def sample_cell(surf: ContactSurface, yp: wp.vec3d):
    """The grid cell holding intermediate point yp (clamped to the grid) and yp's local
    coordinates in it, in [0, 1]^3."""
    g = (yp - surf.grid.origin) / surf.grid.h
    cells = surf.grid.shape - wp.vec3i(1, 1, 1)
    cell = wp.vec3i()
    t = wp.vec3d()
    for d in range(3):
        gd = wp.clamp(g[d], wp.float64(0.0), wp.float64(cells[d]))
        cell[d] = wp.min(int(gd), cells[d] - 1)
        t[d] = gd - wp.float64(cell[d])
    return cell, t


@wp.func
def accumulate_row(acc: wp.array2d(dtype=wp.float64), flag: wp.array(dtype=wp.int32), surf: ContactSurface,
                   collider: int, yp: wp.vec3d, coeff: wp.vec3d, rhs: wp.float64, overlap: wp.float64) -> int:
    """Add one sample to its row: Phi_s(yp) coeff on the 8 nodes of its grid cell, rhs and overlap;
    returns the row's slot."""
    cell, t = sample_cell(surf, yp)
    k = surf.block
    cc = wp.vec3i(cell[0] // k, cell[1] // k, cell[2] // k)
    nc = surf.ccells
    row = ((collider * nc[0] + cc[0]) * nc[1] + cc[1]) * nc[2] + cc[2]
    flag[row] = 1
    # the sample's velocity as the mass-weighted mean of its cell's nodes, sum Phi m w / sum Phi m:
    # an impulse then changes every node of the cell by about the same velocity, instead of
    # flinging the nodes that hold a sliver of material (see the module docstring)
    ny = surf.grid.shape[1]
    nz = surf.grid.shape[2]
    pm = wp.float64(0.0)
    for c in range(8):
        node = ((cell[0] + c // 4) * ny + cell[1] + (c // 2) % 2) * nz + cell[2] + c % 2
        pm += corner_weight(c, t) * surf.mass[node]
    for c in range(8):
        li = cell[0] + c // 4 - k * cc[0]
        lj = cell[1] + (c // 2) % 2 - k * cc[1]
        lk = cell[2] + c % 2 - k * cc[2]
        slot = 3 * ((li * (k + 1) + lj) * (k + 1) + lk)
        phi = corner_weight(c, t)
        if pm > wp.float64(0.0):
            node = ((cell[0] + c // 4) * ny + cell[1] + (c // 2) % 2) * nz + cell[2] + c % 2
            phi = phi * surf.mass[node] / pm
        for d in range(3):
            wp.atomic_add(acc, row, slot + d, phi * coeff[d])
    n = acc.shape[1]
    wp.atomic_add(acc, row, n - 2, rhs)
    wp.atomic_add(acc, row, n - 1, overlap)
    return row


@wp.func
def pushed_area(an: wp.vec3d, cn: wp.vec3d) -> wp.vec3d:
    """A sample's row coefficient (world): its area element an projected on the collider's normal
    cn, always towards the inside, -|an . cn| cn, so that its impulse pushes out whichever way the
    surface faces (see the module docstring)."""
    return -wp.abs(wp.dot(an, cn)) * cn


@wp.func
def add_sample(acc: wp.array2d(dtype=wp.float64), flag: wp.array(dtype=wp.int32), surf: ContactSurface,
               collider: int, yp: wp.vec3d, an: wp.vec3d, cn: wp.vec3d, depth: wp.float64, v_B: wp.vec3d):
    """A sample inside the collider: coefficient -|n_A . n_B| n_B in the velocity axes
    (``pushed_area``), right side that coefficient . v_B - overlap / tau with v_B the collider's
    velocity at the sample, overlap |n_A . n_B| depth. Returns the row's slot."""
    coeff = pushed_area(an, cn)
    vol = wp.abs(wp.dot(an, cn)) * depth
    return accumulate_row(acc, flag, surf, collider, yp, surf.to_axes * coeff, wp.dot(coeff, v_B) - vol * surf.inv_tau, vol)


@wp.kernel
def plane_rows(
    surf: ContactSurface,
    normal: wp.vec3d,
    height: wp.float64,
    collider: int,
    acc: wp.array2d(dtype=wp.float64),
    flag: wp.array(dtype=wp.int32),
):
    """Samples below the (static) plane normal . x = height."""
    i = wp.tid()
    yp, x, an = sample_world(surf, i)
    depth = height - wp.dot(normal, x)
    if depth > wp.float64(0.0):
        add_sample(acc, flag, surf, collider, yp, an, normal, depth, wp.vec3d())


@wp.kernel
def mesh_rows(
    surf: ContactSurface,
    mesh: wp.uint64,
    to_local: wp.mat44d,
    rotation: wp.mat33d,
    max_dist: float,
    G: wp.mat33d,
    g: wp.vec3d,
    collider: int,
    closed: int,
    acc: wp.array2d(dtype=wp.float64),
    flag: wp.array(dtype=wp.int32),
):
    """Samples inside a collider mesh (``query_inside``; ``closed`` 0: an open, one-sided sheet)
    moving with v_B = G x + g."""
    i = wp.tid()
    yp, x, an = sample_world(surf, i)
    pl = to_local * wp.vec4d(x[0], x[1], x[2], wp.float64(1.0))
    p = wp.vec3(float(pl[0]), float(pl[1]), float(pl[2]))
    q = query_inside(mesh, p, max_dist, closed)
    if q.result and q.sign < 0.0:
        closest = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        n = wp.mesh_eval_face_normal(mesh, q.face)
        cn = rotation * wp.vec3d(wp.float64(n[0]), wp.float64(n[1]), wp.float64(n[2]))
        add_sample(acc, flag, surf, collider, yp, an, cn, wp.float64(wp.length(closest - p)), G * x + g)


@wp.func
def vec3d_of(p: wp.vec3) -> wp.vec3d:
    return wp.vec3d(wp.float64(p[0]), wp.float64(p[1]), wp.float64(p[2]))


vec8d = wp.types.vector(length=8, dtype=wp.float64)


@wp.func
def corner_node(surf: ContactSurface, base: int, c: int) -> int:
    """Flat index of corner c (= 4 i + 2 j + k) of the cell whose first node is ``base``."""
    return base + ((c // 4) * surf.grid.shape[1] + (c // 2) % 2) * surf.grid.shape[2] + c % 2


@wp.func
def cell_weights(surf: ContactSurface, yp: wp.vec3d):
    """The grid cell holding intermediate point yp: its first node's flat index, the 8 corners'
    row weights Phi_c m_c / sum Phi m (the mass-weighted velocity of ``accumulate_row``; zero on
    nodes without mass) and sum Phi m (zero: no corner holds material)."""
    cell, t = sample_cell(surf, yp)
    base = (cell[0] * surf.grid.shape[1] + cell[1]) * surf.grid.shape[2] + cell[2]
    pm = wp.float64(0.0)
    for c in range(8):
        pm += corner_weight(c, t) * surf.mass[corner_node(surf, base, c)]
    weights = vec8d()
    if pm > wp.float64(0.0):
        for c in range(8):
            weights[c] = corner_weight(c, t) * surf.mass[corner_node(surf, base, c)] / pm
    return base, weights, pm


@wp.func
def cell_velocity(surf: ContactSurface, base: int, weights: vec8d, field: wp.array(dtype=wp.vec3d)) -> wp.vec3d:
    """World velocity sum_c weight_c Q field_c of a cell (``cell_weights``), Q = to_axes^T (the
    body's velocity axes -> world)."""
    v = wp.vec3d()
    for c in range(8):
        v += weights[c] * field[corner_node(surf, base, c)]
    return wp.transpose(surf.to_axes) * v


@wp.func
def applied_point(surf: ContactSurface, yp: wp.vec3d) -> wp.vec3d:
    """Where a sample's row impulse acts on this body (intermediate coordinates): the centroid of
    its cell's nodes with the row's weights Phi_s m_s / sum Phi m (``accumulate_row``)."""
    base, weights, pm = cell_weights(surf, yp)
    if pm <= wp.float64(0.0):
        return yp
    y = wp.vec3d()
    for c in range(8):
        y += weights[c] * node_position(corner_node(surf, base, c), surf.grid)
    return y


@wp.kernel
def surface_velocity(p0: wp.array(dtype=wp.vec3d), p1: wp.array(dtype=wp.vec3d), inv_span: wp.float64,
                     velocity: wp.array(dtype=wp.vec3d)):
    """Velocity of a surface vertex moving linearly from p0 to p1 over 1 / inv_span seconds."""
    i = wp.tid()
    velocity[i] = (p1[i] - p0[i]) * inv_span


@wp.kernel
def place_surface(p0: wp.array(dtype=wp.vec3d), p1: wp.array(dtype=wp.vec3d), f: wp.float64,
                  cur: wp.array(dtype=wp.vec3)):
    """A moving surface's vertices at fraction f of the interval (float32: a Warp mesh's points)."""
    i = wp.tid()
    p = p0[i] + f * (p1[i] - p0[i])
    cur[i] = wp.vec3(float(p[0]), float(p[1]), float(p[2]))


@wp.struct
class SurfaceHits:
    """Per contact sample, where it is inside a moving partner's surface (``surface_rows``): its
    row slot (-1: outside), the nearest face and the barycentric weights of the nearest point."""

    row: wp.array(dtype=wp.int32)
    bary: wp.array(dtype=wp.vec3d)
    face: wp.array(dtype=wp.int32)


@wp.kernel
def surface_rows(
    surf: ContactSurface,
    mesh: wp.uint64,
    closed: int,
    velocity: wp.array(dtype=wp.vec3d),
    max_dist: float,
    collider: int,
    acc: wp.array2d(dtype=wp.float64),
    flag: wp.array(dtype=wp.int32),
    hits: SurfaceHits,
):
    """Samples inside another body's closed surface (``mesh``, world coordinates, where it is at
    this step; issue 18), which moves with the velocities of its vertices (``velocity``,
    interpolated at the nearest point: v_B of Eq. 27 for a deformable partner, whose flux through
    the overlap is taken as a rigid one's). With the best-fit rigid motion of the partner instead,
    two equal spheres kept 37 % of their kinetic energy where one on a rigid wall keeps 74 %, and
    their faces overlapped by 0.6 cell as they parted (the partner's springing back was not seen).
    Each sample inside records its row slot, the nearest face and its barycentric weights
    (``hits``; row -1: outside), so that ``surface_reaction`` can hand the partner the opposite
    of what the rows push this body with. ``closed``: ``query_inside``'s test for that surface."""
    i = wp.tid()
    hits.row[i] = -1
    yp, x, an = sample_world(surf, i)
    p = wp.vec3(float(x[0]), float(x[1]), float(x[2]))
    q = query_inside(mesh, p, max_dist, closed)
    if q.result and q.sign < 0.0:
        closest = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        n = wp.mesh_eval_face_normal(mesh, q.face)
        cn = wp.vec3d(wp.float64(n[0]), wp.float64(n[1]), wp.float64(n[2]))
        b = wp.vec3d(wp.float64(q.u), wp.float64(q.v), wp.float64(1.0) - wp.float64(q.u) - wp.float64(q.v))
        v_local = wp.vec3d()
        for k in range(3):
            v_local += b[k] * velocity[wp.mesh_get_index(mesh, 3 * q.face + k)]
        hits.row[i] = add_sample(acc, flag, surf, collider, yp, an, cn, wp.float64(wp.length(closest - p)), v_local)
        hits.bary[i] = b
        hits.face[i] = q.face


@wp.func
def packed_row(row: wp.array(dtype=wp.int32), row_of_slot: wp.array(dtype=wp.int32), i: int) -> int:
    """The packed row of entry i's row slot ``row[i]`` (a sample's hit on a partner's surface,
    ``surface_rows``, or a partner vertex's, ``vertex_rows``), -1 if none."""
    slot = row[i]
    if slot < 0:
        return -1
    return row_of_slot[slot]


@wp.func
def hit_push(surf: ContactSurface, mesh: wp.uint64, f: int, i: int):
    """Sample i's intermediate point, its pushed area c_s = -|n_A . n_B| n_B dGamma against face f of a
    partner's surface (``pushed_area``, world) and that face's normal n_B."""
    yp, x, an = sample_world(surf, i)
    cn = vec3d_of(wp.mesh_eval_face_normal(mesh, f))
    return yp, pushed_area(an, cn), cn


@wp.kernel
def surface_reaction(
    surf: ContactSurface,
    mesh: wp.uint64,
    hits: SurfaceHits,
    row_of_slot: wp.array(dtype=wp.int32),
    lam: wp.array2d(dtype=wp.float64),
    dt: wp.float64,
    impulse: wp.array(dtype=wp.vec3d),
    weight: wp.array(dtype=wp.float64),
):
    """The partner's share of the contact impulse (Newton's third law): the rows push this body's
    nodes by -J^T lambda, sample s of row r contributing -lambda_r c_s with c_s = -|n_A . n_B| n_B
    dGamma (``pushed_area``, world; its node weights sum to one); the partner receives +lambda_r c_s at the sample's
    nearest point (shifted, see below), spread over that face's vertices by barycentric weights.
    ``weight`` gets each vertex's share |lambda_r c_s| b_k at the nearest point itself (positive:
    how the friction's reaction is spread). ``lam`` (lambda_0, lambda_1) is per packed row; the
    step's multiplier is lambda_0 + dt lambda_1."""
    i = wp.tid()
    r = packed_row(hits.row, row_of_slot, i)
    if r < 0:
        return
    l = lam[r, 0] + dt * lam[r, 1]
    if l == wp.float64(0.0):
        return
    f = hits.face[i]
    yp, c, cn = hit_push(surf, mesh, f, i)
    J = l * c
    # the rows push this body's nodes at their mass-weighted centroid, not at the sample: the
    # partner takes J at its nearest point shifted along its face by the same offset (barycentric
    # weights of the shifted point, negative outside the face), so the pair's angular momentum
    # is kept (about any point: J and the offset's normal part are parallel)
    d = surf.F * (applied_point(surf, yp) - yp)
    d = d - wp.dot(d, cn) * cn
    v0 = vec3d_of(wp.mesh_eval_position(mesh, f, 1.0, 0.0))
    v1 = vec3d_of(wp.mesh_eval_position(mesh, f, 0.0, 1.0))
    v2 = vec3d_of(wp.mesh_eval_position(mesh, f, 0.0, 0.0))
    b = hits.bary[i]
    for k in range(3):
        wp.atomic_add(weight, wp.mesh_get_index(mesh, 3 * f + k), b[k] * wp.length(J))
    q = b[0] * v0 + b[1] * v1 + b[2] * v2 + d - v0
    e0 = v1 - v0
    e1 = v2 - v0
    d00 = wp.dot(e0, e0)
    d01 = wp.dot(e0, e1)
    d11 = wp.dot(e1, e1)
    det = d00 * d11 - d01 * d01
    if det > wp.float64(0.0):
        b1 = (d11 * wp.dot(q, e0) - d01 * wp.dot(q, e1)) / det
        b2 = (d00 * wp.dot(q, e1) - d01 * wp.dot(q, e0)) / det
        b = wp.vec3d(wp.float64(1.0) - b1 - b2, b1, b2)
    for k in range(3):
        wp.atomic_add(impulse, wp.mesh_get_index(mesh, 3 * f + k), b[k] * J)


@wp.struct
class VertexHits:
    """Per vertex of a moving partner's surface, where it is inside this body's own surface
    (``vertex_rows``): its row slot (-1: outside), its row coefficient c (world) and the vertex's
    world position."""

    row: wp.array(dtype=wp.int32)
    c: wp.array(dtype=wp.vec3d)
    point: wp.array(dtype=wp.vec3d)


@wp.kernel
def vertex_rows(
    surf: ContactSurface,
    own: wp.uint64,
    own_closed: int,
    points: wp.array(dtype=wp.vec3),
    velocity: wp.array(dtype=wp.vec3d),
    area: wp.array(dtype=wp.float64),
    max_dist: float,
    collider: int,
    acc: wp.array2d(dtype=wp.float64),
    flag: wp.array(dtype=wp.int32),
    hits: VertexHits,
):
    """The other way round from ``surface_rows``: a vertex of a moving partner's surface (``points``,
    where it is at this step) inside this body's own surface (``own``: its tracked surface in the
    world, ``own_closed`` its inside test), so that a corner or an edge of the partner cannot sink
    between this body's samples. The vertex's share of the partner's surface, ``area`` a_v, at the
    nearest point of this surface (outward normal n_A; tracked face f, whose intermediate point
    gives the row's nodes) enters the row of that point's collision cell as a sample would:
    coefficient a_v n_A (``pushed_area`` with n_B = -n_A), right side a_v n_A . v_B - a_v depth /
    tau, v_B the vertex's velocity; the partner receives lambda_r c at the vertex
    (``vertex_reaction``)."""
    i = wp.tid()
    hits.row[i] = -1
    p = points[i]
    q = query_inside(own, p, max_dist, own_closed)
    if q.result and q.sign < 0.0:
        closest = wp.mesh_eval_position(own, q.face, q.u, q.v)
        n = vec3d_of(wp.mesh_eval_face_normal(own, q.face))
        tri = surf.faces[q.face]
        b = wp.vec3d(wp.float64(q.u), wp.float64(q.v), wp.float64(1.0) - wp.float64(q.u) - wp.float64(q.v))
        yp = b[0] * surf.y[tri[0]] + b[1] * surf.y[tri[1]] + b[2] * surf.y[tri[2]]
        an = area[i] * n
        cn = -n
        hits.row[i] = add_sample(acc, flag, surf, collider, yp, an, cn, wp.float64(wp.length(closest - p)), velocity[i])
        hits.c[i] = pushed_area(an, cn)
        hits.point[i] = vec3d_of(p)


@wp.kernel
def vertex_reaction(
    hits: VertexHits,
    row_of_slot: wp.array(dtype=wp.int32),
    lam: wp.array2d(dtype=wp.float64),
    dt: wp.float64,
    impulse: wp.array(dtype=wp.vec3d),
    weight: wp.array(dtype=wp.float64),
):
    """The partner's share of a vertex row entry (``vertex_rows``): +lambda_r c at the vertex, and
    |lambda_r c| into ``weight`` (how the friction's reaction is spread)."""
    i = wp.tid()
    r = packed_row(hits.row, row_of_slot, i)
    if r < 0:
        return
    J = (lam[r, 0] + dt * lam[r, 1]) * hits.c[i]
    wp.atomic_add(impulse, i, J)
    wp.atomic_add(weight, i, wp.length(J))


@wp.kernel
def vertex_wrenches(
    hits: VertexHits,
    row_of_slot: wp.array(dtype=wp.int32),
    com: wp.vec3d,
    wrench: wp.array2d(dtype=wp.vec3d),
):
    """``partner_wrenches`` for the vertex row entries: c at the vertex."""
    i = wp.tid()
    r = packed_row(hits.row, row_of_slot, i)
    if r < 0:
        return
    c = hits.c[i]
    wp.atomic_add(wrench, r, 0, c)
    wp.atomic_add(wrench, r, 1, wp.cross(hits.point[i] - com, c))


@wp.kernel
def compact_rows(
    acc: wp.array2d(dtype=wp.float64),
    flag: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    row_id: wp.array(dtype=wp.int32),
    packed: wp.array2d(dtype=wp.float64),
    row_of_slot: wp.array(dtype=wp.int32),
):
    """Pack the rows that received samples (in no set order: the host sorts them by id) and clear
    their slots, so the accumulator is zero for the next step without a full memset;
    ``row_of_slot`` maps every slot to its packed row (-1: no row this step)."""
    r = wp.tid()
    if flag[r] == 0:
        row_of_slot[r] = -1
        return
    slot = wp.atomic_add(count, 0, 1)
    row_id[slot] = r
    row_of_slot[r] = slot
    for q in range(acc.shape[1]):
        packed[slot, q] = acc[r, q]
        acc[r, q] = wp.float64(0.0)
    flag[r] = 0


@wp.func
def row_cell(r: int, surf: ContactSurface) -> wp.vec3i:
    """Collision cell of row slot r (slots are collider-major)."""
    nc = surf.ccells
    cell = r % (nc[0] * nc[1] * nc[2])
    return wp.vec3i(cell // (nc[1] * nc[2]), (cell // nc[2]) % nc[1], cell % nc[2])


@wp.func
def block_origin(r: int, surf: ContactSurface) -> wp.vec3i:
    """First grid node of the collision cell of row slot r."""
    return surf.block * row_cell(r, surf)


@wp.func
def slot_offset(slot: int, k1: int) -> wp.vec3i:
    """(li, lj, lk) of a block slot, k1 = block + 1 nodes per axis."""
    return wp.vec3i(slot // (k1 * k1), (slot // k1) % k1, slot % k1)


@wp.func
def node_index(g: wp.vec3i, surf: ContactSurface) -> int:
    """Flat index of grid node g, or -1 past the grid (a block at the far edge of a grid not
    divisible by the block)."""
    n = surf.grid.shape
    if g[0] >= n[0] or g[1] >= n[1] or g[2] >= n[2]:
        return -1
    return (g[0] * n[1] + g[1]) * n[2] + g[2]


@wp.func
def slot_node(surf: ContactSurface, base: wp.vec3i, slot: int) -> int:
    """Grid node of slot (li, lj, lk) of the block whose first node is ``base`` (-1 past the grid)."""
    return node_index(base + slot_offset(slot, surf.block + 1), surf)


@wp.func
def row_coefficient(packed: wp.array2d(dtype=wp.float64), i: int, slot: int) -> wp.vec3d:
    return wp.vec3d(packed[i, 3 * slot], packed[i, 3 * slot + 1], packed[i, 3 * slot + 2])


@wp.kernel
def row_products(
    surf: ContactSurface,
    packed: wp.array2d(dtype=wp.float64),
    row_id: wp.array(dtype=wp.int32),
    mass: wp.array(dtype=wp.float64),
    w: wp.array(dtype=wp.vec3d),
    a: wp.array(dtype=wp.vec3d),
    m: int,
    system: wp.array(dtype=wp.float64),
):
    """Per packed row i, after S (m x m) in ``system``: J_i w, J_i a, b_i, overlap_i, sum_s J_is
    over nodes with mass (the row's momentum direction, for the contact impulse) and the row's id
    (exact in a float64), each a segment of m values: the host reads them in one copy."""
    i = wp.tid()
    k1 = surf.block + 1
    base = block_origin(row_id[i], surf)
    jw = wp.float64(0.0)
    ja = wp.float64(0.0)
    jsum = wp.vec3d()
    for slot in range(k1 * k1 * k1):
        s = slot_node(surf, base, slot)
        if s >= 0:
            if mass[s] > wp.float64(0.0):
                c = row_coefficient(packed, i, slot)
                jw += wp.dot(c, w[s])
                ja += wp.dot(c, a[s])
                jsum += c
    n = packed.shape[1]
    o = m * m
    system[o + i] = jw
    system[o + m + i] = ja
    system[o + 2 * m + i] = packed[i, n - 2]
    system[o + 3 * m + i] = packed[i, n - 1]
    for d in range(3):
        system[o + (4 + d) * m + i] = jsum[d]
    system[o + 7 * m + i] = wp.float64(row_id[i])


@wp.kernel
def schur_complement(
    surf: ContactSurface,
    packed: wp.array2d(dtype=wp.float64),
    row_id: wp.array(dtype=wp.int32),
    row_of_slot: wp.array(dtype=wp.int32),
    mass: wp.array(dtype=wp.float64),
    m: int,
    system: wp.array(dtype=wp.float64),
):
    """S_ij = sum_s J_is . J_js / m_s (S = J M^-1 J^T, the QP's dual matrix) for packed row i and the
    row j of collider q // 27 in the collision cell at offset q % 27 (-1..1 per axis) from i's:
    only such rows share nodes with i, so each nonzero of S is written by exactly one thread (the
    rest of ``system``'s m x m block is zeroed beforehand). The shared nodes are visited in the
    same order from either side, so S is exactly symmetric."""
    i, q = wp.tid()
    nc = surf.ccells
    per = nc[0] * nc[1] * nc[2]
    k = surf.block
    cc = row_cell(row_id[i], surf)
    o = q % 27
    cj = cc + wp.vec3i(o // 9 - 1, (o // 3) % 3 - 1, o % 3 - 1)
    if cj[0] < 0 or cj[1] < 0 or cj[2] < 0 or cj[0] >= nc[0] or cj[1] >= nc[1] or cj[2] >= nc[2]:
        return
    j = row_of_slot[(q // 27) * per + (cj[0] * nc[1] + cj[1]) * nc[2] + cj[2]]
    if j < 0:
        return
    k1 = k + 1
    base_i = k * cc
    base_j = k * cj
    total = wp.float64(0.0)
    for slot in range(k1 * k1 * k1):
        g = base_i + slot_offset(slot, k1)
        l = g - base_j
        if l[0] >= 0 and l[0] <= k and l[1] >= 0 and l[1] <= k and l[2] >= 0 and l[2] <= k:
            s = node_index(g, surf)
            if s >= 0:
                if mass[s] > wp.float64(0.0):
                    other = (l[0] * k1 + l[1]) * k1 + l[2]
                    total += wp.dot(row_coefficient(packed, i, slot), row_coefficient(packed, j, other)) / mass[s]
    system[i * m + j] = total


@wp.kernel
def apply_impulses(
    surf: ContactSurface,
    packed: wp.array2d(dtype=wp.float64),
    row_id: wp.array(dtype=wp.int32),
    mass: wp.array(dtype=wp.float64),
    lam: wp.array2d(dtype=wp.float64),
    group: int,
    cells_per_group: int,
    dt: wp.float64,
    w: wp.array(dtype=wp.vec3d),
    a: wp.array(dtype=wp.vec3d),
):
    """group < 0: w -= M^-1 J^T lambda_0 and a -= M^-1 J^T lambda_1 over every row (Eq. 31 on the
    frozen active set: the unconstrained w and a become w_0 and w_1 in place). group >= 0: only
    the rows of that row group (a collider or a moving surface: row id // cells_per_group), w -=
    M^-1 J^T (lambda_0 + dt lambda_1): the velocity change that group's multipliers at dt give
    each node (what friction against that surface acts on; ``a`` is not touched)."""
    i = wp.tid()
    l0 = lam[i, 0]
    l1 = lam[i, 1]
    if group >= 0:
        if row_id[i] // cells_per_group != group:
            return
        l0 = l0 + dt * l1
        l1 = wp.float64(0.0)
    if l0 == wp.float64(0.0) and l1 == wp.float64(0.0):
        return
    k1 = surf.block + 1
    base = block_origin(row_id[i], surf)
    for slot in range(k1 * k1 * k1):
        s = slot_node(surf, base, slot)
        if s >= 0:
            if mass[s] > wp.float64(0.0):
                c = row_coefficient(packed, i, slot) / mass[s]
                wp.atomic_sub(w, s, l0 * c)
                if group < 0:
                    wp.atomic_sub(a, s, l1 * c)


@wp.kernel
def node_friction(
    surf: ContactSurface,
    push: wp.array(dtype=wp.vec3d),
    mass: wp.array(dtype=wp.float64),
    w0: wp.array(dtype=wp.vec3d),
    w1: wp.array(dtype=wp.vec3d),
    dt: wp.float64,
    G: wp.mat33d,
    g: wp.vec3d,
    mu: wp.float64,
    impulse: wp.array(dtype=wp.vec3d),
):
    """Coulomb friction at the grid nodes a surface pushes (grid-node friction, as in MPM contact):
    with the node's normal velocity change dv_n = |push| along n = push / |push| and its slip
    u_t, the tangential part of u - v_B (u = w0 + dt w1 the node's velocity after the normal
    contact, v_B = G x + g the surface's), the slip changes by -u_t min(1, mu dv_n / |u_t|):
    stopped if the push can, else reduced by mu times it (kinetic friction). Applied to w0 (the
    dt-independent part); the momentum it takes, sum m dv_t, is added to ``impulse[0]`` (velocity
    axes) and its moment about the world origin, sum x_s x m dv_t, to ``impulse[1]`` (world), for
    the surface's body."""
    s = wp.tid()
    p = push[s]
    pn = wp.length(p)
    if pn == wp.float64(0.0) or mass[s] <= wp.float64(0.0):
        return
    n = p / pn
    x = surf.F * node_position(s, surf.grid) + surf.T
    rel = w0[s] + dt * w1[s] - surf.to_axes * (G * x + g)
    slip = rel - wp.dot(n, rel) * n
    st = wp.length(slip)
    if st == wp.float64(0.0):
        return
    d = -slip * wp.min(wp.float64(1.0), mu * pn / st)
    w0[s] = w0[s] + d
    wp.atomic_add(impulse, 0, mass[s] * d)
    wp.atomic_add(impulse, 1, wp.cross(x, wp.transpose(surf.to_axes) * (mass[s] * d)))


@wp.kernel
def partner_wrenches(
    surf: ContactSurface,
    mesh: wp.uint64,
    hits: SurfaceHits,
    row_of_slot: wp.array(dtype=wp.int32),
    com: wp.vec3d,
    wrench: wp.array2d(dtype=wp.vec3d),
):
    """What a unit multiplier of each packed row r does to a moving partner taken as a rigid body:
    wrench[r, 0] = sum_s c_s (the force), wrench[r, 1] = sum_s (p_s - com) x c_s (the moment about
    its centre of mass), over the samples s of row r inside it, c_s = -|n_A . n_B| n_B dGamma
    (``pushed_area``, world) applied at the sample's nearest point p_s, where the row's right side
    takes the partner's velocity (``surface_rows``). ``wrench`` is zeroed on its first m rows
    beforehand."""
    i = wp.tid()
    r = packed_row(hits.row, row_of_slot, i)
    if r < 0:
        return
    f = hits.face[i]
    yp, c, cn = hit_push(surf, mesh, f, i)
    b = hits.bary[i]
    p = vec3d_of(wp.mesh_eval_position(mesh, f, float(b[0]), float(b[1])))
    wp.atomic_add(wrench, r, 0, c)
    wp.atomic_add(wrench, r, 1, wp.cross(p - com, c))


@wp.kernel
def partner_compliance(wrench: wp.array2d(dtype=wp.vec3d), inv_mass: wp.float64, inv_inertia: wp.mat33d,
                       elastic: wp.float64, m: int, system: wp.array(dtype=wp.float64)):
    """S_ij += f_i . f_j / M + t_i . I^-1 t_j (``partner_wrenches``' force f and moment t per row),
    and S_ii += |f_i| elastic: the give of a moving partner of mass M and inertia I (world, about
    its centre of mass) to the rows' impulses, rigid and elastic. elastic = 1 / (rho c_p T)
    (``EolBody._elastic_give``): a push of impulse P spread over the row's area |f_i| for the
    coupling interval T moves that patch at P / (rho c_p |f_i| T), the plane-wave impedance; the
    patches of different rows are taken as independent. A partner that yields moves away as it
    takes lambda, so the rows' right side (its flux) grows by S_B lambda and the dual matrix of Eq. (29) becomes S + S_B: the QP shares
    each correction between this body's nodes and the partner by their masses. Without it the
    partner is kinematic, and a heavy EoL body matched a light partner's velocity with all its own
    mass: a 48 kg EoL slab flung the 0.8 kg BEM box sliding on it (+5.4 J). The partner is taken
    as rigid (its response over a coupling interval to a push spread over its face; lumping it
    on the touched vertices let it sink 10 mm into the slab). Each (i, j) is one thread, after
    ``schur_complement`` (a later launch): no atomics."""
    i, j = wp.tid()
    fi = wrench[i, 0]
    ti = wrench[i, 1]
    fj = wrench[j, 0]
    tj = wrench[j, 1]
    give = wp.dot(fi, fj) * inv_mass + wp.dot(ti, inv_inertia * tj)
    if i == j:  # each row's own patch yields elastically: |f_i| / (rho c_p T) (``EolBody._elastic_give``)
        give = give + wp.length(fi) * elastic
    system[i * m + j] = system[i * m + j] + give


@wp.kernel
def partner_push(surface: wp.array(dtype=wp.vec3), step_impulse: wp.array(dtype=wp.vec3d), com: wp.vec3d,
                 total: wp.array(dtype=wp.vec3d)):
    """total[0] += J_v, total[1] += (x_v - com) x J_v: the momentum and angular momentum (about the
    partner's centre of mass) of this step's reaction (``surface_reaction``) at vertices x_v."""
    v = wp.tid()
    J = step_impulse[v]
    wp.atomic_add(total, 0, J)
    wp.atomic_add(total, 1, wp.cross(vec3d_of(surface[v]) - com, J))


@wp.kernel
def partner_yield(velocity: wp.array(dtype=wp.vec3d), surface: wp.array(dtype=wp.vec3), total: wp.array(dtype=wp.vec3d),
                  push: wp.float64, received: wp.vec3d, received_moment: wp.vec3d, com: wp.vec3d, inv_mass: wp.float64,
                  inv_inertia: wp.mat33d, step_impulse: wp.array(dtype=wp.vec3d), received_v: wp.array(dtype=wp.vec3d),
                  share: wp.float64, area: wp.array(dtype=wp.float64), elastic: wp.float64):
    """v_v += (P - s R) / M + (I^-1 (L - s R_L)) x (x_v - com) + (J_v - s R_v) elastic / A_v: the
    partner's vertices yield to this step's reaction (``partner_push``: P, L; J_v at vertex v of
    lumped area A_v) as a rigid body and elastically (``partner_compliance``'s give), in the
    velocity the next step's rows see (their right side); the partner's own stepping receives it
    after the coupling interval. Without it each step of the interval saw the partner closing in
    at its old speed and pushed it again. Only the change of the push yields: the partner takes
    the last interval's push (R, R_L about com, R_v per vertex) during this one, and its motion
    p0 -> p1 already carries that, so the share s = dt / T of it a step covers is taken off
    (before the step at the QP's dt, ``EolBody._expect_partners``, squared with the dt taken
    after it). A resting pusher then pushes what the partner already takes, and sees it still; a
    push that changes sees it yield to the change, rigidly and elastically. 8 kg EoL and BEM boxes
    stacked (dt = 2 ms): with the whole push yielding, the BEM box shook at 13 mm/s; with the
    change yielding but the step's share taken off only after it, the deepest vertex was 0.77 mm
    in (0.27 mm now)."""
    v = wp.tid()
    P = push * total[0] - received
    L = push * total[1] - received_moment
    dv = inv_mass * P + wp.cross(inv_inertia * L, vec3d_of(surface[v]) - com)
    if area[v] > wp.float64(0.0):
        dv = dv + (push * step_impulse[v] - share * received_v[v]) * (elastic / area[v])
    velocity[v] = velocity[v] + dv


@wp.kernel
def accumulate(total: wp.array(dtype=wp.vec3d), part: wp.array(dtype=wp.vec3d)):
    """total += part: a step's reaction impulses (``surface_reaction``) summed over an ``advance``
    on the device."""
    i = wp.tid()
    total[i] = total[i] + part[i]



# -- contact between EoL bodies in one QP (Eq. 29 across objects; issue 18) -------------------------

@wp.kernel
def world_surface(surf: ContactSurface, out: wp.array(dtype=wp.vec3)):
    """The tracked surface's vertices in the world, x = F y + T (float32: a Warp mesh's points)."""
    i = wp.tid()
    x = surf.F * surf.y[i] + surf.T
    out[i] = wp.vec3(float(x[0]), float(x[1]), float(x[2]))


@wp.kernel
def surface_bounds(points: wp.array(dtype=wp.vec3), slot: int, bounds: wp.array2d(dtype=wp.float32)):
    """The bounding box of a surface's points: bounds[slot, 0:3] min, bounds[slot, 3:6] max (atomic;
    start from +inf and -inf)."""
    i = wp.tid()
    p = points[i]
    for d in range(3):
        wp.atomic_min(bounds, slot, d, p[d])
        wp.atomic_max(bounds, slot, 3 + d, p[d])


#: floats of one pair sample's record (``pair_samples``)
PAIR_RECORD = 48


@wp.kernel
def pair_samples(
    own: ContactSurface,
    other: ContactSurface,
    other_inverse: wp.mat33d,
    mesh: wp.uint64,
    closed: int,
    max_dist: float,
    own_is_a: int,
    pair: int,
    own_w: wp.array(dtype=wp.vec3d),
    own_a: wp.array(dtype=wp.vec3d),
    other_w: wp.array(dtype=wp.vec3d),
    other_a: wp.array(dtype=wp.vec3d),
    count: wp.array(dtype=wp.int32),
    rec_i: wp.array2d(dtype=wp.int32),
    rec_f: wp.array2d(dtype=wp.float64),
):
    """The samples of one EoL body inside another's closed surface (``mesh``: the other's tracked
    surface in the world, where it is at this step), each one record of a contact row of both
    bodies (``wsim.eol.pairs``). Sample s, at x_s with area element n dGamma, inside the other body
    (nearest face normal n_B, depth d) constrains the bodies' relative velocity there,
    c_s . (v_own(x_s) - v_other(x_s)) with c_s = -|n dGamma . n_B| n_B (``pushed_area``): the
    own surface's share of Eq. (27) with the other body's velocity in place of a collider's, so
    that its impulse -lambda c_s on the own body is +lambda c_s on the other (equal and opposite
    at the same point: the pair's momentum is exact). Each body's velocity at x_s is the
    mass-weighted mean of its cell's nodes (``cell_weights``, against flinging nodes that hold a
    sliver of material; the impulse then acts at each cell's mass centroid, and the host makes up
    the pair's angular momentum with a couple, ``wsim.eol.pairs.moment_couples``); a sample in a
    cell of either body that holds no material is skipped. The row is the pair's (``pair``) collision cell of body A
    (``own_is_a``: this body, else the other) at x_s: samples of both bodies in one cell make one
    row, the paper's collision grid of Sec. 3.5.

    ``closed``: the inside test of ``query_inside`` for the other's surface (ray parity where it
    is one watertight piece). A sample whose normal is perpendicular to the nearest face's (c_s = 0)
    pushes with zero and is skipped.

    Record (``rec_i``): pair, own_is_a, own cell's first node, other's, A's collision cell.
    ``rec_f`` (``PAIR_RECORD`` floats): own weights (8), other's (8), own node masses (8), other's
    (8), c_s (3, world), overlap volume |n dGamma . n_B| d (1), own velocity at x_s from w and a
    (3 + 3, world), other's (3 + 3). Records past the buffer's rows are counted, not
    written: the caller grows the buffer and launches again."""
    i = wp.tid()
    yp, x, an = sample_world(own, i)
    yo = other_inverse * (x - other.T)
    g = (yo - other.grid.origin) / other.grid.h
    for d in range(3):  # outside the other's grid box: not inside its surface
        if g[d] < wp.float64(0.0) or g[d] > wp.float64(other.grid.shape[d] - 1):
            return
    # the cells' material first: it is 16 reads, the inside query below a tree walk, and
    # most samples in the other's grid box lie in its empty cells
    base_o, wo, pm_o = cell_weights(own, yp)
    base_b, wb, pm_b = cell_weights(other, yo)
    if pm_o <= wp.float64(0.0) or pm_b <= wp.float64(0.0):
        return
    p = wp.vec3(float(x[0]), float(x[1]), float(x[2]))
    q = query_inside(mesh, p, max_dist, closed)
    if not (q.result and q.sign < 0.0):
        return
    closest = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    n = wp.mesh_eval_face_normal(mesh, q.face)
    cn = wp.vec3d(wp.float64(n[0]), wp.float64(n[1]), wp.float64(n[2]))
    coeff = pushed_area(an, cn)
    if wp.length_sq(coeff) == wp.float64(0.0):  # its normal is perpendicular to the other's face's: no push
        return
    vol = wp.abs(wp.dot(an, cn)) * wp.float64(wp.length(closest - p))
    slot = wp.atomic_add(count, 0, 1)
    if slot >= rec_i.shape[0]:
        return
    cell = wp.vec3i()
    k = own.block
    nc = own.ccells
    if own_is_a != 0:
        cell, t = sample_cell(own, yp)
    else:
        cell, t = sample_cell(other, yo)
        k = other.block
        nc = other.ccells
    rec_i[slot, 0] = pair
    rec_i[slot, 1] = own_is_a
    rec_i[slot, 2] = base_o
    rec_i[slot, 3] = base_b
    rec_i[slot, 4] = ((cell[0] // k) * nc[1] + cell[1] // k) * nc[2] + cell[2] // k
    for c in range(8):
        rec_f[slot, c] = wo[c]
        rec_f[slot, 8 + c] = wb[c]
        rec_f[slot, 16 + c] = own.mass[corner_node(own, base_o, c)]
        rec_f[slot, 24 + c] = other.mass[corner_node(other, base_b, c)]
    vw = cell_velocity(own, base_o, wo, own_w)
    va = cell_velocity(own, base_o, wo, own_a)
    bw = cell_velocity(other, base_b, wb, other_w)
    ba = cell_velocity(other, base_b, wb, other_a)
    for d in range(3):
        rec_f[slot, 32 + d] = coeff[d]
        rec_f[slot, 36 + d] = vw[d]
        rec_f[slot, 39 + d] = va[d]
        rec_f[slot, 42 + d] = bw[d]
        rec_f[slot, 45 + d] = ba[d]
    rec_f[slot, 35] = vol


@wp.kernel
def add_node_changes(nodes: wp.array(dtype=wp.int32), d0: wp.array(dtype=wp.vec3d), d1: wp.array(dtype=wp.vec3d),
                     w: wp.array(dtype=wp.vec3d), a: wp.array(dtype=wp.vec3d)):
    """w[nodes] += d0 and a[nodes] += d1 (velocity changes the host computed for the nodes that
    contact rows between bodies touch; each node once)."""
    i = wp.tid()
    s = nodes[i]
    w[s] = w[s] + d0[i]
    a[s] = a[s] + d1[i]


#: floats of a row entry of ``pair_entries``: c . (v_own - v_other) from w and from a, vol / tau,
#: vol, sigma c (3), sigma |c| (v_own - v_other) from w (3) and from a (3), |c|
PAIR_ROW_VALUES = 14
#: floats of a node entry: w c' (3; c' = sign Q^T c, velocity axes), w sign sigma |c|, w
PAIR_NODE_VALUES = 5


@wp.kernel
def pair_entries(
    rec_i: wp.array2d(dtype=wp.int32),
    rec_f: wp.array2d(dtype=wp.float64),
    own: int,
    pair_a: wp.array(dtype=wp.int32),
    pair_b: wp.array(dtype=wp.int32),
    axes: wp.array(dtype=wp.mat33d),
    node_shape: wp.array(dtype=wp.vec3i),
    inv_tau: wp.array(dtype=wp.float64),
    row_stride: wp.int64,
    rows: wp.int64,
    nodes: wp.int64,
    offset: int,
    node_keys: wp.array(dtype=wp.int64),
    node_values: wp.array2d(dtype=wp.float64),
    node_mass: wp.array(dtype=wp.float64),
    row_keys: wp.array(dtype=wp.int64),
    row_values: wp.array2d(dtype=wp.float64),
):
    """One ``pair_samples`` record of body ``own`` (group index) as the entries the rows between
    bodies are summed from (``wsim.eol.pairs``): one row entry, keyed by the row (pair p, A's
    collision cell k: p ``row_stride`` + k), and 16 node entries, one per corner of each body's
    cell (X the body, n the corner's node: key (X ``rows`` + row) ``nodes`` + n).

    With c the sample's pushed area (world), sigma = +1 if the own body is the pair's A else -1,
    and sign = +1 on the own body's side, -1 on the other's: a node entry holds w c' with
    c' = sign Q_X^T c (the row's coefficient on that node's velocity, X's velocity axes; w the
    corner's weight of X's cell, ``cell_weights``), w sign sigma |c| (the node's part of the
    row's slip v_A - v_B, before the division by the row's total |c|) and w (zero: no material,
    the entry is dropped). Its mass is the node's. Record r of this buffer writes row entry
    ``offset`` + r and node entries 16 (``offset`` + r) + 8 side + corner."""
    r = wp.tid()
    pair = rec_i[r, 0]
    own_is_a = rec_i[r, 1]
    other = pair_a[pair]
    sigma = wp.float64(-1.0)
    if own_is_a != 0:
        other = pair_b[pair]
        sigma = wp.float64(1.0)
    row = wp.int64(pair) * row_stride + wp.int64(rec_i[r, 4])
    c = wp.vec3d(rec_f[r, 32], rec_f[r, 33], rec_f[r, 34])
    vol = rec_f[r, 35]
    rel_w = wp.vec3d(rec_f[r, 36] - rec_f[r, 42], rec_f[r, 37] - rec_f[r, 43], rec_f[r, 38] - rec_f[r, 44])
    rel_a = wp.vec3d(rec_f[r, 39] - rec_f[r, 45], rec_f[r, 40] - rec_f[r, 46], rec_f[r, 41] - rec_f[r, 47])
    area = wp.length(c)
    e = offset + r
    row_keys[e] = row
    row_values[e, 0] = wp.dot(c, rel_w)
    row_values[e, 1] = wp.dot(c, rel_a)
    row_values[e, 2] = vol * inv_tau[own]
    row_values[e, 3] = vol
    for d in range(3):
        row_values[e, 4 + d] = sigma * c[d]
        row_values[e, 7 + d] = sigma * area * rel_w[d]
        row_values[e, 10 + d] = sigma * area * rel_a[d]
    row_values[e, 13] = area
    for side in range(2):
        body = own
        sign = wp.float64(1.0)
        if side == 1:
            body = other
            sign = wp.float64(-1.0)
        cq = sign * (wp.transpose(axes[body]) * c)
        g = sign * sigma * area
        base = rec_i[r, 2 + side]
        shape = node_shape[body]
        for k in range(8):
            n = base + ((k // 4) * shape[1] + (k // 2) % 2) * shape[2] + k % 2
            w = rec_f[r, 8 * side + k]
            j = 16 * e + 8 * side + k
            node_keys[j] = (wp.int64(body) * rows + row) * nodes + wp.int64(n)
            node_values[j, 0] = w * cq[0]
            node_values[j, 1] = w * cq[1]
            node_values[j, 2] = w * cq[2]
            node_values[j, 3] = w * g
            node_values[j, 4] = w
            node_mass[j] = rec_f[r, 16 + 8 * side + k]
