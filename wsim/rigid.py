"""Rigid-frame maths shared by every method: skew matrices, rotations, and the moving frame.

A body frame has rotation R (body -> world), origin T (the centre of mass, world), velocity
T_dot and angular velocity omega (world). One explicit step of length dt, with the new
velocities already known (symplectic Euler, the order of the BEM paper's Eq. 11f-g and of the
EoL pose update of Algorithm 1):

    T_k = T_{k-1} + dt T_dot_k                                   (11f)
    R_k = exp(dt [omega_k]x) R_{k-1}   (Rodrigues)               (11g)

``advance_pose`` is that step; every method that carries a rigid frame calls it.

``RigidFrame`` is the BEM body's frame state (paper Eq. 11), with the accelerations (a, alpha)
in body coordinates:

    T_dot_k = T_dot_{k-1} + dt R_{k-1} a_k                       (11d; R a = g + R a_ext since g' = R^T g)
    omega_k = omega_{k-1} + dt R_{k-1} alpha_k                    (11e)

With ``gyroscopic=True`` (default) (11e) is replaced by its torque-free-correct form: the world
angular momentum L_k = L_{k-1} + dt R_{k-1} I alpha_k is integrated and omega_k = R_{k-1} I^-1
R_{k-1}^T L_k. For a spin about a principal axis the two agree exactly; about any other axis
(11e) keeps omega fixed, which misses the precession of Euler's equations (the paper omits the
term), while the L form keeps |L| exactly and the kinetic energy bounded at any spin rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def cross_matrix(v: np.ndarray) -> np.ndarray:
    """[v]x with [v]x w = v x w, for (..., 3) arrays."""
    v = np.asarray(v)
    if v.shape == (3,):  # one vector (several times per EoL step): 10x cheaper than the stacks
        x, y, w = (float(c) for c in v)
        return np.array([[0.0, -w, y], [w, 0.0, -x], [-y, x, 0.0]])
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [np.stack([z, -v[..., 2], v[..., 1]], -1), np.stack([v[..., 2], z, -v[..., 0]], -1), np.stack([-v[..., 1], v[..., 0], z], -1)],
        axis=-2,
    )


def rodrigues(phi: np.ndarray) -> np.ndarray:
    """exp([phi]x): rotation by |phi| about phi / |phi| (Rodrigues' formula)."""
    phi = np.asarray(phi, dtype=np.float64)
    angle = float(np.linalg.norm(phi))
    if angle < 1e-12:
        return np.eye(3) + cross_matrix(phi)
    k = cross_matrix(phi / angle)
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """phi with rodrigues(phi) = R (|phi| <= pi): the inverse of ``rodrigues``."""
    R = np.asarray(R, dtype=np.float64)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = 0.5 * np.linalg.norm(axis)
    c = np.clip(0.5 * (np.trace(R) - 1.0), -1.0, 1.0)
    angle = np.arctan2(s, c)
    if s < 1e-12:
        return 0.5 * axis  # small angle: phi ~ vee(R - R^T) / 2
    if angle > np.pi - 1e-6:  # near pi: the axis from the largest column of R + I
        M = R + np.eye(3)
        k = int(np.argmax(np.linalg.norm(M, axis=0)))
        return angle * M[:, k] / np.linalg.norm(M[:, k])
    return angle * axis / (2.0 * s)


def nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation closest to m in the Frobenius norm (polar factor, det = +1); m may be a stack
    (..., 3, 3)."""
    u, _, vt = np.linalg.svd(m)
    d = np.where(np.linalg.det(u @ vt) < 0.0, -1.0, 1.0)
    u = u.copy()
    u[..., :, 2] *= d[..., None]  # u diag(1, 1, d) vt
    return u @ vt


def advance_pose(R: np.ndarray, T: np.ndarray, velocity: np.ndarray, omega: np.ndarray,
                 dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(R_k, T_k) of Eq. (11f-g): the frame moved for dt at the new world velocity and angular
    velocity (``omega`` in world axes)."""
    return rodrigues(dt * np.asarray(omega)) @ R, T + dt * np.asarray(velocity)


@dataclass
class RigidFrame:
    """Mutable frame state of one body (world coordinates unless noted).

    Attributes:
        R: (3, 3) rotation body -> world.  T: (3,) origin (centre of mass) [m].
        velocity: T_dot [m/s].  omega: angular velocity [rad/s].
        L: angular momentum about the centre of mass [kg m^2/s] (used with ``gyroscopic``).
    """

    R: np.ndarray
    T: np.ndarray
    velocity: np.ndarray
    omega: np.ndarray
    L: np.ndarray

    @classmethod
    def at_rest(cls, R: np.ndarray, T: np.ndarray, velocity: np.ndarray, omega: np.ndarray,
                inertia: np.ndarray) -> RigidFrame:
        R = np.array(R, dtype=np.float64)
        omega = np.array(omega, dtype=np.float64)
        return cls(R=R, T=np.array(T, dtype=np.float64), velocity=np.array(velocity, dtype=np.float64),
                   omega=omega, L=R @ inertia @ R.T @ omega)

    def update(self, dt: float, gravity: np.ndarray, a_body: np.ndarray, alpha_body: np.ndarray,
               inertia: np.ndarray, inertia_inv: np.ndarray, gyroscopic: bool) -> None:
        """Eq. (11d-g) with body-frame accelerations a_body = a - g' (traction and correction part) and alpha."""
        R = self.R
        self.velocity = self.velocity + dt * (gravity + R @ a_body)
        if gyroscopic:
            self.L = self.L + dt * (R @ (inertia @ alpha_body))
            self.omega = R @ (inertia_inv @ (R.T @ self.L))
        else:
            self.omega = self.omega + dt * (R @ alpha_body)
            self.L = R @ inertia @ R.T @ self.omega
        self.R, self.T = advance_pose(R, self.T, self.velocity, self.omega, dt)

    def copy(self) -> RigidFrame:
        return RigidFrame(R=self.R.copy(), T=self.T.copy(), velocity=self.velocity.copy(), omega=self.omega.copy(),
                          L=self.L.copy())

    def reorthonormalize(self) -> None:
        """Remove the round-off that repeated products leave in R."""
        self.R = nearest_rotation(self.R)


def point_inertia(r: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """(3, 3) second moment of points r (n, 3) (offsets from their centre) as an inertia tensor,
    sum_k w_k (|r_k|^2 I - r_k r_k^T); unit weights when ``weights`` is None."""
    if weights is None:
        return (r * r).sum() * np.eye(3) - r.T @ r
    return (weights * (r * r).sum(axis=1)).sum() * np.eye(3) - (r * weights[:, None]).T @ r


def rigid_fit(p0: np.ndarray, p1: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The rigid velocity field v(x) = G x + g (G = [omega]x) that best fits, in least squares,
    points moving from p0 to p1 (each (n, 3)) in dt seconds: the mean velocity plus the angular
    velocity of the points' spread about their mean position (the 'inertia' of the points). A
    degenerate spread (one point, collinear points) gets no spin about its own axis."""
    x = 0.5 * (np.asarray(p0, dtype=np.float64) + np.asarray(p1, dtype=np.float64))
    v = (np.asarray(p1, dtype=np.float64) - np.asarray(p0, dtype=np.float64)) / dt
    c = x.mean(axis=0)
    r = x - c
    v_mean = v.mean(axis=0)
    inertia = point_inertia(r)
    omega = np.linalg.lstsq(inertia, np.cross(r, v - v_mean).sum(axis=0), rcond=1e-12)[0]
    G = cross_matrix(omega)
    return G, v_mean - G @ c
