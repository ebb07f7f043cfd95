"""Elastic forces and lumped masses of an EoL body (the Warp kernel ``sample_forces``; see there)."""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.eol.grid import EolGrid
from wsim.kernels import eol_elastic as ke
from wsim.materials import ElasticMaterial


def elastic_forces(grid: EolGrid, z_nodes: np.ndarray, y: np.ndarray, volumes: np.ndarray, material: ElasticMaterial,
                   device=None, F_L: np.ndarray | None = None, Fp_inv: np.ndarray | None = None,
                   ) -> tuple[np.ndarray, np.ndarray, float]:
    """Nodal forces (n_nodes, 3) [N] in F_L's axes, lumped masses (n_nodes,) [kg] and elastic energy [J]
    of material points at intermediate positions y (P, 3) with material volumes (P,) [m^3].

    A host-side convenience (tests, tools); ``EolBody`` launches the kernel on its device arrays.
    """
    shape = grid.node_shape
    z = wp.array(np.asarray(z_nodes, dtype=np.float64).reshape(*shape, 3), dtype=wp.vec3d, device=device)
    ya = wp.array(np.asarray(y, dtype=np.float64), dtype=wp.vec3d, device=device)
    w = wp.array(np.asarray(volumes, dtype=np.float64), dtype=wp.float64, device=device)
    plastic = Fp_inv is not None
    fp = wp.array(np.asarray(Fp_inv, dtype=np.float64) if plastic else np.eye(3)[None], dtype=wp.mat33d, device=device)
    forces = wp.zeros(shape, dtype=wp.vec3d, device=device)
    mass = wp.zeros(shape, dtype=wp.float64, device=device)
    energy = wp.zeros(1, dtype=wp.float64, device=device)
    FL = wp.mat33d(*np.asarray(np.eye(3) if F_L is None else F_L, dtype=np.float64).ravel())
    wp.launch(ke.sample_forces, dim=len(w), device=device,
              inputs=[z, wp.vec3d(*grid.origin), wp.float64(grid.h), ya, w, fp, int(plastic), FL,
                      wp.float64(material.mu), wp.float64(material.lam), wp.float64(material.rho), forces, mass, energy])
    return forces.numpy().reshape(-1, 3), mass.numpy().ravel(), float(energy.numpy()[0])
