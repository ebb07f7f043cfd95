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

# longest Newton step [cells]: a step moves material well under a cell (cfl < 1), and a tracking
# guess from rest (tests, a regrid) may be a few cells off; longer steps come from a folded field
MAX_STEP = 4.0


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
    """Algorithm 2 for one vertex per thread: y with z(y) = z_v to |e| < tol (or max_iter steps).

    Safeguarded Newton: a step is at most ``MAX_STEP`` cells long and is halved (up to 8 times)
    until the residual falls; the point with the smallest residual is kept. Where the field is (nearly)
    folded, grad_y z is (nearly) singular and a plain Newton step jumped a vertex hundreds of
    cells away, which read as material leaving the grid (issue 16 item 6)."""
    v = wp.tid()
    p = guess[v]
    n = int(0)
    e = z_vertex[v] - sample_trilinear(z_field, p, grid)
    r = wp.length(e)
    while r >= tol and n < max_iter:
        step = wp.inverse(sample_gradient(z_field, p, grid)) * e
        size = wp.length(step)
        if not wp.isfinite(size):
            break
        if size > wp.float64(MAX_STEP) * grid.h:
            step = step * (wp.float64(MAX_STEP) * grid.h / size)
        q = p + step
        eq = z_vertex[v] - sample_trilinear(z_field, q, grid)
        halvings = int(0)
        while wp.length(eq) >= r and halvings < 8:
            step = step * wp.float64(0.5)
            q = p + step
            eq = z_vertex[v] - sample_trilinear(z_field, q, grid)
            halvings += 1
        n += 1
        if wp.length(eq) >= r:
            break  # no descent along the Newton direction: keep the best point
        p = q
        e = eq
        r = wp.length(e)
    y_vertex[v] = p
    iterations[v] = wp.int32(n)
