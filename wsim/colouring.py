"""Graph colouring of constraints, so that Gauss-Seidel projection runs in parallel without races.

Two constraints conflict when they share a particle. Two colourings:

- ``colour_constraints``: each colour is a maximal independent set of the conflict graph, built
  in vectorized rounds (Luby / Jones-Plassmann style): among the constraints not yet coloured, a
  constraint joins the current colour when it holds the smallest random priority at every one of
  its particles; repeated until no uncoloured constraint fits. Fast; its colours are few but not
  the fewest.
- ``colour_smallest_last``: sequential greedy colouring in smallest-last order (Matula and Beck
  1983: repeatedly remove a constraint of smallest remaining degree, colour in reverse removal
  order, each constraint the smallest colour none of its neighbours has). It uses at most one
  colour more than the graph's degeneracy, and it leaves the colours of a few high-valence
  vertices (the poles of a capped tube) to the constraints there instead of spreading them over
  the mesh: on the posed 15k model 12 + 24 colours for edges and hinges (Luby: 12 + 25), of which
  7 + 16 hold a constraint outside the pinned and driven regions (Luby: 9 + 20). PBD models use
  it (``wsim.pbd.model``): on a GPU each colour is a launch of every iteration of every substep.

Why colouring and not Jacobi with atomics: coloured Gauss-Seidel converges like the serial
XPBD solver (so compliance means the same stiffness at any iteration count), needs no
under-relaxation, and is deterministic: no floating-point atomics on the particle positions
(only the float64 block sums of the global volume constraint depend on block order). The cost
is one launch per colour (CUDA graph replay keeps each near 4 us; see README for the measured
budget). Because constraints are stored sorted by colour, a serial sweep over the whole
array (what a single-threaded CPU launch does) performs exactly the same operations in the same
order as the per-colour launches.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def colour_constraints(indices: np.ndarray, n_particles: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Colour constraints so that no two of one colour share a particle.

    Args:
        indices: (K, a) int particle indices of K constraints of arity a.
        n_particles: number of particles (upper bound of the indices).
        seed: seed of the random priorities (the colouring is deterministic for a seed).

    Returns:
        order: (K,) permutation that sorts the constraints by colour.
        offsets: (C + 1,) int64; the constraints of colour c are order[offsets[c]:offsets[c + 1]].
    """
    idx = np.asarray(indices, dtype=np.int64)
    k = idx.shape[0]
    if k == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(1, dtype=np.int64)
    arity = idx.shape[1]
    priority = np.random.default_rng(seed).permutation(k).astype(np.int64)
    colour = np.full(k, -1, dtype=np.int64)
    remaining = np.arange(k)
    current = 0
    big = np.iinfo(np.int64).max
    while remaining.size:
        used = np.zeros(n_particles, dtype=bool)
        candidates = remaining
        while candidates.size:
            best = np.full(n_particles, big, dtype=np.int64)
            np.minimum.at(best, idx[candidates].ravel(), np.repeat(priority[candidates], arity))
            wins = np.all(best[idx[candidates]] == priority[candidates, None], axis=1)
            chosen = candidates[wins]
            colour[chosen] = current
            used[idx[chosen].ravel()] = True
            candidates = candidates[~wins]
            candidates = candidates[~np.any(used[idx[candidates]], axis=1)]
        remaining = remaining[colour[remaining] < 0]
        current += 1
    # within a colour keep the original order: neighbouring constraints stay close in memory
    order = np.lexsort((np.arange(k), colour))
    counts = np.bincount(colour, minlength=current)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return order, offsets


def colour_smallest_last(indices: np.ndarray, n_particles: int) -> tuple[np.ndarray, np.ndarray]:
    """Colour constraints so that no two of one colour share a particle, greedily in smallest-last
    order (module docstring); deterministic. Arguments and returns as ``colour_constraints``."""
    idx = np.asarray(indices, dtype=np.int64)
    k = idx.shape[0]
    if k == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(1, dtype=np.int64)
    a = idx.shape[1]
    inc = sp.csr_matrix((np.ones(k * a, dtype=np.int8), (np.repeat(np.arange(k), a), idx.ravel())),
                        shape=(k, n_particles))
    adj = (inc @ inc.T).tocsr()  # constraints sharing a particle
    adj.setdiag(0)
    adj.eliminate_zeros()
    # Python lists: the loops below touch every edge once or twice (numpy per element is slower)
    ptr, nbr = adj.indptr.tolist(), adj.indices.tolist()
    deg = np.diff(adj.indptr).tolist()
    # buckets of equal degree as insertion-ordered dicts: the removal order (and so the colouring)
    # is fixed by the language, not by a set's iteration order
    buckets: list[dict[int, None]] = [{} for _ in range(max(deg) + 1)]
    for v, d in enumerate(deg):
        buckets[d][v] = None
    removed = [False] * k
    order = []
    d = 0
    for _ in range(k):
        d = max(d - 1, 0)  # a removal lowers a neighbour's degree by one at most
        while not buckets[d]:
            d += 1
        v = next(iter(buckets[d]))
        del buckets[d][v]
        removed[v] = True
        order.append(v)
        for u in nbr[ptr[v]:ptr[v + 1]]:
            if not removed[u]:
                du = deg[u]
                del buckets[du][u]
                deg[u] = du - 1
                buckets[du - 1][u] = None
    colour = [-1] * k
    for v in reversed(order):
        used = {colour[u] for u in nbr[ptr[v]:ptr[v + 1]]}
        c = 0
        while c in used:
            c += 1
        colour[v] = c
    col = np.asarray(colour, dtype=np.int64)
    # within a colour keep the original order: neighbouring constraints stay close in memory
    order_out = np.lexsort((np.arange(k), col))
    offsets = np.concatenate([[0], np.cumsum(np.bincount(col))]).astype(np.int64)
    return order_out, offsets


def is_valid_colouring(indices: np.ndarray, offsets: np.ndarray) -> bool:
    """True when no two constraints in one colour (of colour-sorted ``indices``) share a particle."""
    idx = np.asarray(indices)
    for c in range(len(offsets) - 1):
        block = idx[offsets[c] : offsets[c + 1]].ravel()
        if np.unique(block).size != block.size:
            return False
    return True
