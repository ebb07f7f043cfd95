"""``wsim.segments.KeySums``: rows summed per int64 key on the device, against numpy."""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.segments import KeySums


def _reference(keys: np.ndarray, values: np.ndarray, first: np.ndarray):
    uk, first_at, inv = np.unique(keys, return_index=True, return_inverse=True)
    sums = np.zeros((len(uk), values.shape[1]))
    for i, k in enumerate(inv.reshape(-1)):  # entry order, as the device sums them
        sums[k] += values[i]
    return uk, sums, first[first_at]


def test_sums_per_key_match_numpy_in_entry_order(device):
    """Random keys (a few distinct among many entries, and keys near 2^62 that differ only in
    their high bits), sums bitwise equal to numpy's in entry order, the first entry's value per
    key; the scratch grows for more entries and more columns, a second sum does not change the
    first's results, an empty sum returns nothing, and the inputs are left as they were."""
    rng = np.random.default_rng(3)
    d = wp.get_device(device)
    ks = KeySums(d)
    cases = [(rng.integers(0, 7, 200), 2), (rng.integers(0, 37, 5000), 5),
             ((rng.integers(0, 3, 50) << 60) + rng.integers(0, 2, 50), 14), (np.full(9, 11), 1), (np.array([4]), 3)]
    done = []
    for keys, q in cases:
        keys = keys.astype(np.int64)
        values = rng.standard_normal((len(keys), q))
        first = rng.standard_normal(len(keys))
        dk, dv, df = (wp.array(keys, dtype=wp.int64, device=d), wp.array(values, dtype=wp.float64, device=d),
                      wp.array(first, dtype=wp.float64, device=d))
        got = ks.sum_by_key(dk, dv, df, len(keys), key_bound=int(keys.max()) + 1)
        ref = _reference(keys, values, first)
        for g, r in zip(got, ref):
            np.testing.assert_array_equal(g, r)
        np.testing.assert_array_equal(dk.numpy(), keys)  # not sorted in place
        done.append((got, ref))
    for got, ref in done:  # results are copies, not views of the reused scratch
        for g, r in zip(got, ref):
            np.testing.assert_array_equal(g, r)
    empty, full = KeySums(d), KeySums(d)
    empty.launch(wp.zeros(4, dtype=wp.int64, device=d), wp.zeros((4, 2), dtype=wp.float64, device=d), None, 0)
    full.launch(wp.array(np.array([2, 1, 2], dtype=np.int64), device=d),
                wp.array(np.ones((3, 2)), dtype=wp.float64, device=d), None, 3)
    (k0, v0, _), (k1, v1, f1) = KeySums.fetch_all([empty, full])
    assert len(k0) == 0 and v0.shape == (0, 2)
    np.testing.assert_array_equal(k1, [1, 2])
    np.testing.assert_array_equal(v1, [[1.0, 1.0], [2.0, 2.0]])
    np.testing.assert_array_equal(f1, [0.0, 0.0])
