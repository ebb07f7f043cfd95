"""The Eulerian grid of an EoL body in its intermediate domain y (Fan et al., Sec. 3.1 and 4).

A uniform grid of cubic cells (spacing h) around the body, with trilinear nodal shape functions
Phi_s. The material is represented by quadrature samples: ``per_axis``^3 Gauss points per cell,
kept where the generalized winding number of the material surface says "inside". Node masses are
lumped: m_s = sum over samples of rho w Phi_s (paper: M_2 diagonal). At rest y = z (u = 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from wsim.mesh.inside import inside_surface  # the package's one point-in-mesh test
from wsim.validate import positive_int

# 8 corners of a cell in (i, j, k) offsets; the trilinear weight of corner c at local (a, b, c)
CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int64)


@dataclass(frozen=True)
class EolGrid:
    """Uniform grid: ``cells`` (nx, ny, nz), spacing ``h`` [m], ``origin`` the (0, 0, 0) node [m]."""

    origin: np.ndarray
    h: float
    cells: tuple[int, int, int]

    @property
    def node_shape(self) -> tuple[int, int, int]:
        return (self.cells[0] + 1, self.cells[1] + 1, self.cells[2] + 1)

    @property
    def n_nodes(self) -> int:
        a, b, c = self.node_shape
        return a * b * c

    def node_index(self, ijk: np.ndarray) -> np.ndarray:
        """Flat node index of integer node coordinates (..., 3)."""
        _, b, c = self.node_shape
        return (ijk[..., 0] * b + ijk[..., 1]) * c + ijk[..., 2]

    def node_positions(self) -> np.ndarray:
        """(n_nodes, 3) node positions in y [m], in flat index order."""
        a, b, c = self.node_shape
        i, j, k = np.meshgrid(np.arange(a), np.arange(b), np.arange(c), indexing="ij")
        return self.origin + self.h * np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1).astype(np.float64)

    def locate(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell (..., 3) and local coordinates in [0, 1]^3 of points y (clamped to the grid)."""
        g = (np.asarray(y, dtype=np.float64) - self.origin) / self.h
        cell = np.clip(np.floor(g).astype(np.int64), 0, np.array(self.cells) - 1)
        return cell, g - cell

    def cell_nodes(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The 8 corner nodes (P, 8) of the cell holding each point y (P, 3), in ``CORNERS`` order,
        and the local coordinates (P, 3)."""
        cell, t = self.locate(y)
        return self.node_index(cell[:, None, :] + CORNERS[None, :, :]), t

    def shape_functions(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Trilinear Phi at points y: (P, 8) node indices and (P, 8) weights (a partition of unity)."""
        nodes, t = self.cell_nodes(y)
        w = np.ones((len(t), 8))
        for axis in range(3):
            w *= np.where(CORNERS[None, :, axis] == 1, t[:, None, axis], 1.0 - t[:, None, axis])
        return nodes, w


def make_grid(vertices: np.ndarray, resolution: int, padding: int = 1) -> EolGrid:
    """A grid whose longest side of the body's bounding box spans ``resolution`` cells, plus
    ``padding`` empty cells on every side (room to deform), centred on the box."""
    positive_int(resolution, "EoL grid resolution", 4)
    v = np.asarray(vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    h = float(np.max(hi - lo)) / int(resolution)
    inner = np.maximum(np.ceil((hi - lo) / h - 1e-9).astype(int), 1)
    cells = inner + 2 * int(padding)
    centre = 0.5 * (lo + hi)
    origin = centre - 0.5 * h * cells
    return EolGrid(origin=origin, h=h, cells=tuple(int(c) for c in cells))


@dataclass(frozen=True)
class MaterialSamples:
    """Quadrature of the body: points z (S, 3) [m], volumes w (S,) [m^3], with their trilinear
    node indices and weights (S, 8) on the grid."""

    points: np.ndarray
    weights: np.ndarray
    nodes: np.ndarray
    phi: np.ndarray

    @property
    def volume(self) -> float:
        return float(self.weights.sum())


def material_samples(grid: EolGrid, vertices: np.ndarray, faces: np.ndarray, per_axis: int = 2,
                     device: Any = None) -> MaterialSamples:
    """Gauss-Legendre points (``per_axis`` per cell axis) inside the closed surface (winding number > 1/2,
    by ``inside_surface`` on ``device``)."""
    x, _ = np.polynomial.legendre.leggauss(per_axis)
    local = 0.5 * (x + 1.0)
    lx, ly, lz = np.meshgrid(local, local, local, indexing="ij")
    offsets = np.stack([lx.ravel(), ly.ravel(), lz.ravel()], axis=1)  # (q, 3) in [0, 1]
    ci, cj, ck = np.meshgrid(*(np.arange(n) for n in grid.cells), indexing="ij")
    cells = np.stack([ci.ravel(), cj.ravel(), ck.ravel()], axis=1)
    points = grid.origin + grid.h * (cells[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
    inside = inside_surface(vertices, faces, points, device)
    points = points[inside]
    weights = np.full(len(points), grid.h**3 / per_axis**3)
    nodes, phi = grid.shape_functions(points)
    return MaterialSamples(points=points, weights=weights, nodes=nodes, phi=phi)


def lumped_masses(grid: EolGrid, samples: MaterialSamples, rho: float) -> np.ndarray:
    """m_s = int rho Phi_s dz per node [kg] (zero on empty nodes)."""
    m = np.zeros(grid.n_nodes)
    np.add.at(m, samples.nodes.ravel(), (rho * samples.weights[:, None] * samples.phi).ravel())
    return m
