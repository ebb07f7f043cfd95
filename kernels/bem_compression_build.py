"""Kernels of the GPU build of the compressed BEM operators (issue 20;
``wsim.bem.compression_device.DeviceCoefficients``): the padded matrix permuted and Haar
transformed in float64, the coefficients at or above a threshold counted, their dropped part
multiplied with tuning vectors, the kept ones extracted as CSR.

A module of its own: a scene that steps compressed bodies from the operator cache never compiles
these, and a build never compiles the step's kernels (Warp compiles a module whole).
"""

from __future__ import annotations

from typing import Any

import warp as wp

HALF = wp.constant(wp.float64(0.7071067811865476))  # sqrt(1/2): one orthonormal Haar level
COUNT_BLOCK = wp.constant(256)


@wp.kernel
def permute_pad(A: wp.array2d(dtype=Any), perm: wp.array(dtype=wp.int32), out: wp.array2d(dtype=wp.float64)):
    """out = P A P^T zero padded to out's size (P: new -> old ``perm``), float64."""
    i, j = wp.tid()
    n = perm.shape[0]
    v = wp.float64(0.0)
    if i < n and j < n:
        v = wp.float64(A[perm[i], perm[j]])
    out[i, j] = v


@wp.kernel
def haar_level_cols(src: wp.array2d(dtype=wp.float64), dst: wp.array2d(dtype=wp.float64), half: int):
    """One level of the 1-D Haar transform along every row's first 2 half entries (``haar``):
    dst[r, j] = (a + b) / sqrt 2, dst[r, half + j] = (a - b) / sqrt 2 for a, b = src[r, 2j], src[r, 2j + 1]."""
    r, j = wp.tid()
    a = src[r, 2 * j]
    b = src[r, 2 * j + 1]
    dst[r, j] = (a + b) * HALF
    dst[r, half + j] = (a - b) * HALF


@wp.kernel
def haar_level_rows(src: wp.array2d(dtype=wp.float64), dst: wp.array2d(dtype=wp.float64), half: int):
    """``haar_level_cols`` along every column's first 2 half entries (rows 2i, 2i + 1)."""
    i, c = wp.tid()
    a = src[2 * i, c]
    b = src[2 * i + 1, c]
    dst[i, c] = (a + b) * HALF
    dst[half + i, c] = (a - b) * HALF


@wp.kernel
def copy_corner(src: wp.array2d(dtype=wp.float64), dst: wp.array2d(dtype=wp.float64)):
    """dst[i, j] = src[i, j] over the launch's (rows, columns): a level's result back in place."""
    i, j = wp.tid()
    dst[i, j] = src[i, j]


@wp.kernel
def count_at_least(C: wp.array2d(dtype=wp.float64), t: wp.float64, counts: wp.array(dtype=wp.int32),
                   kept2: wp.array(dtype=wp.float64)):
    """Per row: how many |C_ij| >= t (counts) and the sum of their squares (kept2)."""
    row, lane = wp.tid()
    n = C.shape[1]
    c = int(0)
    s = wp.float64(0.0)
    j = lane
    while j < n:
        v = C[row, j]
        if wp.abs(v) >= t:
            c += 1
            s += v * v
        j += wp.block_dim()
    wp.tile_store(counts, wp.tile_sum(wp.tile(c)), offset=row)
    wp.tile_store(kept2, wp.tile_sum(wp.tile(s)), offset=row)


@wp.kernel
def compact_rows(C: wp.array2d(dtype=wp.float64), t: wp.float64, indptr: wp.array(dtype=wp.int64),
                 cols: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64)):
    """The coefficients |C_ij| >= t of row r, in column order, at indptr[r] (CSR)."""
    r = wp.tid()
    e = indptr[r]
    for j in range(C.shape[1]):
        v = C[r, j]
        if wp.abs(v) >= t:
            cols[e] = j
            vals[e] = v
            e += wp.int64(1)


#: tuning vectors a block of ``kept_products`` multiplies at once (C is read once per group;
#: 16 float64 accumulators a thread)
PRODUCT_GROUP = 16
vecgd = wp.types.vector(length=PRODUCT_GROUP, dtype=wp.float64)


@wp.kernel
def kept_products(C: wp.array2d(dtype=wp.float64), t: wp.float64, X: wp.array2d(dtype=vecgd),
                  out: wp.array2d(dtype=wp.float64)):
    """out[r, 16 g + i] = sum over the kept |C_rj| >= t of C_rj X[g, j][i]: C_kept X for the tuning
    vectors in groups of 16 (one block per row and group reads the row once for all 16). X is read
    only where a coefficient is kept, a few percent of them: reading it for every coefficient (the
    dropped ones' product) cost 8 bytes x vectors x size per row from L2, 262 GB a pass at
    N = 10088. With t = 0 it is C X, from which (C - C_kept) X, whose column norms are the matvec
    errors of the kept set (orthonormal W), is one subtraction."""
    row, g, lane = wp.tid()
    n = C.shape[1]
    s = vecgd()
    j = lane
    while j < n:
        v = C[row, j]
        if wp.abs(v) >= t:
            s += v * X[g, j]
        j += wp.block_dim()
    wp.tile_store(out[row], wp.tile_sum(wp.tile(s), axis=1), offset=g * PRODUCT_GROUP)
