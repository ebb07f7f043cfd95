"""The Haar coefficients of one BEM operator on a Warp device: the GPU build of the compressed
operators (issue 20; ``wsim.bem.compression`` holds the maths and the host build).

``DeviceCoefficients`` answers what ``compression.compress`` and ``compression.choose_keep`` ask
of a coefficient set without the padded matrix ever leaving the device:

* the transform C = W P A P^T W^T (``kernels/bem_compression_build.py``: the matrix permuted and zero
  padded in float64, then log2(size) Haar levels along the rows and as many along the columns,
  each level written to a work matrix and copied back over the part it changed);
* a *level* is a threshold: the coefficients kept are those with |C_ij| >= t, where t runs over
  the float32 numbers (level = FLOAT32_INF_BITS - the bits of t, so more level keeps more and
  bisecting over levels takes at most 31 passes); a count of the kept ones is one pass
  (``count_at_least``), so is the product of the kept ones with tuning vectors
  (``kept_products``; the dropped ones' product is C X less that), and so is the extraction
  into CSR (``compact_rows``, columns in order).

Memory: two float64 matrices of the padded size (2 x 8 size^2 bytes: 4.3 GB at size 16384) and
the input matrix; one instance serves every matrix of an operator set (``load`` reuses them).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp
import warp as wp

from wsim.bem.compression import CompressedMatrix, _pow2
from wsim.kernels import bem_compression_build as kc

FLOAT32_INF_BITS = 0x7F800000  # the bits of +inf: level 0 keeps nothing


def _threshold(level: int) -> float:
    """The float32 number whose bits are FLOAT32_INF_BITS - level (float64 for the kernels); the
    top level keeps everything (t = 0, zeros included)."""
    if level >= FLOAT32_INF_BITS:
        return 0.0
    return float(np.array([FLOAT32_INF_BITS - level], dtype=np.uint32).view(np.float32)[0])


class DeviceCoefficients:
    """C = W P A P^T W^T of one matrix at a time on a Warp device (see the module docstring)."""

    def __init__(self, n: int, device: Any) -> None:
        self.device = wp.get_device(device)
        self.n = int(n)
        self.size = _pow2(self.n)
        shape = (self.size, self.size)
        self.C = wp.zeros(shape, dtype=wp.float64, device=self.device)
        self._work = wp.zeros(shape, dtype=wp.float64, device=self.device)
        self._counts = wp.zeros(self.size, dtype=wp.int32, device=self.device)
        self._kept2 = wp.zeros(self.size, dtype=wp.float64, device=self.device)
        self.levels = (1, FLOAT32_INF_BITS)  # t = the smallest float32 > 0 ... t = 0: everything
        self._counted: dict[int, tuple[int, float]] = {}
        self._X: dict[int, tuple[wp.array, wp.array, np.ndarray, np.ndarray]] = {}
        self.perm = np.arange(self.n)
        self.norm = 0.0
        self.total2 = 0.0

    def load(self, A: np.ndarray, perm: np.ndarray) -> "DeviceCoefficients":
        """Transform A (n x n, float32 or float64, original order) under the new -> old ``perm``."""
        A = np.asarray(A)
        if A.shape != (self.n, self.n):
            raise ValueError(f"DeviceCoefficients: expected a {self.n} x {self.n} matrix, got {A.shape}")
        d = self.device
        self.perm = np.asarray(perm, dtype=np.int64)
        self._counted.clear()
        self._X.clear()
        src = wp.array(np.ascontiguousarray(A), device=d)
        wp.launch(kc.permute_pad, dim=(self.size, self.size), device=d,
                  inputs=[src, wp.array(self.perm.astype(np.int32), dtype=wp.int32, device=d), self.C])
        del src
        size = self.size
        m = size
        while m > 1:  # along the rows (pairs of columns), then along the columns (pairs of rows)
            wp.launch(kc.haar_level_cols, dim=(size, m // 2), inputs=[self.C, self._work, m // 2], device=d)
            wp.launch(kc.copy_corner, dim=(size, m), inputs=[self._work, self.C], device=d)
            m //= 2
        m = size
        while m > 1:
            wp.launch(kc.haar_level_rows, dim=(m // 2, size), inputs=[self.C, self._work, m // 2], device=d)
            wp.launch(kc.copy_corner, dim=(m, size), inputs=[self._work, self.C], device=d)
            m //= 2
        self.total2 = self._count(self.levels[1])[1]
        self.norm = float(np.sqrt(self.total2))  # ||C||_F = ||A||_F: W is orthonormal, the padding zero
        return self

    def _count_rows(self, level: int) -> tuple[int, float]:
        """Count the coefficients kept at ``level`` row by row (into ``_counts``, ``_kept2``);
        returns (their number, the sum of their squares)."""
        wp.launch_tiled(kc.count_at_least, dim=self.size, block_dim=int(kc.COUNT_BLOCK), device=self.device,
                        inputs=[self.C, wp.float64(_threshold(level)), self._counts, self._kept2])
        found = self._counted[level] = (int(self._counts.numpy().astype(np.int64).sum()), float(self._kept2.numpy().sum()))
        return found

    def _count(self, level: int) -> tuple[int, float]:
        """(coefficients kept at ``level``, the sum of their squares), counted once per level."""
        found = self._counted.get(level)
        return found if found is not None else self._count_rows(level)

    def level_for(self, keep: int) -> int:
        """The lowest level keeping at least ``keep`` coefficients (ties at the threshold all kept)."""
        lo, hi = self.levels
        while lo < hi:
            mid = (lo + hi) // 2
            if self._count(mid)[0] >= keep:
                hi = mid
            else:
                lo = mid + 1
        found = self._count(hi)[0]
        if found > 2 * keep + self.size:  # ties at one float32 threshold cannot explain this
            below = self._count(hi - 1)[0] if hi > 1 else 0
            raise RuntimeError(f"DeviceCoefficients.level_for: {keep} coefficients asked, level {hi} "
                               f"(threshold {_threshold(hi):.3e}) keeps {found} and the level below "
                               f"{below}; ||C||^2 = {self.total2:.3e} (non-finite coefficients?)")
        return hi

    def dropped(self, level: int, X_hat: np.ndarray) -> np.ndarray:
        """(C - C_kept) X_hat (size x k, float64) for the coefficients kept at ``level``: C X_hat
        (once per X_hat) less C_kept X_hat (``kept_products``: X read only where kept)."""
        found = self._X.get(id(X_hat))
        k = X_hat.shape[1]
        groups = -(-k // kc.PRODUCT_GROUP)
        if found is None or found[3] is not X_hat:  # the entry holds X_hat: its id is not reused while cached
            # the vectors in groups of 16 (zero padded), each group's rows contiguous: (groups, size) of vec16
            Xp = np.zeros((X_hat.shape[0], groups * kc.PRODUCT_GROUP))
            Xp[:, :k] = X_hat
            Xg = wp.array(np.ascontiguousarray(Xp.reshape(X_hat.shape[0], groups, kc.PRODUCT_GROUP).transpose(1, 0, 2)),
                          dtype=kc.vecgd, device=self.device)
            out = wp.zeros(Xp.shape, dtype=wp.float64, device=self.device)
            full = self._products(Xg, 0.0, out)[:, :k]
            found = self._X[id(X_hat)] = (Xg, out, full, X_hat)
        Xg, out, full, _ = found
        return full - self._products(Xg, _threshold(level), out)[:, :k]

    def _products(self, Xg: wp.array, t: float, out: wp.array) -> np.ndarray:
        wp.launch_tiled(kc.kept_products, dim=(self.size, Xg.shape[0]), block_dim=int(kc.COUNT_BLOCK),
                        device=self.device, inputs=[self.C, wp.float64(t), Xg, out])
        return np.array(out.numpy())  # a copy: on the CPU numpy() is a view of ``out``, which the next call overwrites

    def extract(self, level: int) -> CompressedMatrix:
        """The kept coefficients as a host ``CompressedMatrix`` (CSR, columns in order)."""
        t = _threshold(level)
        kept, kept2 = self._count_rows(level)  # the per-row counts too: the CSR's row starts
        indptr = np.concatenate([[0], np.cumsum(self._counts.numpy().astype(np.int64))])
        cols = wp.empty(max(kept, 1), dtype=wp.int32, device=self.device)
        vals = wp.empty(max(kept, 1), dtype=wp.float64, device=self.device)
        wp.launch(kc.compact_rows, dim=self.size, device=self.device,
                  inputs=[self.C, wp.float64(t), wp.array(indptr, dtype=wp.int64, device=self.device), cols, vals])
        C = sp.csr_matrix((vals.numpy()[:kept], cols.numpy()[:kept], indptr), shape=(self.size, self.size))
        dropped = float(np.sqrt(max(self.total2 - kept2, 0.0)))
        return CompressedMatrix(n=self.n, perm=self.perm, C=C, norm=self.norm, dropped=dropped)
