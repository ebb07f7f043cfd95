"""Surface tracking of an EoL body (Algorithm 2; the Warp kernel ``track_surface``).

``track_points`` launches the kernel on device arrays: ``EolBody`` calls it every step for its
material points and its surface vertices. ``track_surface`` is the host convenience (tests)
around the same launch.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.eol.grid import EolGrid
from wsim.kernels import eol_track as kt
from wsim.kernels.eol_grid import Grid, grid_struct
from wsim.launch import Launcher, launch_on


def track_points(grid: Grid, z_field: wp.array, z_points: wp.array, guess: wp.array, tol: float, max_iter: int,
                 out: wp.array, iterations: wp.array, device, launcher: Launcher | None = None) -> None:
    """Algorithm 2 on the device: ``out`` (P,) the intermediate positions y with z(y) = z_points to
    |z(y) - z_p| < ``tol`` [m] (or ``max_iter`` Newton steps) in the nodal field ``z_field`` (3-D, on
    ``grid``), starting from ``guess`` (may be ``out`` itself: each thread reads its guess first);
    Newton iterations per point into ``iterations`` (at least P long)."""
    launch_on(device, launcher, kt.track_surface, z_points.shape[0],
              [z_field, grid, z_points, guess, wp.float64(tol), int(max_iter), out, iterations])


def track_surface(grid: EolGrid, z_nodes: np.ndarray, z_vertices: np.ndarray, guess: np.ndarray,
                  tol: float = 1e-10, max_iter: int = 20, device=None) -> tuple[np.ndarray, np.ndarray]:
    """Intermediate positions (V, 3) of material-space vertices z_vertices, and Newton iterations (V,).

    ``tol`` is the material-space residual |z(y) - z_v| [m] at which a vertex stops.
    """
    field = wp.array(np.asarray(z_nodes, dtype=np.float64).reshape(*grid.node_shape, 3), dtype=wp.vec3d, device=device)
    zv = wp.array(np.asarray(z_vertices, dtype=np.float64), dtype=wp.vec3d, device=device)
    g = wp.array(np.asarray(guess, dtype=np.float64), dtype=wp.vec3d, device=device)
    out = wp.empty_like(zv)
    iters = wp.zeros(len(z_vertices), dtype=wp.int32, device=device)
    track_points(grid_struct(grid), field, zv, g, tol, max_iter, out, iters, device)
    return out.numpy(), iters.numpy()
