"""Lagrangian coordinates of an EoL body and the mass blocks of Eq. (11) (Fan et al., Secs. 3.1-3.3).

The spatial velocity of a material point at intermediate position y is (Eqs. 2 and 9)

    x_dot = R (J_L(y) q1_dot + F v)          (R = I for the affine case, F = I for the rigid one)

* ``rigid``: q1_dot = (omega, nu) in the frame, J_L(y) = [ [y]^T  I ] (3 x 6), F = I (Eq. 2);
* ``affine`` (the linear-modal case with the 12 affine modes): x = A y + b, q1_dot = (A_dot
  columns, b_dot), J_L(y) = [ y1 I  y2 I  y3 I  I ] (3 x 12), F = F_1 = A (Eq. 9).

With J = [J_L, F Phi] the kinetic energy 1/2 q_dot^T M q_dot gives M = int rho J^T J (Eqs. 6, 10):

    M_1  = int rho J_L^T J_L                      (by the material quadrature, "exact")
    M_12 = sum_s m_s J_L(y_s)^T F                 (lumped: node s carries its mass m_s)
    M_2  = diag(m_s F^T F)                        (lumped, paper)

Lumping M_12 at the nodes makes M_C = M_2^-1 M_12^T = F^-1 J_L(y_s) per node, so the velocity
rebuilt from (q1_dot, v*) by Eq. (2)/(9) is exactly the input velocity (spec test T3). Then
M_12 M_2^-1 M_12^T = sum_s m_s J_L(y_s)^T J_L(y_s): exact for translation (sum m_s = mass),
O(h^2) for the rotational (second-moment) block (spec Sec. 3.1 caveat). ``consistent_blocks``
gives the consistent M_12, M_2, for which Eq. (20) holds to round-off.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wsim.rigid import cross_matrix
from wsim.eol.grid import EolGrid, MaterialSamples

KINDS = {"rigid": 6, "affine": 12}


def lagrangian_jacobian(kind: str, y: np.ndarray) -> np.ndarray:
    """J_L(y): (P, 3, n1) for points y (P, 3)."""
    y = np.atleast_2d(np.asarray(y, dtype=np.float64))
    P = len(y)
    eye = np.broadcast_to(np.eye(3), (P, 3, 3))
    if kind == "rigid":  # [y]^T = -[y]: [y]^T omega = omega x y
        return np.concatenate([-cross_matrix(y), eye], axis=2)
    if kind == "affine":
        return np.concatenate([y[:, 0, None, None] * eye, y[:, 1, None, None] * eye, y[:, 2, None, None] * eye, eye],
                              axis=2)
    raise ValueError(f"unknown Lagrangian coordinates {kind!r}; use one of {', '.join(KINDS)}")


@dataclass(frozen=True)
class MassBlocks:
    """M_1 (n1, n1), M_12 (n1, 3 n_active), M_2 as per-node 3x3 blocks (n_active, 3, 3), for the
    ``active`` nodes (those with mass), at Lagrangian deformation gradient F."""

    kind: str
    M1: np.ndarray
    M12: np.ndarray
    M2_blocks: np.ndarray
    active: np.ndarray
    F: np.ndarray

    @property
    def M_C(self) -> np.ndarray:
        """M_2^-1 M_12^T (3 n_active, n1): per node F^-1 J_L(y_s)."""
        M12t = self.M12.T.reshape(-1, 3, self.M12.shape[0])
        return np.linalg.solve(self.M2_blocks, M12t).reshape(-1, self.M12.shape[0])

    def dense_M2(self) -> np.ndarray:
        n = len(self.active)
        out = np.zeros((3 * n, 3 * n))
        for i in range(n):
            out[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = self.M2_blocks[i]
        return out


def mass_blocks(kind: str, grid: EolGrid, samples: MaterialSamples, masses: np.ndarray, rho: float,
                y_samples: np.ndarray | None = None, F: np.ndarray | None = None) -> MassBlocks:
    """The lumped blocks at intermediate sample positions ``y_samples`` (default: rest, y = z)."""
    if kind not in KINDS:
        raise ValueError(f"unknown Lagrangian coordinates {kind!r}; use one of {', '.join(KINDS)}")
    F = np.eye(3) if F is None else np.asarray(F, dtype=np.float64)
    y = samples.points if y_samples is None else y_samples
    J = lagrangian_jacobian(kind, y)
    M1 = np.einsum("p,pin,pim->nm", rho * samples.weights, J, J)
    active = np.flatnonzero(masses > 0.0)
    m = masses[active]
    JN = lagrangian_jacobian(kind, grid.node_positions()[active])  # (n, 3, n1)
    M12 = np.einsum("s,sin,ij->nsj", m, JN, F).reshape(KINDS[kind], -1)
    M2_blocks = m[:, None, None] * (F.T @ F)[None]
    return MassBlocks(kind=kind, M1=M1, M12=M12, M2_blocks=M2_blocks, active=active, F=F)


def consistent_blocks(kind: str, grid: EolGrid, samples: MaterialSamples, rho: float,
                      active: np.ndarray, F: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Consistent M_12 = int rho J_L^T F Phi_s and M_2 = int rho Phi_s Phi_t F^T F (dense; small grids)."""
    F = np.eye(3) if F is None else np.asarray(F, dtype=np.float64)
    slot = -np.ones(grid.n_nodes, dtype=np.int64)
    slot[active] = np.arange(len(active))
    n = len(active)
    JF = np.einsum("pin,ij->pnj", lagrangian_jacobian(kind, samples.points), F)  # (P, n1, 3)
    M12 = np.zeros((n, KINDS[kind], 3))
    phi_m = np.zeros((n, n))
    w = rho * samples.weights
    for c in range(8):
        s = slot[samples.nodes[:, c]]
        np.add.at(M12, s, (w * samples.phi[:, c])[:, None, None] * JF)
        for d in range(8):
            np.add.at(phi_m, (s, slot[samples.nodes[:, d]]), w * samples.phi[:, c] * samples.phi[:, d])
    return M12.transpose(1, 0, 2).reshape(KINDS[kind], -1), np.kron(phi_m, F.T @ F)
