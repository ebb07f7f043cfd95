"""Triangle rules of the BEM quadrature: polynomial degree, sub-triangles, the polar rule."""

from __future__ import annotations

from math import factorial

import numpy as np
import pytest

import wsim
from wsim.bem.quadrature import Quadrature, duffy_rule, quadrature_from, subdivided_rule, triangle_rule


def monomial_exact(a: int, b: int) -> float:
    """int over the reference triangle of xi^a eta^b, divided by its area 1/2."""
    return 2.0 * factorial(a) * factorial(b) / factorial(a + b + 2)


def rule_error(bary, w, a, b):
    xi, eta = bary[:, 1], bary[:, 2]
    return abs(np.sum(w * xi**a * eta**b) - monomial_exact(a, b))


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_conical_rule_has_degree_2_order_minus_1(order):
    bary, w = triangle_rule(order)
    assert len(w) == order**2 and np.all(w > 0) and np.allclose(bary.sum(axis=1), 1.0)
    deg = 2 * order - 1
    assert max(rule_error(bary, w, a, d - a) for d in range(deg + 1) for a in range(d + 1)) < 1e-14
    # and not one degree more: the claim "degree 5" for the paper's 9-point rule is exact, not loose
    assert max(rule_error(bary, w, a, deg + 1 - a) for a in range(deg + 2)) > 1e-6


def test_subdivided_rule_keeps_the_degree_and_covers_the_triangle():
    bary, w = subdivided_rule(3, 4)
    assert len(w) == 16 * 9 and w.sum() == pytest.approx(1.0, abs=1e-14)
    assert np.all(bary >= -1e-15)
    assert max(rule_error(bary, w, a, d - a) for d in range(6) for a in range(d + 1)) < 1e-14
    # a smooth non-polynomial integrand converges at the rule's order h^6 (ratio -> 64 per halving)
    f = lambda b: np.exp(3.0 * b[:, 1]) * np.cos(2.0 * b[:, 2])  # noqa: E731
    pr, wr = subdivided_rule(8, 32)
    ref = np.sum(wr * f(pr))
    errs = [abs(np.sum(w * f(p)) - ref) for p, w in (subdivided_rule(3, n) for n in (2, 4, 8))]
    assert errs[1] < errs[0] / 40 and errs[2] < errs[1] / 50


def test_polar_rule_integrates_one_over_r_from_a_vertex():
    """int_T 1/r dA from a vertex has the closed form h [asinh(tan t1) - asinh(tan t0)], with h the
    height over the opposite edge and t0, t1 the angles of its ends from the foot of the height."""
    P0, P1, P2 = np.zeros(3), np.array([1.0, -0.3, 0.0]), np.array([0.4, 0.9, 0.0])
    e = P2 - P1
    foot = P1 + e * np.dot(P0 - P1, e) / np.dot(e, e)
    h = np.linalg.norm(foot)
    along = e / np.linalg.norm(e)
    t0, t1 = np.arctan(np.dot(P1 - foot, along) / h), np.arctan(np.dot(P2 - foot, along) / h)
    exact = h * (np.arcsinh(np.tan(t1)) - np.arcsinh(np.tan(t0)))
    area = 0.5 * np.linalg.norm(np.cross(P1 - P0, P2 - P0))
    errs = []
    for order in (4, 8, 16):
        bary, w = duffy_rule(order)
        y = bary @ np.stack([P0, P1, P2])
        errs.append(abs(area * np.sum(w / np.linalg.norm(y, axis=1)) / exact - 1.0))
    assert errs[1] < 1e-7 and errs[2] < 1e-13  # spectral: the Jacobian's u cancels 1/r exactly
    assert np.allclose(bary[:, 0], 1.0 - (bary[:, 1] + bary[:, 2]))


def test_quadrature_knobs_are_validated():
    assert Quadrature().order == 3 and Quadrature().subdivision == 2  # the paper's 4 x 9-point rule
    for bad in (dict(order=0), dict(subdivision=0), dict(near_ratio=-1.0), dict(singular_order=1), dict(order=2.5)):
        with pytest.raises(wsim.InvalidParameter):
            Quadrature(**bad)
    with pytest.raises(wsim.InvalidParameter, match="unknown quadrature"):
        quadrature_from({"oder": 3})
    bary, w, off = Quadrature(near_levels=2).regular_rules()
    assert off.tolist() == [0, 36, 36 + 144, 36 + 144 + 576]
