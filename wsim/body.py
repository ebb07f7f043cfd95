"""The interface every body (PBD, BEM, EoL) implements so that one World can step and export it.

A body owns its operators (immutable, possibly shared) and its state, and advances itself from
one frame time to the next with whatever internal step it needs: PBD with fixed substeps, BEM
with the dt baked into its operators, EoL with an adaptive dt. The World only asks it to
``advance``, to report non-finite state, and for world-space surface points for export.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Sequence

import numpy as np
import warp as wp

from wsim.errors import InvalidParameter
from wsim.validate import as_vec3

if TYPE_CHECKING:
    from wsim.colliders import Collider


class Body(ABC):
    """Base class of simulated bodies.

    Args:
        name: the body's name (its USD prim is /World/<name>); unique within a World.
        velocity: initial linear velocity of the centre of mass [m/s].
        angular_velocity: initial angular velocity about the centre of mass [rad/s].
    """

    def __init__(
        self,
        name: str,
        velocity: Sequence[float] = (0.0, 0.0, 0.0),
        angular_velocity: Sequence[float] = (0.0, 0.0, 0.0),
    ) -> None:
        if not isinstance(name, str) or not name:
            raise InvalidParameter(f"a body name must be a non-empty string, got {name!r}")
        self.name = name
        self.initial_velocity = as_vec3(velocity, f"body '{name}': velocity")
        self.initial_angular_velocity = as_vec3(angular_velocity, f"body '{name}': angular_velocity")

    @property
    @abstractmethod
    def faces(self) -> np.ndarray:
        """(M, 3) int32 surface triangles, fixed for the body's life."""

    @abstractmethod
    def bind(self, device: wp.Device, gravity: np.ndarray, up: np.ndarray) -> None:
        """Allocate state on ``device``; called once by ``World.add``, so state can be read at once.

        ``gravity`` [m/s^2] and the unit ``up`` vector are the World's.
        """

    @abstractmethod
    def attach_colliders(self, colliders: Sequence[Collider]) -> None:
        """Prepare contact with the World's colliders; called once before the first step."""

    @abstractmethod
    def advance(self, t0: float, t1: float) -> None:
        """Advance the state from time t0 to t1 [s] (one frame)."""

    @abstractmethod
    def points(self) -> np.ndarray:
        """(N, 3) world-space surface vertex positions [m] at the current time, as numpy float64."""

    @abstractmethod
    def check_finite(self, frame: int, time: float) -> None:
        """Raise ``SimulationDiverged`` naming this body, the frame and the quantity if state is NaN/Inf."""

    def _tick(self, stage: str, t0: float) -> float:
        """Add the seconds since t0 to ``self.timings[stage]`` and return now. With ``self.profile``
        the device (``self._device``) is synchronized first, so GPU time lands in its own stage."""
        if getattr(self, "profile", False) and not self._device.is_cpu:
            wp.synchronize_device(self._device)
        t1 = time.perf_counter()
        self.timings[stage] += t1 - t0
        return t1
