"""Convolution quadrature (Lubich) weights, paper Eq. (15).

A convolution y(t) = int_0^t f(t - tau) g(tau) dtau whose kernel is known by its Laplace
transform f_hat(s) is approximated at t_n = n dt by y_n = sum_k psi_k g_{n-k}, with

    psi_k = R^-k / L * sum_{l=0}^{L-1} f_hat(gamma(R zeta^l) / dt) zeta^(-k l),   zeta = e^(2 pi i / L),

gamma the generating polynomial of a linear multistep method (BDF1: 1 - z; BDF2:
3/2 - 2z + z^2/2), R = eps^(1 / (2 n_max)) and eps = 1e-10 (Schanz & Antes). The DFT is
L-periodic in k, so k = 0..n_max needs L = n_max + 1 samples: with the paper's printed L = n_max
the last weight would alias psi_0 multiplied by R^-L = 1e5.

For a real kernel f_hat(conj s) = conj f_hat(s): sample l and sample L - l are conjugates, so only
l = 0..floor(L/2) are evaluated (the expensive part for BEM: one Laplace-domain assembly each),
and the weights are real.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from wsim.errors import InvalidParameter

GAMMA = {
    "bdf1": lambda z: 1.0 - z,
    "bdf2": lambda z: 1.5 - 2.0 * z + 0.5 * z**2,
}


def n_max_for(r_max: float, c2: float, dt: float) -> int:
    """History length n_max = floor(lam + max(2, 1.2 sqrt(lam))), lam = r_max / (c2 dt).

    The kernels vanish after t = r_max / c2, i.e. after lam steps; the paper adds 2 steps. But BDF1
    CQ smears a sharp wavefront over about sqrt(lam) steps (the weights of e^(-s tau) are a
    Poisson distribution of mean tau / dt), so for small dt the paper's cut falls inside the
    smeared front. The truncated history then no longer annihilates rigid motion consistently
    and the error-correction loop grows (measured on a 42-node sphere: lam = 53 with n_max = 55
    diverges after ~1200 steps, n_max = 61 and above stay bounded; tools/study_bem_stability.py).
    The margin 1.2 sqrt(lam) exceeds 2 only for lam > 2.8, so every scene of the paper's Table 1
    keeps its n_max.
    """
    lam = r_max / (c2 * dt)
    return int(np.floor(lam + max(2.0, 1.2 * np.sqrt(lam))))


def sample_points(dt: float, n_max: int, method: str = "bdf1", eps: float = 1e-10) -> tuple[np.ndarray, float, int]:
    """The Laplace-domain frequencies s_l = gamma(R zeta^l) / dt for l = 0..floor(L/2), with R and L."""
    if method not in GAMMA:
        raise InvalidParameter(f"CQ method = {method!r} must be one of {', '.join(GAMMA)}")
    if not (dt > 0.0 and np.isfinite(dt)):
        raise InvalidParameter(f"dt = {dt} s must be > 0")
    if n_max < 1:
        raise InvalidParameter(f"n_max = {n_max} must be >= 1")
    L = n_max + 1
    R = eps ** (1.0 / (2.0 * n_max))
    l = np.arange(L // 2 + 1)
    zeta = np.exp(2j * np.pi * l / L)
    return GAMMA[method](R * zeta) / dt, R, L


def combine(samples: np.ndarray, R: float, L: int, n_max: int) -> np.ndarray:
    """psi_k, k = 0..n_max, from f_hat at the half set of samples (leading axis l = 0..floor(L/2)).

    The missing samples are the conjugates: f_hat(s_{L-l}) = conj(f_hat(s_l)). Returns real weights
    with the sample axis replaced by k.
    """
    samples = np.asarray(samples)
    half = L // 2 + 1
    if samples.shape[0] != half:
        raise ValueError(f"expected {half} samples, got {samples.shape[0]}")
    full = np.concatenate([samples, np.conj(samples[1 : L - half + 1][::-1])], axis=0)  # l = 0..L-1
    k = np.arange(n_max + 1)
    l = np.arange(L)
    W = np.exp(-2j * np.pi * np.outer(k, l) / L) * (R ** (-k.astype(np.float64)))[:, None] / L  # (n_max + 1, L)
    out = np.tensordot(W, full, axes=(1, 0))
    return out.real


def half_weights(R: float, L: int, n_max: int) -> np.ndarray:
    """(floor(L/2) + 1, n_max + 1) complex W with psi_k = Re sum_l W[l, k] f_hat(s_l) over the half set.

    W[l, k] = m_l R^-k zeta^(-k l) / L, where m_l = 2 for samples whose conjugate partner L - l is
    skipped and 1 for l = 0 and (L even) l = L / 2. This is what the Warp CQ kernel applies to each
    assembled Laplace-domain matrix; ``combine`` is the same sum done explicitly.
    """
    half = L // 2 + 1
    l = np.arange(half)
    k = np.arange(n_max + 1)
    mult = np.where((l == 0) | (2 * l == L), 1.0, 2.0)
    return mult[:, None] * np.exp(-2j * np.pi * np.outer(l, k) / L) * (R ** (-k.astype(np.float64)))[None, :] / L


def weights(f_hat: Callable[[np.ndarray], np.ndarray], dt: float, n_max: int, method: str = "bdf1", eps: float = 1e-10) -> np.ndarray:
    """psi_k(f_hat), k = 0..n_max, for a scalar or array-valued f_hat (vectorized over s)."""
    s, R, L = sample_points(dt, n_max, method, eps)
    values = np.stack([np.asarray(f_hat(si)) for si in s])
    return combine(values, R, L, n_max)


def convolve(psi: np.ndarray, g: np.ndarray) -> np.ndarray:
    """y_n = sum_{k=0}^{min(n, n_max)} psi_k g_{n-k} for scalar weights and samples g_0..g_N."""
    g = np.asarray(g, dtype=np.float64)
    y = np.zeros_like(g)
    for k, w in enumerate(psi):
        y[k:] += w * g[: len(g) - k]
    return y
