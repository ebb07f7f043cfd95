"""The factorization step of the BEM build (``wsim.bem.factorization``): the scipy backend on the
CPU; the CuPy backend, where CuPy and a GPU exist, against it."""

from __future__ import annotations

import numpy as np
import pytest

import wsim
from wsim.bem import factorization


def _system(n: int = 60, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    H0 = rng.standard_normal((n, n)) + n * np.eye(n) * 0.3
    return H0, rng.standard_normal((n, n))


def test_scipy_factors_solve_the_system() -> None:
    H0, Gp = _system()
    (lu, piv), H0_inv, H0_inv_Gp, _ = factorization.factorize(H0, Gp, "scipy")
    np.testing.assert_allclose(H0 @ H0_inv, np.eye(len(H0)), atol=1e-12)
    np.testing.assert_allclose(H0 @ H0_inv_Gp, Gp, atol=1e-11)
    import scipy.linalg

    b = np.arange(len(H0), dtype=float)
    np.testing.assert_allclose(H0 @ scipy.linalg.lu_solve((lu, piv), b), b, atol=1e-11)


def test_backend_names_are_checked_and_auto_falls_back_to_scipy() -> None:
    with pytest.raises(wsim.InvalidParameter, match="must be one of"):
        factorization.resolve("magma", False)
    assert factorization.resolve("auto", False) == "scipy"  # a CPU build never asks for CuPy
    if factorization.cupy_module() is None:
        assert factorization.resolve("auto", True) == "scipy"
        with pytest.raises(wsim.InvalidParameter, match="needs CuPy"):
            factorization.resolve("cupy", True)


@pytest.mark.skipif(factorization.cupy_module() is None or not __import__("warp").is_cuda_available(),
                    reason="CuPy and a CUDA device needed")
def test_cupy_factors_equal_scipy() -> None:
    H0, Gp = _system(300, seed=1)
    (lu_s, piv_s), inv_s, prod_s, _ = factorization.factorize(H0, Gp, "scipy")
    (lu_c, piv_c), inv_c, prod_c, _ = factorization.factorize(H0, Gp, "cupy")
    np.testing.assert_allclose(inv_c, inv_s, atol=1e-12 * np.abs(inv_s).max())
    np.testing.assert_allclose(prod_c, prod_s, atol=1e-12 * np.abs(prod_s).max())
    import scipy.linalg

    b = np.linspace(-1, 1, len(H0))
    np.testing.assert_allclose(scipy.linalg.lu_solve((lu_c, piv_c), b), scipy.linalg.lu_solve((lu_s, piv_s), b),
                               atol=1e-12)


def _frame_terms(n: int, seed: int = 2) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    return rng.standard_normal((n, 3)), rng.standard_normal((n, 3)), rng.standard_normal((3, n)), rng.standard_normal((3, n))


def test_frame_terms_are_folded_into_G_prime_before_the_solve() -> None:
    """G' = G_0 + D_0 A + Q_0 C (Eq. 10 folded into Eq. 12), returned with the products of it."""
    H0, G0 = _system()
    D, Q, A, C = _frame_terms(len(H0))
    Gp_expected = G0 + D @ A + Q @ C
    f = factorization.factorize(H0, G0.copy(), "scipy", frame_terms=(D, Q, A, C))
    np.testing.assert_allclose(f.Gp, Gp_expected, atol=1e-12)
    np.testing.assert_allclose(H0 @ f.H0_inv_Gp, Gp_expected, atol=1e-10)


@pytest.mark.skipif(factorization.cupy_module() is None or not __import__("warp").is_cuda_available(),
                    reason="CuPy and a CUDA device needed")
def test_cupy_takes_the_builds_device_buffers_and_folds_there() -> None:
    """H_0 and G_0 handed over as Warp arrays on the GPU (the build's path) give scipy's results."""
    import warp as wp

    H0, G0 = _system(300, seed=3)
    terms = _frame_terms(300)
    ref = factorization.factorize(H0, G0.copy(), "scipy", frame_terms=terms)
    H0_d, G0_d = (wp.array(a, dtype=wp.float64, device="cuda:0") for a in (H0, G0))
    f = factorization.factorize(H0_d, G0_d, "cupy", 0, np.float32, frame_terms=terms)
    np.testing.assert_allclose(f.Gp, ref.Gp, atol=1e-12 * np.abs(ref.Gp).max())
    assert f.H0_inv.dtype == np.float32 and f.H0_inv_Gp.dtype == np.float32
    np.testing.assert_allclose(f.H0_inv_Gp, ref.H0_inv_Gp, atol=1e-6 * np.abs(ref.H0_inv_Gp).max())
    np.testing.assert_allclose(f.H0_inv, ref.H0_inv, atol=1e-6 * np.abs(ref.H0_inv).max())


@pytest.mark.parametrize("backend", ["scipy", "cupy"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_H0_is_refused_by_either_backend(backend: str, bad: float) -> None:
    """scipy's check_finite, and on the GPU the row-sum check that stands in for it."""
    if backend == "cupy" and (factorization.cupy_module() is None or not __import__("warp").is_cuda_available()):
        pytest.skip("CuPy and a CUDA device needed")
    H0, G0 = _system(50, seed=4)
    H0[7, 3] = bad
    with pytest.raises(ValueError, match="infs or NaNs"):
        factorization.factorize(H0, G0, backend)
