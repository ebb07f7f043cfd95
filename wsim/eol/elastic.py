"""Elastic forces and lumped masses of an EoL body (the Warp kernel ``sample_forces``; see there).

``sample_forces`` launches the kernel on device arrays: ``EolBody``'s force pass calls it every
step. ``elastic_forces`` is the host convenience (tests, tools) around the same launch.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.eol.grid import EolGrid
from wsim.kernels import eol_elastic as ke
from wsim.kernels.eol_grid import Grid, grid_struct
from wsim.materials import ElasticMaterial
from wsim.launch import Launcher, launch_on


#: the identity F_L of rigid and Eulerian coordinates, one read-only object: ``mat33`` and
#: ``inverse_mat33`` then hand the step's launches one Warp matrix, not a new one a launch
I3 = np.eye(3)
I3.setflags(write=False)
_MAT_I3 = wp.mat33d(*I3.ravel())


def mat33(M: np.ndarray) -> wp.mat33d:
    """M as a Warp float64 matrix (the one shared identity for ``I3``)."""
    return _MAT_I3 if M is I3 else wp.mat33d(*np.asarray(M, dtype=np.float64).ravel())


def inverse_mat33(M: np.ndarray) -> wp.mat33d:
    """M^-1 as a Warp float64 matrix (the one shared identity for ``I3``)."""
    return _MAT_I3 if M is I3 else mat33(np.linalg.inv(np.asarray(M, dtype=np.float64)))


def sample_forces(grid: Grid, z: wp.array, y: wp.array, volumes: wp.array, Fp_inv: wp.array, plastic: bool,
                  F_L: np.ndarray, material: ElasticMaterial, forces: wp.array, mass: wp.array, energy: wp.array,
                  device, launcher: Launcher | None = None) -> None:
    """Zero ``forces``, ``mass`` (3-D node arrays of ``grid``) and ``energy`` (1,), then accumulate
    the nodal forces in F_L's axes [N], the lumped masses [kg] and the elastic energy [J] of the
    material points at intermediate positions ``y`` with material volumes ``volumes``. ``Fp_inv``
    (P,) is read only when ``plastic`` (a 1-element placeholder otherwise)."""
    launch_on(device, launcher, ke.zero_nodes, forces.shape, [forces, mass, energy])
    block = ke.FORCES_BLOCK if wp.get_device(device).is_cuda else 1  # a CPU block is one thread
    launch_on(device, launcher, ke.sample_forces, -(-volumes.shape[0] // block),
              [z, grid, y, volumes, Fp_inv, int(bool(plastic)),
                      mat33(F_L), wp.float64(material.mu), wp.float64(material.lam), wp.float64(material.rho), forces,
                      mass, energy],
              block_dim=ke.FORCES_BLOCK)


def hourglass_forces(grid: Grid, z: wp.array, y: wp.array, volumes: wp.array, full: float, F_L: np.ndarray,
                     stiffness: float, filled: wp.array, forces: wp.array, energy: wp.array, device,
                     launcher: Launcher | None = None) -> None:
    """Add the hourglass control of under-integrated cells (kernel ``hourglass_forces``: force
    k F r_c / h^2 with k = ``stiffness`` V (1 - V / full), ``stiffness`` [Pa]) to ``forces`` [N] and its energy to
    ``energy`` [J]; ``filled`` (cells-shaped scratch) receives each cell's material volume [m^3]."""
    filled.zero_()
    launch_on(device, launcher, ke.cell_fill, volumes.shape[0], [z, grid, y, volumes, filled])
    launch_on(device, launcher, ke.hourglass_forces, filled.shape,
              [z, filled, grid.h, wp.float64(full), mat33(F_L),
                      wp.float64(stiffness), forces, energy])


def viscous_forces(grid: Grid, w: wp.array, y: wp.array, volumes: wp.array, F_L: np.ndarray, eta: float,
                   mass: wp.array, dt: float, forces: wp.array, bound: wp.array, device,
                   launcher: Launcher | None = None) -> None:
    """Zero ``forces`` (3-D node array) and accumulate the Kelvin-Voigt damping forces [N] of the
    node velocities ``w`` (3-D, F_L's axes) with viscosity ``eta`` [Pa s], explicit at steps up to
    ``dt`` with node masses ``mass`` [kg] (kernels ``viscous_row_bound``, then ``viscous_forces``:
    points next to nodes too light for that step are damped less); ``bound`` is node-shaped scratch."""
    F_L_inv = inverse_mat33(F_L)
    bound.zero_()
    launch_on(device, launcher, ke.viscous_row_bound, volumes.shape[0], [grid, w, y, volumes, F_L_inv, wp.float64(eta), bound])
    forces.zero_()
    launch_on(device, launcher, ke.viscous_forces, volumes.shape[0],
              [w, grid, y, volumes, F_L_inv, wp.float64(eta), mass, bound, wp.float64(dt), forces])


def elastic_forces(grid: EolGrid, z_nodes: np.ndarray, y: np.ndarray, volumes: np.ndarray, material: ElasticMaterial,
                   device=None, F_L: np.ndarray | None = None, Fp_inv: np.ndarray | None = None,
                   ) -> tuple[np.ndarray, np.ndarray, float]:
    """Nodal forces (n_nodes, 3) [N] in F_L's axes, lumped masses (n_nodes,) [kg] and elastic energy [J]
    of material points at intermediate positions y (P, 3) with material volumes (P,) [m^3].

    A host-side convenience (tests, tools) around ``sample_forces``, which ``EolBody`` calls on its
    device arrays.
    """
    shape = grid.node_shape
    z = wp.array(np.asarray(z_nodes, dtype=np.float64).reshape(*shape, 3), dtype=wp.vec3d, device=device)
    ya = wp.array(np.asarray(y, dtype=np.float64), dtype=wp.vec3d, device=device)
    w = wp.array(np.asarray(volumes, dtype=np.float64), dtype=wp.float64, device=device)
    plastic = Fp_inv is not None
    fp = wp.array(np.asarray(Fp_inv, dtype=np.float64) if plastic else np.eye(3)[None], dtype=wp.mat33d, device=device)
    forces = wp.empty(shape, dtype=wp.vec3d, device=device)
    mass = wp.empty(shape, dtype=wp.float64, device=device)
    energy = wp.empty(1, dtype=wp.float64, device=device)
    sample_forces(grid_struct(grid), z, ya, w, fp, plastic, np.eye(3) if F_L is None else F_L, material,
                  forces, mass, energy, device)
    return forces.numpy().reshape(-1, 3), mass.numpy().ravel(), float(energy.numpy()[0])
