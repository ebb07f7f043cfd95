"""Colliders: static or kinematic geometry that bodies bounce off but never move.

``GroundPlane`` is the half-space above a plane; ``MeshCollider`` is a triangle mesh posed by a
fixed 4x4 matrix or by a function of time (kinematic). Each collider carries its Coulomb
friction coefficient. The device copy of a mesh (a Warp BVH) is built once per device and shared
by every body that collides with it.
"""

from __future__ import annotations

from typing import Callable, Union

import numpy as np
import warp as wp

from wsim import mesh as wmesh
from wsim.validate import as_vec3
from wsim.errors import InvalidParameter

TransformLike = Union[np.ndarray, Callable[[float], np.ndarray], None]


def _check_friction(friction: float, name: str) -> float:
    mu = float(friction)
    if not np.isfinite(mu) or mu < 0.0:
        raise InvalidParameter(f"collider '{name}': friction = {friction} must be >= 0")
    return mu


class Collider:
    """Common fields: ``name`` (USD prim name) and Coulomb ``friction`` coefficient [-]."""

    name: str
    friction: float
    kinematic: bool = False


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


def _check_matrix(m: np.ndarray, name: str, t: float | None) -> np.ndarray:
    at = "" if t is None else f" at t = {t:.6g} s"
    try:
        a = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidParameter(f"collider '{name}': transform{at} must be a finite 4x4 matrix, got {m!r:.60}") from None
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise InvalidParameter(f"collider '{name}': transform{at} must be a finite 4x4 matrix")
    R = a[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) <= 0.0 or not np.allclose(a[3], [0, 0, 0, 1]):
        raise InvalidParameter(
            f"collider '{name}': transform{at} must be rigid (rotation + translation); bake scale into the mesh"
        )
    return a


class MeshCollider(Collider):
    """A triangle-mesh collider, static (``transform`` a 4x4 matrix or None) or kinematic
    (``transform`` a function t [s] -> 4x4 local-to-world matrix, rigid).

    The mesh should be closed and outward-oriented: inside/outside comes from its normals.
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
        if len(self.faces) == 0:
            raise InvalidParameter(f"collider '{name}': the mesh has no faces")
        self.friction = _check_friction(friction, name)
        self.kinematic = callable(transform)
        self._transform = transform if self.kinematic else _check_matrix(
            np.eye(4) if transform is None else transform, name, None
        )
        self._device_meshes: dict[str, wp.Mesh] = {}
        self.extent = float(np.linalg.norm(self.vertices.max(0) - self.vertices.min(0)))

    def matrix(self, t: float) -> np.ndarray:
        """Local-to-world 4x4 matrix at time t [s]."""
        if self.kinematic:
            return _check_matrix(self._transform(t), self.name, t)  # type: ignore[operator]
        return self._transform  # type: ignore[return-value]

    def device_mesh(self, device: wp.Device) -> wp.Mesh:
        """The Warp mesh (with its BVH) on ``device``, built on first use and shared."""
        key = device.alias
        if key not in self._device_meshes:
            self._device_meshes[key] = wp.Mesh(
                points=wp.array(self.vertices.astype(np.float32), dtype=wp.vec3, device=device),
                indices=wp.array(self.faces.ravel().astype(np.int32), dtype=wp.int32, device=device),
            )
        return self._device_meshes[key]
