"""Colliders: static or kinematic surfaces that bodies bounce off but never move.

Every collider is a kinematic surface with one interface: its rigid pose ``matrix(t)`` (local to
world), ``friction``, whether it is ``kinematic``, its device mesh (a Warp BVH, or None for an
analytic surface), its analytic ``plane(up)`` (or None) and a ``display_mesh`` for export.
``GroundPlane`` is the half-space above a plane; ``MeshCollider`` is a triangle mesh posed by a
fixed 4x4 matrix or by a function of time. The device copy of a mesh is built once per device
and shared by every body that collides with it.

Bodies and the USD writer never call a collider's pose function themselves: the World owns one
``Surfaces`` (its colliders resolved against its up axis) and every consumer asks it for poses
and velocities at the times it needs, so a kinematic pose is evaluated and validated once per
time however many bodies query it. Contact between bodies will extend the same seam.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Callable, Iterator, Sequence, Union

import numpy as np
import warp as wp

from wsim import mesh as wmesh
from wsim.validate import as_vec3, call_user, finite_number
from wsim.errors import InvalidParameter

TransformLike = Union[np.ndarray, Callable[[float], np.ndarray], None]


def _check_friction(friction: float, name: str) -> float:
    mu = finite_number(friction, f"collider '{name}': friction")  # a string or NaN: said so, not a ValueError
    if mu < 0.0:
        raise InvalidParameter(f"collider '{name}': friction = {friction} must be >= 0")
    return mu


class Collider(ABC):
    """A kinematic surface. Common fields: ``name`` (USD prim name), Coulomb ``friction``
    coefficient [-], ``kinematic`` (its pose depends on time)."""

    name: str
    friction: float
    kinematic: bool = False
    extent: float = float("inf")  # diagonal of the surface's bounding box [m] (inf: unbounded)

    def matrix(self, t: float, frame: int | None = None) -> np.ndarray:
        """Local-to-world rigid 4x4 matrix at time t [s] (identity: the surface is given in world);
        ``frame``: the World frame being computed, for error messages."""
        return np.eye(4)

    def plane(self, up: np.ndarray) -> tuple[np.ndarray, float] | None:
        """(unit normal, height) when the surface is the analytic half-space normal . x >= height, else None."""
        return None

    def device_mesh(self, device: wp.Device) -> wp.Mesh | None:
        """The triangle mesh (local coordinates, with its BVH) on ``device``; None for an analytic surface."""
        return None

    @abstractmethod
    def display_mesh(self, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(points (P, 3), faces (F, k)) to show the surface, in its local coordinates [m]."""


class GroundPlane(Collider):
    """The half-space above a plane: every particle is kept at ``normal . x >= height``.

    Args:
        height: offset of the plane along its normal [m].
        friction: Coulomb friction coefficient [-].
        normal: unit normal; None means the World's up axis.
        size: edge length of the square written to USD for display [m].
    """

    def __init__(
        self,
        height: float = 0.0,
        friction: float = 0.5,
        normal: tuple[float, float, float] | None = None,
        name: str = "ground",
        size: float = 20.0,
    ) -> None:
        self.name = name
        self.height = float(height)
        if not np.isfinite(self.height):
            raise InvalidParameter(f"collider '{name}': height = {height} must be finite")
        self.friction = _check_friction(friction, name)
        self.normal = None
        if normal is not None:
            n = as_vec3(normal, f"collider '{name}': normal")
            norm = np.linalg.norm(n)
            if norm == 0.0:
                raise InvalidParameter(f"collider '{name}': normal must be non-zero")
            self.normal = n / norm
        self.size = float(size)

    def resolved_normal(self, up: np.ndarray) -> np.ndarray:
        return up if self.normal is None else self.normal

    def plane(self, up: np.ndarray) -> tuple[np.ndarray, float]:
        return self.resolved_normal(up), self.height

    def display_mesh(self, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A square of edge ``size`` on the plane, counter-clockwise seen from above (one quad)."""
        n = self.resolved_normal(up)
        a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        half = 0.5 * self.size
        quad = self.height * n + half * np.array([-a - b, a - b, a + b, -a + b])
        if np.dot(np.cross(quad[1] - quad[0], quad[2] - quad[0]), n) < 0:
            quad = quad[::-1]
        return quad, np.array([[0, 1, 2, 3]], dtype=np.int32)


_EYE = np.eye(3)
_OFF = ~np.eye(3, dtype=bool)
_LAST = np.array([0.0, 0.0, 0.0, 1.0])


def _check_matrix(m: np.ndarray, name: str, t: float | None, frame: int | None = None) -> np.ndarray:
    at = ("" if t is None else f" at t = {t:.6g} s") + ("" if frame is None else f" (in frame {frame})")
    try:
        a = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidParameter(f"collider '{name}': transform{at} must be a finite 4x4 matrix, got {m!r:.60}") from None
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise InvalidParameter(f"collider '{name}': transform{at} must be a finite 4x4 matrix")
    R = a[:3, :3]
    # np.allclose's test (|x - y| <= 1e-5 + 1e-5 |y|) written out: kinematic colliders are checked
    # at every new time a body asks for, and allclose and det cost ~10x this on a 3 x 3
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    det = r00 * (r11 * r22 - r12 * r21) - r01 * (r10 * r22 - r12 * r20) + r02 * (r10 * r21 - r11 * r20)
    err = np.abs(R.T @ R - _EYE)
    if (err.max() > 2e-5 or err[_OFF].max() > 1e-5 or det <= 0.0
            or np.abs(a[3] - _LAST).max() > 2e-5 or np.abs(a[3, :3]).max() > 1e-5):
        raise InvalidParameter(
            f"collider '{name}': transform{at} must be rigid (rotation + translation); bake scale into the mesh"
        )
    return a


class MeshCollider(Collider):
    """A triangle-mesh collider, static (``transform`` a 4x4 matrix or None) or kinematic
    (``transform`` a function t [s] -> 4x4 local-to-world matrix, rigid).

    A closed mesh must be outward-oriented; contact tells its inside by the generalized winding
    number, or by ray parity where it is one watertight piece (``kernels/mesh.py``
    ``query_inside``, ``wsim.mesh.inside_test``). An open one (a terrain sheet) is one-sided: the
    side its normals point away from is inside.
    """

    def __init__(
        self,
        mesh,
        transform: TransformLike = None,
        friction: float = 0.5,
        name: str = "collider",
    ) -> None:
        self.name = name
        self.vertices, self.faces = wmesh.surface_arrays(mesh, name=f"collider '{name}'")
        # a closed collider must be outward-oriented (inside/outside comes from its normals);
        # an open one (a terrain sheet) is one-sided, on the side its normals point to
        closed = len(self.faces) > 0 and not wmesh.has_boundary(self.faces)
        wmesh.check_surface(self.vertices, self.faces, name=f"collider '{name}'", closed=closed)
        self.closed = closed
        # contact kernels' inside test (``wsim.kernels.mesh.query_inside``): one-sided, winding
        # number, or ray parity for one watertight piece (``wsim.mesh.inside_test``)
        self.inside_test = wmesh.inside_test(self.faces) if closed else 0
        if len(self.faces) == 0:
            raise InvalidParameter(f"collider '{name}': the mesh has no faces")
        self.friction = _check_friction(friction, name)
        self.kinematic = callable(transform)
        self._transform = transform if self.kinematic else _check_matrix(
            np.eye(4) if transform is None else transform, name, None
        )
        self._device_meshes: dict[str, wp.Mesh] = {}
        # the vertices' box and a ball around them, in the mesh's own axes (broad phases)
        self.local_box = (self.vertices.min(axis=0), self.vertices.max(axis=0))
        self.extent = float(np.linalg.norm(self.local_box[1] - self.local_box[0]))
        self._centre = 0.5 * (self.local_box[0] + self.local_box[1])
        self.radius = float(np.sqrt(((self.vertices - self._centre) ** 2).sum(axis=1).max()))

    def ball(self, t: float) -> tuple[np.ndarray, float]:
        """(world centre, radius) of a ball holding the mesh at time t (a rigid pose keeps the radius)."""
        M = self.matrix(t)
        return M[:3, :3] @ self._centre + M[:3, 3], self.radius

    def matrix(self, t: float, frame: int | None = None) -> np.ndarray:
        """Local-to-world 4x4 matrix at time t [s]; a transform function that raises comes back as
        ``InvalidParameter`` naming the collider, t and ``frame`` (the World frame being computed)."""
        if self.kinematic:
            M = call_user(self._transform, t, f"collider '{self.name}': transform", frame)
            return _check_matrix(M, self.name, t, frame)  # type: ignore[arg-type]
        return self._transform  # type: ignore[return-value]

    def display_mesh(self, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices, self.faces

    def device_mesh(self, device: wp.Device) -> wp.Mesh:
        """The Warp mesh (with its BVH) on ``device``, built on first use and shared."""
        key = device.alias
        if key not in self._device_meshes:
            self._device_meshes[key] = wp.Mesh(
                points=wp.array(self.vertices.astype(np.float32), dtype=wp.vec3, device=device),
                indices=wp.array(self.faces.ravel().astype(np.int32), dtype=wp.int32, device=device),
                support_winding_number=self.closed,  # contact's inside test (kernels/mesh.py query_inside)
            )
        return self._device_meshes[key]


class Surfaces:
    """The World's colliders as kinematic surfaces, the one place bodies and the writer query.

    ``matrix(i, t)`` evaluates (and validates) collider i's pose at t once and keeps it until the
    World starts the next frame (``new_frame``), so every body and the writer see the same pose
    for the same time. ``velocity(i, t, eps)`` is the rigid velocity field of the collider's
    material, v = G x + g, by a forward difference of its pose over eps (zero for a static one).
    """

    def __init__(self, colliders: Sequence[Collider], up: np.ndarray) -> None:
        self.colliders: tuple[Collider, ...] = tuple(colliders)
        self.up = np.asarray(up, dtype=np.float64)
        self._poses: dict[tuple[int, float], np.ndarray] = {}
        self.frame: int | None = None  # the World frame being computed (error messages)

    def __len__(self) -> int:
        return len(self.colliders)

    def __iter__(self) -> Iterator[Collider]:
        return iter(self.colliders)

    def __getitem__(self, i: int) -> Collider:
        return self.colliders[i]

    def new_frame(self, frame: int | None = None) -> None:
        """Forget the poses of the last frame (a long run must not keep every substep's matrix);
        ``frame``: the one now computed (named in a transform's error)."""
        self._poses.clear()
        self.frame = frame

    def plane(self, i: int) -> tuple[np.ndarray, float] | None:
        """(normal, height) of an analytic half-space collider, in the World's axes; else None."""
        return self.colliders[i].plane(self.up)

    def matrix(self, i: int, t: float) -> np.ndarray:
        """Local-to-world 4x4 pose of collider i at time t [s]."""
        c = self.colliders[i]
        if not c.kinematic:
            return c.matrix(t)
        key = (i, float(t))
        found = self._poses.get(key)
        if found is None:
            found = self._poses[key] = c.matrix(t, self.frame)
        return found

    def velocity(self, i: int, t: float, eps: float) -> tuple[np.ndarray, np.ndarray]:
        """(G, g): the world velocity [m/s] of collider i's material at x is G x + g, at time t."""
        if not self.colliders[i].kinematic:
            return np.zeros((3, 3)), np.zeros(3)
        M0 = self.matrix(i, t)
        D = self.matrix(i, t + eps) @ np.linalg.inv(M0)
        return (D[:3, :3] - np.eye(3)) / eps, D[:3, 3] / eps
