"""Haar-wavelet compression of the BEM's dense operators (the paper's Sec. 3.3; spec Sec. 1.6).

The matrices H_k, G_k, H_0^-1 and H_0^-1 G' are smooth away from wavefronts: rows (and columns)
of nearby nodes with similar normals are alike. After reordering, a 2-D Haar transform gathers
each matrix's energy in few coefficients, and keeping the largest ones compresses it.

* **Reordering** (``permutation``): the nodes by a spatial locality order ("v"), the coordinates
  as all x, then all y, then all z ("c"; the paper's Fig. 3: 3 x 3 subblocks of smooth kernels),
  or both ("v+c", the default). The node order is a Morton (Z-order) curve of the node positions:
  like the authors' cache-oblivious layout [YLPM05] it is local at every scale, so each Haar
  block of 2^k consecutive indices is a compact patch of surface (no maintained library offers
  that layout; the curve is ten lines). Reverse Cuthill-McKee on the node graph (scipy), the
  obvious library order, was measured worse than no reordering at all: its indices sweep along
  BFS fronts, so consecutive indices lie on a ring, not a patch (``tools/study_bem_compression.py``:
  bumpy cube N = 602, H_1 at CR 8: v+c Morton 0.13, c alone 0.18, v+c RCM 0.25, none 0.50, naive
  pruning 0.53). A double node stays next to its original.
* **Transform**: the orthonormal 1-D Haar transform W (full depth) on rows and columns of the
  reordered matrix padded with zeros to a power of two, C = W P A P^T W^T (the tensor-product
  "standard form"). Orthonormality makes the relative Frobenius error of the reconstruction the
  norm of the dropped coefficients over the norm of all, known without reconstructing.
* **Keeping**: the ``keep`` largest |C_ij| (the paper's rule; CR = entries / kept), stored CSR.
* **Products**: A x = P^T W^T C W P x (two O(n) transforms and one sparse product), and a row of
  A (for Gauss-Seidel) from the log2(n) + 1 rows of C that its Haar basis touches.

``choose_keep`` picks, for a target ``eps``, the fewest coefficients whose relative matvec error
on given vectors stays below eps (what the history products see), by bisection on the sorted
coefficients.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import scipy.sparse as sp

from wsim.bem.factorization import fold_frame_terms
from wsim.errors import InvalidParameter

ORDERINGS = ("none", "v", "c", "v+c")
MARGIN = 0.6  # ``choose_keep``: the unseen half of the tuning vectors must stay below MARGIN eps


def _pow2(n: int) -> int:
    return 1 << max(0, int(n - 1).bit_length())


def haar(x: np.ndarray, axis: int = 0) -> np.ndarray:
    """The orthonormal full-depth 1-D Haar transform of ``x`` along ``axis`` (length a power of
    two): [coarsest average, coarsest detail, ..., finest details]."""
    y = np.moveaxis(np.asarray(x, dtype=np.float64), axis, 0).copy()
    n = y.shape[0]
    if n & (n - 1):
        raise InvalidParameter(f"haar: length {n} is not a power of two")
    s = np.sqrt(0.5)
    m = n
    while m > 1:
        a = (y[0:m:2] + y[1:m:2]) * s
        d = (y[0:m:2] - y[1:m:2]) * s
        y[: m // 2], y[m // 2: m] = a, d
        m //= 2
    return np.moveaxis(y, 0, axis)


def inverse_haar(y: np.ndarray, axis: int = 0) -> np.ndarray:
    """The inverse of ``haar`` (its transpose: the transform is orthonormal)."""
    x = np.moveaxis(np.asarray(y, dtype=np.float64), axis, 0).copy()
    n = x.shape[0]
    s = np.sqrt(0.5)
    m = 2
    while m <= n:
        a, d = x[: m // 2].copy(), x[m // 2: m].copy()
        x[0:m:2], x[1:m:2] = (a + d) * s, (a - d) * s
        m *= 2
    return np.moveaxis(x, 0, axis)


def haar_basis(i: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The nonzero entries of column i of W (W e_i: the Haar coefficients of a unit vector at i),
    as (indices, values): one per level plus the average, log2(n) + 1 of them."""
    idx, val = [0], [n ** -0.5]
    m = n
    while m > 1:  # detail of the block of size m holding i, at position n/m + i // m
        half = m // 2
        k = i // m
        idx.append(n // m + k)
        val.append((m ** -0.5) * (1.0 if (i % m) < half else -1.0))
        m = half
    return np.asarray(idx), np.asarray(val)


def node_order(nodes: np.ndarray, faces: np.ndarray, vertex: np.ndarray | None = None, how: str = "morton") -> np.ndarray:
    """A locality order of the surface's nodes (new -> old node index). ``how``: "morton" (Z-curve
    of the positions; the default, see the module docstring) or "rcm" (reverse Cuthill-McKee on
    the vertex graph of the faces, scipy; measured worse).
    ``vertex`` (node -> vertex) keeps the double nodes of a vertex next to each other."""
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    nodes = np.asarray(nodes, dtype=np.float64)
    n = len(nodes)
    vertex = np.arange(n) if vertex is None else np.asarray(vertex)
    nv = int(vertex.max()) + 1
    if how == "rcm":
        f = np.asarray(faces)
        fv = vertex[f] if f.max() < n else f  # faces over nodes or over vertices
        rows = np.concatenate([fv[:, 0], fv[:, 1], fv[:, 2]])
        cols = np.concatenate([fv[:, 1], fv[:, 2], fv[:, 0]])
        graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(nv, nv)).tocsr()
        graph = ((graph + graph.T) > 0).astype(np.int8).tocsr()
        vorder = np.asarray(reverse_cuthill_mckee(graph, symmetric_mode=True))
    elif how == "morton":
        vpos = np.zeros((nv, 3))
        vpos[vertex] = nodes
        q = ((vpos - vpos.min(0)) / max(np.ptp(vpos, axis=0).max(), 1e-300) * 1023).astype(np.int64)
        code = np.zeros(nv, dtype=np.int64)
        for b in range(10):
            for d in range(3):
                code |= ((q[:, d] >> b) & 1) << (3 * b + d)
        vorder = np.argsort(code, kind="stable")
    else:
        raise InvalidParameter(f"node order {how!r} must be 'rcm' or 'morton'")
    rank = np.empty(nv, dtype=np.int64)
    rank[vorder] = np.arange(nv)
    return np.lexsort((np.arange(n), rank[vertex]))  # by the vertex's rank; a vertex's nodes in their order


def permutation(n_nodes: int, ordering: str = "v+c", order: np.ndarray | None = None) -> np.ndarray:
    """(3 N,) new -> old index of the 3N unknowns (node-major x, y, z: old index 3 i + c) for an
    ``ordering`` of ``ORDERINGS``; ``order`` the node order ("v"; ``node_order``)."""
    if ordering not in ORDERINGS:
        raise InvalidParameter(f"ordering {ordering!r} must be one of {', '.join(ORDERINGS)}")
    nodes = np.arange(n_nodes) if ordering in ("none", "c") or order is None else np.asarray(order)
    if ordering in ("c", "v+c"):  # all x, then all y, then all z
        return (3 * nodes[None, :] + np.arange(3)[:, None]).ravel()
    return (3 * nodes[:, None] + np.arange(3)[None, :]).ravel()


def to_wavelet(x: np.ndarray, perm: np.ndarray, size: int) -> np.ndarray:
    """W P x for x (n,) or (n, k): reordered, zero padded to ``size``, Haar transformed."""
    xp = np.zeros((size,) + x.shape[1:])
    xp[: len(perm)] = x[perm]
    return haar(xp, axis=0)


def from_wavelet(y_hat: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """P^T W^T y_hat: back to the original order (the inverse of ``to_wavelet``)."""
    yp = inverse_haar(y_hat, axis=0)[: len(perm)]
    y = np.empty_like(yp)
    y[perm] = yp
    return y


@dataclass(frozen=True)
class CompressedMatrix:
    """A square matrix A (n x n) as kept Haar coefficients: A ~ P^T W^T C W P, C sparse (CSR over
    the padded size), ``perm`` P's new -> old index. ``norm`` = ||A||_F and ``dropped`` = the norm
    of the coefficients not kept: by orthonormality the Frobenius error of the padded
    reconstruction, so a bound on (and without padding equal to) the error of A's."""

    n: int
    perm: np.ndarray
    C: sp.csr_matrix
    norm: float
    dropped: float

    @property
    def size(self) -> int:
        return self.C.shape[0]

    @property
    def kept(self) -> int:
        return int(self.C.nnz)

    @property
    def ratio(self) -> float:
        """CR = n^2 / kept (the paper's: entries of the matrix over entries kept)."""
        return self.n * self.n / max(self.kept, 1)

    @property
    def relative_error(self) -> float:
        """||A - A_compressed||_F / ||A||_F, bounded from above (``dropped``)."""
        return self.dropped / self.norm if self.norm > 0.0 else 0.0

    @property
    def nbytes(self) -> int:
        return int(self.C.data.nbytes + self.C.indices.nbytes + self.C.indptr.nbytes + self.perm.nbytes)

    def matvec(self, x: np.ndarray) -> np.ndarray:
        """A x for x of shape (n,) or (n, k)."""
        return from_wavelet(self.C @ to_wavelet(np.asarray(x, dtype=np.float64), self.perm, self.size), self.perm)

    def rows(self, rs: np.ndarray) -> np.ndarray:
        """Rows ``rs`` of A (the reconstruction), (len(rs), n) in the original column order: each
        row is w_r^T C W P, w_r = W P e_r with log2(size) + 1 entries (``haar_basis``), so
        log2(size) + 1 sparse rows of C combined and one inverse transform."""
        inv = np.empty(self.n, dtype=np.int64)
        inv[self.perm] = np.arange(self.n)
        basis = [haar_basis(int(inv[r]), self.size) for r in np.asarray(rs, dtype=np.int64)]
        per_row = int(np.log2(self.size)) + 1
        Psi = sp.csr_matrix((np.concatenate([v for _, v in basis] + [np.zeros(0)]),
                             np.concatenate([i for i, _ in basis] + [np.zeros(0, dtype=np.int64)]),
                             np.arange(len(basis) + 1) * per_row), shape=(len(basis), self.size))
        return from_wavelet(np.asarray((Psi @ self.C).todense()).T, self.perm).T

    def row(self, r: int) -> np.ndarray:
        """Row r of A (the reconstruction), in the original column order."""
        return self.rows([r])[0]

    def row_dot(self, r: int, x: np.ndarray) -> float:
        """(A x)_r from row r alone (what a Gauss-Seidel sweep asks)."""
        return float(self.row(r) @ np.asarray(x, dtype=np.float64))

    def to_dense(self) -> np.ndarray:
        """The reconstructed A (n x n), original order."""
        full = inverse_haar(inverse_haar(self.C.toarray(), axis=0), axis=1)[: self.n, : self.n]
        out = np.empty_like(full)
        out[np.ix_(self.perm, self.perm)] = full
        return out


def transform(A: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """C = W P A P^T W^T, padded to the next power of two (dense, float64)."""
    A = np.asarray(A)
    n = A.shape[0]
    size = _pow2(n)
    Ap = np.zeros((size, size))
    Ap[:n, :n] = A[np.ix_(perm, perm)]
    return haar(haar(Ap, axis=0), axis=1)


def _largest(coeffs: np.ndarray, keep: int) -> np.ndarray:
    flat = np.abs(coeffs).ravel()
    keep = int(min(max(keep, 1), flat.size))
    if keep >= flat.size:
        return np.arange(flat.size)
    return np.argpartition(flat, flat.size - keep)[flat.size - keep:]


def _from_coefficients(coeffs: np.ndarray, n: int, perm: np.ndarray, keep: int, norm: float,
                       order: np.ndarray | None = None) -> CompressedMatrix:
    """The ``keep`` largest coefficients (the first ``keep`` of ``order``, their ranking, if given)."""
    size = coeffs.shape[0]
    sel = _largest(coeffs, keep) if order is None else order[: int(min(max(keep, 1), order.size))]
    r, c = np.divmod(sel, size)
    vals = coeffs.ravel()[sel]
    C = sp.csr_matrix((vals, (r, c)), shape=(size, size))
    C.sort_indices()
    dropped2 = max(float(np.sum(coeffs * coeffs)) - float(np.sum(vals * vals)), 0.0)
    return CompressedMatrix(n=n, perm=np.asarray(perm, dtype=np.int64), C=C, norm=norm, dropped=float(np.sqrt(dropped2)))


class HostCoefficients:
    """The Haar coefficients C = W P A P^T W^T of one matrix in host memory (numpy: the CPU build).

    What ``compress`` and ``choose_keep`` ask of a coefficient set (``DeviceCoefficients`` answers
    the same on a Warp device): a *level* is an integer in ``levels`` (inclusive) and more level
    keeps more coefficients, the largest first; here the level is the count kept."""

    def __init__(self, A: np.ndarray, perm: np.ndarray) -> None:
        self.n = int(A.shape[0])
        self.perm = np.asarray(perm, dtype=np.int64)
        self.coeffs = transform(A, perm)
        self.size = self.coeffs.shape[0]
        self.norm = float(np.linalg.norm(A))
        self.levels = (1, self.coeffs.size)
        self._order: np.ndarray | None = None
        # id -> (X_hat, the dropped products at every CHECKPOINTS-th level) per tuning block
        self._sums: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    CHECKPOINTS = 64  # stored dropped products per tuning block: a level costs 1/64 of a full product

    def level_for(self, keep: int) -> int:
        return int(min(max(keep, 1), self.coeffs.size))

    def _product(self, lo: int, hi: int, X_hat: np.ndarray) -> np.ndarray:
        """C_S X_hat for S the coefficients ranked lo..hi-1 (largest first)."""
        r, c = np.divmod(self._order[lo:hi], self.size)
        return sp.csr_matrix((self.coeffs[r, c], (r, c)), shape=self.coeffs.shape) @ X_hat

    def dropped(self, level: int, X_hat: np.ndarray) -> np.ndarray:
        """(C - C_kept) X_hat for the coefficients kept at ``level``: the dropped ones' product,
        the stored one of the nearest checkpoint level at or above ``level`` plus the few ranked
        between. A bisection of ``choose_keep`` asks for ~20 levels per target and tightens the
        target several times; each from scratch was a product with all kept coefficients (a
        386-node body's 12 history matrices took 108 s of tuning on one CPU core). The checkpoints
        cost one pass over the coefficients per tuning block, summed from the smallest up."""
        total = self.coeffs.size
        if self._order is None:
            self._order = np.argsort(np.abs(self.coeffs).ravel())[::-1]
        step = -(-total // self.CHECKPOINTS)
        found = self._sums.get(id(X_hat))
        if found is None or found[0] is not X_hat:  # the entry holds X_hat: its id is not reused while cached
            sums = np.zeros((self.CHECKPOINTS + 1, self.size, X_hat.shape[1]))
            for j in range(self.CHECKPOINTS - 1, -1, -1):  # sums[j]: the product of ranks j step .. total
                sums[j] = sums[j + 1] + self._product(j * step, min((j + 1) * step, total), X_hat)
            found = self._sums[id(X_hat)] = (X_hat, sums)
        j = min(-(-level // step), self.CHECKPOINTS)
        return found[1][j] + self._product(level, min(j * step, total), X_hat)

    def extract(self, level: int) -> CompressedMatrix:
        return _from_coefficients(self.coeffs, self.n, self.perm, level, self.norm, self._order)


def coefficients(A: np.ndarray, perm: np.ndarray, device=None, reuse=None):
    """The coefficient set of A under ``perm``: on the host (numpy) for ``device`` None, else on
    that Warp device (``DeviceCoefficients``; float64, the whole padded matrix on the device;
    ``reuse`` a previous one of the same size, whose device memory is taken over)."""
    if device is None:
        return HostCoefficients(np.asarray(A), perm)
    from wsim.bem.compression_device import DeviceCoefficients

    coef = reuse if reuse is not None else DeviceCoefficients(np.asarray(A).shape[0], device)
    return coef.load(A, perm)


def compress(A: np.ndarray, perm: np.ndarray | None = None, ratio: float | None = None,
             keep: int | None = None, device=None) -> CompressedMatrix:
    """A (n x n) compressed with the permutation ``perm`` (default: none) keeping ``keep``
    coefficients or n^2 / ``ratio`` of them (ratio 1: all, lossless to round-off); the transform
    and the choice on the host (``device`` None) or on a Warp device."""
    A = np.asarray(A)
    n = A.shape[0]
    if A.ndim != 2 or A.shape[1] != n:
        raise InvalidParameter(f"compress: a square matrix is needed, got shape {A.shape}")
    perm = np.arange(n) if perm is None else np.asarray(perm)
    if (ratio is None) == (keep is None):
        raise InvalidParameter("compress: give exactly one of ratio (CR >= 1) or keep")
    if ratio is not None:
        if not ratio >= 1.0:
            raise InvalidParameter(f"compress: compression ratio {ratio} must be >= 1")
        keep = int(round(n * n / ratio))
    return _keep_count(coefficients(A, perm, device), ratio, int(keep))


def _keep_count(coef, ratio: float | None, keep: int) -> CompressedMatrix:
    return coef.extract(coef.levels[1] if ratio == 1.0 else coef.level_for(keep))  # CR 1: everything


def prune(A: np.ndarray, ratio: float) -> tuple[np.ndarray, float]:
    """Naive pruning (the paper's Fig. 7 baseline): keep the n^2 / ratio largest raw entries.
    Returns (the pruned matrix, its relative Frobenius error)."""
    A = np.asarray(A, dtype=np.float64)
    sel = _largest(A, int(round(A.size / ratio)))
    out = np.zeros_like(A)
    out.ravel()[sel] = A.ravel()[sel]
    return out, float(np.linalg.norm(A - out) / np.linalg.norm(A))


def choose_keep(A: np.ndarray, perm: np.ndarray, eps: float, vectors: np.ndarray, device=None) -> CompressedMatrix:
    """The fewest largest coefficients whose relative matvec error ||(A - A_c) x|| / ||A x|| stays
    below ``eps`` for the columns x of ``vectors`` (n x k, k >= 2; e.g. the history vectors of a
    run), with a margin for vectors it has not seen: the count is chosen on one half of the
    columns and checked on the other (and the other way round); while the unseen half exceeds
    ``MARGIN`` eps, the target tightens by 0.7. The error falls as more are kept, so each choice
    is a bisection (over the coefficient set's levels: on the host or on a Warp ``device``). A
    guarantee for vectors of the same kind as the tuning ones, not for any vector: one with
    ||A x|| far below ||A|| ||x|| can have any relative error."""
    A = np.asarray(A)
    return _keep_error(coefficients(A, perm, device), A, eps, vectors)


def _keep_error(coef, A: np.ndarray, eps: float, vectors: np.ndarray) -> CompressedMatrix:
    """``choose_keep`` on a coefficient set of A."""
    if not eps > 0.0:
        raise InvalidParameter(f"compression_error = {eps} must be > 0")
    n = A.shape[0]
    X = np.asarray(vectors, dtype=np.float64).reshape(n, -1)
    if X.shape[1] < 2:
        raise InvalidParameter("compression_error: at least two tuning vectors are needed")
    ref_norm = np.maximum(np.linalg.norm(A @ X.astype(A.dtype, copy=False), axis=0).astype(np.float64), 1e-300)
    Xh = to_wavelet(X, coef.perm, coef.size)  # W P x, once
    halves = (np.arange(0, X.shape[1], 2), np.arange(1, X.shape[1], 2))
    everything = np.arange(X.shape[1])
    by_level: dict[int, np.ndarray] = {}  # level -> every column's error: the bisections share their first levels

    def errors(level: int, cols_x: np.ndarray) -> np.ndarray:
        """||W^T (C - C_kept) W P x|| / ||A x|| = ||(C - C_kept) W P x|| / ||A x|| (orthonormal W)."""
        found = by_level.get(level)
        if found is None:
            found = by_level[level] = np.linalg.norm(coef.dropped(level, Xh), axis=0) / ref_norm
        return found[cols_x]

    def fewest(target: float, cols_x: np.ndarray) -> int:
        lo, hi = coef.levels
        while lo < hi:
            mid = (lo + hi) // 2
            if errors(mid, cols_x).max() <= target:
                hi = mid
            else:
                lo = mid + 1
        return hi

    target, level = eps, coef.levels[1]
    for _ in range(20):
        level = max(fewest(target, h) for h in halves)
        if all(errors(fewest(target, a), b).max() <= MARGIN * eps for a, b in (halves, halves[::-1])):
            break
        target *= 0.7
    return coef.extract(max(level, fewest(eps, everything)))


def smooth_fields(nodes: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """k smooth vector fields on the nodes (3N x k, node-major x, y, z): random combinations of
    low-order polynomials and long waves of the positions, per component; what displacement and
    traction histories look like away from wavefronts (part of ``tuning_fields``)."""
    x = np.asarray(nodes, dtype=np.float64)
    x = (x - x.mean(0)) / max(np.ptp(x, axis=0).max(), 1e-300)
    basis = [np.ones(len(x)), *x.T, *(x.T ** 2), x[:, 0] * x[:, 1], x[:, 1] * x[:, 2], x[:, 0] * x[:, 2],
             *np.sin(3.0 * x.T), *np.cos(3.0 * x.T)]
    B = np.stack(basis, axis=1)
    rng = np.random.default_rng(seed)
    return np.stack([(B @ rng.standard_normal((B.shape[1], 3))).ravel() for _ in range(k)], axis=1)


def tuning_fields(surface: Any, seed: int = 0) -> np.ndarray:
    """The default tuning vectors of ``compression_error`` (3N x 32, node-major x, y, z): what a
    step multiplies, smooth and not. 12 ``smooth_fields`` (displacements, distributed loads);
    8 half-space indicators times a constant vector and 6 times the surface normal (a load on
    one side or on faces: jumps across a plane and, with the normal, across the mesh's edges);
    6 patches exp(-|x - c|^2 / (0.1 L)^2) about random nodes (contact-like, L the bounding box's
    largest side; on a coarse mesh, under ~10 node spacings across, a patch is nearly a point
    load, which keeps more coefficients there). Each kind has an even count, so the even and odd
    columns (``choose_keep``'s halves) hold every kind.

    Why not smooth fields alone: they compress a large mesh so well (the N = 10088 cube kept one
    coefficient in 67 at eps 0.03) that its response to a load on one side came out 12x too
    large. With these kinds (and G_k stored: ``CompressedHistory`` says why G'_k) it kept one in
    22 and every product of that load was within 2 %, yet the response was 3.2x too large; with
    G'_k stored it keeps one in 10.8 and the response is within 5 % during the load."""
    from wsim.mesh.surface import vertex_normals

    x = np.asarray(surface.nodes, dtype=np.float64)
    xc = x - x.mean(0)
    L = max(float(np.ptp(x, axis=0).max()), 1e-300)
    normals = vertex_normals(x, surface.faces)
    rng = np.random.default_rng(seed)

    def half_space() -> np.ndarray:
        d = rng.standard_normal(3)
        return (xc @ (d / np.linalg.norm(d)) > rng.uniform(-0.3, 0.3) * L).astype(np.float64)

    sharp = [(half_space()[:, None] * rng.standard_normal(3)).ravel() for _ in range(8)]
    faces = [(half_space()[:, None] * normals * rng.standard_normal()).ravel() for _ in range(6)]
    patches = []
    for c in x[rng.integers(len(x), size=6)]:
        w = np.exp(-np.sum((x - c) ** 2, axis=1) / (0.1 * L) ** 2)
        patches.append((w[:, None] * rng.standard_normal(3)).ravel())
    return np.hstack([smooth_fields(x, 12, seed=seed), np.stack(sharp + faces + patches, axis=1)])


@dataclass(frozen=True)
class CompressedHistory:
    """H_k, G'_k (k = 1..n_max), H_0^-1 and H_0^-1 G' of an operator set, compressed with one
    permutation (v+c), and the products of a step in the wavelet domain: the history sum_k G'_k
    p_(n-k) - H_k u_(n-k) transforms the ring's vectors once (all slots in one pass), sums the
    sparse products and transforms back once.

    G'_k = G_k + D_k A + Q_k C (``folded_G``) is stored rather than G_k: Eq. (9)'s history sums
    G_k p and [D_k Q_k] [a - g', alpha] of the same step, whose rigid parts cancel (a traction's
    net force is what accelerates the frame: a = A p + ...), so that G_1 p alone is 18-32x
    the history on a 488-node bumpy cube pushed from one side. A compression error relative to G_k p
    is then that much larger relative to h; G'_k has the cancellation done exactly, as G' =
    G_0 + D_0 A + Q_0 C does for k = 0, and the caller's frame terms use [D_k Q_k] ([a - g',
    alpha] - [A p, C p]) (``rigid_fold``). The constraint solver reads rows of H_0^-1 G'
    (``CompressedMatrix.rows``). ``spec``: how it was made (ratio or error)."""

    perm: np.ndarray
    H: tuple[CompressedMatrix, ...]
    G: tuple[CompressedMatrix, ...]
    H0_inv: CompressedMatrix
    H0_inv_Gp: CompressedMatrix
    spec: str

    @property
    def n(self) -> int:
        return self.H0_inv.n

    @property
    def size(self) -> int:
        return self.H0_inv.size

    @property
    def matrices(self) -> tuple[CompressedMatrix, ...]:
        return (*self.H, *self.G, self.H0_inv, self.H0_inv_Gp)

    @property
    def nbytes(self) -> int:
        return int(sum(m.nbytes for m in self.matrices) - (len(self.matrices) - 1) * self.perm.nbytes)

    @property
    def ratio(self) -> float:
        """Entries of the dense matrices over coefficients kept, over all of them."""
        return len(self.matrices) * self.n * self.n / max(sum(m.kept for m in self.matrices), 1)

    def history(self, U: np.ndarray, P: np.ndarray, step: int) -> np.ndarray:
        """sum_k G'_k P[(step - k) % n_max] - H_k U[(step - k) % n_max] (rows of U, P: the rings,
        at least n long)."""
        n_max = len(self.H)
        n = self.n
        U_hat = to_wavelet(np.asarray(U, dtype=np.float64)[:, :n].T, self.perm, self.size)
        P_hat = to_wavelet(np.asarray(P, dtype=np.float64)[:, :n].T, self.perm, self.size)
        acc = np.zeros(self.size)
        for k in range(1, n_max + 1):
            s = (step - k) % n_max
            acc += self.G[k - 1].C @ P_hat[:, s]
            acc -= self.H[k - 1].C @ U_hat[:, s]
        return from_wavelet(acc, self.perm)


def folded_G(ops, k: int) -> np.ndarray:
    """G'_k = G_k + D_k A + Q_k C (3N, 3N, G_k's precision; ``CompressedHistory``; k = 0 gives the
    operators' G'), on a copy of G_k (``factorization.fold_frame_terms``)."""
    return fold_frame_terms(np.array(ops.G[k]), ops.D[k], ops.Q[k], ops.A, ops.C)


def rigid_fold(ops, B: np.ndarray, P: np.ndarray) -> np.ndarray:
    """The frame-term ring that goes with G'_k (``folded_G``): B - [A; C] p per ring row
    (B (rows, 6): [a - g', alpha]; P (rows, >= 3N): the tractions)."""
    n = ops.A.shape[1]
    return np.asarray(B, dtype=np.float64) - np.asarray(P, dtype=np.float64)[:, :n] @ np.vstack([ops.A, ops.C]).T


def compress_history(ops, ratio: float | None = None, error: float | None = None,
                     vectors: np.ndarray | None = None, device=None) -> CompressedHistory:
    """Compress ``ops``' (``BemOperators``) H_k, G'_k (k >= 1, ``folded_G``), H_0^-1 and H_0^-1 G' with the v+c ordering:
    at one compression ``ratio`` (the paper's CR), or each with the fewest coefficients whose
    relative matvec error stays below ``error`` on ``vectors`` (default: ``tuning_fields``).
    The transforms and choices run on the host (``device`` None) or on a Warp device (one
    ``DeviceCoefficients`` reused for every matrix)."""
    if (ratio is None) == (error is None):
        raise InvalidParameter("give exactly one of compression (a ratio CR >= 1) or compression_error (eps > 0)")
    s = ops.surface
    n = 3 * s.n_nodes
    perm = permutation(s.n_nodes, "v+c", node_order(s.nodes, s.faces, s.vertex))
    X = None
    if error is not None:
        X = tuning_fields(s, seed=0) if vectors is None else vectors
    work = None

    def one(A: np.ndarray) -> CompressedMatrix:
        nonlocal work
        coef = coefficients(A, perm, device, reuse=work)
        work = coef if device is not None else None
        if X is not None:
            return _keep_error(coef, A, error, X)
        return _keep_count(coef, ratio, int(round(n * n / ratio)))

    n_max = ops.n_max
    return CompressedHistory(perm=perm, H=tuple(one(ops.H[k]) for k in range(1, n_max + 1)),
                             G=tuple(one(folded_G(ops, k)) for k in range(1, n_max + 1)), H0_inv=one(ops.H0_inv),
                             H0_inv_Gp=one(ops.H0_inv_Gp),
                             spec=f"error={error:g}" if error is not None else f"ratio={ratio:g}")


QUAD = 4  # coefficients a lane loads at once: 16-byte values, 8-byte columns


def pack_rows(matrices: Sequence[CompressedMatrix]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kept coefficients of several matrices of one size, laid out row by row for the device
    (``wsim.kernels.bem_compressed``): (bounds (size, len + 1) int64: where matrix j's part of
    row i starts, columns uint16, values float32). Each part is padded with zeros (value 0, the
    part's last column) to a multiple of QUAD coefficients, so that a lane loads four at once:
    6 bytes a coefficient, the padding ~0.5 % more at CR 32."""
    size = matrices[0].size
    if size > 65536:
        raise InvalidParameter(f"pack_rows: padded size {size} exceeds the uint16 columns (3N <= 65536)")
    counts = np.stack([np.diff(m.C.indptr) for m in matrices], axis=1)  # (size, J)
    padded = -(-counts // QUAD) * QUAD
    starts = np.concatenate([[0], np.cumsum(padded.ravel())])
    J = len(matrices)
    bounds = np.empty((size, J + 1), dtype=np.int64)
    bounds[:, :J] = starts[:-1].reshape(size, J)
    bounds[:, J] = starts[J::J]
    cols = np.zeros(int(starts[-1]), dtype=np.uint16)
    vals = np.zeros(int(starts[-1]), dtype=np.float32)
    for j, m in enumerate(matrices):
        c = m.C
        n_row = np.diff(c.indptr)
        dest = np.repeat(bounds[:, j] - c.indptr[:-1], n_row) + np.arange(c.nnz)
        cols[dest] = c.indices
        vals[dest] = c.data
        pad = padded[:, j] - n_row  # the padding repeats the part's last column (a cached gather)
        if pad.any() and c.nnz:
            rows = np.repeat(np.arange(size), pad)
            fill = np.repeat(bounds[:, j] + n_row, pad) + (np.arange(pad.sum()) - np.repeat(np.cumsum(pad) - pad, pad))
            last = np.where(n_row > 0, c.indices[np.maximum(c.indptr[1:] - 1, 0)], 0)
            cols[fill] = last[rows]
    return bounds, cols, vals


def work_items(bounds: np.ndarray, chunk: int) -> tuple[np.ndarray, ...]:
    """The rows of a ``pack_rows`` layout cut into work items, each part of one matrix's part of one
    row and at most ``chunk`` (a multiple of QUAD) coefficients long
    (``wsim.kernels.bem_compressed.chunk_sums``), ordered matrix by matrix (all of H_1's items, then
    H_2's, ...): the GPU then works on one or two matrices at a time, and the vector each gathers
    from stays in its SMs' L1 cache. Returns (item matrix uint8, item start int64, item length
    uint16 - both in quads of QUAD coefficients -, row_items (size + 1) int64, row_list int32): the
    items of row r are row_list[row_items[r] .. row_items[r + 1]], in matrix order. 15 bytes an
    item: at CR 32 on the 2906-node cube about 1 % of the coefficients' bytes."""
    size, J = bounds.shape[0], bounds.shape[1] - 1
    if J > 255 or chunk > 65535 * QUAD or chunk % QUAD or np.any(bounds % QUAD):
        raise InvalidParameter(f"work_items: {J} matrices (<= 255), chunks of {chunk} (a multiple of {QUAD}) "
                               f"and a pack_rows layout (parts padded to {QUAD}) are needed")
    start, end = bounds[:, :J].T.ravel(), bounds[:, 1:].T.ravel()  # segment (j, row), matrix-major
    per_seg = -(-(end - start) // chunk)
    seg = np.repeat(np.arange(size * J), per_seg)
    first = np.concatenate([[0], np.cumsum(per_seg)])[:-1]
    local = np.arange(len(seg)) - first[seg]
    item_start = start[seg] + local * chunk
    item_len = np.minimum(item_start + chunk, end[seg]) - item_start
    row = seg % size
    row_list = np.argsort(row, kind="stable").astype(np.int32)  # by row, matrix order kept within a row
    row_items = np.concatenate([[0], np.cumsum(np.bincount(row, minlength=size))]).astype(np.int64)
    return ((seg // size).astype(np.uint8), (item_start // QUAD).astype(np.int64), (item_len // QUAD).astype(np.uint16),
            row_items, row_list)
