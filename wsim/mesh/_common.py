"""Small helpers shared by the ``wsim.mesh`` modules: error-message prefixes, per-face corner
arrays, row scatter-adds and the positive-length check (one definition each)."""

from __future__ import annotations

from typing import Any

import numpy as np

from wsim.errors import InvalidParameter
from wsim.validate import finite_number


def _prefix(name: str) -> str:
    """Start of every error message: a bare name becomes ``mesh 'name'``; a label the caller has
    already formatted (it contains a quote, e.g. ``body 'horse'``) is used as is."""
    name = str(name)
    return name if ("'" in name or '"' in name) else f"mesh '{name}'"


def _fmt_vec(v: np.ndarray) -> str:
    """A 3-vector as ``[x, y, z]`` with 6 significant digits, for error messages."""
    return "[" + ", ".join(f"{x:.6g}" for x in np.asarray(v, dtype=np.float64)) + "]"


def _corners(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The three (M, 3) corner arrays of the faces."""
    return vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]


def _scatter_add_rows(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum the rows of ``values`` (K, 3) into ``n`` bins; bincount is much faster than np.add.at."""
    out = np.empty((n, 3), dtype=np.float64)
    for k in range(3):
        out[:, k] = np.bincount(index, weights=values[:, k], minlength=n)
    return out


def _positive(value: Any, what: str) -> float:
    """A strictly positive, finite length [m] or other real parameter, or InvalidParameter naming
    ``what`` (non-numbers and non-finite values are refused by ``finite_number``)."""
    x = finite_number(value, what)
    if x <= 0.0:
        raise InvalidParameter(f"{what} = {x:g} must be positive")
    return x
