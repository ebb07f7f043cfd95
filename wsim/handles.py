"""Kinematic handles: vertex sets whose positions a script drives over time.

A handle poses a model the way the PBD-reconstruction paper drives its horse: the vertices of
the torso are held, those of the head are carried along a path, and the simulation fills in the
neck. ``motion(t)`` returns either a 4x4 matrix applied to the handle's rest positions, or the
(K, 3) target positions directly.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from wsim.errors import InvalidParameter


class Handle:
    """Vertices ``vertices`` follow ``motion(t)`` exactly (they get infinite mass).

    Args:
        vertices: indices into the body's particles.
        motion: t [s] -> 4x4 matrix (applied to the rest positions) or (K, 3) positions [m].
        name: used in error messages.
    """

    def __init__(self, vertices: Sequence[int] | np.ndarray, motion: Callable[[float], np.ndarray], name: str = "handle"):
        idx = np.asarray(vertices, dtype=np.int64).ravel()
        if idx.size == 0:
            raise InvalidParameter(f"handle '{name}': no vertices")
        if np.unique(idx).size != idx.size:
            raise InvalidParameter(f"handle '{name}': repeated vertex indices")
        if not callable(motion):
            raise InvalidParameter(f"handle '{name}': motion must be a function of time t [s]")
        self.vertices = idx
        self.motion = motion
        self.name = name

    def targets(self, t: float, rest: np.ndarray) -> np.ndarray:
        """(K, 3) target positions at time t, given the (K, 3) rest positions of the handle's vertices."""
        out = np.asarray(self.motion(t), dtype=np.float64)
        if out.shape == (4, 4):
            out = rest @ out[:3, :3].T + out[:3, 3]
        if out.shape != rest.shape:
            raise InvalidParameter(
                f"handle '{self.name}': motion({t:.6g}) must return a 4x4 matrix or a {rest.shape} array, got {out.shape}"
            )
        return out
