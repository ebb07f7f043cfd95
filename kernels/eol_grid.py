"""Warp functions of the EoL grid: trilinear shape functions of a cell, and sampling a nodal field.

Cell corners are numbered c = 4 i + 2 j + k (i, j, k in {0, 1}), the order of ``wsim.eol.grid.CORNERS``.
A nodal field is a (nx + 1, ny + 1, nz + 1) array of vec3d; points outside the grid box are
clamped onto it.
"""

from __future__ import annotations

import warp as wp


@wp.func
def corner_weight(c: int, t: wp.vec3d) -> wp.float64:
    """Phi of cell corner c at local coordinates t in [0, 1]^3."""
    one = wp.float64(1.0)
    wx = wp.where(c // 4 == 1, t[0], one - t[0])
    wy = wp.where((c // 2) % 2 == 1, t[1], one - t[1])
    wz = wp.where(c % 2 == 1, t[2], one - t[2])
    return wx * wy * wz


@wp.func
def corner_gradient(c: int, t: wp.vec3d, h: wp.float64) -> wp.vec3d:
    """grad Phi of cell corner c at local coordinates t (cell size h)."""
    i = c // 4
    j = (c // 2) % 2
    k = c % 2
    one = wp.float64(1.0)
    wx = wp.where(i == 1, t[0], one - t[0])
    wy = wp.where(j == 1, t[1], one - t[1])
    wz = wp.where(k == 1, t[2], one - t[2])
    dx = wp.where(i == 1, one, -one)
    dy = wp.where(j == 1, one, -one)
    dz = wp.where(k == 1, one, -one)
    return wp.vec3d(dx * wy * wz, wx * dy * wz, wx * wy * dz) / h


@wp.func
def grid_coordinates(q: wp.array3d(dtype=wp.vec3d), p: wp.vec3d, origin: wp.vec3d, h: wp.float64) -> wp.vec3d:
    """p in cell units, clamped into the grid box of the nodal field q."""
    g = (p - origin) / h
    zero = wp.float64(0.0)
    return wp.vec3d(wp.clamp(g[0], zero, wp.float64(q.shape[0] - 1)), wp.clamp(g[1], zero, wp.float64(q.shape[1] - 1)),
                    wp.clamp(g[2], zero, wp.float64(q.shape[2] - 1)))


@wp.func
def cell_of(q: wp.array3d(dtype=wp.vec3d), g: wp.vec3d) -> wp.vec3i:
    """The cell holding clamped grid coordinates g (the last cell for points on the far faces)."""
    return wp.vec3i(wp.min(int(g[0]), q.shape[0] - 2), wp.min(int(g[1]), q.shape[1] - 2),
                    wp.min(int(g[2]), q.shape[2] - 2))


@wp.func
def corner_value(q: wp.array3d(dtype=wp.vec3d), cell: wp.vec3i, c: int) -> wp.vec3d:
    return q[cell[0] + c // 4, cell[1] + (c // 2) % 2, cell[2] + c % 2]


@wp.func
def local_coordinates(g: wp.vec3d, cell: wp.vec3i) -> wp.vec3d:
    """Local coordinates in [0, 1]^3 of grid coordinates g inside ``cell``."""
    return g - wp.vec3d(wp.float64(cell[0]), wp.float64(cell[1]), wp.float64(cell[2]))


@wp.func
def sample_trilinear(q: wp.array3d(dtype=wp.vec3d), p: wp.vec3d, origin: wp.vec3d, h: wp.float64) -> wp.vec3d:
    """q at point p (trilinear; p clamped into the grid box)."""
    g = grid_coordinates(q, p, origin, h)
    cell = cell_of(q, g)
    t = local_coordinates(g, cell)
    out = wp.vec3d()
    for c in range(8):
        out += corner_weight(c, t) * corner_value(q, cell, c)
    return out


@wp.func
def gradient_in_cell(q: wp.array3d(dtype=wp.vec3d), cell: wp.vec3i, t: wp.vec3d, h: wp.float64) -> wp.mat33d:
    """grad_y q of the trilinear field in ``cell`` at local coordinates t."""
    G = wp.mat33d()
    for c in range(8):
        G += wp.outer(corner_value(q, cell, c), corner_gradient(c, t, h))
    return G


@wp.func
def sample_gradient(q: wp.array3d(dtype=wp.vec3d), p: wp.vec3d, origin: wp.vec3d, h: wp.float64) -> wp.mat33d:
    """grad_y q of the trilinear field at p (p clamped into the grid box, like ``sample_trilinear``)."""
    g = grid_coordinates(q, p, origin, h)
    cell = cell_of(q, g)
    return gradient_in_cell(q, cell, local_coordinates(g, cell), h)


@wp.kernel
def inside_mesh(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), inside: wp.array(dtype=wp.int32)):
    """1 where the generalized winding number of the closed surface at the point exceeds 1/2
    (Warp's fast winding number: exact triangle solid angles near the point, the dipole expansion
    of far BVH clusters; 0/1 away from the surface, so the 1/2 threshold is robust)."""
    i = wp.tid()
    q = wp.mesh_query_point_sign_winding_number(mesh, points[i], 1.0e30, 2.0, 0.5)
    inside[i] = wp.where(q.result and q.sign < 0.0, 1, 0)
