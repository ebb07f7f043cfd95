"""Kernels of the compressed BEM history (issue 20; ``wsim.bem.compression``).

The history h = sum_k G_k p_(n-k) - H_k u_(n-k) with every matrix stored as its kept Haar
coefficients C_k (A_k = P^T W^T C_k W P, W the orthonormal Haar transform over the padded size n,
P the v+c reordering) is computed in the wavelet domain: the ring holds W P u and W P p (each
vector transformed once, when it enters the ring), the kept coefficients of all 2 n_max matrices
are summed against them row by row, and one inverse transform brings h back.

* ``haar_first_pass`` + ``haar_pass``: the forward transform of rows in passes of 4 levels
  (log2(size) / 4 launches, 4 for a size of 16384): a thread loads 16 block sums of the previous
  pass (the reordered, zero-padded entries in the first, gathered in the kernel from one or two
  source arrays) into registers at once and combines them into their 15 detail coefficients and
  their sum, float64 throughout.
* the inverse transform, fused with the scatter back to the original order (``inverse_history``,
  ``inverse_set``): x_i = c_0 / sqrt(n) + sum over the log2(n) blocks holding i of
  +-c_block / sqrt(m) (+ in the block's first half).
* ``chunk_sums`` (CPU; on CUDA ``bem_compressed_warps.chunk_sums_warps``) + ``row_sums``: the sparse products,
  balanced. The kept coefficients of the 2 n_max history matrices (values float32, columns uint16:
  6 bytes a coefficient, n <= 65536) are laid out per row as [H_1 | ... | H_n_max | G_1 | ... |
  G_n_max] (``bounds[row, j]`` the start of matrix j; ``compression.pack_rows``), and each row's
  part of each matrix is cut into work items of at most CHUNK coefficients
  (``compression.work_items``): the coarse rows of a Haar basis keep thousands of coefficients,
  the fine ones tens, so one block per row would leave the GPU waiting on the few long rows. The
  items run matrix by matrix (the vector gathered from stays in L1); one warp an item writes its
  partial sum, one warp a row adds its items in a fixed order (no atomics: the same result every
  run).
"""

from __future__ import annotations

import warp as wp

SPMV_BLOCK = wp.constant(32)  # one warp an item (``chunk_sums``, ``row_sums``)
CHUNK = 1024  # coefficients per work item of ``chunk_sums`` (8 quads a lane): rows of any length, balanced
# (on an H100 at CR 32: 128 -> 124 us, 256 -> 80, 512 -> 77, 1024 -> 74 for the sum of the 2906-node cube)
PASS_GROUP = 16  # entries or block sums one thread of a transform pass combines (4 levels a pass: 32
# in registers made a two-vector transform slower on an H100, 68 us against 41, though one launch fewer)


vec16d = wp.types.vector(length=16, dtype=wp.float64)
vec4us = wp.types.vector(length=4, dtype=wp.uint16)  # four uint16 columns: one 8-byte load


@wp.func
def _pass_levels(x: vec16d, group: int, bs: int, size: int, base: int, out: wp.array2d(dtype=wp.float32),
                 dest: int) -> wp.float64:
    """The levels a pass spans, in registers: x holds ``group`` (<= 16) consecutive block sums of
    ``bs`` entries each, starting at block ``base``. A block of width w sums (m = bs w entries) at
    index b has the detail (sum of its first half - sum of its second half) / sqrt(m), at position
    size / m + b of out[dest]. Returns the group's sum."""
    width = int(2)
    for level in range(4):
        n_blocks = group // width
        for b in range(8):
            if b < n_blocks:
                first = x[2 * b]
                second = x[2 * b + 1]
                m = bs * width
                out[dest, size // m + base // width + b] = wp.float32((first - second) / wp.sqrt(wp.float64(m)))
                x[b] = first + second
        width *= 2
    return x[0]


@wp.kernel
def haar_first_pass(src_a: wp.array2d(dtype=wp.float32), row_a: int, rows_a: int,
                    src_b: wp.array2d(dtype=wp.float32), row_b: int, perm: wp.array(dtype=wp.int32), group: int,
                    size: int, out_row0: int, out_row_stride: int,
                    out: wp.array2d(dtype=wp.float32), sums: wp.array2d(dtype=wp.float64)):
    """The first pass of the forward transform (``wsim.bem.compression.haar`` layout) of rows
    reordered by ``perm`` and zero padded to ``size``: rows r < rows_a are src_a[row_a + r], the
    others src_b[row_b + r - rows_a] (a step's u and p in one launch). Thread (r, g) loads its
    ``group`` (16) entries x_i = src[.., perm[i]] (i from g group; 0 past len(perm)) into
    registers at once, writes the detail coefficients of the 4 finest levels (``_pass_levels``)
    to out[out_row0 + r out_row_stride] and the group's sum to sums[r, g] for the next pass
    (``haar_pass``). Float64 sums."""
    r, g = wp.tid()
    base = g * group
    n = perm.shape[0]
    x = vec16d()
    for i in range(16):
        if i < group and base + i < n:
            if r < rows_a:
                x[i] = wp.float64(src_a[row_a + r, perm[base + i]])
            else:
                x[i] = wp.float64(src_b[row_b + r - rows_a, perm[base + i]])
    total = _pass_levels(x, group, 1, size, base, out, out_row0 + r * out_row_stride)
    sums[r, g] = total
    if group == size:
        out[out_row0 + r * out_row_stride, 0] = wp.float32(total / wp.sqrt(wp.float64(size)))


@wp.kernel
def haar_pass(src: wp.array2d(dtype=wp.float64), group: int, size: int, out_row0: int, out_row_stride: int,
              out: wp.array2d(dtype=wp.float32), sums: wp.array2d(dtype=wp.float64)):
    """A later pass of the forward transform: src[r] holds the sums of consecutive blocks of
    size / count entries (count = src.shape[1]); thread (r, g) combines the ``group`` (<= 16) sums
    at g group into the detail coefficients of the levels they span and their sum (sums[r, g]);
    the last pass (one group) writes the average, sum / sqrt(size)."""
    r, g = wp.tid()
    count = src.shape[1]
    base = g * group
    x = vec16d()
    for i in range(16):
        if i < group:
            x[i] = src[r, base + i]
    total = _pass_levels(x, group, size // count, size, base, out, out_row0 + r * out_row_stride)
    sums[r, g] = total
    if group == count:
        out[out_row0 + r * out_row_stride, 0] = wp.float32(total / wp.sqrt(wp.float64(size)))


@wp.func
def _inverse_at(C: wp.array2d(dtype=wp.float32), r: int, i: int) -> wp.float64:
    """(W^T C[r])_i: the average plus the +-details of the log2(size) blocks holding i. The loop
    has a fixed bound (sizes up to 2^16, the uint16 columns' limit) so it unrolls and its loads
    go out together instead of one after another."""
    size = C.shape[1]
    v = wp.float64(C[r, 0]) / wp.sqrt(wp.float64(size))
    m = int(size)
    for level in range(16):
        if m > 1:
            d = wp.float64(C[r, size // m + i // m]) / wp.sqrt(wp.float64(m))
            if (i % m) < m // 2:
                v += d
            else:
                v -= d
        m = m // 2
    return v


@wp.func
def _item_sum(item: int, lane: int, stride: int, item_mat: wp.array(dtype=wp.uint8),
              item_start: wp.array(dtype=wp.int64), item_len: wp.array(dtype=wp.uint16),
              cols: wp.array(dtype=vec4us), vals: wp.array(dtype=wp.vec4f),
              X: wp.array2d(dtype=wp.float32), n_max: int, step: int) -> float:
    """One lane's share (quads lane, lane + stride, ...) of item ``item``'s signed sum
    sign_j sum_e vals[e] x_j[cols[e]] over its quads [item_start, item_start + item_len) (four
    coefficients each: one 16-byte value load, one 8-byte column load, four independent gathers),
    all of one matrix j = item_mat (part of one row). History (n_max > 0): matrices H_1..H_n_max
    then G_1..G_n_max against the wavelet-domain rings X (rows 0..n_max-1 u, n_max.. p; step s in
    slot s mod n_max), sign - for H_k and + for G_k, x_j the ring slot of step - k. A solve
    (n_max = 0): matrix j against X[j], sign +."""
    j = int(item_mat[item])
    e = item_start[item] + wp.int64(lane)
    end = item_start[item] + wp.int64(item_len[item])
    x_row = j
    sign = float(1.0)
    if n_max > 0:
        x_row = (step - (j % n_max + 1)) % n_max
        if j < n_max:
            sign = -1.0
        else:
            x_row += n_max
    acc = float(0.0)
    while e < end:
        v = vals[e]
        c = cols[e]
        acc += (v[0] * X[x_row, int(c[0])] + v[1] * X[x_row, int(c[1])]) + (
            v[2] * X[x_row, int(c[2])] + v[3] * X[x_row, int(c[3])])
        e += wp.int64(stride)
    return sign * acc


@wp.kernel
def chunk_sums(item_mat: wp.array(dtype=wp.uint8), item_start: wp.array(dtype=wp.int64),
               item_len: wp.array(dtype=wp.uint16),
               cols: wp.array(dtype=vec4us), vals: wp.array(dtype=wp.vec4f),
               X: wp.array2d(dtype=wp.float32), n_max: int, step: int, partial: wp.array(dtype=wp.float32)):
    """partial[item] = the item's signed sum (``_item_sum``): one block an item, its lanes striding
    (the CPU's form: a CPU block has one thread)."""
    item, lane = wp.tid()
    acc = _item_sum(item, lane, wp.block_dim(), item_mat, item_start, item_len, cols, vals, X, n_max, step)
    wp.tile_store(partial, wp.tile_sum(wp.tile(acc)), offset=item)


@wp.kernel
def row_sums(row_items: wp.array(dtype=wp.int64), row_list: wp.array(dtype=wp.int32),
             partial: wp.array(dtype=wp.float32), y_hat: wp.array2d(dtype=wp.float32)):
    """y_hat[0, row] = the sum of the row's items' partial sums (partial[row_list[i]] for i in
    row_items[row] .. row_items[row + 1]): one block a row, lanes striding over the items (a coarse
    row has hundreds), a fixed order (deterministic)."""
    row, lane = wp.tid()
    acc = float(0.0)
    i = row_items[row] + wp.int64(lane)
    end = row_items[row + 1]
    while i < end:
        acc += partial[int(row_list[i])]
        i += wp.int64(wp.block_dim())
    wp.tile_store(y_hat[0], wp.tile_sum(wp.tile(acc)), offset=row)


@wp.kernel
def inverse_history(h_hat: wp.array2d(dtype=wp.float32), perm: wp.array(dtype=wp.int32),
                    DQ: wp.array3d(dtype=wp.float32), B: wp.array2d(dtype=wp.float32), step: int,
                    h: wp.array(dtype=wp.float32)):
    """h[perm[i]] = (W^T h_hat)_i + sum_k [D_k Q_k][perm[i]] . b_(n-k): the compressed history back
    in the original order with the (dense, 3N x 6) frame-acceleration terms of Eq. (9)."""
    i = wp.tid()
    row = perm[i]
    n_max = DQ.shape[0]
    acc = _inverse_at(h_hat, 0, i)
    for k in range(1, n_max + 1):
        slot = (step - k) % n_max
        for j in range(6):
            acc += wp.float64(DQ[k - 1, row, j] * B[slot, j])
    h[row] = wp.float32(acc)


@wp.kernel
def inverse_set(y_hat: wp.array2d(dtype=wp.float32), perm: wp.array(dtype=wp.int32), y: wp.array(dtype=wp.float32)):
    """y[perm[i]] = (W^T y_hat)_i: every entry written (no zeroing pass first)."""
    i = wp.tid()
    y[perm[i]] = wp.float32(_inverse_at(y_hat, 0, i))


FOLD_BLOCK = wp.constant(64)  # lanes of one ``rigid_fold`` dot product (3N / 64 terms a lane)


@wp.kernel
def rigid_fold(AC: wp.array2d(dtype=wp.float32), P: wp.array2d(dtype=wp.float32), B: wp.array2d(dtype=wp.float32),
               slot0: int, n: int, out: wp.array2d(dtype=wp.float32)):
    """out[s, j] = B[s, j] - AC[j] . P[s, :n] for ring rows s = slot0 + r: the frame terms that go
    with the stored G'_k = G_k + D_k A + Q_k C (``wsim.bem.compression.folded_G``; AC = [A; C],
    Eq. 10's a_ext = A p, alpha_ext = C p). One block a (row, j); the dot in float64."""
    r, j, lane = wp.tid()
    s = slot0 + r
    acc = wp.float64(0.0)
    if lane == 0:
        acc = wp.float64(B[s, j])
    i = lane
    while i < n:
        acc -= wp.float64(AC[j, i]) * wp.float64(P[s, i])
        i += wp.block_dim()
    total = wp.tile_sum(wp.tile(acc))
    if lane == 0:
        out[s, j] = wp.float32(total[0])
