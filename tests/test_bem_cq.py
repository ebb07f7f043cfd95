"""Convolution-quadrature weights (paper Eq. 15) against exact convolutions."""

from __future__ import annotations

import math

import numpy as np
import pytest

import wsim
from wsim.bem import cq


def exact(k: int, p: int, t: np.ndarray) -> np.ndarray:
    """Inverse transform of s^k applied to g(t) = t^p: s^-m -> t^(p+m) p!/(p+m)!, s -> p t^(p-1), 1 -> t^p."""
    if k <= 0:
        m = -k
        return t ** (p + m) * math.factorial(p) / math.factorial(p + m)
    return p * t ** (p - 1)


def cq_error(k: int, p: int, n: int, method: str) -> float:
    dt = 1.0 / n
    psi = cq.weights(lambda s: s**k, dt, n, method)  # n_max = n: the whole history
    t = np.arange(n + 1) * dt
    y = cq.convolve(psi, t**p)
    return abs(y[-1] - exact(k, p, t)[-1])


@pytest.mark.parametrize("k", [-2, -1, 0, 1])
@pytest.mark.parametrize("method, order", [("bdf1", 1), ("bdf2", 2)])
def test_cq_reproduces_polynomial_convolutions_with_the_method_order(k, method, order):
    """K(s) = s^k on g(t) = t^3: the error at t = 1 falls like dt^order."""
    e1, e2 = cq_error(k, 3, 40, method), cq_error(k, 3, 80, method)
    if k == 0:  # identity: exact up to the eps of the contour
        assert e1 < 1e-5 and e2 < 1e-5
        return
    assert e2 < 0.05
    assert math.log2(e1 / e2) == pytest.approx(order, abs=0.25)


def test_known_weights_and_conjugate_symmetry():
    dt, n_max = 0.01, 20
    # BDF1: 1/s -> dt for every k, 1/s^2 -> dt^2 (k + 1). The contour's aliasing error is the
    # weight L places further on times R^L = sqrt(eps): psi_{k+L} 1e-5.
    k = np.arange(n_max + 1)
    L = n_max + 1
    np.testing.assert_allclose(cq.weights(lambda s: 1.0 / s, dt, n_max), dt, rtol=2e-5)
    err = np.abs(cq.weights(lambda s: 1.0 / s**2, dt, n_max) - dt**2 * (k + 1))
    assert np.all(err <= 1.5e-5 * dt**2 * (k + L + 1))
    # the half-sample shortcut equals the full DFT of all L samples
    s_half, R, L = cq.sample_points(dt, n_max)
    f = lambda s: np.exp(-0.05 * s) / (s + 3.0)  # noqa: E731  (a delayed, damped kernel)
    l = np.arange(L)
    s_all = (1.0 - R * np.exp(2j * np.pi * l / L)) / dt
    full = np.array([(R ** -k / L) * np.sum(f(s_all) * np.exp(-2j * np.pi * k * l / L)) for k in range(n_max + 1)])
    np.testing.assert_allclose(cq.combine(f(s_half), R, L, n_max), full.real, atol=1e-12 * np.abs(full).max())
    assert np.abs(full.imag).max() < 1e-9 * np.abs(full.real).max()


def test_last_weight_needs_L_equal_n_max_plus_one():
    """With L = n_max (the paper's printing) psi_{n_max} aliases psi_0 * R^-L; L = n_max + 1 is right."""
    dt, n_max = 0.01, 10
    psi = cq.weights(lambda s: 1.0 / s, dt, n_max)
    assert psi[-1] == pytest.approx(dt, rel=2e-5)
    s, R, _ = cq.sample_points(dt, n_max)
    L = n_max  # the printed choice
    l = np.arange(L)
    s_bad = (1.0 - R * np.exp(2j * np.pi * l / L)) / dt
    bad = (R ** -n_max / L) * np.sum((1.0 / s_bad) * np.exp(-2j * np.pi * n_max * l / L))
    assert abs(bad.real / dt) > 1e4


def test_history_length_and_bad_input():
    assert cq.n_max_for(r_max=0.8, c2=22.36, dt=0.01) == 5  # the paper's bumpy cube: n_max = 5
    # Table 1 (r_max inside the spec's Sec. 3.2 ranges): the bunny and fish keep the paper's n_max;
    # the torus (lam = 30.5) and beam (lam = 6.5) get the BDF1 smear margin 1.2 sqrt(lam) > 2
    assert cq.n_max_for(r_max=0.19, c2=18.26, dt=0.003) == 5
    assert cq.n_max_for(r_max=0.15, c2=100.0, dt=0.001) == 3
    assert cq.n_max_for(r_max=0.305, c2=10.0, dt=0.001) == 37  # paper: 32
    assert cq.n_max_for(r_max=0.56, c2=17.32, dt=0.005) == 9  # paper: 8
    lam = 159.0
    assert cq.n_max_for(r_max=lam, c2=1.0, dt=1.0) == int(lam + 1.2 * np.sqrt(lam))
    for bad in (dict(dt=0.0, n_max=5), dict(dt=0.01, n_max=0)):
        with pytest.raises(wsim.InvalidParameter):
            cq.sample_points(**bad)
    with pytest.raises(wsim.InvalidParameter, match="bdf3"):
        cq.sample_points(0.01, 5, "bdf3")


@pytest.mark.parametrize("n_max", [5, 6])  # odd and even L
def test_half_weights_are_the_combine_sum(n_max):
    """The weights the Warp CQ kernel applies per sample give exactly ``combine``'s result."""
    dt = 0.01
    s, R, L = cq.sample_points(dt, n_max)
    f = np.exp(-0.03 * s) / (s + 2.0)
    W = cq.half_weights(R, L, n_max)
    ref = cq.combine(f, R, L, n_max)
    # both sums carry R^-k (up to 1/sqrt(eps) = 1e5): agreement to 1e-16 * 1e5
    np.testing.assert_allclose(np.real(W.T @ f), ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())
