"""The factorization step of the operator build (paper Eq. 12): the LU of H_0 and the products
H_0^-1 and H_0^-1 G' (3N x 3N, float64).

Two backends, chosen by ``factorize(..., backend=)``:

* ``"scipy"``: LAPACK on the host (``scipy.linalg.lu_factor`` / ``lu_solve``); the CPU path.
* ``"cupy"``: cuSOLVER / cuBLAS on the GPU through CuPy (``cupyx.scipy.linalg``), the optional
  ``gpu`` extra. CuPy because it is the maintained NumPy-shaped front end to cuSOLVER's getrf /
  getrs with the same (lu, piv) layout as scipy, so the host keeps the factors it needs for its
  small re-solves (``BemOperators.solve_H0``) without a second factorization; it replaces the
  11.8 s the bunny's (N = 3485) LU and two 10,455-column solves took on the host (issue 21).

``"auto"``: CuPy when the build runs on a CUDA device and CuPy imports, else scipy. Both give the
same factors to round-off (pivoting may differ only on exact ties).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg

from wsim.errors import InvalidParameter

BACKENDS = ("auto", "scipy", "cupy")


def cupy_module():
    """CuPy (the optional ``gpu`` extra) if it imports with a usable driver, else None."""
    try:
        import cupy  # noqa: F401
        import cupyx.scipy.linalg  # noqa: F401
    except Exception:  # not installed, or no usable CUDA driver
        return None
    return cupy


def resolve(backend: str, cuda: bool) -> str:
    """The backend that will run: ``backend`` checked, "auto" resolved (``cuda``: the build's
    device is a GPU)."""
    if backend not in BACKENDS:
        raise InvalidParameter(f"factorization = {backend!r} must be one of {', '.join(BACKENDS)}")
    if backend == "auto":
        return "cupy" if cuda and cupy_module() is not None else "scipy"
    if backend == "cupy" and cupy_module() is None:
        raise InvalidParameter("factorization = 'cupy' needs CuPy (pip install 'wsim[gpu]' with the "
                               "cupy wheel of your CUDA, e.g. cupy-cuda12x)")
    return backend


def factorize(H0: np.ndarray, Gp: np.ndarray, backend: str = "scipy", device_ordinal: int = 0,
              dtype: Any = np.float64) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray, np.ndarray]:
    """(LU factors and pivots of H_0 in scipy's layout (float64), H_0^-1 and H_0^-1 G' in ``dtype``)
    as host arrays, with a resolved ``backend`` ("scipy" or "cupy" on GPU ``device_ordinal``). The
    products are solved in float64 and cast where they are made (on the GPU for CuPy): a 10k-node
    body's float64 copies would be 15 GB of host memory more at the build's peak."""
    n = H0.shape[0]
    if backend == "scipy":
        lu = scipy.linalg.lu_factor(H0, check_finite=True)
        return (lu, scipy.linalg.lu_solve(lu, np.eye(n)).astype(dtype, copy=False),
                scipy.linalg.lu_solve(lu, Gp).astype(dtype, copy=False))
    cp = cupy_module()
    import cupyx.scipy.linalg as cpl

    with cp.cuda.Device(device_ordinal):
        a = cp.asarray(H0, dtype=cp.float64)
        if not bool(cp.isfinite(a).all()):
            raise ValueError("array must not contain infs or NaNs")  # scipy's check_finite message
        lu, piv = cpl.lu_factor(a, overwrite_a=True, check_finite=False)
        del a
        eye = cp.eye(n, dtype=cp.float64)
        H0_inv = cpl.lu_solve((lu, piv), eye, overwrite_b=True, check_finite=False).astype(dtype, copy=False).get()
        del eye
        H0_inv_Gp = cpl.lu_solve((lu, piv), cp.asarray(Gp, dtype=cp.float64), overwrite_b=True,
                                 check_finite=False).astype(dtype, copy=False).get()
        factors = (lu.get(order="F"), piv.get().astype(np.int32))  # Fortran order, as LAPACK (scipy) wants it: no copy a solve
        del lu, piv
        cp.get_default_memory_pool().free_all_blocks()
    return factors, H0_inv, H0_inv_Gp
