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
from wsim.validate import call_user, callback_array


class Handle:
    """Vertices ``vertices`` follow ``motion(t)`` exactly (they get infinite mass).

    A PBD body evaluates ``motion`` at the end of each of its substeps, just before that substep
    runs (a motion that reads the body sees it after the substep before); in a frame where the
    body steps in lockstep with other PBD bodies it touches, at the start of the frame for all of
    the frame's substeps. A matrix is applied on the body's device.

    Args:
        vertices: indices into the body's particles.
        motion: t [s] -> 4x4 matrix (applied to the rest positions) or (K, 3) positions [m].
        name: used in error messages.
    """

    def __init__(self, vertices: Sequence[int] | np.ndarray, motion: Callable[[float], np.ndarray], name: str = "handle"):
        idx = as_indices(vertices, f"handle '{name}': vertices")
        if idx.size == 0:
            raise InvalidParameter(f"handle '{name}': no vertices")
        if np.unique(idx).size != idx.size:
            raise InvalidParameter(f"handle '{name}': repeated vertex indices")
        if not callable(motion):
            raise InvalidParameter(f"handle '{name}': motion must be a function of time t [s]")
        self.vertices = idx
        self.motion = motion
        self.name = name

    def targets(self, t: float, rest: np.ndarray, what: str | None = None, frame: int | None = None) -> np.ndarray:
        """(K, 3) target positions at time t, given the (K, 3) rest positions of the handle's vertices.

        ``what`` names the handle in error messages (default ``handle '<name>' motion``; a body
        passes ``body 'neck': handle 'tip' (handles[0]) motion``) and ``frame`` is the World frame
        being computed, so a bad motion is reported with the body, the frame and the time."""
        return self.place(self.pose(t, rest.shape, what, frame), rest)

    @staticmethod
    def place(pose: np.ndarray, rest: np.ndarray) -> np.ndarray:
        """(K, 3) targets of a checked pose (``pose``): a 4x4 matrix applied to the rest positions,
        or the positions themselves."""
        return rest @ pose[:3, :3].T + pose[:3, 3] if pose.shape == (4, 4) else pose

    def pose(self, t: float, shape: tuple[int, ...], what: str | None = None, frame: int | None = None) -> np.ndarray:
        """``motion(t)`` checked (``targets``): a 4x4 matrix, or the ``shape`` (K, 3) positions."""
        what = what or f"handle '{self.name}' motion"
        return callback_array(call_user(self.motion, t, what, frame), ((4, 4), shape), what, t, frame)


def as_indices(values: Sequence[int] | np.ndarray, what: str) -> np.ndarray:
    """Integer indices from a list/array of ints, or from a boolean mask (its True positions)."""
    a = np.asarray(values)
    if a.dtype == bool:
        return np.flatnonzero(a.ravel()).astype(np.int64)
    if a.size and not np.issubdtype(a.dtype, np.integer):
        if not (np.issubdtype(a.dtype, np.floating) and np.all(np.isfinite(a)) and np.all(a == np.round(a))):
            raise InvalidParameter(f"{what} must be integer indices or a boolean mask, got {a.dtype} values")
    return a.astype(np.int64).ravel()
