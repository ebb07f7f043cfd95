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

import contextlib
from typing import Any, Iterator, NamedTuple

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


class _StreamHandle:
    """A raw CUDA stream as an object of the CUDA stream protocol (``__cuda_stream__``: version
    0 and the handle), which CuPy 14 takes (``cupy.cuda.Stream.from_external``) in place of its
    deprecated ``ExternalStream``."""

    def __init__(self, handle: int) -> None:
        self.handle = int(handle)

    def __cuda_stream__(self) -> tuple[int, int]:
        return (0, self.handle)


@contextlib.contextmanager
def on_stream(cp: Any, ordinal: int, handle: int) -> Iterator[None]:
    """CuPy's work inside runs on device ``ordinal``'s CUDA stream ``handle`` (a Warp stream's
    ``cuda_stream``: ordered with Warp's launches, no synchronization). CuPy 14's stream protocol
    where it has it, else ``ExternalStream`` (CuPy 13, which has no ``from_external``)."""
    from_external = getattr(cp.cuda.Stream, "from_external", None)
    stream = (from_external(_StreamHandle(handle)) if from_external is not None
              else cp.cuda.ExternalStream(int(handle), int(ordinal)))
    with cp.cuda.Device(ordinal), stream:
        yield


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


class Factors(NamedTuple):
    """What ``factorize`` returns, as host arrays."""

    lu: tuple[np.ndarray, np.ndarray]  # LU factors and pivots of H_0, scipy's layout, float64
    H0_inv: np.ndarray  # H_0^-1 in the requested dtype
    H0_inv_Gp: np.ndarray  # H_0^-1 G' in the requested dtype
    Gp: np.ndarray  # G' = G_0 + D_0 A + Q_0 C, float64


def fold_frame_terms(G: Any, D: np.ndarray, Q: np.ndarray, A: np.ndarray, C: np.ndarray) -> Any:
    """G + D A + Q C in G's own buffer (returned): G_k with the frame acceleration its traction
    causes folded in (Eq. 10: a_ext = A p, alpha_ext = C p). k = 0 gives G'; the compressed sets
    store G'_k (``compression.folded_G``). In row blocks: the expression's full-size temporaries
    (875 MB each for the bunny, 7 GB at N = 10088, faulted in fresh) cost more than the sums.
    ``G`` may be a CuPy array (the factorization's device): the rank-6 term is uploaded once."""
    DQ, AC = np.concatenate([D, Q], axis=1), np.concatenate([A, C], axis=0)
    if not isinstance(G, np.ndarray):  # a CuPy array: the same sums where G lies
        import cupy as cp

        DQ, AC = cp.asarray(DQ), cp.asarray(AC)
    for r0 in range(0, G.shape[0], 1024):
        G[r0:r0 + 1024] += DQ[r0:r0 + 1024] @ AC
    return G


def factorize(H0: Any, G0: Any, backend: str = "scipy", device_ordinal: int = 0, dtype: Any = np.float64,
              frame_terms: tuple[np.ndarray, ...] | None = None) -> Factors:
    """The LU of H_0, H_0^-1 and H_0^-1 G' with a resolved ``backend`` ("scipy" or "cupy" on GPU
    ``device_ordinal``); G' = G_0 + D_0 A + Q_0 C with ``frame_terms`` = (D_0, Q_0, A, C), else G_0.

    ``H0``, ``G0``: float64 (3N, 3N) host arrays, or for "cupy" also arrays on that GPU with
    ``__cuda_array_interface__`` (the build's Warp buffers): then H_0 and G_0 never cross to the
    host and back (1.75 GB each way for the bunny, issue 21). G_0's buffer may be overwritten
    with G' (it is on the host path, and returned as ``Gp``); a caller that passes its only
    references to device buffers (``factorize(bufs.pop(0), bufs.pop(0), ...)``) has them freed
    as soon as their copies are made. The products are solved in float64 and cast where they are made (on the GPU for CuPy): a
    10k-node body's float64 copies would be 15 GB of host memory more at the build's peak."""
    n = H0.shape[0]
    if backend == "scipy":
        Gp = np.asarray(G0)
        if frame_terms is not None:
            Gp = fold_frame_terms(Gp, *frame_terms)
        lu = scipy.linalg.lu_factor(H0, check_finite=True)
        return Factors(lu, scipy.linalg.lu_solve(lu, np.eye(n)).astype(dtype, copy=False),
                       scipy.linalg.lu_solve(lu, Gp).astype(dtype, copy=False), Gp)
    cp = cupy_module()
    import cupyx.scipy.linalg as cpl

    with cp.cuda.Device(device_ordinal):
        a = cp.asarray(H0, dtype=cp.float64)  # a view of a device buffer, an upload of a host one
        del H0  # a caller that handed over its only reference frees the buffer with `a` below
        # scipy's check_finite: a NaN or inf makes its row's sum non-finite (a finite row summing
        # past 1.8e308 would be refused too), so one matrix-vector product and 3N numbers on the
        # host check it. CuPy's all() over the (3N)^2 flags compiled a reduction for that size on
        # a fresh machine's first build (6.1 s for the bunny, tools/results/cupy_first_use_h100.jsonl)
        if not np.isfinite((a @ cp.ones(n, dtype=cp.float64)).get()).all():
            raise ValueError("array must not contain infs or NaNs")  # scipy's check_finite message
        lu, piv = cpl.lu_factor(a, overwrite_a=True, check_finite=False)  # on a Fortran-ordered copy of C-ordered `a`
        del a
        cp.cuda.runtime.deviceSynchronize()  # freed stream-ordered (Warp) memory goes back to the driver here
        g = cp.asarray(G0, dtype=cp.float64)
        del G0
        if frame_terms is not None:
            g = fold_frame_terms(g, *frame_terms)
        Gp = g.get()
        # the solves work in Fortran order: made here once, and the right-hand sides overwritten
        # (a C-ordered one would be copied by each solve), so the peak stays ~3.5 (3N)^2 float64
        # with the buffers handed over (N = 10088: ~26 GB)
        g = cp.asfortranarray(g)
        cp.cuda.runtime.deviceSynchronize()
        eye = cp.eye(n, dtype=cp.float64).T  # Fortran-ordered (the identity is its own transpose)
        H0_inv = cpl.lu_solve((lu, piv), eye, overwrite_b=True, check_finite=False).astype(dtype, copy=False).get()
        del eye
        H0_inv_Gp = cpl.lu_solve((lu, piv), g, overwrite_b=True, check_finite=False).astype(dtype, copy=False).get()
        del g
        factors = (lu.get(order="F"), piv.get().astype(np.int32))  # Fortran order, as LAPACK (scipy) wants it: no copy a solve
        del lu, piv
        cp.get_default_memory_pool().free_all_blocks()
    return Factors(factors, H0_inv, H0_inv_Gp, Gp)
