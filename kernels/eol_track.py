"""Warp kernel of EoL surface tracking (Fan et al. Sec. 3.8, Algorithm 2).

The surface mesh lives in the material domain z. Each step, each vertex's intermediate position y
is found from the advected material-coordinate field z(y) (trilinear on the grid): solve
z(y) = z_v by Newton's method, p <- p + F e with e = z_v - z(p) and F = (grad_y z)^-1 (the
Eulerian deformation gradient), starting from the previous step's y. Zero displacement (z = y)
returns every vertex exactly to its rest position; an affine field converges in one iteration.
"""

from __future__ import annotations

import warp as wp

from wsim.kernels.eol_grid import Grid, sample_gradient, sample_trilinear


@wp.kernel
def track_surface(
    z_field: wp.array3d(dtype=wp.vec3d),
    grid: Grid,
    z_vertex: wp.array(dtype=wp.vec3d),
    guess: wp.array(dtype=wp.vec3d),
    tol: wp.float64,
    max_iter: int,
    y_vertex: wp.array(dtype=wp.vec3d),
    iterations: wp.array(dtype=wp.int32),
):
    """Algorithm 2 for one vertex per thread: y with z(y) = z_v to |e| < tol (or max_iter steps)."""
    v = wp.tid()
    p = guess[v]
    n = int(0)
    e = z_vertex[v] - sample_trilinear(z_field, p, grid)
    while wp.length(e) >= tol and n < max_iter:
        p = p + wp.inverse(sample_gradient(z_field, p, grid)) * e
        e = z_vertex[v] - sample_trilinear(z_field, p, grid)
        n += 1
    y_vertex[v] = p
    iterations[v] = wp.int32(n)
