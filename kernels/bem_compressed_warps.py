"""The CUDA form of ``bem_compressed.chunk_sums``: several work items a block, one warp each.

A module of its own because Warp compiles a module whole for each device, and on the CPU a block
has one thread: the (WARPS, 32) reshape below cannot compile there.
"""

from __future__ import annotations

import warp as wp

from wsim.kernels.bem_compressed import _item_sum, vec4us

WARPS = wp.constant(4)  # items a block (block_dim 32 WARPS)


@wp.kernel
def chunk_sums_warps(item_mat: wp.array(dtype=wp.uint8), item_start: wp.array(dtype=wp.int64),
                     item_len: wp.array(dtype=wp.uint16),
                     cols: wp.array(dtype=vec4us), vals: wp.array(dtype=wp.vec4f),
                     X: wp.array2d(dtype=wp.float32), n_max: int, step: int, partial: wp.array(dtype=wp.float32)):
    """partial[item] = the item's signed sum (``bem_compressed._item_sum``) for WARPS items a block,
    warp w of block b taking item b WARPS + w: a block of one warp caps an SM at half its threads
    (32 blocks an SM), four fill it. ``partial`` holds a multiple of WARPS entries; items past the
    last write 0."""
    block, t = wp.tid()
    item = block * WARPS + t // 32
    acc = float(0.0)
    if item < item_mat.shape[0]:
        acc = _item_sum(item, t % 32, 32, item_mat, item_start, item_len, cols, vals, X, n_max, step)
    sums = wp.tile_sum(wp.tile_reshape(wp.tile(acc), shape=(WARPS, 32)), axis=1)
    wp.tile_store(partial, sums, offset=block * WARPS)
