"""Sum the rows of a device array that share an int64 key, on the device (``kernels/segments.py``).

For assemblies whose entries arrive in no set order (atomic counters) and must be summed per key
before the host sees them: the host then reads one row per distinct key instead of every entry.
A stable radix sort, run heads, a scan, and one thread per run summing its rows in input order:
the sums are deterministic for a given entry order (entries written at slots taken from an atomic
counter on a GPU come in a varying order, and their sums may differ in the last bits from run to
run).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.kernels import segments as ks


class KeySums:
    """One keyed sum on one device (``launch``, then ``fetch``), its scratch grown on demand.
    Several may be launched before any is fetched; ``fetch_all`` reads them back with two
    synchronizations in all (the run counts, then the sums into page-locked host buffers)."""

    def __init__(self, device: wp.Device) -> None:
        self.device = device
        self._capacity = 0
        self._columns = 0
        self._count = 0
        self._q = 0
        self.runs = wp.zeros(1, dtype=wp.int32, device=device)

    def _ensure(self, count: int, columns: int) -> None:
        if count <= self._capacity and columns <= self._columns:
            return
        grow = count > self._capacity  # more columns alone keep the entry capacity
        cap = max(count, 2 * self._capacity, 64) if grow else self._capacity
        cols, d = max(columns, self._columns), self.device
        pinned = d.is_cuda
        self.keys = wp.empty(2 * cap, dtype=wp.int64, device=d)  # the radix sort's double buffer
        self.order = wp.empty(2 * cap, dtype=wp.int32, device=d)
        self.ids = wp.array(np.arange(cap, dtype=np.int32), device=d)
        self.head = wp.empty(cap, dtype=wp.int32, device=d)
        self.run = wp.empty(cap, dtype=wp.int32, device=d)
        self.starts = wp.empty(cap + 1, dtype=wp.int32, device=d)
        self.zeros = wp.zeros(cap, dtype=wp.float64, device=d)
        self.out_keys = wp.empty(cap, dtype=wp.int64, device=d)
        self.out = wp.empty((cap, cols), dtype=wp.float64, device=d)
        self.out_first = wp.empty(cap, dtype=wp.float64, device=d)
        self.host = [wp.empty(a.shape, dtype=a.dtype, device="cpu", pinned=pinned)
                     for a in (self.out_keys, self.out, self.out_first)]
        self._capacity, self._columns = cap, cols

    def launch(self, keys: wp.array, values: wp.array, first: wp.array | None, count: int,
               key_bound: int | None = None) -> None:
        """Sort keys[:count] and sum values[:count] (2-D float64) per key, in entry order;
        ``first`` (float64, optional) is taken from each key's first entry. The inputs are
        device arrays of at least ``count`` entries, not changed. ``key_bound``: the keys are
        known to lie in [0, key_bound), so the sort passes over that many bits only."""
        self._count, self._q = count, values.shape[1]
        if count == 0:
            return
        self._ensure(count, self._q)
        d = self.device
        wp.copy(self.keys, keys, count=count)
        wp.copy(self.order, self.ids, count=count)
        end_bit = None if key_bound is None else max(int(key_bound - 1).bit_length(), 1)
        wp.utils.radix_sort_pairs(self.keys, self.order, count, end_bit=end_bit)
        sorted_keys = self.keys[:count]
        head, run = self.head[:count], self.run[:count]
        wp.launch(ks.segment_heads, count, [sorted_keys, head], device=d)
        wp.utils.array_scan(head, run, inclusive=True)
        wp.launch(ks.segment_starts, count, [head, run, count, self.starts], device=d)
        wp.launch(ks.segment_sums, count, [sorted_keys, self.order, run, self.starts, count, values,
                                           self.zeros if first is None else first, self.out_keys, self.out,
                                           self.out_first, self.runs, 0], device=d)

    @staticmethod
    def fetch_all(sums: list[KeySums]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Each launched sum's (distinct keys ascending, sums (runs, columns), first) on the host."""
        live = [s for s in sums if s._count]
        if len({str(s.device) for s in live}) > 1:
            raise ValueError("KeySums.fetch_all: sums on one device at a time")
        if live:
            counts = np.concatenate([s.runs.numpy() for s in live])  # waits for every launch
            for s, n in zip(live, counts):
                s._runs = int(n)
                for dst, src in zip(s.host, (s.out_keys, s.out, s.out_first)):
                    wp.copy(dst, src, count=int(n) * (src.shape[1] if src.ndim == 2 else 1))
            wp.synchronize_device(live[0].device)
        out = []
        for s in sums:
            if not s._count:
                out.append((np.zeros(0, dtype=np.int64), np.zeros((0, s._q)), np.zeros(0)))
                continue
            n = s._runs
            # copies: the host buffers are overwritten by the next fetch
            keys, vals, first = (h.numpy() for h in s.host)
            out.append((keys[:n].copy(), vals[:n, :s._q].copy(), first[:n].copy()))
        return out

    def sum_by_key(self, keys: wp.array, values: wp.array, first: wp.array | None, count: int,
                   key_bound: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``launch`` and ``fetch_all`` of this one sum."""
        self.launch(keys, values, first, count, key_bound)
        return KeySums.fetch_all([self])[0]
