"""Device side of the BEM time step: the operator set uploaded once, and the two dense passes.

``StepOperators`` holds, on one Warp device, what every step reads: H_k, G_k (k = 1..n_max),
the (3N, 6) blocks [D_k Q_k], H_0^-1 and H_0^-1 G' (paper Eq. 12) in the storage precision, plus
the error-correction pieces (``wsim.bem.correction``). It is immutable and shared by every body
built on the same operator set and device.

Two backends compute the passes (``history`` and ``solve``):

* ``"warp"``: the kernels of ``wsim.kernels.bem_step`` (one block per row, bandwidth bound);
* ``"blas"``: numpy matrix-vector products on views of the same arrays (CPU device only).

``"auto"`` picks Warp on CUDA and BLAS on the CPU, where Warp's kernels run on one thread and
numpy's BLAS uses every core (``tools/bench_bem_step.py`` measures both).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from wsim.bem.correction import Correction
from wsim.bem.operators import PRECISIONS, BemOperators
from wsim.errors import InvalidParameter
from wsim.kernels import bem_step as ks

BACKENDS = ("auto", "warp", "blas")


@dataclass(frozen=True)
class StepOperators:
    """Per-device, per-precision operator arrays of the step (see module docstring)."""

    operators: BemOperators
    device: wp.Device
    dtype: Any
    H: wp.array  # (n_max, 3N, 3N): H_1..H_n_max
    G: wp.array
    DQ: wp.array  # (n_max, 3N, 6)
    H0_inv: wp.array
    H0_inv_Gp: wp.array
    correction: Correction

    @property
    def n_max(self) -> int:
        return self.operators.n_max

    @property
    def size(self) -> int:
        """3N, the length of u and p."""
        return 3 * self.operators.n_nodes

    @property
    def matrix_bytes(self) -> int:
        """Bytes the two passes read per step: 2 n_max + 2 dense matrices (and the small blocks)."""
        return int(self.H.capacity + self.G.capacity + self.DQ.capacity + self.H0_inv.capacity + self.H0_inv_Gp.capacity)


# One upload per (operator set, device): bodies sharing a set share device memory too. Entries
# disappear with the last body that holds them; nothing here changes results.
_SHARED: weakref.WeakValueDictionary = weakref.WeakValueDictionary()


def step_operators(ops: BemOperators, device: wp.Device) -> StepOperators:
    """The (shared) device copy of ``ops`` for ``device``."""
    key = (ops.key or f"id{id(ops)}", device.alias)  # the content key covers precision and every input
    found = _SHARED.get(key)
    if found is not None:
        return found
    dtype = PRECISIONS[ops.precision]
    wdt = wp.float32 if dtype == np.float32 else wp.float64
    dq = np.concatenate([ops.D[1:], ops.Q[1:]], axis=2).astype(dtype)

    def upload(a: np.ndarray) -> wp.array:
        a = np.ascontiguousarray(a, dtype=dtype)
        # on the CPU the Warp array aliases the host operator (no second copy of gigabytes)
        return wp.array(a, dtype=wdt, device=device, copy=not device.is_cpu)

    out = StepOperators(
        operators=ops, device=device, dtype=wdt, H=upload(ops.H[1:]), G=upload(ops.G[1:]), DQ=upload(dq),
        H0_inv=upload(ops.H0_inv), H0_inv_Gp=upload(ops.H0_inv_Gp), correction=Correction.from_operators(ops),
    )
    _SHARED[key] = out
    return out


def resolve_backend(backend: str, device: wp.Device) -> str:
    if backend not in BACKENDS:
        raise InvalidParameter(f"matvec = {backend!r} must be one of {', '.join(BACKENDS)}")
    if backend == "auto":
        return "warp" if device.is_cuda else "blas"
    if backend == "blas" and not device.is_cpu:
        raise InvalidParameter("matvec = 'blas' runs on the CPU device only (use 'warp' or 'auto' on CUDA)")
    return backend


def history(so: StepOperators, backend: str, U: wp.array, P: wp.array, B: wp.array, step: int, h: wp.array) -> None:
    """h_n of Eq. (9) into ``h`` (ring row m holds step m mod n_max)."""
    if backend == "warp":
        wp.launch_tiled(ks.history_matvec, dim=so.size, block_dim=int(ks.MATVEC_BLOCK), device=so.device,
                        inputs=[so.H, so.G, U, P, so.DQ, B, step, h])
        return
    H, G, DQ = so.H.numpy(), so.G.numpy(), so.DQ.numpy()
    Un, Pn, Bn = U.numpy(), P.numpy(), B.numpy()
    out = np.zeros(so.size, dtype=Un.dtype)
    n_max = so.n_max
    for k in range(1, n_max + 1):
        s = (step - k) % n_max
        out += G[k - 1] @ Pn[s]
        out -= H[k - 1] @ Un[s]
        out += DQ[k - 1] @ Bn[s]
    h.numpy()[:] = out


def solve(so: StepOperators, backend: str, p: wp.array, h: wp.array, u: wp.array) -> None:
    """u_n = H_0^-1 G' p_n + H_0^-1 h_n (Eq. 12) into ``u``."""
    if backend == "warp":
        wp.launch_tiled(ks.solve_matvec, dim=so.size, block_dim=int(ks.MATVEC_BLOCK), device=so.device,
                        inputs=[so.H0_inv_Gp, so.H0_inv, p, h, u])
        return
    u.numpy()[:] = so.H0_inv_Gp.numpy() @ p.numpy() + so.H0_inv.numpy() @ h.numpy()
