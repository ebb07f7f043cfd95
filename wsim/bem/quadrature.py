"""Triangle quadrature for the collocation BEM: regular, near-singular and weakly singular rules.

All rules are returned in barycentric coordinates (b0, b1, b2) of the parent triangle with weights
normalized to sum to 1, so that int_T f dA ~= area(T) * sum_q w_q f(y_q); the barycentric
coordinates are also the values of the three linear shape functions at y_q.

- **Regular integrals** (collocation point away from the triangle): the triangle is split into n^2
  congruent sub-triangles (n = ``subdivision``; the paper splits into 4, n = 2) and a conical
  product Gauss rule with ``order`` points per direction is applied on each: Gauss-Jacobi
  (weight 1 - u) in the collapsed direction times Gauss-Legendre in the other, exact for total
  degree 2 * order - 1. ``order = 3`` is a 9-point rule exact to degree 5, the paper's choice
  (tested on monomials in ``tests/test_bem_quadrature.py``).
- **Near-singular integrals** (collocation point closer to the triangle than ``near_ratio`` times
  its longest edge): the sub-triangle count grows by 4 per level, up to ``near_levels`` levels,
  one level per halving of the distance ratio.
- **Weakly singular integrals** (the collocation point is a vertex of the triangle): polar
  coordinates about that vertex in Duffy's form, y = P0 + u[(1 - v)(P1 - P0) + v(P2 - P0)],
  dA = 2 area u du dv. The Jacobian's factor u cancels the 1/r of the kernels exactly (r is u
  times a smooth function of v), so a ``singular_order``^2 Gauss-Legendre product rule converges
  spectrally. Strongly singular parts are never integrated directly (see ``assembly``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.special import roots_jacobi, roots_legendre

from wsim.errors import InvalidParameter


def gauss_legendre01(n: int) -> tuple[np.ndarray, np.ndarray]:
    """n-point Gauss-Legendre nodes and weights on [0, 1]."""
    x, w = roots_legendre(n)
    return 0.5 * (x + 1.0), 0.5 * w


def triangle_rule(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Conical product rule on one triangle: (order^2, 3) barycentrics and weights summing to 1.

    With xi = u, eta = (1 - u) v on the reference triangle, dxi deta = (1 - u) du dv: Gauss-Jacobi
    with weight (1 - u) in u and Gauss-Legendre in v integrate every monomial of total degree
    <= 2 order - 1 exactly.
    """
    xj, wj = roots_jacobi(order, 1.0, 0.0)  # weight (1 - x) on [-1, 1]
    u = 0.5 * (xj + 1.0)
    wu = wj / 4.0  # (1 - x) dx = 4 (1 - u) du
    v, wv = gauss_legendre01(order)
    U, V = np.meshgrid(u, v, indexing="ij")
    xi = U.ravel()
    eta = ((1.0 - U) * V).ravel()
    w = np.outer(wu, wv).ravel() * 2.0  # reference area 1/2 -> weights sum to 1
    return np.stack([1.0 - xi - eta, xi, eta], axis=1), w


def subdivided_rule(order: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``triangle_rule(order)`` on each of the n^2 congruent sub-triangles of a triangle."""
    base_b, base_w = triangle_rule(order)
    corners = []
    for a in range(n):  # rows of the subdivision grid in barycentric steps of 1/n
        for b in range(n - a):
            p = np.array([[n - a - b, a, b], [n - a - b - 1, a + 1, b], [n - a - b - 1, a, b + 1]], float) / n
            corners.append(p)  # "upward" sub-triangle
            if b < n - a - 1:
                q = np.array([[n - a - b - 1, a + 1, b], [n - a - b - 2, a + 1, b + 1], [n - a - b - 1, a, b + 1]], float) / n
                corners.append(q)  # "downward" sub-triangle
    pts = np.concatenate([base_b @ c for c in corners])
    w = np.tile(base_w, len(corners)) / len(corners)
    return pts, w


def duffy_rule(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Polar (Duffy) rule about barycentric vertex 0: (order^2, 3) barycentrics, weights summing to 1.

    b = (1 - u, u (1 - v), u v); the weight carries the Jacobian 2u of the map from [0, 1]^2.
    """
    u, wu = gauss_legendre01(order)
    v, wv = gauss_legendre01(order)
    U, V = np.meshgrid(u, v, indexing="ij")
    U, V = U.ravel(), V.ravel()
    w = np.outer(wu, wv).ravel() * 2.0 * U
    return np.stack([1.0 - U, U * (1.0 - V), U * V], axis=1), w


@dataclass(frozen=True)
class Quadrature:
    """Speed/accuracy knobs of the boundary integrals (see the module docstring).

    Attributes:
        order: Gauss points per direction of the regular rule (degree 2 order - 1; 3 = paper).
        subdivision: sub-triangles per edge for regular integrals (2 = the paper's 4 sub-triangles).
        near_ratio: distance / longest edge below which a triangle counts as near (0 disables).
        near_levels: at most this many extra 4x refinements for near triangles.
        singular_order: Gauss points per direction of the polar rule at a triangle's own vertex.
    """

    order: int = 3
    subdivision: int = 2
    near_ratio: float = 1.0
    near_levels: int = 3
    singular_order: int = 8

    def __post_init__(self) -> None:
        for name, lo, hi in (("order", 1, 12), ("subdivision", 1, 32), ("near_levels", 0, 4), ("singular_order", 2, 32)):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or not lo <= value <= hi:
                raise InvalidParameter(f"quadrature {name} = {value!r} must be an integer in [{lo}, {hi}]")
        if not (np.isfinite(self.near_ratio) and 0.0 <= self.near_ratio <= 16.0):
            raise InvalidParameter(f"quadrature near_ratio = {self.near_ratio!r} must be in [0, 16]")

    def as_key(self) -> dict:
        return asdict(self)

    def regular_rules(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Concatenated rules of levels 0..near_levels: barycentrics, weights and (levels + 1) offsets."""
        pts, ws, offsets = [], [], [0]
        for level in range(self.near_levels + 1):
            p, w = subdivided_rule(self.order, self.subdivision * 2**level)
            pts.append(p)
            ws.append(w)
            offsets.append(offsets[-1] + len(w))
        return np.concatenate(pts), np.concatenate(ws), np.asarray(offsets, dtype=np.int32)

    def singular_rule(self) -> tuple[np.ndarray, np.ndarray]:
        return duffy_rule(self.singular_order)


def quadrature_from(options: dict) -> Quadrature:
    """A :class:`Quadrature` from keyword options, rejecting unknown names with a clear error."""
    known = set(Quadrature.__dataclass_fields__)
    unknown = set(options) - known
    if unknown:
        raise InvalidParameter(f"unknown quadrature option(s) {sorted(unknown)}; known: {sorted(known)}")
    return Quadrature(**options)
