"""Elastic forces of an EoL body on its grid (the Warp kernel ``neo_hookean_forces``; see there)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from wsim.eol.grid import EolGrid
from wsim.kernels import eol_elastic as ke
from wsim.materials import ElasticMaterial


@dataclass(frozen=True)
class QuadraturePoints:
    """Intermediate-domain quadrature: 8 node indices (P, 8), local coordinates (P, 3), volumes (P,)."""

    nodes: wp.array
    local: wp.array
    weight: wp.array


def quadrature_points(grid: EolGrid, y: np.ndarray, weights: np.ndarray, device) -> QuadraturePoints:
    """Upload points y (P, 3) with volumes (P,) as the kernel's quadrature."""
    nodes, local = grid.cell_nodes(y)
    return QuadraturePoints(nodes=wp.array(nodes.astype(np.int32), dtype=wp.int32, device=device),
                            local=wp.array(local, dtype=wp.vec3d, device=device),
                            weight=wp.array(np.asarray(weights, dtype=np.float64), dtype=wp.float64, device=device))


def elastic_forces(grid: EolGrid, z_nodes: np.ndarray, points: QuadraturePoints, material: ElasticMaterial,
                   device) -> tuple[np.ndarray, float]:
    """Nodal forces on the Eulerian displacements (n_nodes, 3) [N] and the elastic energy [J]."""
    z = wp.array(np.asarray(z_nodes, dtype=np.float64), dtype=wp.vec3d, device=device)
    forces = wp.zeros(grid.n_nodes, dtype=wp.vec3d, device=device)
    energy = wp.zeros(1, dtype=wp.float64, device=device)
    wp.launch(ke.neo_hookean_forces, dim=points.weight.shape[0], device=device,
              inputs=[z, points.nodes, points.local, points.weight, wp.float64(grid.h), wp.float64(material.mu),
                      wp.float64(material.lam), forces, energy])
    return forces.numpy(), float(energy.numpy()[0])
