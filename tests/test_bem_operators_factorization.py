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
    (lu, piv), H0_inv, H0_inv_Gp = factorization.factorize(H0, Gp, "scipy")
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
    (lu_s, piv_s), inv_s, prod_s = factorization.factorize(H0, Gp, "scipy")
    (lu_c, piv_c), inv_c, prod_c = factorization.factorize(H0, Gp, "cupy")
    np.testing.assert_allclose(inv_c, inv_s, atol=1e-12 * np.abs(inv_s).max())
    np.testing.assert_allclose(prod_c, prod_s, atol=1e-12 * np.abs(prod_s).max())
    import scipy.linalg

    b = np.linspace(-1, 1, len(H0))
    np.testing.assert_allclose(scipy.linalg.lu_solve((lu_c, piv_c), b), scipy.linalg.lu_solve((lu_s, piv_s), b),
                               atol=1e-12)
