"""Advection of nodal vec3 fields on the EoL grid (Eq. 15): semi-Lagrangian or BFECC (Warp kernels)."""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.eol.grid import EolGrid
from wsim.errors import InvalidParameter
from wsim.kernels import eol_advect as ka

SCHEMES = ("semi-lagrangian", "bfecc")


def advect(grid: EolGrid, q: np.ndarray, v: np.ndarray, dt: float, scheme: str = "semi-lagrangian",
           device=None) -> np.ndarray:
    """Advect nodal values q (n_nodes, 3) by nodal velocities v (n_nodes, 3) over dt [s].

    ``semi-lagrangian`` is first order and diffusive (the paper's scheme, which its time-step rule
    Eq. 30 assumes); ``bfecc`` costs three semi-Lagrangian passes and is second order on smooth fields.
    """
    if scheme not in SCHEMES:
        raise InvalidParameter(f"advection = {scheme!r} must be one of {', '.join(SCHEMES)}")
    shape = (*grid.node_shape,)
    origin = wp.vec3d(*grid.origin)
    h, dtw = wp.float64(grid.h), wp.float64(dt)
    qa = wp.array(np.asarray(q, dtype=np.float64).reshape(*shape, 3), dtype=wp.vec3d, device=device)
    va = wp.array(np.asarray(v, dtype=np.float64).reshape(*shape, 3), dtype=wp.vec3d, device=device)
    out = wp.empty_like(qa)
    wp.launch(ka.semi_lagrangian, dim=shape, inputs=[qa, va, origin, h, dtw, out], device=device)
    if scheme == "bfecc":
        back = wp.empty_like(qa)
        wp.launch(ka.semi_lagrangian, dim=shape, inputs=[out, va, origin, h, wp.float64(-dt), back], device=device)
        fixed = wp.empty_like(qa)
        wp.launch(ka.bfecc_combine, dim=shape, inputs=[qa, back, fixed], device=device)
        wp.launch(ka.semi_lagrangian, dim=shape, inputs=[fixed, va, origin, h, dtw, out], device=device)
    return out.numpy().reshape(-1, 3)
