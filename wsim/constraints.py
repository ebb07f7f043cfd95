"""Point constraints solved against a dense linear response: the seam between a body's dynamics
and its contacts, fixed points and joints (Sugimoto et al. 2022, Sec. 3.4).

A body that can linearize the end-of-step world positions of some of its surface points in the
forces applied there, V(f) = V0 + K f, hands (V0, K) and a ``PointSet`` to ``solve_points``, which
runs projected Gauss-Seidel on the device (``wsim.kernels.pgs``) and returns the forces. The body
then applies them. Nothing here knows which method produced K, so another body's points can join
the same solve by stacking their blocks (the contact-between-bodies issue).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from wsim.kernels import pgs

CONTACT = 0
FIXED = 1


@dataclass
class PointSet:
    """The constraints of m points (``wsim.kernels.pgs``'s kinds and data), host arrays.

    Attributes:
        kind: (m,) CONTACT or FIXED.
        normal, height: (m, 3), (m,) the half-space n . x >= height of a CONTACT point (world) [m].
        target: (m, 3) a FIXED point's target, or a CONTACT point's no-slip position [m].
        mu: (m,) Coulomb friction coefficient of a CONTACT point.
    """

    kind: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    height: np.ndarray = field(default_factory=lambda: np.zeros(0))
    target: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    mu: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    def add(self, kind: int, normal: np.ndarray, height: np.ndarray, target: np.ndarray, mu: np.ndarray) -> None:
        """Append points (arrays of one length)."""
        k = len(np.atleast_1d(height))
        self.kind = np.concatenate([self.kind, np.full(k, kind, dtype=np.int32)])
        self.normal = np.concatenate([self.normal, np.asarray(normal, dtype=np.float64).reshape(k, 3)])
        self.height = np.concatenate([self.height, np.asarray(height, dtype=np.float64).reshape(k)])
        self.target = np.concatenate([self.target, np.asarray(target, dtype=np.float64).reshape(k, 3)])
        self.mu = np.concatenate([self.mu, np.broadcast_to(np.asarray(mu, dtype=np.float64), (k,))])


@dataclass(frozen=True)
class SolveRecord:
    """One constraint solve: the step, its points (contacts among them), the Gauss-Seidel sweeps,
    the last sweep's residual [m] (the largest position change it made) and whether it reached the
    tolerance."""

    step: int
    points: int
    contacts: int
    sweeps: int
    residual: float
    converged: bool


def solve_points(K: wp.array, V0: np.ndarray, points: PointSet, f0: np.ndarray, tol: float, max_iter: int,
                 device: wp.Device) -> tuple[np.ndarray, np.ndarray, int, float]:
    """Forces (m, 3) [N] from projected Gauss-Seidel started at ``f0``; also the linear model's
    positions V0 + K f (m, 3) [m], the sweeps and the last sweep's residual [m]."""
    def dev(a: np.ndarray, dtype) -> wp.array:
        return wp.array(np.ascontiguousarray(a), dtype=dtype, device=device)

    f = dev(f0, wp.vec3d)
    stats = wp.zeros(2, dtype=wp.float64, device=device)
    V = wp.empty(len(V0), dtype=wp.vec3d, device=device)
    wp.launch(pgs.pgs_points, dim=1, device=device,
              inputs=[K, dev(V0, wp.vec3d), dev(points.kind, wp.int32), dev(points.normal, wp.vec3d),
                      dev(points.height, wp.float64), dev(points.target, wp.vec3d), dev(points.mu, wp.float64),
                      int(max_iter), wp.float64(tol), f, stats, V])
    s = stats.numpy()
    return f.numpy().astype(np.float64), V.numpy().astype(np.float64), int(s[0]), float(s[1])
