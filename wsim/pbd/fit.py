"""Fit keyframe curves of a PBD animation and evaluate the reconstruction (numpy, float64).

Keyframes are every ``stride``-th frame (and the last frame). The reconstruction is piecewise in
time: between consecutive keyframes, a segment follows the paper's two-keyframe model. Why
piecewise rather than one fit over all keyframes: the paper's closed form has two time functions,
so with two keyframes it interpolates both exactly (and its 8 coefficients reduce to one 4-term
spatial fit per keyframe, shared with the neighbouring segment), while one 8-coefficient form
over J + 1 > 2 keyframes cannot follow a general motion (measured as method ``pde_joint``).

Methods (``METHODS``):

- ``pde``: per curve and coordinate one spatial constant lam (sign and D0, searched on a grid
  minimizing the keyframe fit error over all keyframes), 4 coefficients per keyframe, and per
  segment a time constant m (searched on a grid minimizing the error over the segment's simulated
  in-between frames, which the PBD run produced anyway); Eq. (2) of ``wsim.pbd.pde`` in between.
  The time family follows the sign of lam (cos/sin for lam > 0, cosh/sinh for lam < 0), the
  physically consistent pairing.
- ``bezier``, ``bspline``: cubic Bezier / uniform cubic B-spline fitted per keyframe curve (the
  paper's baselines), control points interpolated linearly in time.
- ``linear``: keyframe vertex positions interpolated linearly in time (the naive baseline).

``mode="displacement"`` (default) fits x - x_rest instead of x: the decoder has the rest mesh
anyway (connectivity and u come from it), static parts then cost no error, and the PDE model,
which is not translation-invariant, no longer depends on where the model sits. ``"position"``
fits positions, as the paper does.

Stored data (``stored_floats``) counts what a decoder needs beyond the rest mesh: keyframe
coefficients, lam per curve and coordinate, m per segment, curve and coordinate, and for
``parametrization="paper"`` the u values.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from wsim.errors import InvalidParameter
from wsim.validate import positive_int
from wsim.pbd import baselines, pde
from wsim.pbd.curves import Curve, auto_curves, chord_parameters, paper_parameters, validate_curves

METHODS = ("pde", "bezier", "bspline", "linear")

#: spatial constants searched for lam = +-D0^4 (plus the cubic limit lam = 0)
D0_GRID = np.geomspace(0.25, 30.0, 40)
#: time constants searched: sin family m in (0, 3] (m < pi), sinh family m in (0, 12]
M_GRID_SIN = np.linspace(0.1, 3.0, 30)
M_GRID_SINH = np.linspace(0.4, 12.0, 30)


def keyframe_indices(n_frames: int, stride: int) -> np.ndarray:
    """Frames 0, K, 2K, ... and the last frame."""
    positive_int(stride, "stride")
    if n_frames < 2:
        raise InvalidParameter(f"a reconstruction needs at least 2 keyframes, got {n_frames} frame(s)")
    k = np.arange(0, n_frames, stride)
    if k[-1] != n_frames - 1:
        k = np.append(k, n_frames - 1)
    return k


@dataclass(frozen=True)
class CurveLayout:
    """Curves flattened into padded arrays of fit points (closed curves repeat their first vertex)."""

    curves: tuple[Curve, ...]
    index: np.ndarray  # (C, P) vertex of each fit point (padding repeats the last point)
    mask: np.ndarray  # (C, P) True for real fit points
    u: np.ndarray  # (C, P, 3) parameter per fit point and coordinate
    vertex_curve: np.ndarray  # (N,) curve of each vertex
    vertex_u: np.ndarray  # (N, 3) its parameter per coordinate
    stored_u_floats: int  # u values a decoder must store (0 for chord parameters)

    @property
    def n_curves(self) -> int:
        return len(self.curves)


def make_layout(rest: np.ndarray, curves: Sequence[Curve], parametrization: str, keyframes: np.ndarray) -> CurveLayout:
    n = len(rest)
    P = max(len(c.fit_indices) for c in curves)
    C = len(curves)
    index = np.zeros((C, P), dtype=np.int64)
    mask = np.zeros((C, P), dtype=bool)
    u = np.zeros((C, P, 3))
    vertex_curve = np.full(n, -1, dtype=np.int64)
    vertex_u = np.zeros((n, 3))
    for c, curve in enumerate(curves):
        fi = curve.fit_indices
        if parametrization == "chord":
            uc = np.repeat(chord_parameters(rest, curve)[:, None], 3, axis=1)
        elif parametrization == "paper":
            uc = paper_parameters(keyframes, curve)
        else:
            raise InvalidParameter(f"parametrization = {parametrization!r} must be 'chord' or 'paper'")
        k = len(fi)
        index[c, :k], index[c, k:] = fi, fi[-1]
        mask[c, :k] = True
        u[c, :k], u[c, k:] = uc, uc[-1]
        own = vertex_curve[curve.indices] < 0  # a vertex on several curves is rebuilt from the first
        vertex_curve[curve.indices[own]] = c
        vertex_u[curve.indices[own]] = uc[: len(curve.indices)][own]
    stored = 0 if parametrization == "chord" else int(3 * mask.sum())
    return CurveLayout(tuple(curves), index, mask, u, vertex_curve, vertex_u, stored)


def _lstsq(B: np.ndarray, Y: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Batched least squares: B (C, P, 4), Y (C, P, K), rows outside ``mask`` ignored -> (C, 4, K)."""
    Bm = B * mask[..., None]
    return np.linalg.pinv(Bm, rcond=1e-12) @ (Y * mask[..., None])


def _poly_basis(method: str, u: np.ndarray) -> np.ndarray:
    return baselines.bernstein(u) if method == "bezier" else baselines.uniform_cubic_bspline(u)


@dataclass(frozen=True)
class Reconstruction:
    """A fitted reconstruction: everything a decoder stores, plus the rest mesh it is given.

    ``coef`` (nk, C, 3, 4): per keyframe, curve and coordinate (PDE spatial-basis coefficients or
    control-point coordinates); ``lam`` (C, 3) and ``m`` (nk - 1, C, 3) for ``pde``;
    ``key_positions`` (nk, N, 3) for ``linear``.
    """

    method: str
    mode: str
    keyframes: np.ndarray
    n_frames: int
    rest: np.ndarray
    layout: CurveLayout | None
    coef: np.ndarray | None = None
    lam: np.ndarray | None = None
    m: np.ndarray | None = None
    key_positions: np.ndarray | None = None

    @property
    def stored_floats(self) -> int:
        if self.method == "linear":
            return int(self.key_positions.size)
        n = int(self.coef.size) + self.layout.stored_u_floats
        if self.method == "pde":
            n += int(self.lam.size + self.m.size)
        return n

    @property
    def data_ratio(self) -> float:
        """Stored floats over the raw per-frame vertex data they replace (all frames, 3 per vertex)."""
        return self.stored_floats / (self.n_frames * self.rest.size)

    def segment(self, frame: float) -> tuple[int, float]:
        """(segment index j, local time tau in [0, 1]) of a (possibly fractional) frame."""
        k = self.keyframes
        if not (0.0 <= frame <= k[-1]):
            raise InvalidParameter(f"frame {frame} is outside the reconstructed range [0, {int(k[-1])}]")
        j = int(np.clip(np.searchsorted(k, frame, side="right") - 1, 0, len(k) - 2))
        return j, (frame - k[j]) / (k[j + 1] - k[j])

    def evaluate(self, frame: float) -> np.ndarray:
        """(N, 3) vertex positions at ``frame`` (numpy float64 reference of the Warp kernel)."""
        j, tau = self.segment(frame)
        if self.method == "linear":
            return (1.0 - tau) * self.key_positions[j] + tau * self.key_positions[j + 1]
        lay = self.layout
        c = lay.vertex_curve
        out = np.empty_like(self.rest)
        for w in range(3):
            u = lay.vertex_u[:, w]
            if self.method == "pde":
                vals = np.empty(len(u))
                for lam in np.unique(self.lam[:, w]):
                    sel = self.lam[c, w] == lam
                    F = pde.spatial_basis(u[sel], lam)
                    W0 = np.einsum("nk,nk->n", F, self.coef[j, c[sel], w])
                    W1 = np.einsum("nk,nk->n", F, self.coef[j + 1, c[sel], w])
                    a = np.empty(sel.sum())
                    b = np.empty(sel.sum())
                    for m0 in np.unique(self.m[j, c[sel], w]):
                        s2 = self.m[j, c[sel], w] == m0
                        a[s2], b[s2] = pde.blend_weights(np.array(tau), m0, lam)
                    vals[sel] = a * W0 + b * W1
            else:
                F = _poly_basis(self.method, u)
                ctrl = (1.0 - tau) * self.coef[j, c, w] + tau * self.coef[j + 1, c, w]
                vals = np.einsum("nk,nk->n", F, ctrl)
            out[:, w] = vals
        return out + self.rest if self.mode == "displacement" else out


def fit(
    frames: np.ndarray,
    rest: np.ndarray,
    stride: int,
    *,
    method: str = "pde",
    curves: str | Sequence[Curve | Sequence[int]] = "auto",
    points_per_curve: int = 12,
    closed: bool = False,
    mode: str = "displacement",
    parametrization: str = "chord",
    fixed_lam: float | None = None,
    fixed_m: float | None = None,
) -> Reconstruction:
    """Fit a reconstruction of ``frames`` (F, N, 3) with rest shape ``rest`` (N, 3).

    ``curves``: "auto" (meridians, ``points_per_curve`` vertices each) or index lists (``closed``
    applies to plain lists). ``fixed_lam`` / ``fixed_m`` skip the searches (tests, studies).
    """
    frames = np.asarray(frames, dtype=np.float64)
    rest = np.asarray(rest, dtype=np.float64)
    if frames.ndim != 3 or frames.shape[1:] != rest.shape or rest.ndim != 2 or rest.shape[1] != 3:
        raise InvalidParameter(f"frames must be (F, N, 3) and rest (N, 3); got {frames.shape} and {rest.shape}")
    if not np.all(np.isfinite(frames)):
        raise InvalidParameter("frames contain NaN or Inf")
    if method not in METHODS:
        raise InvalidParameter(f"method = {method!r} must be one of {', '.join(METHODS)}")
    if mode not in ("displacement", "position"):
        raise InvalidParameter(f"mode = {mode!r} must be 'displacement' or 'position'")
    keys = keyframe_indices(len(frames), stride)
    if method == "linear":
        return Reconstruction(method, mode, keys, len(frames), rest, None, key_positions=frames[keys].copy())

    n = len(rest)
    if isinstance(curves, str):
        if curves != "auto":
            raise InvalidParameter(f"curves = {curves!r} must be 'auto' or a list of vertex-index lists")
        curve_list = auto_curves(rest, points_per_curve)
    else:
        curve_list = validate_curves(curves, n, closed)
    layout = make_layout(rest, curve_list, parametrization, frames[keys])
    data = frames - rest if mode == "displacement" else frames
    Y = data[:, layout.index]  # (F, C, P, 3)
    Yk = Y[keys]  # (nk, C, P, 3)
    C, P = layout.index.shape
    nk = len(keys)

    if method in ("bezier", "bspline"):
        coef = np.empty((nk, C, 3, 4))
        for w in range(3):
            B = _poly_basis(method, layout.u[..., w])
            coef[:, :, w] = np.moveaxis(_lstsq(B, np.moveaxis(Yk[..., w], 0, -1), layout.mask), -1, 0)
        return Reconstruction(method, mode, keys, len(frames), rest, layout, coef=coef)

    # ---- pde: spatial constant per curve and coordinate, searched over all keyframes
    candidates = np.array([fixed_lam]) if fixed_lam is not None else np.concatenate([[0.0], D0_GRID**4, -(D0_GRID**4)])
    best_err = np.full((C, 3), np.inf)
    lam = np.zeros((C, 3))
    coef = np.zeros((nk, C, 3, 4))
    for cand in candidates:
        for w in range(3):
            B = pde.spatial_basis(layout.u[..., w], cand)  # (C, P, 4)
            Yw = np.moveaxis(Yk[..., w], 0, -1)  # (C, P, nk)
            cw = _lstsq(B, Yw, layout.mask)  # (C, 4, nk)
            resid = ((B @ cw - Yw) ** 2 * layout.mask[..., None]).sum(axis=(1, 2))
            better = resid < best_err[:, w] * (1.0 - 1e-12)
            best_err[better, w] = resid[better]
            lam[better, w] = cand
            coef[:, better, w] = np.moveaxis(cw[better], -1, 0)

    # ---- pde: time constant per segment, curve and coordinate, from the in-between frames
    m = np.zeros((nk - 1, C, 3))
    if fixed_m is not None:
        m[:] = fixed_m
    else:
        fitted = np.empty((nk, C, P, 3))
        for w in range(3):
            for cand in np.unique(lam[:, w]):
                sel = lam[:, w] == cand
                B = pde.spatial_basis(layout.u[sel, :, w], cand)  # (c, P, 4)
                fitted[..., w][:, sel] = np.einsum("cpk,jck->jcp", B, coef[:, sel, w])
        for j in range(nk - 1):
            inner = np.arange(keys[j] + 1, keys[j + 1])
            if inner.size == 0:
                continue
            tau = (inner - keys[j]) / (keys[j + 1] - keys[j])
            W0, W1, Yin = fitted[j], fitted[j + 1], Y[inner]  # (C, P, 3), (C, P, 3), (f, C, P, 3)
            msk = layout.mask[None, ..., None]
            best = (((1 - tau)[:, None, None, None] * W0 + tau[:, None, None, None] * W1 - Yin) ** 2 * msk).sum(axis=(0, 2))
            for grid, family in ((M_GRID_SIN, 1.0), (M_GRID_SINH, -1.0)):
                valid = (np.sign(lam) >= 0) if family > 0 else (lam < 0)  # (C, 3)
                for m0 in grid:
                    a, b = pde.blend_weights(tau, m0, family)
                    err = ((a[:, None, None, None] * W0 + b[:, None, None, None] * W1 - Yin) ** 2 * msk).sum(axis=(0, 2))
                    better = valid & (err < best * (1.0 - 1e-12))
                    best[better] = err[better]
                    m[j][better] = m0
    return Reconstruction("pde", mode, keys, len(frames), rest, layout, coef=coef, lam=lam, m=m)


def fit_joint_pde(frames: np.ndarray, rest: np.ndarray, stride: int, **kwargs) -> tuple[np.ndarray, float]:
    """The alternative to piecewise segments: one 8-coefficient closed form per curve and coordinate
    over the whole animation (t = frame / last frame), fitted to all keyframes, lam taken from the
    piecewise fit and m searched on the grids. Returns (reconstructed frames (F, N, 3), stored floats)."""
    piece = fit(frames, rest, stride, method="pde", **kwargs)
    lay, keys = piece.layout, piece.keyframes
    frames = np.asarray(frames, dtype=np.float64)
    data = frames - rest if piece.mode == "displacement" else frames
    t_all = np.arange(len(frames)) / (len(frames) - 1)
    tk = t_all[keys]
    out = np.empty_like(frames)
    C = lay.n_curves
    for w in range(3):
        for c in range(C):
            lamc = piece.lam[c, w]
            pts = lay.index[c, lay.mask[c]]
            F = pde.spatial_basis(lay.u[c, lay.mask[c], w], lamc)  # (P, 4)
            Yk = data[keys][:, pts, w]  # (nk, P)
            best = (np.inf, None, 0.0)
            grid = M_GRID_SIN if lamc >= 0 else M_GRID_SINH
            for m0 in np.concatenate([[0.0], grid]):
                T = pde.time_basis(tk, m0, lamc)  # (nk, 2)
                A = np.einsum("ja,pk->jpak", T, F).reshape(len(keys) * len(pts), 8)
                cf, *_ = np.linalg.lstsq(A, Yk.reshape(-1), rcond=None)
                err = float(((A @ cf - Yk.reshape(-1)) ** 2).sum())
                if err < best[0]:
                    best = (err, cf.reshape(2, 4), m0)
            members = np.flatnonzero(lay.vertex_curve == c)
            Fv = pde.spatial_basis(lay.vertex_u[members, w], lamc)
            out[:, members, w] = pde.time_basis(t_all, best[2], lamc) @ best[1] @ Fv.T
    if piece.mode == "displacement":
        out += rest
    return out, 8 * 3 * C + piece.lam.size + 3 * C
