"""Sums of rows that share a key, after a sort by key (``wsim.segments.KeySums``).

A radix sort (``wp.utils.radix_sort_pairs``) puts equal keys next to each other with their entry
ids in input order (it is stable); these kernels mark where each run of equal keys starts, and
sum each run's rows in that order, one thread per run: no atomics, so the sum is fixed by the
entries' order.
"""

from __future__ import annotations

import warp as wp


@wp.kernel
def segment_heads(keys: wp.array(dtype=wp.int64), head: wp.array(dtype=wp.int32)):
    """head[i] = 1 where a run of equal keys starts (i = 0 or keys[i] != keys[i - 1]), else 0."""
    i = wp.tid()
    if i == 0:
        head[i] = 1
    elif keys[i] != keys[i - 1]:
        head[i] = 1
    else:
        head[i] = 0


@wp.kernel
def segment_starts(head: wp.array(dtype=wp.int32), run: wp.array(dtype=wp.int32), count: int,
                   starts: wp.array(dtype=wp.int32)):
    """starts[r] = the first position of run r (``run``: the inclusive scan of ``head``, so run
    r's positions hold r + 1), and starts[runs] = count: run r spans starts[r]..starts[r + 1]."""
    i = wp.tid()
    if head[i] != 0:
        starts[run[i] - 1] = i
    if i == count - 1:
        starts[run[i]] = count


@wp.kernel
def segment_sums(keys: wp.array(dtype=wp.int64), order: wp.array(dtype=wp.int32), run: wp.array(dtype=wp.int32),
                 starts: wp.array(dtype=wp.int32), count: int, values: wp.array2d(dtype=wp.float64),
                 first: wp.array(dtype=wp.float64), out_keys: wp.array(dtype=wp.int64),
                 out: wp.array2d(dtype=wp.float64), out_first: wp.array(dtype=wp.float64),
                 runs: wp.array(dtype=wp.int32), slot: int):
    """Run r: out[r] = sum of values[order[p]] over its positions p, in order; out_keys[r] its
    key; out_first[r] = first[order[p0]] of its first position (a quantity the run's entries
    share, such as a node's mass, taken once instead of summed); runs[slot] = the number of runs.
    Threads past the last run exit."""
    r = wp.tid()
    if r == 0:
        runs[slot] = run[count - 1]
    if r >= run[count - 1]:
        return
    p0 = starts[r]
    p1 = starts[r + 1]
    out_keys[r] = keys[p0]
    out_first[r] = first[order[p0]]
    for q in range(values.shape[1]):
        s = wp.float64(0.0)
        for p in range(p0, p1):
            s += values[order[p], q]
        out[r, q] = s
