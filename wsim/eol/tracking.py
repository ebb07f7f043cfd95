"""Surface tracking of an EoL body (Algorithm 2; the Warp kernel ``track_surface``)."""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.eol.grid import EolGrid
from wsim.kernels import eol_track as kt


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
    wp.launch(kt.track_surface, dim=len(z_vertices), device=device,
              inputs=[field, wp.vec3d(*grid.origin), wp.float64(grid.h), zv, g, wp.float64(tol), int(max_iter), out, iters])
    return out.numpy(), iters.numpy()
