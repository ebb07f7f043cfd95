"""Warp functions of the EoL grid: trilinear shape functions of a cell, and sampling a nodal field.

Cell corners are numbered c = 4 i + 2 j + k (i, j, k in {0, 1}), the order of ``wsim.eol.grid.CORNERS``.
A nodal field is a (nx + 1, ny + 1, nz + 1) array of vec3d; points outside the grid box are
clamped onto it. Every EoL kernel takes the grid as one ``Grid`` struct (``grid_struct`` builds
it from a ``wsim.eol.grid.EolGrid``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp


@wp.struct
class Grid:
    """The EoL grid on the device: ``shape`` nodes per axis (cells + 1), ``origin`` the (0, 0, 0)
    node [m], ``h`` the cell size [m]. Node s = (i ny + j) nz + k sits at origin + h (i, j, k)."""

    shape: wp.vec3i
    origin: wp.vec3d
    h: wp.float64


def grid_struct(grid: Any) -> Grid:
    """The ``Grid`` struct of an ``EolGrid`` (anything with ``node_shape``, ``origin`` and ``h``)."""
    g = Grid()
    g.shape = wp.vec3i(*(int(n) for n in grid.node_shape))
    g.origin = wp.vec3d(*np.asarray(grid.origin, dtype=np.float64))
    g.h = wp.float64(float(grid.h))
    return g


@wp.func
def node_position(s: int, grid: Grid) -> wp.vec3d:
    """Position of flat node s [m]."""
    shape = grid.shape
    i = s // (shape[1] * shape[2])
    j = (s // shape[2]) % shape[1]
    k = s % shape[2]
    return grid.origin + grid.h * wp.vec3d(wp.float64(i), wp.float64(j), wp.float64(k))


@wp.func
def node_at(grid: Grid, i: int, j: int, k: int) -> wp.vec3d:
    """Position of node (i, j, k) [m]."""
    return grid.origin + grid.h * wp.vec3d(wp.float64(i), wp.float64(j), wp.float64(k))


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
def grid_coordinates(q: wp.array3d(dtype=wp.vec3d), p: wp.vec3d, grid: Grid) -> wp.vec3d:
    """p in cell units, clamped into the grid box of the nodal field q."""
    g = (p - grid.origin) / grid.h
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
def sample_trilinear(q: wp.array3d(dtype=wp.vec3d), p: wp.vec3d, grid: Grid) -> wp.vec3d:
    """q at point p (trilinear; p clamped into the grid box)."""
    g = grid_coordinates(q, p, grid)
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
def sample_gradient(q: wp.array3d(dtype=wp.vec3d), p: wp.vec3d, grid: Grid) -> wp.mat33d:
    """grad_y q of the trilinear field at p (p clamped into the grid box, like ``sample_trilinear``)."""
    g = grid_coordinates(q, p, grid)
    cell = cell_of(q, g)
    return gradient_in_cell(q, cell, local_coordinates(g, cell), grid.h)
