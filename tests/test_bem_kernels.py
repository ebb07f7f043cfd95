"""Laplace-domain fundamental solutions: static limits, reciprocity, the PDE they solve, the
traction they imply, the body-force flux identities, the incompressible limit, and the Warp
implementation against the numpy reference."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import wsim
from wsim.bem import fundamental as F
from wsim.kernels import bem_step

MATERIALS = {
    "nu0.3": wsim.ElasticMaterial(E=1e6, nu=0.3, rho=1000.0),
    "nu0.49": wsim.ElasticMaterial(E=2e5, nu=0.49, rho=500.0),
    "incompressible": wsim.ElasticMaterial(mu=5e5, nu=0.5, rho=1000.0, incompressible=True),
}
S_VALUES = [300.0 + 200.0j, 20.0 - 5.0j, 4000.0 + 1.0j]


def points(rng, k=6):
    x, y = rng.normal(size=(k, 3)), rng.normal(size=(k, 3))
    n = rng.normal(size=(k, 3))
    return x, y, n / np.linalg.norm(n, axis=1, keepdims=True)


def fd_gradient(f, y, h=1e-5):
    """d f / d y_k by central differences: f(y) (..., A, B) -> (..., A, B, 3)."""
    out = []
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        out.append((f(y + e) - f(y - e)) / (2 * h))
    return np.stack(out, axis=-1)


@pytest.mark.parametrize("name", ["nu0.3", "nu0.49", "incompressible"])
def test_static_limit_is_kelvin(name, rng):
    """u(s) = Kelvin + O(s r / c): the difference vanishes linearly in s (p has no O(s) term)."""
    mat = MATERIALS[name]
    x, y, n = points(rng)
    K = F.kelvin_u(x, y, mat)
    gaps = []
    for s in (1e-6, 1e-7, 1e-6j):
        gaps.append(np.abs(F.u_hat(x, y, s, mat) - K).max() / np.abs(K).max())
        np.testing.assert_allclose(F.p_hat(x, y, n, s, mat), F.kelvin_p(x, y, n, mat), rtol=1e-9, atol=1e-12)
    assert gaps[0] < 1e-6 and gaps[0] / gaps[1] == pytest.approx(10.0, rel=1e-3)


def test_reciprocity_and_symmetry(rng):
    x, y, _ = points(rng)
    for mat in MATERIALS.values():
        for s in S_VALUES:
            U = F.u_hat(x, y, s, mat)
            np.testing.assert_allclose(U, np.swapaxes(U, -1, -2), rtol=1e-13, atol=0)
            np.testing.assert_allclose(U, F.u_hat(y, x, s, mat), rtol=1e-13, atol=0)


@pytest.mark.parametrize("name", ["nu0.3", "nu0.49"])
def test_u_hat_solves_the_laplace_domain_navier_equation(name, rng):
    """mu lap u + (lambda + mu) grad div u = rho s^2 u away from the source (second differences)."""
    mat = MATERIALS[name]
    x, y, _ = points(rng, 3)
    s = 30.0 + 20.0j
    U = lambda yy: F.u_hat(x, yy, s, mat)  # noqa: E731  u_ij: load i, component j

    def residual(h: float) -> float:
        hess = np.zeros(U(y).shape + (3, 3), dtype=complex)
        for k in range(3):
            for m in range(3):
                ek, em = np.zeros(3), np.zeros(3)
                ek[k], em[m] = h, h
                hess[..., k, m] = (U(y + ek + em) - U(y + ek - em) - U(y - ek + em) + U(y - ek - em)) / (4 * h * h)
        lap = np.einsum("aijkk->aij", hess)
        grad_div = np.einsum("aikkj->aij", hess)  # d_j (d_k u_ik)
        rhs = mat.rho * s**2 * U(y)
        return np.abs(mat.mu * lap + (mat.lam + mat.mu) * grad_div - rhs).max() / np.abs(rhs).max()

    coarse, fine = residual(2e-3), residual(1e-3)
    assert fine < 1e-3
    assert coarse / fine == pytest.approx(4.0, rel=0.1)  # the residual is the O(h^2) differencing error


@pytest.mark.parametrize("name", ["nu0.3", "nu0.49"])
def test_p_hat_is_the_traction_of_u_hat(name, rng):
    """Catches transcription errors in Eq. (17): p_ij = sigma_jk(u_i.) n_k, for load direction i."""
    mat = MATERIALS[name]
    x, y, n = points(rng)
    for s in S_VALUES[:2]:
        grad = fd_gradient(lambda yy: F.u_hat(x, yy, s, mat), y)  # (a, i, j, k) = d u_ij / d y_k
        eps = 0.5 * (grad + np.swapaxes(grad, -1, -2))
        sigma = mat.lam * np.einsum("aijj->ai", eps)[..., None, None] * np.eye(3) + 2 * mat.mu * eps
        traction = np.einsum("aijk,ak->aij", sigma, n)
        P = F.p_hat(x, y, n, s, mat)
        assert np.abs(traction - P).max() < 1e-7 * np.abs(P).max()


@pytest.mark.parametrize("name", ["nu0.3", "incompressible"])
def test_body_force_kernels_are_fluxes_of_the_volume_integrands(name, rng):
    """d = V.n and l = W.n with div V = -rho u and div W = -rho u [y - x]x^T (Eqs. 4, 19, 21): the
    surface integrals of d and q equal the body-force volume integrals (their fluxes through a small
    sphere around x vanish: V and W are bounded there)."""
    mat = MATERIALS[name]
    x, y, _ = points(rng, 4)
    s = 200.0 + 150.0j
    unit = np.eye(3)

    def flux_field(kernel):
        return lambda yy: np.stack([kernel(x, yy, np.broadcast_to(unit[k], yy.shape if yy.ndim == 2 else x.shape), s, mat)
                                    for k in range(3)], axis=-1)

    V = flux_field(F.d_hat)
    W = flux_field(lambda xx, yy, nn, ss, mm: F.q_hat(xx, yy, nn, ss, mm, xx))  # x_bar = x: q = l
    U = F.u_hat(x, y, s, mat)
    divV = np.einsum("aijkk->aij", fd_gradient(V, y))
    divW = np.einsum("aijkk->aij", fd_gradient(W, y))
    assert np.abs(divV + mat.rho * U).max() < 1e-7 * np.abs(mat.rho * U).max()
    target = -mat.rho * U @ np.swapaxes(F.cross_matrix(y - x), -1, -2)
    assert np.abs(divW - target).max() < 1e-7 * np.abs(target).max()


def test_incompressible_branch_is_the_limit(rng):
    """nu -> 0.5 converges to the explicit branch linearly in 1 - 2 nu (the O(s r / c1) terms cancel;
    the leading difference is O(1 / c1^2))."""
    x, y, n = points(rng)
    exact = MATERIALS["incompressible"]
    for s in S_VALUES:
        for f in (F.u_hat, lambda a, b, s_, m: F.p_hat(a, b, n, s_, m), lambda a, b, s_, m: F.d_hat(a, b, n, s_, m)):
            A = f(x, y, s, exact)
            assert np.all(np.isfinite(A))
            gaps = [np.abs(A - f(x, y, s, wsim.ElasticMaterial(mu=exact.mu, nu=0.5 - eps, rho=exact.rho))).max() / np.abs(A).max()
                    for eps in (1e-8, 1e-10)]
            assert gaps[1] < 1e-5 and gaps[0] / gaps[1] == pytest.approx(100.0, rel=0.05)


def test_phi_series_and_closed_form_agree():
    """Just inside the switch radius the series is used; the closed form there agrees to round-off."""
    z = F.PHI_SERIES_LIMIT * (1 - 1e-12) * np.exp(1j * np.linspace(0, 2 * np.pi, 13))
    closed = ((1 + z) * np.exp(-z) - 1) / z**2
    assert np.abs(F.phi(z) - closed).max() < 1e-14
    assert abs(F.phi(np.array([1e-9]))[0] + 0.5) < 1e-9


# ----------------------------------------------------------------------------- Warp
def test_warp_kernels_match_numpy(device, rng):
    from wsim.bem.warp_eval import evaluate_kernels

    x, y, n = points(rng, 64)
    y[0] = x[0] + 1e-7 * n[0]  # |s r / c| tiny: the series branch
    for mat in MATERIALS.values():
        for s in S_VALUES + [1e-3 + 0j]:
            got = evaluate_kernels(x, y, n, s, mat, x_bar=np.zeros(3), device=device)
            for key, ref in (
                ("u", F.u_hat(x, y, s, mat)),
                ("p", F.p_hat(x, y, n, s, mat)),
                ("d", F.d_hat(x, y, n, s, mat)),
                ("q", F.q_hat(x, y, n, s, mat, np.zeros(3))),
            ):
                scale = np.abs(ref).max(axis=(-1, -2), keepdims=True)
                assert np.abs(got[key] - ref).max() < 1e-12 * scale.max(), key
                assert np.all(np.abs(got[key] - ref) <= 1e-11 * scale), key  # measured <= 1.4e-12 per pair
    wp.synchronize()


@wp.kernel
def _polar_of(A: wp.array(dtype=wp.mat33d), R: wp.array(dtype=wp.mat33d)):
    i = wp.tid()
    R[i] = bem_step.polar_rotation(A[i])


def test_device_polar_rotation_is_the_nearest_rotation(device):
    """The shape matching's R_e on the device (``kernels.bem_step.polar_rotation``: scaled Newton
    iterations, the SVD where det A <= 0) against ``wsim.rigid.nearest_rotation`` (numpy's SVD):
    near-rotations scaled by a stretched body's moment (anisotropy 1000:1), general matrices,
    and reflections (det < 0, the rotation nearest them)."""
    from wsim.rigid import nearest_rotation, rodrigues

    rng = np.random.default_rng(3)
    mats = []
    for k in range(40):
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        M = Q @ np.diag([1.0, 10.0 ** rng.uniform(0, 3), 10.0 ** rng.uniform(-3, 0)]) @ Q.T
        mats.append(M @ rodrigues(rng.normal(size=3) * (0.01 if k % 2 else 1.0)))
    mats += [rng.normal(size=(3, 3)) for _ in range(20)]
    mats += [np.diag([1.0, 2.0, -0.5]) @ rodrigues(rng.normal(size=3)) for _ in range(5)]
    A = np.array(mats)
    A = np.where(np.linalg.det(A)[:, None, None] == 0.0, A + np.eye(3), A)
    out = wp.zeros(len(A), dtype=wp.mat33d, device=device)
    wp.launch(_polar_of, dim=len(A), inputs=[wp.array(A, dtype=wp.mat33d, device=device)], outputs=[out], device=device)
    R = out.numpy()
    ref = nearest_rotation(A)
    positive = np.linalg.det(A) > 0
    # the polar factor's sensitivity to round-off grows with A's condition number
    cond = np.linalg.cond(A)
    err = np.abs(R - ref).max(axis=(1, 2))
    assert np.all(err[positive] < 1e-14 * cond[positive])
    assert np.all(err[~positive] < 1e-5)  # the float32-tuned SVD branch
    assert np.allclose(np.linalg.det(R), 1.0, atol=1e-5)
