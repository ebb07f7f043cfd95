"""Kernels of the compressed BEM history (issue 20; ``wsim.bem.compression``).

The history h = sum_k G_k p_(n-k) - H_k u_(n-k) with every matrix stored as its kept Haar
coefficients C_k (A_k = P^T W^T C_k W P, W the orthonormal Haar transform over the padded size n,
P the v+c reordering) is computed in the wavelet domain: the ring holds W P u and W P p (each
vector transformed once, when it enters the ring), the kept coefficients of all 2 n_max matrices
are summed against them row by row, and one inverse transform brings h back.

* ``haar_coefficients``: the Haar coefficients of rows from their float64 inclusive prefix sums
  S (``wp.utils.array_scan`` over the rows laid end to end): the average is S(n) / sqrt(n), a
  detail of a block [a, a + m) is (2 S(a + m/2) - S(a) - S(a + m)) / sqrt(m); O(1) each.
* ``haar_inverse``: x_i = c_0 / sqrt(n) + sum over the log2(n) blocks holding i of
  +-c_block / sqrt(m) (+ in the block's first half).
* ``history_spmv``: one block of threads per output row; the row's kept coefficients of the
  2 n_max matrices (values float32, columns uint16: 6 bytes a coefficient, n <= 65536) are laid out
  per row as [H_1 | ... | H_n_max | G_1 | ... | G_n_max], ``bounds[row, j]`` the start of matrix j.
"""

from __future__ import annotations

import warp as wp

SPMV_BLOCK = wp.constant(128)


@wp.func
def _prefix(S: wp.array(dtype=wp.float64), base: int, i: int) -> wp.float64:
    """sum of the row's first i entries from the rows' joint inclusive prefix sums S."""
    before = wp.float64(0.0)
    if base > 0:
        before = S[base - 1]
    if i == 0:
        return wp.float64(0.0)
    return S[base + i - 1] - before


@wp.kernel
def haar_coefficients(S: wp.array(dtype=wp.float64), size: int, out: wp.array2d(dtype=wp.float32)):
    """out[r, c] = the c-th Haar coefficient (``wsim.bem.compression.haar`` layout) of row r of the
    rows whose joint inclusive prefix sums are S (rows of ``size`` entries, laid end to end)."""
    r, c = wp.tid()
    base = r * size
    if c == 0:
        out[r, c] = wp.float32(_prefix(S, base, size) / wp.sqrt(wp.float64(size)))
        return
    blocks = int(1)
    while blocks * 2 <= c:
        blocks *= 2
    m = size // blocks
    a = (c - blocks) * m
    val = wp.float64(2.0) * _prefix(S, base, a + m // 2) - _prefix(S, base, a) - _prefix(S, base, a + m)
    out[r, c] = wp.float32(val / wp.sqrt(wp.float64(m)))


@wp.kernel
def haar_inverse(C: wp.array2d(dtype=wp.float32), out: wp.array2d(dtype=wp.float32)):
    """out[r] = W^T C[r]: the inverse of ``haar_coefficients`` (``compression.inverse_haar``)."""
    r, i = wp.tid()
    size = C.shape[1]
    v = wp.float64(C[r, 0]) / wp.sqrt(wp.float64(size))
    m = int(size)
    while m > 1:
        idx = size // m + i // m
        d = wp.float64(C[r, idx]) / wp.sqrt(wp.float64(m))
        if (i % m) < m // 2:
            v += d
        else:
            v -= d
        m = m // 2
    out[r, i] = wp.float32(v)


@wp.kernel
def history_spmv(
    bounds: wp.array2d(dtype=wp.int64),
    cols: wp.array(dtype=wp.uint16),
    vals: wp.array(dtype=wp.float32),
    U_hat: wp.array2d(dtype=wp.float32),
    P_hat: wp.array2d(dtype=wp.float32),
    step: int,
    h_hat: wp.array2d(dtype=wp.float32),
):
    """h_hat[0, row] = sum_k (C_Gk W P p_(n-k))[row] - (C_Hk W P u_(n-k))[row] over the kept
    coefficients (the ring's row m holds step m mod n_max, transformed)."""
    row, lane = wp.tid()
    stride = wp.block_dim()
    n_max = U_hat.shape[0]
    acc = float(0.0)
    for j in range(2 * n_max):
        k = j % n_max + 1
        slot = (step - k) % n_max
        e = bounds[row, j] + wp.int64(lane)
        end = bounds[row, j + 1]
        part = float(0.0)
        while e < end:
            col = int(cols[e])
            if j < n_max:
                part += vals[e] * U_hat[slot, col]
            else:
                part += vals[e] * P_hat[slot, col]
            e += wp.int64(stride)
        if j < n_max:
            acc -= part
        else:
            acc += part
    total = wp.tile_sum(wp.tile(acc))
    wp.tile_store(h_hat[0], total, offset=row)


@wp.kernel
def gather_rows(src: wp.array2d(dtype=wp.float32), perm: wp.array(dtype=wp.int32), size: int,
                out: wp.array(dtype=wp.float64)):
    """out[r * size + i] = src[r, perm[i]] for i < len(perm), 0 past it: rows of the (pitched)
    ring or vector reordered and zero padded, laid end to end for one prefix scan."""
    r, i = wp.tid()
    v = wp.float64(0.0)
    if i < perm.shape[0]:
        v = wp.float64(src[r, perm[i]])
    out[r * size + i] = v


@wp.kernel
def rows_spmv(bounds: wp.array2d(dtype=wp.int64), cols: wp.array(dtype=wp.uint16), vals: wp.array(dtype=wp.float32),
              x_hat: wp.array2d(dtype=wp.float32), y_hat: wp.array2d(dtype=wp.float32)):
    """y_hat[0, row] = (C x_hat[0])[row] for one packed matrix C (``bounds[row, 0..1]``)."""
    row, lane = wp.tid()
    stride = wp.block_dim()
    acc = float(0.0)
    e = bounds[row, 0] + wp.int64(lane)
    end = bounds[row, 1]
    while e < end:
        acc += vals[e] * x_hat[0, int(cols[e])]
        e += wp.int64(stride)
    total = wp.tile_sum(wp.tile(acc))
    wp.tile_store(y_hat[0], total, offset=row)


@wp.kernel
def scatter_history(h_p: wp.array2d(dtype=wp.float32), perm: wp.array(dtype=wp.int32),
                    DQ: wp.array3d(dtype=wp.float32), B: wp.array2d(dtype=wp.float32), step: int,
                    h: wp.array(dtype=wp.float32)):
    """h[perm[i]] = h_p[0, i] + sum_k [D_k Q_k][perm[i]] . b_(n-k): the compressed history back in
    the original order with the (dense, 3N x 6) frame-acceleration terms of Eq. (9)."""
    i = wp.tid()
    row = perm[i]
    n_max = DQ.shape[0]
    acc = float(h_p[0, i])
    for k in range(1, n_max + 1):
        slot = (step - k) % n_max
        for j in range(6):
            acc += DQ[k - 1, row, j] * B[slot, j]
    h[row] = acc


@wp.kernel
def scatter_add(y_p: wp.array2d(dtype=wp.float32), perm: wp.array(dtype=wp.int32), y: wp.array(dtype=wp.float32)):
    """y[perm[i]] += y_p[0, i]."""
    i = wp.tid()
    y[perm[i]] = y[perm[i]] + y_p[0, i]
