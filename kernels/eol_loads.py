"""Warp kernels of EoL external loads (issue 16): point forces scattered to the grid nodes, and the
check that the material stays inside its grid.

A point force f at intermediate position y (a surface vertex's share of a traction, or a material
point's share of a body force) goes to the 8 nodes of y's cell with the trilinear weights
Phi_s(y), the shape functions the lumped masses use. Nodes without mass take no force (their
acceleration is undefined): the weights are renormalized over the cell's nodes with mass, so the
force's total (its momentum) is kept exactly. Since sum_s Phi_s(y) y_s = y, the torque about any
point is kept too when every node of the cell has mass (the usual case). ``applied`` sums what
was delivered (a force with no node with mass in its cell is dropped and not counted).
"""

from __future__ import annotations

import warp as wp

from wsim.kernels.eol_grid import (
    Grid,
    cell_of,
    corner_weight,
    grid_coordinates,
    local_coordinates,
)
from wsim.kernels.mesh import query_inside


@wp.kernel
def scatter_point_forces(
    y: wp.array(dtype=wp.vec3d),
    f: wp.array(dtype=wp.vec3d),
    mass: wp.array3d(dtype=wp.float64),
    grid: Grid,
    mass_weighted: int,
    forces: wp.array3d(dtype=wp.vec3d),
    applied: wp.array(dtype=wp.float64),
    at: int,
):
    """forces_s += w_s f_i over the nodes with mass of y_i's cell, w_s = Phi_s(y_i) / sum Phi (a body
    force: the particle-to-grid transfer of the point's mass) or, ``mass_weighted``, Phi_s m_s /
    sum Phi m (a surface force: every node of the cell is accelerated alike, as the contact rows
    do - with plain Phi a node holding a sliver of material at the mass floor takes a share of a
    surface push out of all proportion to its mass, and advecting its Eulerian velocity loses
    momentum: 5 % of the exchange between two colliding EoL spheres, issue 18). The force
    delivered is summed into applied[at:at + 3] (a slot of the step's read-back)."""
    i = wp.tid()
    fi = f[i]
    g = grid_coordinates(forces, y[i], grid)
    cell = cell_of(forces, g)
    t = local_coordinates(g, cell)
    total = wp.float64(0.0)
    for c in range(8):
        m = mass[cell[0] + c // 4, cell[1] + (c // 2) % 2, cell[2] + c % 2]
        if m > wp.float64(0.0):
            if mass_weighted != 0:
                total += corner_weight(c, t) * m
            else:
                total += corner_weight(c, t)
    if total <= wp.float64(0.0):
        return
    for c in range(8):
        a = cell[0] + c // 4
        b = cell[1] + (c // 2) % 2
        d = cell[2] + c % 2
        m = mass[a, b, d]
        if m > wp.float64(0.0):
            w = corner_weight(c, t) / total
            if mass_weighted != 0:
                w = w * m
            wp.atomic_add(forces, a, b, d, w * fi)
    for k in range(3):
        wp.atomic_add(applied, at + k, fi[k])


@wp.kernel
def outside_margin(
    y: wp.array(dtype=wp.vec3d),
    grid: Grid,
    margin: wp.float64,
    out: wp.array(dtype=wp.float64),
    slot: int,
):
    """out[slot] = max over points of how far (in cells) a point lies beyond the box shrunk by
    ``margin`` cells on every side (0 inside; 1e30 for a non-finite point)."""
    i = wp.tid()
    g = (y[i] - grid.origin) / grid.h
    worst = wp.float64(0.0)
    for d in range(3):
        gd = g[d]
        if not wp.isfinite(gd):
            worst = wp.float64(1e30)
        else:
            hi = wp.float64(grid.shape[d] - 1) - margin
            worst = wp.max(worst, wp.max(margin - gd, gd - hi))
    wp.atomic_max(out, slot, worst)


@wp.kernel
def mesh_depth(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_dist: float, closed: int,
               depth: wp.array(dtype=wp.float32)):
    """Distance from each point (collider-local coordinates) to the collider's surface if the point
    is inside the mesh (``query_inside``, as the contact rows ask), else 0."""
    i = wp.tid()
    p = points[i]
    depth[i] = wp.float32(0.0)
    q = query_inside(mesh, p, max_dist, closed)
    if q.result and q.sign < 0.0:
        depth[i] = wp.length(wp.mesh_eval_position(mesh, q.face, q.u, q.v) - p)
