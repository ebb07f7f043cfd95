"""Warp kernels of the BEM time step (paper Eqs. 9 and 12): the two dense matrix-vector passes.

Both are memory-bandwidth bound: every step reads 2 n_max + 2 dense 3N x 3N matrices once.
One block of ``MATVEC_BLOCK`` threads computes one output row: each thread strides over the
columns four at a time (vec4 loads; consecutive threads read consecutive 16-byte words, so every
load is coalesced and wide) and keeps one running sum; the block then reduces its partial sums
(``tile_sum``). Rows are stored with a pitch padded to a multiple of 4 columns (zeros), and the
vectors with the same zero padding. The kernels are generic over the storage precision:
float32 (default, half the bytes; vec4) or float64 (vec4d), partial sums in the storage type.

Launch with ``wp.launch_tiled(..., dim=rows, block_dim=MATVEC_BLOCK)``. The stride is read with
``wp.block_dim()``: on the CPU Warp runs a block as one thread, which then sums the whole row.
"""

from __future__ import annotations

from typing import Any

import warp as wp

MATVEC_BLOCK = wp.constant(256)


@wp.kernel
def history_matvec(
    H: wp.array2d(dtype=Any),
    G: wp.array2d(dtype=Any),
    U: wp.array2d(dtype=Any),
    P: wp.array2d(dtype=Any),
    DQ: wp.array3d(dtype=Any),
    B: wp.array2d(dtype=Any),
    step: int,
    h: wp.array(dtype=Any),
):
    """History term of Eq. (9) at step n = ``step``:

        h_n = sum_{k=1}^{n_max} ( -H_k u_{n-k} + G_k p_{n-k} + [D_k Q_k] [a - g', alpha]_{n-k} ).

    H, G (n_max 3N rows of vec4 columns) hold H_k, G_k (k = 1..n_max) one after the other: row
    (k - 1) 3N + i is row i of H_k. Two-dimensional on purpose: a Warp array's strides are 32-bit
    byte counts, and a (n_max, 3N, 3N) float32 stack's first stride passes 2 GiB at N ~ 7.7k. DQ[k-1]
    is the (3N, 6) block [D_k Q_k]. The ring buffers U, P (n_max, pitch / 4) and B (n_max, 6) hold
    step m in row m mod n_max.
    """
    row, lane = wp.tid()
    stride = wp.block_dim()
    n_max = U.shape[0]
    n = H.shape[0] // n_max
    cols = H.shape[1]
    acc = h.dtype(0.0)
    for k in range(1, n_max + 1):
        slot = (step - k) % n_max
        r = (k - 1) * n + row
        c = lane
        while c < cols:
            acc += wp.dot(G[r, c], P[slot, c]) - wp.dot(H[r, c], U[slot, c])
            c += stride
        j = lane
        while j < 6:
            acc += DQ[k - 1, row, j] * B[slot, j]
            j += stride
    total = wp.tile_sum(wp.tile(acc))
    wp.tile_store(h, total, offset=row)


@wp.kernel
def solve_matvec(
    H0_inv_Gp: wp.array2d(dtype=Any),
    H0_inv: wp.array2d(dtype=Any),
    p: wp.array(dtype=Any),
    h: wp.array(dtype=Any),
    with_p: int,
    u: wp.array(dtype=Any),
):
    """Displacement of Eq. (12): u_n = H_0^-1 G' p_n + H_0^-1 h_n (the first term only if ``with_p``:
    a step without tractions reads one matrix instead of two)."""
    row, lane = wp.tid()
    stride = wp.block_dim()
    cols = H0_inv.shape[1]
    acc = u.dtype(0.0)
    c = lane
    if with_p != 0:
        while c < cols:
            acc += wp.dot(H0_inv_Gp[row, c], p[c]) + wp.dot(H0_inv[row, c], h[c])
            c += stride
    else:
        while c < cols:
            acc += wp.dot(H0_inv[row, c], h[c])
            c += stride
    total = wp.tile_sum(wp.tile(acc))
    wp.tile_store(u, total, offset=row)


@wp.kernel
def write_ring_rows(
    src: wp.array2d(dtype=Any),
    rows: wp.array(dtype=wp.int32),
    slots: wp.array(dtype=wp.int32),
    ring: wp.array3d(dtype=Any),
):
    """ring[rows[i], slots[i], j] = src[rows[i], j]: the bodies of an instance set store their
    step's u, p or [a - g', alpha] (the rings of Eq. 9) in one launch (``wsim.bem.instances``).
    Launch with dim = (len(rows), src.shape[1])."""
    i, j = wp.tid()
    r = rows[i]
    ring[r, slots[i], j] = src[r, j]
