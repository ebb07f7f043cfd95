"""Sum the rows of a device array that share an int64 key, on the device (``kernels/segments.py``).

For assemblies whose entries arrive in no set order (atomic counters) and must be summed per key
before the host sees them: the host then reads one row per distinct key instead of every entry.
A stable radix sort, run heads, a scan, and one thread per run summing its rows in input order,
so the sums are deterministic.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.kernels import segments as ks


class KeySums:
    """Scratch for ``sum_by_key`` on one device, grown on demand (entries and value columns)."""

    def __init__(self, device: wp.Device) -> None:
        self.device = device
        self._capacity = 0
        self._columns = 0

    def _ensure(self, count: int, columns: int) -> None:
        if count <= self._capacity and columns <= self._columns:
            return
        cap, cols, d = max(count, 2 * self._capacity, 64), max(columns, self._columns), self.device
        self.keys = wp.empty(2 * cap, dtype=wp.int64, device=d)  # the radix sort's double buffer
        self.order = wp.empty(2 * cap, dtype=wp.int32, device=d)
        self.ids = wp.array(np.arange(cap, dtype=np.int32), device=d)
        self.head = wp.empty(cap, dtype=wp.int32, device=d)
        self.run = wp.empty(cap, dtype=wp.int32, device=d)
        self.starts = wp.empty(cap + 1, dtype=wp.int32, device=d)
        self.out_keys = wp.empty(cap, dtype=wp.int64, device=d)
        self.out = wp.empty((cap, cols), dtype=wp.float64, device=d)
        self.out_first = wp.empty(cap, dtype=wp.float64, device=d)
        self._capacity, self._columns = cap, cols

    def sum_by_key(self, keys: wp.array, values: wp.array, first: wp.array | None,
                   count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The distinct keys of keys[:count] (ascending), the sum of values[:count] rows per key
        (in entry order) and ``first`` of each key's first entry (zeros without ``first``), on
        the host. ``keys`` (int64), ``values`` (2-D float64) and ``first`` (float64) are device
        arrays of at least ``count`` entries; they are not changed."""
        q = values.shape[1]
        if count == 0:
            return np.zeros(0, dtype=np.int64), np.zeros((0, q)), np.zeros(0)
        self._ensure(count, q)
        d = self.device
        wp.copy(self.keys, keys, count=count)
        wp.copy(self.order, self.ids, count=count)
        wp.utils.radix_sort_pairs(self.keys, self.order, count)
        sorted_keys = self.keys[:count]
        head, run = self.head[:count], self.run[:count]
        wp.launch(ks.segment_heads, count, [sorted_keys, head], device=d)
        wp.utils.array_scan(head, run, inclusive=True)
        wp.launch(ks.segment_starts, count, [head, run, count, self.starts], device=d)
        first = first if first is not None else wp.zeros(count, dtype=wp.float64, device=d)
        wp.launch(ks.segment_sums, count, [sorted_keys, self.order, run, self.starts, count, values, first,
                                           self.out_keys, self.out, self.out_first], device=d)
        runs = int(run[count - 1:count].numpy()[0])
        # copies: on the CPU ``numpy()`` is a view of the scratch, which the next call overwrites
        return (self.out_keys[:runs].numpy().copy(), self.out[:runs].numpy()[:, :q].copy(),
                self.out_first[:runs].numpy().copy())
