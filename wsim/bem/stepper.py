"""Device side of the BEM time step: the operator set uploaded once, and the two dense passes.

``StepOperators`` holds, on one Warp device, what every step reads: H_k, G_k (k = 1..n_max),
the (3N, 6) blocks [D_k Q_k], H_0^-1 and H_0^-1 G' (paper Eq. 12) in the storage precision, plus
H_0^-1 [D_0 Q_0] and, built on first use, the error-correction pieces (``wsim.bem.correction``).
It is immutable and shared by every body built on the same operator set, device and backend.

Two backends compute the passes (``history`` and ``solve``):

* ``"warp"``: the kernels of ``wsim.kernels.bem_step`` (one block per row, vec4 loads, bandwidth
  bound). Rows are stored with a pitch padded to a multiple of 4 columns, vectors likewise;
* ``"blas"``: numpy matrix-vector products (CPU device only) on the host operator arrays
  themselves (no copy, pitch 3N).

``"auto"`` picks Warp on CUDA and BLAS on the CPU, where Warp's kernels run on one thread and
numpy's BLAS uses every core (``tools/bench_bem_step.py`` measures both: 7x on 2 cores).

With a ``CompressedHistory`` (``wsim.bem.compression``; built on the GPU or the host and kept in
the operator cache, ``compressed_history``) the history and the H_0^-1 h + H_0^-1 G' p products
run on the kept Haar coefficients instead (BLAS backend: scipy on the host; Warp backend:
``wsim.kernels.bem_compressed``, with the rings kept in the wavelet domain in the body's
``CompressedScratch``: a step transforms its two new vectors, ``ring_written``), and no dense
matrix is uploaded; the constraint solver reads the rows of H_0^-1 G' it needs
(``wsim.bem.constraints.response_rows``).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import warp as wp

from wsim.bem.correction import Correction, load_balance
from wsim.bem.factorization import cupy_module, on_stream
from wsim.bem.operators import PRECISIONS, BemOperators
from wsim.errors import InvalidParameter
from wsim.launch import concrete
from wsim.kernels import bem_compressed as kc
from wsim.kernels import bem_compressed_warps as kw
from wsim.kernels import bem_step as ks

BACKENDS = ("auto", "warp", "blas")
_VEC4 = {wp.float32: wp.vec4f, wp.float64: wp.vec4d}


@dataclass(frozen=True)
class StepOperators:
    """Per-device, per-backend operator arrays of the step (see module docstring).

    ``pitch`` is the stored row length (3N, or 3N rounded up to a multiple of 4 for Warp).
    """

    operators: BemOperators
    device: wp.Device
    backend: str
    dtype: Any
    pitch: int
    H: wp.array  # (n_max 3N, pitch): H_1..H_n_max one after the other (2-D: see ``kernels.bem_step``)
    G: wp.array
    DQ: wp.array  # (n_max, 3N, 6)
    H0_inv: wp.array  # (3N, pitch)
    H0_inv_Gp: wp.array
    E: np.ndarray  # (3N, 6) [H_0^-1 D_0, H_0^-1 Q_0], float64: re-solves for changed a, alpha
    vec4: dict[str, wp.array]  # Warp backend: vec4 views of H, G, H0_inv, H0_inv_Gp
    compressed: Any = None  # a CompressedHistory: H, G, H0_inv are then empty placeholders
    packed: Any = None  # Warp backend with compression: the device layout (``_compressed_step_operators``)
    # node -> its three rows of the compressed H_0^-1 G', rebuilt once (``constraints.response_rows``):
    # a memo of a constant, so sharing it changes no result
    W_rows: dict = field(default_factory=dict, compare=False, repr=False)
    # the last node set's (W rows, row_of) on the device: a body in steady contact asks for the same
    # nodes solve after solve (the response matrix, then the point displacements)
    W_uploaded: dict = field(default_factory=dict, compare=False, repr=False)

    @cached_property
    def correction(self) -> Correction:
        """Error-correction pieces, built on first use (bodies without the correction never pay)."""
        return Correction.from_operators(self.operators, self.E)

    @cached_property
    def load_balance(self) -> np.ndarray:
        """(6, 3N) ``correction.load_balance``, built when a body on this set first takes a load
        (a dense solve with the summed history H_s: bodies without loads never pay), on the GPU
        through CuPy where the set's device is one and CuPy works there."""
        if self.device.is_cuda and _cupy_works(self.device):
            cp = cupy_module()
            with cp.cuda.Device(self.device.ordinal):
                return load_balance(self.operators, self.correction, cp)
        return load_balance(self.operators, self.correction)

    @cached_property
    def device_correction(self) -> Any:
        """The correction's pieces on the device (``wsim.bem.device_step``), built on the first
        step a body keeps on the device."""
        from wsim.bem.device_step import DeviceCorrection  # it launches the passes of this module

        return DeviceCorrection.build(self.correction, self.device)

    @cached_property
    def many_backend(self) -> str:
        """How the passes of several bodies on this set run together (``history_many``,
        ``solve_many``): "blas" (numpy matrix-matrix products on the host arrays), "cupy" (cuBLAS
        through CuPy, the ``gpu`` extra, on Warp's stream) or "each" (the one-body passes per body:
        compressed sets, CUDA without CuPy, and Warp kernels on the CPU)."""
        if self.compressed is not None or self.packed is not None:
            return "each"
        if self.backend == "blas":
            return "blas"
        if self.device.is_cuda and _cupy_works(self.device):
            return "cupy"
        return "each"

    @cached_property
    def node_rows(self) -> wp.array:
        """Node -> its row block in H0_inv_Gp (the identity: all rows stored; the constraint
        kernels take a map because a compressed set gives them only the rows they need)."""
        return wp.array(np.arange(self.operators.n_nodes, dtype=np.int32), dtype=wp.int32, device=self.device)

    @property
    def n_max(self) -> int:
        return self.operators.n_max

    @property
    def size(self) -> int:
        """3N, the length of u and p."""
        return 3 * self.operators.n_nodes

    def _stored_bytes(self, part: str) -> int:
        """Bytes of the compressed ``part`` ("history" or "solve": H_0^-1 and H_0^-1 G') as stored
        for the passes: the packed device arrays (Warp) or the host CSR matrices (BLAS)."""
        if self.packed is not None:
            extra = sum(a.capacity for a in self.packed["solve_h"][1:]) if part == "solve" else 0
            return int(sum(a.capacity for a in self.packed[part]) + extra)
        c = self.compressed
        mats = (*c.H, *c.G) if part == "history" else (c.H0_inv, c.H0_inv_Gp)
        return int(sum(m.nbytes for m in mats))

    @property
    def history_matrix_bytes(self) -> int:
        """Bytes of the 2 n_max history matrices H_k, G_k as stored (dense, or compressed with their
        index arrays)."""
        if self.compressed is not None:
            return self._stored_bytes("history")
        return int(self.H.capacity + self.G.capacity)

    @property
    def history_bytes(self) -> int:
        """Bytes the history pass reads: the history matrices and the (dense, 3N x 6) [D_k Q_k] blocks."""
        return self.history_matrix_bytes + int(self.DQ.capacity)

    @property
    def matrix_bytes(self) -> int:
        """Bytes a step with tractions reads: 2 n_max + 2 dense (or compressed) matrices and the small blocks."""
        if self.compressed is not None:
            return self.history_bytes + self._stored_bytes("solve")
        return self.history_bytes + int(self.H0_inv.capacity + self.H0_inv_Gp.capacity)

    def vectors(self, rows: int | None = None) -> wp.array:
        """Zeroed storage for ``rows`` vectors (or one) of length ``pitch`` on the device."""
        shape = self.pitch if rows is None else (rows, self.pitch)
        return wp.zeros(shape, dtype=self.dtype, device=self.device)


def vec4_view(a: wp.array) -> wp.array:
    """The same memory as ``a`` (last axis a multiple of 4) seen as vec4 elements."""
    shape = (*a.shape[:-1], a.shape[-1] // 4)
    return wp.array(ptr=a.ptr, dtype=_VEC4[a.dtype], shape=shape, device=a.device, copy=False)


def _upload_padded(a: np.ndarray, dtype: Any, wdt: Any, pitch: int, device: wp.Device) -> wp.array:
    """(..., R, C) host matrix(es) into a (M R, pitch) device array (M matrices one after the other:
    2-D, see ``kernels.bem_step``), zero padded, staged one matrix at a time."""
    out = wp.zeros((int(np.prod(a.shape[:-1])), pitch), dtype=wdt, device=device)
    mats = a.reshape(-1, *a.shape[-2:])
    rows = mats.shape[1]
    staging = np.zeros((rows, pitch), dtype=dtype)
    for m, mat in enumerate(mats):
        staging[:, : a.shape[-1]] = mat
        wp.copy(out, wp.array(staging, dtype=wdt, device="cpu", copy=False), dest_offset=m * rows * pitch)
        wp.synchronize_device(device)  # the staging buffer is reused
    return out


# One upload per (operator set, device, backend): bodies sharing a set share device memory too.
# Entries disappear with the last body that holds them; nothing here changes results.
_SHARED: weakref.WeakValueDictionary = weakref.WeakValueDictionary()


def step_operators(ops: BemOperators, device: wp.Device, backend: str,
                   compression: tuple[str, float] | None = None, cache: Any = True) -> StepOperators:
    """The (shared) device copy of ``ops`` for ``device`` and a resolved ``backend``; with
    ``compression`` (("ratio", CR) or ("error", eps)) the history matrices compressed
    (``compressed_history``: built on the GPU or the host, kept in the operator ``cache``)."""
    key = (ops.key or f"id{id(ops)}", device.alias, backend, compression)  # the content key covers precision and inputs
    found = _SHARED.get(key)
    if found is not None:
        return found
    if compression is not None:
        return _compressed_step_operators(ops, device, backend, compression, key, cache)
    dtype = PRECISIONS[ops.precision]
    wdt = wp.float32 if dtype == np.float32 else wp.float64
    n3 = 3 * ops.n_nodes
    dq = np.concatenate([ops.D[1:], ops.Q[1:]], axis=2).astype(dtype)
    if backend == "warp":
        pitch = -(-n3 // 4) * 4

        def upload(a: np.ndarray) -> wp.array:
            return _upload_padded(a, dtype, wdt, pitch, device)
    else:  # BLAS on the CPU: the Warp arrays alias the host operators (no second copy of gigabytes)
        pitch = n3

        def upload(a: np.ndarray) -> wp.array:
            a = np.ascontiguousarray(a, dtype=dtype)
            return wp.array(a.reshape(-1, a.shape[-1]), dtype=wdt, device=device, copy=False)

    # H_k, G_k stacked 2-D: Warp's 32-bit strides would overflow a 3-D stack past 2 GiB a matrix
    mats = {"H": upload(ops.H[1:]), "G": upload(ops.G[1:]), "H0_inv": upload(ops.H0_inv), "H0_inv_Gp": upload(ops.H0_inv_Gp)}
    out = StepOperators(
        operators=ops, device=device, backend=backend, dtype=wdt, pitch=pitch, DQ=wp.array(dq, dtype=wdt, device=device),
        E=ops.solve_H0(np.hstack([ops.D[0], ops.Q[0]])), vec4={k: vec4_view(v) for k, v in mats.items()} if backend == "warp" else {},
        **mats,
    )
    _SHARED[key] = out
    return out


#: bump when the stored compressed arrays or their meaning change
COMPRESSED_FORMAT = 4  # 2: H_0^-1 G' compressed too; 3: compression_error tuned on tuning_fields; 4: G'_k stored


def _compressed_arrays(ch: Any, dtype: Any) -> dict[str, np.ndarray]:
    """A ``CompressedHistory`` as cache datasets: the permutation and, per matrix, its CSR (values
    in the operators' precision) and (norm, dropped)."""
    out: dict[str, np.ndarray] = {"perm": ch.perm, "spec": np.frombuffer(ch.spec.encode(), dtype=np.uint8)}
    for name, m in zip(_compressed_names(len(ch.H)), ch.matrices):
        out[f"{name}_indptr"] = m.C.indptr.astype(np.int64)
        out[f"{name}_indices"] = m.C.indices.astype(np.int32)
        out[f"{name}_data"] = m.C.data.astype(dtype)
        out[f"{name}_norms"] = np.array([m.norm, m.dropped])
    return out


def _compressed_names(n_max: int) -> list[str]:
    return [*(f"H{k}" for k in range(1, n_max + 1)), *(f"G{k}" for k in range(1, n_max + 1)), "H0_inv", "H0_inv_Gp"]


def _compressed_from_arrays(a: dict[str, np.ndarray], n: int, n_max: int) -> Any:
    import scipy.sparse as sp

    from wsim.bem.compression import CompressedHistory, CompressedMatrix, _pow2

    size = _pow2(n)
    perm = np.asarray(a["perm"], dtype=np.int64)
    mats = []
    for name in _compressed_names(n_max):
        C = sp.csr_matrix((a[f"{name}_data"].astype(np.float64), a[f"{name}_indices"], a[f"{name}_indptr"]),
                          shape=(size, size))
        norm, dropped = a[f"{name}_norms"].tolist()
        mats.append(CompressedMatrix(n=n, perm=perm, C=C, norm=norm, dropped=dropped))
    return CompressedHistory(perm=perm, H=tuple(mats[:n_max]), G=tuple(mats[n_max: 2 * n_max]), H0_inv=mats[-2],
                             H0_inv_Gp=mats[-1],
                             spec=bytes(a["spec"]).decode())


def compressed_history(ops: BemOperators, compression: tuple[str, float], device: wp.Device,
                       cache: Any = True) -> Any:
    """``compress_history`` of ``ops`` (built on ``device`` when it is a GPU, else on the host with
    numpy), through the operator cache (``cache``: True, False or an ``OperatorCache``) when the
    operator set has a content key."""
    from wsim.bem.compression import compress_history
    from wsim.cache import OperatorCache

    how, value = compression
    dtype = PRECISIONS[ops.precision]

    def build() -> dict[str, np.ndarray]:
        ch = compress_history(ops, ratio=value if how == "ratio" else None, error=value if how == "error" else None,
                              device=device if device.is_cuda else None)
        return _compressed_arrays(ch, dtype)

    if cache is False or not ops.key:
        arrays = build()
    else:
        store = cache if isinstance(cache, OperatorCache) else OperatorCache()
        arrays = store.get_or_build("bem_compressed", arrays={}, version=COMPRESSED_FORMAT, build=build,
                                    params={"operators": ops.key, "how": how, "value": float(value)},
                                    meta={"n_nodes": ops.n_nodes, "n_max": ops.n_max, "compression": f"{how}={value:g}"})
    return _compressed_from_arrays(arrays, 3 * ops.n_nodes, ops.n_max)


def _compressed_step_operators(ops: BemOperators, device: wp.Device, backend: str, compression: tuple[str, float],
                               key: tuple, cache: Any) -> StepOperators:
    """H_k, G_k, H_0^-1, H_0^-1 G' compressed (``CompressedHistory``): on the host for the BLAS
    backend, packed for ``wsim.kernels.bem_compressed`` for the Warp backend (float32 operators):
    "history" (the 2 n_max history matrices) and "solve" (H_0^-1 then H_0^-1 G', against h and p;
    ``solve_h`` the first matrix's items alone, for a step without tractions)."""
    from wsim.bem.compression import pack_rows, work_items

    if backend == "warp" and ops.precision != "float32":
        raise InvalidParameter("compressed operators on the Warp backend need float32 operators (precision='float32')")
    ch = compressed_history(ops, compression, device, cache)
    dtype = PRECISIONS[ops.precision]
    wdt = wp.float32 if dtype == np.float32 else wp.float64
    pitch = -(-3 * ops.n_nodes // 4) * 4 if backend == "warp" else 3 * ops.n_nodes
    packed = None
    if backend == "warp":
        def dev(parts, types) -> tuple[wp.array, ...]:
            return tuple(wp.array(a, dtype=t, device=device) for a, t in zip(parts, types))

        def arrays(mats) -> tuple[tuple[wp.array, ...], np.ndarray]:
            """(cols, vals, item_mat, item_start, item_len, row_items, row_list) on the device, and the bounds."""
            b, c, v = pack_rows(mats)
            parts = (c.reshape(-1, 4), v.reshape(-1, 4), *work_items(b, kc.CHUNK))  # quads of four
            return dev(parts, (kc.vec4us, wp.vec4f, wp.uint8, wp.int64, wp.uint16, wp.int64, wp.int32)), b

        solve, b = arrays([ch.H0_inv, ch.H0_inv_Gp])
        first = work_items(b[:, :2], kc.CHUNK)  # H_0^-1's items are the first ones (matrix by matrix)
        packed = {"perm": wp.array(ch.perm.astype(np.int32), dtype=wp.int32, device=device), "size": ch.size,
                  "history": arrays([*ch.H, *ch.G])[0], "solve": solve,
                  "solve_h": (len(first[0]), *dev(first[3:], (wp.int64, wp.int32))),
                  "AC": wp.array(np.vstack([ops.A, ops.C]).astype(np.float32), dtype=wp.float32, device=device)}
    empty = wp.zeros((0, pitch), dtype=wdt, device=device)
    out = StepOperators(
        operators=ops, device=device, backend=backend, dtype=wdt, pitch=pitch, H=empty, G=empty,
        DQ=wp.array(np.concatenate([ops.D[1:], ops.Q[1:]], axis=2).astype(dtype), dtype=wdt, device=device),
        H0_inv=empty, H0_inv_Gp=empty,
        E=ops.solve_H0(np.hstack([ops.D[0], ops.Q[0]])), vec4={}, compressed=ch, packed=packed)
    _SHARED[key] = out
    return out


class CompressedScratch:
    """One body's arrays for the compressed Warp passes: the rings in the wavelet domain
    (``hat``: rows 0..n_max-1 W P u, rows n_max.. W P p, slot m holding step m mod n_max), kept
    current by ``ring_written`` after each step (two vectors transformed) and rebuilt whole when
    ``stale`` (a new or restored state), and the work arrays."""

    def __init__(self, so: StepOperators) -> None:
        size, n_max, d = so.packed["size"], so.n_max, so.device
        self.sums = pass_buffers(2 * n_max, size, d)
        self.hat = wp.zeros((2 * n_max, size), dtype=wp.float32, device=d)
        self.stale = True
        self.one_hat = wp.zeros((2, size), dtype=wp.float32, device=d)  # h and p of a solve
        self.B_fold = wp.zeros((n_max, 6), dtype=wp.float32, device=d)  # B - [A; C] p, the ring G'_k needs
        self.y_hat = wp.zeros((1, size), dtype=wp.float32, device=d)
        items = max(len(so.packed["history"][2]), len(so.packed["solve"][2]))
        warps = int(kw.WARPS)
        self.partial = wp.zeros(-(-items // warps) * warps, dtype=wp.float32, device=d)  # whole blocks of items


def _scalar(a: wp.array, so: StepOperators) -> wp.array:
    """The scalar (float) view of a vec4 view or a plain array: same memory, rows of ``pitch``."""
    n = a.shape[-1] * (4 if a.dtype in _VEC4.values() else 1)
    return wp.array(ptr=a.ptr, dtype=so.dtype, shape=(*a.shape[:-1], n), device=a.device, copy=False)


def pass_buffers(rows: int, size: int, device: wp.Device) -> list[wp.array]:
    """The block-sum arrays of the passes of ``haar_rows`` for up to ``rows`` rows of ``size``."""
    out, count = [], size
    while count > 1:
        count //= min(kc.PASS_GROUP, count)
        out.append(wp.zeros((rows, count), dtype=wp.float64, device=device))
    return out


def haar_rows(sources: list[tuple[wp.array, int, int]], perm: wp.array, size: int, sums: list[wp.array],
              out: wp.array, row0: int = 0, row_stride: int = 1) -> None:
    """W P of rows: ``sources`` lists one or two (float32 array (rows, >= len(perm)), first row,
    rows); those rows, reordered by ``perm`` (new -> old) and zero padded to ``size`` (a power of
    two), go in order to out[row0 + r row_stride] (float32): one ``haar_first_pass`` launch for
    both sources, then ``haar_pass`` launches (log2(size) / 4 in all); ``sums`` from
    ``pass_buffers``."""
    if not 1 <= len(sources) <= 2:
        raise ValueError(f"haar_rows: one or two sources, got {len(sources)}")
    (src_a, first_a, rows_a), (src_b, first_b, rows_b) = sources[0], sources[-1]
    total = rows_a + (rows_b if len(sources) == 2 else 0)
    group = min(kc.PASS_GROUP, size)
    wp.launch(kc.haar_first_pass, dim=(total, size // group), device=out.device,
              inputs=[src_a, first_a, rows_a, src_b, first_b, perm, group, size, row0, row_stride],
              outputs=[out, sums[0][:total]])
    count, k = size // group, 0
    while count > 1:
        group = min(kc.PASS_GROUP, count)
        wp.launch(kc.haar_pass, dim=(total, count // group), inputs=[sums[k][:total], group, size, row0, row_stride],
                  outputs=[out, sums[k + 1][:total]], device=out.device)
        count, k = count // group, k + 1


def _transform(so: StepOperators, sources: list[tuple[wp.array, int, int]], sc: CompressedScratch,
               out: wp.array, row0: int, row_stride: int) -> None:
    haar_rows(sources, so.packed["perm"], so.packed["size"], sc.sums, out, row0, row_stride)


def ring_written(so: StepOperators, U: wp.array, P: wp.array, slot: int, scratch: CompressedScratch | None,
                 b_fold: wp.array | None) -> None:
    """Ring slot ``slot`` of U and P (vec4 views or plain) now holds the step's u and p: for a
    compressed Warp body, their wavelet images enter the wavelet-domain rings (two vectors), and
    ``b_fold`` ((6,) float32, host or device: the step's [a - g', alpha] - [A p, C p], which the
    body knows without a reduction over p) the folded frame-term ring."""
    if scratch is None or scratch.stale:
        return  # nothing kept in the wavelet domain, or rebuilt whole at the next history
    if b_fold is None:
        raise ValueError("ring_written: a compressed Warp body's step needs its folded frame terms (b_fold)")
    _transform(so, [(_scalar(U, so), slot, 1), (_scalar(P, so), slot, 1)], scratch, scratch.hat, slot, so.n_max)
    wp.copy(scratch.B_fold, b_fold, dest_offset=slot * 6, count=6)


def _sparse_sum(so: StepOperators, part: str, X: wp.array, n_max: int, step: int, sc: CompressedScratch,
                items: int | None = None, rows: tuple[wp.array, wp.array] | None = None) -> None:
    """sc.y_hat = the packed ``part``'s product with X (``chunk_sums`` then ``row_sums``); ``items``
    and ``rows`` (row_items, row_list) restrict it to the first matrices' items."""
    cols, vals, item_mat, item_start, item_len, row_items, row_list = so.packed[part]
    n_items = len(item_mat) if items is None else items
    row_items, row_list = (row_items, row_list) if rows is None else rows
    args = [item_mat, item_start, item_len, cols, vals, X, n_max, step, sc.partial]
    if so.device.is_cuda:
        warps = int(kw.WARPS)
        wp.launch_tiled(kw.chunk_sums_warps, dim=-(-n_items // warps), block_dim=32 * warps,
                        device=so.device, inputs=args)
    else:
        wp.launch_tiled(kc.chunk_sums, dim=n_items, block_dim=int(kc.SPMV_BLOCK), device=so.device, inputs=args)
    wp.launch_tiled(kc.row_sums, dim=so.packed["size"], block_dim=int(kc.SPMV_BLOCK), device=so.device,
                    inputs=[row_items, row_list, sc.partial, sc.y_hat])


def _compressed_history(so: StepOperators, U: wp.array, P: wp.array, B: wp.array, step: int, h: wp.array,
                        sc: CompressedScratch) -> None:
    n_max = so.n_max
    if sc.stale:  # the whole rings, once
        _transform(so, [(_scalar(U, so), 0, n_max), (_scalar(P, so), 0, n_max)], sc, sc.hat, 0, 1)
        # the folded frame terms of every row, from the rings (``compression.rigid_fold``)
        wp.launch_tiled(kc.rigid_fold, dim=(n_max, 6), block_dim=int(kc.FOLD_BLOCK), device=so.device,
                        inputs=[so.packed["AC"], _scalar(P, so), B, 0, so.size, sc.B_fold])
        sc.stale = False
    _sparse_sum(so, "history", sc.hat, n_max, step, sc)
    wp.launch(kc.inverse_history, dim=so.size, inputs=[sc.y_hat, so.packed["perm"], so.DQ, sc.B_fold, step,
                                                       _scalar(h, so)], device=so.device)


def _compressed_solve(so: StepOperators, p: wp.array | None, h: wp.array, u: wp.array, sc: CompressedScratch) -> None:
    """u = H_0^-1 h + H_0^-1 G' p on the "solve" pack: h (and p) transformed in one launch, the
    kept coefficients of both summed at once (``chunk_sums`` with n_max = 0: matrix j against row j
    of the transformed pair), one inverse transform. Without p only H_0^-1's items run."""
    def row(a: wp.array) -> tuple[wp.array, int, int]:
        a = _scalar(a, so)
        return wp.array(ptr=a.ptr, dtype=so.dtype, shape=(1, so.pitch), device=so.device, copy=False), 0, 1

    _transform(so, [row(h)] if p is None else [row(h), row(p)], sc, sc.one_hat, 0, 1)
    if p is None:
        n0, row_items, row_list = so.packed["solve_h"]
        _sparse_sum(so, "solve", sc.one_hat, 0, 0, sc, n0, (row_items, row_list))
    else:
        _sparse_sum(so, "solve", sc.one_hat, 0, 0, sc)
    wp.launch(kc.inverse_set, dim=so.size, inputs=[sc.y_hat, so.packed["perm"], _scalar(u, so)], device=so.device)


def resolve_backend(backend: str, device: wp.Device) -> str:
    if backend not in BACKENDS:
        raise InvalidParameter(f"matvec = {backend!r} must be one of {', '.join(BACKENDS)}")
    if backend == "auto":
        return "warp" if device.is_cuda else "blas"
    if backend == "blas" and not device.is_cpu:
        raise InvalidParameter("matvec = 'blas' runs on the CPU device only (use 'warp' or 'auto' on CUDA)")
    return backend


def history(so: StepOperators, U: wp.array, P: wp.array, B: wp.array, step: int, h: wp.array,
            scratch: CompressedScratch | None = None) -> None:
    """h_n of Eq. (9) into ``h`` (ring row m holds step m mod n_max). For the Warp backend U and P
    are the vec4 views of the rings (``vec4_view``); compressed operators on it need the body's
    ``scratch``."""
    if so.packed is not None:
        _compressed_history(so, U, P, B, step, h, scratch)
        return
    if so.backend == "warp":
        V, S = _VEC4[so.dtype], so.dtype
        kernel = concrete(ks.history_matvec, H=(2, V), G=(2, V), U=(2, V), P=(2, V), DQ=(3, S), B=(2, S), h=(1, S))
        wp.launch_tiled(kernel, dim=so.size, block_dim=int(ks.MATVEC_BLOCK), device=so.device,
                        inputs=[so.vec4["H"], so.vec4["G"], U, P, so.DQ, B, step, h])
        return
    DQ = so.DQ.numpy()
    Un, Pn, Bn = U.numpy(), P.numpy(), B.numpy()
    n_max = so.n_max
    if so.compressed is not None:  # G'_k stored: the frame terms take the folded ring
        from wsim.bem.compression import rigid_fold

        out = so.compressed.history(Un, Pn, step)
        Bf = rigid_fold(so.operators, Bn, Pn)
        for k in range(1, n_max + 1):
            out += DQ[k - 1] @ Bf[(step - k) % n_max]
        h.numpy()[: so.size] = out
        return
    H, G = (a.numpy().reshape(n_max, so.size, so.pitch) for a in (so.H, so.G))
    out = np.zeros(so.size, dtype=Un.dtype)
    for k in range(1, n_max + 1):
        s = (step - k) % n_max
        out += G[k - 1] @ Pn[s]
        out -= H[k - 1] @ Un[s]
        out += DQ[k - 1] @ Bn[s]
    h.numpy()[:] = out


def solve(so: StepOperators, p: wp.array | None, h: wp.array, u: wp.array,
          scratch: CompressedScratch | None = None) -> None:
    """u_n = H_0^-1 G' p_n + H_0^-1 h_n (Eq. 12) into ``u``; ``p=None`` means p_n = 0. For the Warp
    backend p and h are vec4 views."""
    if so.packed is not None:
        _compressed_solve(so, p, h, u, scratch)
        return
    if so.backend == "warp":
        V = _VEC4[so.dtype]
        kernel = concrete(ks.solve_matvec, H0_inv_Gp=(2, V), H0_inv=(2, V), p=(1, V), h=(1, V), u=(1, so.dtype))
        wp.launch_tiled(kernel, dim=so.size, block_dim=int(ks.MATVEC_BLOCK), device=so.device,
                        inputs=[so.vec4["H0_inv_Gp"], so.vec4["H0_inv"], h if p is None else p, h, int(p is not None), u])
        return
    if so.compressed is not None:
        out = so.compressed.H0_inv.matvec(h.numpy()[: so.size])
        if p is not None:
            out += so.compressed.H0_inv_Gp.matvec(p.numpy()[: so.size])
    else:
        out = so.H0_inv.numpy() @ h.numpy()
        if p is not None:
            out += so.H0_inv_Gp.numpy() @ p.numpy()
    u.numpy()[:] = out


def _cupy_works(device: wp.Device) -> bool:
    """Whether CuPy imports and runs a product on ``device`` (a wheel built for another CUDA
    imports and then fails at its first kernel: the passes then stay per body)."""
    cp = cupy_module()
    if cp is None:
        return False
    try:
        with cp.cuda.Device(device.ordinal):
            a = cp.ones((2, 2), dtype=cp.float32)
            return bool(float((a @ a).sum()) == 8.0)
    except Exception:
        return False


def _slots(steps: np.ndarray, n_max: int) -> np.ndarray:
    """(K, n_max): ring row of step n - k (k = 1..n_max) for each instance's step n."""
    return (np.asarray(steps, dtype=np.int64)[:, None] - np.arange(1, n_max + 1)[None, :]) % n_max


def history_many(so: StepOperators, U: wp.array, P: wp.array, B: wp.array, steps: np.ndarray, h: wp.array) -> None:
    """``history`` for K bodies on one operator set at once (``so.many_backend`` "blas" or "cupy"):
    U, P (K, n_max, pitch) and B (K, n_max, 6) hold the bodies' rings one after the other, steps
    (K,) each body's step n, h (K, pitch) receives the h_n. Each H_k, G_k is read once for all K
    (a matrix-matrix product, K columns) instead of once per body."""
    n3, n_max = so.size, so.n_max
    S = _slots(steps, n_max)
    K = S.shape[0]
    if so.many_backend == "blas":
        Un, Pn, Bn = U.numpy(), P.numpy(), B.numpy()
        H, G = (a.numpy().reshape(n_max, n3, so.pitch) for a in (so.H, so.G))
        DQ = so.DQ.numpy()
        rows = np.arange(K)
        out = np.zeros((K, n3), dtype=Un.dtype)
        for k in range(1, n_max + 1):
            s = S[:, k - 1]
            out += Pn[rows, s] @ G[k - 1].T
            out -= Un[rows, s] @ H[k - 1].T
            out += Bn[rows, s] @ DQ[k - 1].T
        h.numpy()[:, :n3] = out
        return
    cp = cupy_module()
    with on_stream(cp, so.device.ordinal, wp.get_stream(so.device).cuda_stream):
        H, G = (cp.asarray(a).reshape(n_max, n3, so.pitch) for a in (so.H, so.G))
        DQ = cp.asarray(so.DQ)
        Uc, Pc, Bc = cp.asarray(U), cp.asarray(P), cp.asarray(B)
        rows = cp.arange(K)[:, None]
        Sc = cp.asarray(S)
        # (n_max, K, .) gathers of the rows each k reads: small copies next to the matrices
        Ug, Pg, Bg = (cp.ascontiguousarray(a[rows, Sc].transpose(1, 0, 2)) for a in (Uc, Pc, Bc))
        out = cp.zeros((K, n3), dtype=Uc.dtype)
        tmp = cp.empty_like(out)
        for k in range(n_max):  # 2-D products with the transposed operator: cuBLAS reads it in place
            out += cp.matmul(Pg[k], G[k].T, out=tmp)
            out -= cp.matmul(Ug[k], H[k].T, out=tmp)
            out += cp.matmul(Bg[k], DQ[k].T, out=tmp)
        cp.asarray(h)[:, :n3] = out


def solve_many(so: StepOperators, p: wp.array | None, h: wp.array, u: wp.array) -> None:
    """``solve`` for K bodies at once: u (K, pitch) = p H_0^-T G'^T + h H_0^-T row by row, i.e.
    u_i = H_0^-1 G' p_i + H_0^-1 h_i (Eq. 12); p None: no body has tractions."""
    n3 = so.size
    if so.many_backend == "blas":
        out = h.numpy() @ so.H0_inv.numpy().T
        if p is not None:
            out += p.numpy() @ so.H0_inv_Gp.numpy().T
        u.numpy()[:, :n3] = out
        return
    cp = cupy_module()
    with on_stream(cp, so.device.ordinal, wp.get_stream(so.device).cuda_stream):
        out = cp.matmul(cp.asarray(h), cp.asarray(so.H0_inv).T)
        if p is not None:
            out += cp.matmul(cp.asarray(p), cp.asarray(so.H0_inv_Gp).T)
        cp.asarray(u)[:, :n3] = out
