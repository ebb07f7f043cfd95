"""Advection of nodal vec3 fields on the EoL grid (Eq. 15): semi-Lagrangian or BFECC (Warp kernels)."""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.eol.grid import EolGrid
from wsim.errors import InvalidParameter
from wsim.kernels import eol_advect as ka
from wsim.kernels.eol_grid import Grid, grid_struct
from wsim.launch import Launcher, launch_on

SCHEMES = ("semi-lagrangian", "bfecc")


def check_scheme(scheme: str, what: str = "advection") -> str:
    if scheme not in SCHEMES:
        raise InvalidParameter(f"{what} = {scheme!r} must be one of {', '.join(SCHEMES)}")
    return scheme


def advect_arrays(q: wp.array, v: wp.array, out: wp.array, grid: Grid, dt_at: wp.array, scheme: str,
                  scratch: tuple[wp.array, wp.array] | None, device, limit: bool = True,
                  launcher: Launcher | None = None) -> None:
    """out = q advected by v over dt [s] (``dt_at[0]``, on the device); 3-D vec3d node arrays on
    ``grid`` (a ``Grid`` struct; ``out`` must not alias ``q``).

    ``semi-lagrangian`` is first order and diffusive (the paper's scheme, which its time-step rule
    Eq. 30 assumes); ``bfecc`` costs three semi-Lagrangian passes, is second order on smooth
    fields and needs two ``scratch`` arrays shaped like q. ``limit`` clamps its last pass to the range
    of q (Selle et al. 2008: no new extrema, which contact needs; it clips smooth peaks, so the
    max-norm order drops below 2 there).
    """
    shape = q.shape
    ahead, back_ = wp.float64(1.0), wp.float64(-1.0)
    if scheme == "semi-lagrangian":
        launch_on(device, launcher, ka.semi_lagrangian, shape, [q, v, grid, dt_at, ahead, out])
        return
    fwd, back = scratch  # type: ignore[misc]
    launch_on(device, launcher, ka.semi_lagrangian, shape, [q, v, grid, dt_at, ahead, fwd])
    launch_on(device, launcher, ka.semi_lagrangian, shape, [fwd, v, grid, dt_at, back_, back])
    launch_on(device, launcher, ka.bfecc_combine, shape, [q, back, fwd])
    if limit:
        launch_on(device, launcher, ka.semi_lagrangian_limited, shape, [fwd, q, v, grid, dt_at, out])
    else:
        launch_on(device, launcher, ka.semi_lagrangian, shape, [fwd, v, grid, dt_at, ahead, out])


def extend_reference_map(z: wp.array, mass: wp.array, h: float, layers: int, layer: wp.array, G: wp.array,
                         device, launcher: Launcher | None = None) -> None:
    """Continue the reference map z (3-D vec3d node array, in place) from the nodes with material
    (``mass`` > 0, same shape) into ``layers`` layers of empty nodes around them, each node taking the
    mean first-order prediction z_n + G_n (y_s - y_n) of its neighbours in the layers before
    (``eol_advect.extend_reference_map``): an affine map is continued exactly. ``layer`` (int32) and
    ``G`` (mat33d), shaped like z, are scratch."""
    shape = z.shape
    launch_on(device, launcher, ka.reference_map_gradient, shape, [z, mass, wp.float64(h), layer, G])
    for known in range(1, layers + 1):
        launch_on(device, launcher, ka.extend_reference_map, shape, [z, layer, G, wp.float64(h), known])


def advect(grid: EolGrid, q: np.ndarray, v: np.ndarray, dt: float, scheme: str = "semi-lagrangian",
           device=None, limit: bool = False) -> np.ndarray:
    """Advect nodal values q (n_nodes, 3) by nodal velocities v (n_nodes, 3) over dt [s] (host arrays;
    ``limit`` as in ``advect_arrays``: off here, the plain scheme; ``EolBody`` always limits BFECC)."""
    check_scheme(scheme)
    shape = grid.node_shape
    qa = wp.array(np.asarray(q, dtype=np.float64).reshape(*shape, 3), dtype=wp.vec3d, device=device)
    va = wp.array(np.asarray(v, dtype=np.float64).reshape(*shape, 3), dtype=wp.vec3d, device=device)
    out = wp.empty_like(qa)
    scratch = (wp.empty_like(qa), wp.empty_like(qa)) if scheme == "bfecc" else None
    dt_at = wp.array([dt], dtype=wp.float64, device=device)
    advect_arrays(qa, va, out, grid_struct(grid), dt_at, scheme, scratch, device, limit)
    return out.numpy().reshape(-1, 3)
