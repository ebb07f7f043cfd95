"""Mass properties of a closed surface and the traction-to-acceleration maps A and C (paper Eq. 10).

Mass, centre of mass and inertia come from surface integrals [Mir96]: by the divergence theorem a
volume integral of a polynomial is a flux through the faces, and for flat triangles those fluxes
are exact closed forms. Written per face as the signed tetrahedron (o, a, b, c) from an origin o
(the bounding-box centre, to keep the sums well conditioned):

    V = det / 6,   int y = V (a + b + c + o) / 4,
    int y y^T = V / 20 [sum_k v_k v_k^T + (sum_k v_k)(sum_k v_k)^T]   over the four vertices v_k.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wsim.rigid import cross_matrix
from wsim.bem.surface import BemSurface


@dataclass(frozen=True)
class MassProperties:
    """mass [kg], com (3,) [m], inertia (3, 3) about the com [kg m^2], volume [m^3]."""

    mass: float
    com: np.ndarray
    inertia: np.ndarray
    volume: float


def mass_properties(vertices: np.ndarray, faces: np.ndarray, rho: float) -> MassProperties:
    """Exact mass properties of the solid bounded by a closed, outward-oriented triangle mesh."""
    v = np.asarray(vertices, dtype=np.float64)
    o = 0.5 * (v.min(axis=0) + v.max(axis=0))
    a, b, c = (v[np.asarray(faces)[:, k]] - o for k in range(3))
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    volume = float(vol.sum())
    first = (vol[:, None] * (a + b + c)).sum(axis=0) / 4.0  # int (y - o) dV
    s = a + b + c
    second = (vol[:, None, None] * (np.einsum("fi,fj->fij", a, a) + np.einsum("fi,fj->fij", b, b)
                                     + np.einsum("fi,fj->fij", c, c) + np.einsum("fi,fj->fij", s, s))).sum(axis=0) / 20.0
    centroid = first / volume  # relative to o
    cov = second - volume * np.outer(centroid, centroid)  # int (y - com)(y - com)^T dV
    inertia = rho * (np.trace(cov) * np.eye(3) - cov)
    return MassProperties(mass=rho * volume, com=centroid + o, inertia=inertia, volume=volume)


def traction_maps(surface: BemSurface, props: MassProperties) -> tuple[np.ndarray, np.ndarray]:
    """A and C of Eq. (10), each (3, 3N): a_ext = A p and alpha_ext = C p for nodal tractions p.

    A = (1/m) int N_v dA per node; C = I^-1 [int (y - com) N_v dA]x per node, with
    int_t y N_v dA = area (2 y_v + y_w + y_z) / 12 on a flat triangle (v, w, z).
    """
    n = surface.n_nodes
    f = surface.faces
    y = surface.nodes
    area = surface.areas
    moment = np.zeros((n, 3))
    for k in range(3):
        own = y[f[:, k]]
        others = y[f[:, (k + 1) % 3]] + y[f[:, (k + 2) % 3]]
        np.add.at(moment, f[:, k], area[:, None] * (2.0 * own + others) / 12.0)
    node_area = surface.node_areas()
    moment -= node_area[:, None] * props.com
    A = np.kron(node_area[None, :] / props.mass, np.eye(3))  # (3, 3N)
    blocks = np.linalg.solve(props.inertia, cross_matrix(moment))  # (N, 3, 3)
    C = blocks.transpose(1, 0, 2).reshape(3, 3 * n)
    return A, C
