"""Curves through a mesh's vertices, and their parameters u, for curve-based reconstruction.

The PBD-reconstruction paper picks ordered vertex lists ("curves") by hand on the rest shape and
fits each coordinate along each curve. wsim extracts them automatically so that every vertex
lies on exactly one curve: vertices are binned by their angle around the rest shape's principal
(longest) axis into sectors, and each sector's vertices, ordered along the axis, form a meridian,
cut into open curves of at most ``points_per_curve`` vertices. Along an elongated body (a neck, a tail, a limb) meridians
follow the direction in which deformations vary most smoothly; rings around the axis would fit
cos/sin-like closed profiles that a 4-term basis fits badly. User curves (index lists, open or
closed) are accepted as the paper does.

Parameter u on [0, 1]: ``"chord"`` (default) is the normalized arc length along the curve on the
rest shape, which the decoder can recompute from the mesh, so it costs no stored data.
``"paper"`` is the paper's Eqs. (9)-(10) read literally: one u per point and per coordinate,
u = (w - w_min) / (w_max - w_min), averaged over the keyframes; it must be stored (3 floats per
point) and is undefined for a coordinate that is constant along a curve.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from wsim.errors import InvalidParameter
from wsim.validate import positive_int


@dataclass(frozen=True)
class Curve:
    """An ordered list of vertex indices; a closed curve returns to its first vertex."""

    indices: np.ndarray
    closed: bool = False

    @property
    def fit_indices(self) -> np.ndarray:
        """Vertices in fitting order: a closed curve repeats its first vertex at the end (as the paper does)."""
        return np.append(self.indices, self.indices[0]) if self.closed else self.indices


def validate_curves(curves: Sequence[Curve | Sequence[int]], n_vertices: int, closed: bool = False) -> list[Curve]:
    """Curves from user input: index lists (or Curve objects); every vertex must lie on some curve."""
    out: list[Curve] = []
    seen = np.zeros(n_vertices, dtype=bool)
    for i, c in enumerate(curves):
        cv = c if isinstance(c, Curve) else Curve(np.asarray(c), closed)
        idx = np.asarray(cv.indices)
        if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
            raise InvalidParameter(f"curve {i}: must be a list of integer vertex indices")
        if idx.size == 0:
            raise InvalidParameter(f"curve {i}: is empty")
        if idx.min() < 0 or idx.max() >= n_vertices:
            bad = int(idx[(idx < 0) | (idx >= n_vertices)][0])
            raise InvalidParameter(f"curve {i}: vertex index {bad} is out of range [0, {n_vertices - 1}]")
        if np.unique(idx).size != idx.size:
            vals, counts = np.unique(idx, return_counts=True)
            raise InvalidParameter(f"curve {i}: vertex {int(vals[counts > 1][0])} appears more than once")
        seen[idx] = True
        out.append(Curve(idx.astype(np.int64), bool(cv.closed) and idx.size > 2))  # a closed curve needs 3 vertices
    if not seen.all():
        missing = np.flatnonzero(~seen)
        raise InvalidParameter(
            f"{missing.size} vertices lie on no curve (e.g. vertex {int(missing[0])}); "
            "every vertex is reconstructed from a curve: add curves or use curves='auto'"
        )
    return out


def auto_curves(rest: np.ndarray, points_per_curve: int = 12) -> list[Curve]:
    """Meridian curves covering every vertex once (see module docstring).

    The number of angular sectors is the circumference at the mean distance from the principal
    axis over the typical vertex spacing (median nearest-neighbour distance), so a sector holds
    about one column of vertices; each sector's vertices, ordered along the axis, are then cut
    into consecutive open curves of at most ``points_per_curve`` vertices (fewer vertices per
    curve: smaller fit error, more stored coefficients).
    """
    positive_int(points_per_curve, "points_per_curve", 2)
    rest = np.asarray(rest, dtype=np.float64)
    if len(rest) < 2:
        return [Curve(np.arange(len(rest)), False)] if len(rest) else []
    centre = rest.mean(axis=0)
    rel = rest - centre
    _, _, vt = np.linalg.svd(rel, full_matrices=False)
    axis, e1, e2 = vt[0], vt[1], vt[2]
    along = rel @ axis
    radial = np.hypot(rel @ e1, rel @ e2)
    phi = np.arctan2(rel @ e2, rel @ e1)
    spacing = float(np.median(cKDTree(rest).query(rest, k=2)[0][:, 1]))
    sectors = max(1, int(round(2.0 * np.pi * radial.mean() / max(spacing, 1e-12))))
    sector = np.minimum(((phi + np.pi) / (2.0 * np.pi) * sectors).astype(np.int64), sectors - 1)
    curves = []
    for s in range(sectors):
        members = np.flatnonzero(sector == s)
        if members.size == 0:
            continue
        chain = members[np.argsort(along[members], kind="stable")]
        pieces = int(np.ceil(chain.size / points_per_curve))
        for piece in np.array_split(chain, pieces):
            curves.append(Curve(piece, closed=False))
    return curves


def chord_parameters(rest: np.ndarray, curve: Curve) -> np.ndarray:
    """u in [0, 1] by normalized arc length along the curve's fitting order on the rest shape."""
    p = np.asarray(rest, dtype=np.float64)[curve.fit_indices]
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    return s / s[-1] if s[-1] > 0 else np.linspace(0.0, 1.0, len(s))


def paper_parameters(keyframes: np.ndarray, curve: Curve) -> np.ndarray:
    """The paper's Eqs. (9)-(10): per point and coordinate u = (w - w_min)/(w_max - w_min), averaged
    over keyframes; shape (P, 3). Raises for a coordinate constant along the curve."""
    w = np.asarray(keyframes, dtype=np.float64)[:, curve.fit_indices]  # (K, P, 3)
    lo, hi = w.min(axis=1, keepdims=True), w.max(axis=1, keepdims=True)
    span = hi - lo
    if np.any(span <= 1e-12 * max(float(np.abs(w).max()), 1.0)):
        raise InvalidParameter(
            "parametrization='paper' (Eq. 10) is undefined: a coordinate is constant along a curve; use 'chord'"
        )
    return ((w - lo) / span).mean(axis=0)
