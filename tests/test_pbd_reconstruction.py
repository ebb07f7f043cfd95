"""Keyframe-curve reconstruction: closed forms, fitting, baselines, kernels, metrics, World use."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp
from pxr import Usd, UsdGeom

import wsim
from wsim import mesh as wmesh
from wsim.kernels import pbd_reconstruct as kr
from wsim.pbd import baselines, pde, reconstruction  # noqa: F401 (wsim.pbd.reconstruction below, run alone too)
from wsim.pbd import fit as pf
from wsim.pbd.curves import Curve, auto_curves, paper_parameters

CASES = [(3.0**4, 2.0), (-(3.0**4), 2.0), (9.0**4, 1.1), (-(9.0**4), 5.0)]  # Krylov and scaled regimes, both signs


# ----------------------------------------------------------------------------- closed forms
@pytest.mark.parametrize("lam, m0", CASES)
def test_closed_forms_satisfy_the_beam_pde(lam, m0, rng):
    """m w_tt + D w_uuuu = 0 with D/m = m0^2 / D0^4 for both consistent families: the finite-difference
    residual is small against the size of the two terms (it shrinks as h^2)."""
    coeffs = rng.normal(size=(2, 4))
    uu, tt = np.meshgrid(np.linspace(0.2, 0.8, 7), np.linspace(0.2, 0.8, 7))
    r1 = pde.pde_residual_ratio(uu, tt, coeffs, lam, m0, h=4e-3)
    r2 = pde.pde_residual_ratio(uu, tt, coeffs, lam, m0, h=2e-3)
    assert r2 < 1e-3
    assert r1 / r2 == pytest.approx(4.0, rel=0.3)  # second-order finite differences: a real residual would not shrink


def test_spatial_bases_solve_the_ode_and_span_the_same_space(rng):
    u = np.linspace(0.0, 1.0, 41)
    for lam in (2.0**4, -(2.0**4), 6.0**4, -(6.0**4)):
        K = pde.krylov(u, lam)
        np.testing.assert_allclose(K[0], [1.0, 0.0, 0.0, 0.0], atol=1e-15)  # F_k^(j)(0) = delta_jk
        # the bounded basis spans the Krylov functions exactly
        E = pde.scaled_exponential(u, lam)
        coef, *_ = np.linalg.lstsq(E, K, rcond=None)
        assert np.abs(E @ coef - K).max() < 1e-9 * np.abs(K).max()
    # the series branch and the closed forms agree where they meet
    lam = 5.0**4
    edge = pde.SERIES_LIMIT / 5.0
    a, b = pde.krylov(np.array([edge * (1 - 1e-12), edge * (1 + 1e-12)]), lam)
    np.testing.assert_allclose(a, b, rtol=1e-10)


def test_pde_basis_tends_to_cubics_as_the_spatial_constant_vanishes():
    u = np.linspace(0.0, 1.0, 21)
    cubic = np.stack([u**0, u, u**2 / 2, u**3 / 6], axis=-1)
    errs = [np.abs(pde.spatial_basis(u, s * lam) - cubic).max() for lam in (1e-2, 1e-4, 1e-6) for s in (1, -1)]
    assert errs[0] < 1e-3 and errs[-1] < 1e-7  # leading error lam u^4 / 24
    assert errs[0] / errs[2] == pytest.approx(100.0, rel=0.05)  # linear in lam


def test_segment_closed_form_is_the_keyframe_blend(rng):
    """The paper's 8-coefficient form fitted to two keyframes equals Eq. (2), and m -> 0 is linear interpolation."""
    W0, W1 = rng.normal(size=4), rng.normal(size=4)
    u = np.linspace(0, 1, 9)[:, None]
    t = np.linspace(0, 1, 6)[None, :]
    F = pde.spatial_basis(u[:, 0], 16.0)
    for lam, m0 in [(16.0, 1.3), (-16.0, 2.5), (16.0, 0.0)]:
        c = pde.segment_coefficients(W0, W1, lam, m0)
        a, b = pde.blend_weights(t, m0, lam)
        F = pde.spatial_basis(u[:, 0], lam)
        np.testing.assert_allclose(pde.closed_form(u, t, c, lam, m0), a * (F @ W0)[:, None] + b * (F @ W1)[:, None], atol=1e-12)
    a, b = pde.blend_weights(t, 1e-6, -16.0)
    np.testing.assert_allclose(a, 1 - t, atol=1e-9)


# ----------------------------------------------------------------------------- fitting
def synthetic(lam: float, m0: float, coeffs: np.ndarray, n_points: int = 17, n_frames: int = 9):
    """A straight 'mesh' of points on a line (u = arc length) whose y displacement is the closed form."""
    x = np.linspace(0.0, 2.0, n_points)
    rest = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
    u = x / x[-1]
    t = np.linspace(0.0, 1.0, n_frames)
    disp = pde.closed_form(u[None, :], t[:, None], coeffs, lam, m0)  # (F, N)
    frames = np.repeat(rest[None], n_frames, axis=0)
    frames[:, :, 1] = disp
    return frames, rest


@pytest.mark.parametrize("lam, m0", CASES)
def test_fit_recovers_known_coefficients(lam, m0, rng):
    coeffs = rng.normal(size=(2, 4))
    frames, rest = synthetic(lam, m0, coeffs)
    curve = [list(range(len(rest)))]
    # given the constants, the 8 coefficients come back exactly
    r = pf.fit(frames, rest, stride=len(frames) - 1, curves=curve, fixed_lam=lam, fixed_m=m0)
    got = pde.segment_coefficients(r.coef[0, 0, 1], r.coef[1, 0, 1], lam, m0)
    np.testing.assert_allclose(got, coeffs, rtol=1e-7, atol=1e-7)
    # with the constants searched, the data are reproduced at every frame (a grid point may differ)
    r = pf.fit(frames, rest, stride=len(frames) - 1, curves=curve)
    diag = np.linalg.norm(np.ptp(frames.reshape(-1, 3), axis=0))
    err = max(np.abs(r.evaluate(f) - frames[f]).max() for f in range(len(frames)))
    assert err < 2e-2 * diag


def test_bezier_and_bspline_fits_coincide(rng):
    """One-segment cubic B-spline and cubic Bezier span the same cubics: identical fitted curves (the
    paper's identical table rows), different control points."""
    mesh = wmesh.bumpy_sphere(radius=0.3, subdivisions=2, amplitude=0.2)
    rest = np.asarray(mesh.vertices)
    frames = rest[None] + 0.02 * rng.normal(size=(4, len(rest), 3))
    bz = pf.fit(frames, rest, 1, method="bezier", points_per_curve=9)
    bs = pf.fit(frames, rest, 1, method="bspline", points_per_curve=9)
    for f in (0, 2, 3):
        np.testing.assert_allclose(bz.evaluate(f), bs.evaluate(f), atol=1e-12)
    assert np.abs(bz.coef - bs.coef).max() > 1e-3
    # and Cox-de Boor matches the closed-form uniform cubic basis; both bases sum to one
    u = np.linspace(0, 1, 51)
    np.testing.assert_allclose(baselines.uniform_cubic_bspline(u), baselines.uniform_cubic_bspline_closed(u), atol=1e-15)
    np.testing.assert_allclose(baselines.bernstein(u).sum(-1), 1.0, atol=1e-15)


def test_small_spatial_constant_fit_approaches_the_cubic_fit(rng):
    mesh = wmesh.bumpy_sphere(radius=0.3, subdivisions=2, amplitude=0.2)
    rest = np.asarray(mesh.vertices)
    frames = rest[None] + 0.05 * rng.normal(size=(2, len(rest), 3))
    bz = pf.fit(frames, rest, 1, method="bezier", points_per_curve=9).evaluate(1)
    gaps = [np.abs(pf.fit(frames, rest, 1, method="pde", points_per_curve=9, fixed_lam=lam, fixed_m=0.0).evaluate(1) - bz).max()
            for lam in (1e-2, 1e-4, 1e-6)]
    assert gaps[-1] < 1e-7 and gaps[0] > gaps[1] > gaps[2]


def smooth_motion(n_frames: int = 33):
    """A bumpy body that bends, swings and breathes smoothly in time (analytic, no simulation)."""
    mesh = wmesh.bumpy_sphere(radius=0.3, subdivisions=2, amplitude=0.2, seed=4)
    rest = np.asarray(mesh.vertices)
    t = np.linspace(0.0, 1.0, n_frames)[:, None, None]
    x, y = rest[None, :, 0:1], rest[None, :, 1:2]
    frames = rest[None] * (1 + 0.1 * np.sin(2.0 * t)) + np.concatenate(
        [0.3 * t**2 + 0.1 * np.sin(3.0 * t) * y, 0.2 * np.sin(2.5 * t) * x**2, 0.05 * np.cos(3.0 * t) * x], axis=2
    )
    return frames, rest, mesh.faces


def projection(r: pf.Reconstruction, data: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """Per curve and coordinate, the least-squares fit of ``data`` in the reconstruction's basis."""
    lay = r.layout
    target = data - rest if r.mode == "displacement" else data
    out = np.empty_like(data)
    for c in range(lay.n_curves):
        pts = lay.index[c, lay.mask[c]]
        own = np.flatnonzero(lay.vertex_curve == c)
        for w in range(3):
            if r.method == "pde":
                B, Bv = (pde.spatial_basis(x, r.lam[c, w]) for x in (lay.u[c, lay.mask[c], w], lay.vertex_u[own, w]))
            else:
                fn = baselines.bernstein if r.method == "bezier" else baselines.uniform_cubic_bspline
                B, Bv = fn(lay.u[c, lay.mask[c], w]), fn(lay.vertex_u[own, w])
            coef, *_ = np.linalg.lstsq(B, target[pts, w], rcond=None)
            out[own, w] = Bv @ coef
    return out + rest if r.mode == "displacement" else out


@pytest.mark.parametrize("method", pf.METHODS)
def test_keyframes_reproduced_within_fit_error_and_more_keyframes_never_hurt(method):
    frames, rest, _ = smooth_motion()
    diag = np.linalg.norm(np.ptp(rest, axis=0))
    inbetween = []
    for stride in (16, 8, 4, 2):
        r = pf.fit(frames, rest, stride, method=method, points_per_curve=8)
        keys = r.keyframes
        key_err = max(np.abs(r.evaluate(k) - frames[k]).max() for k in keys)
        if method == "linear":
            assert key_err == 0.0
        else:
            # a keyframe is rebuilt as the least-squares projection of its data onto each curve's
            # basis: recompute that projection independently, curve by curve
            k = int(keys[1])
            np.testing.assert_allclose(r.evaluate(k), projection(r, frames[k], rest), atol=1e-10)
            assert key_err < 0.01 * diag
        inner = np.setdiff1d(np.arange(len(frames)), keys)
        inbetween.append(max(np.abs(r.evaluate(f) - frames[f]).max() for f in inner))
    assert all(b <= a * (1 + 1e-9) for a, b in zip(inbetween, inbetween[1:])), inbetween
    assert inbetween[-1] < 0.5 * inbetween[0]


def test_paper_parametrization_and_data_accounting():
    frames, rest, _ = smooth_motion(9)
    chord = pf.fit(frames, rest, 4, method="pde", points_per_curve=8)
    paper = pf.fit(frames, rest, 4, method="pde", points_per_curve=8, parametrization="paper")
    C, nk = chord.layout.n_curves, len(chord.keyframes)
    assert chord.stored_floats == nk * C * 3 * 4 + C * 3 + (nk - 1) * C * 3
    assert paper.stored_floats == chord.stored_floats + 3 * int(paper.layout.mask.sum())
    assert chord.data_ratio == pytest.approx(chord.stored_floats / frames.size)
    u = paper_parameters(frames[[0, 4, 8]], paper.layout.curves[0])
    assert u.min() >= 0.0 and u.max() <= 1.0
    flat = np.zeros((2, 5, 3))
    flat[:, :, 0] = np.arange(5)
    with pytest.raises(wsim.InvalidParameter, match="constant"):
        paper_parameters(flat, Curve(np.arange(5)))


def test_auto_curves_cover_every_vertex_once():
    mesh = wmesh.neck_body(rings=30, sectors=12)
    curves = auto_curves(mesh.vertices, 10)
    allv = np.concatenate([c.indices for c in curves])
    assert np.array_equal(np.sort(allv), np.arange(len(mesh.vertices)))
    assert max(len(c.indices) for c in curves) <= 10


def test_paper_error_depends_on_the_origin_and_ours_does_not(rng):
    truth = rng.normal(size=(50, 3))
    rec = truth + 0.01 * rng.normal(size=truth.shape)
    shift = np.array([10.0, 0.0, 0.0])
    ea, em = wsim.pbd.reconstruction.paper_errors(rec, truth)
    ea2, _ = wsim.pbd.reconstruction.paper_errors(rec + shift, truth + shift)
    assert ea2 < 0.5 * ea  # moving the model away from the origin shrinks the paper's relative error
    r1 = wsim.pbd.reconstruction.relative_error(rec, truth)
    assert r1 == pytest.approx(wsim.pbd.reconstruction.relative_error(rec + shift, truth + shift), rel=1e-12)
    assert em >= ea


# ----------------------------------------------------------------------------- kernel
def test_kernel_matches_numpy_for_every_basis_and_branch(device, rng):
    """The Warp kernel against the float64 numpy evaluator, with spatial constants of both signs in
    both regimes (series, closed-form Krylov, bounded exponentials) and sin and sinh blends."""
    frames, rest, faces = smooth_motion(9)
    for basis in pf.METHODS:
        rec = wsim.PbdReconstruction(frames, stride=4, basis=basis, faces=faces, points_per_curve=8)
        if basis == "pde":  # force every branch: random constants per curve and coordinate
            m = rec.model
            C = m.layout.n_curves
            lam = rng.choice([1e-3, 2.0**4, 7.0**4, -1e-3, -(2.0**4), -(7.0**4)], size=(C, 3))
            mm = rng.uniform(0.0, 2.5, size=m.m.shape)
            object.__setattr__(m, "lam", lam)
            object.__setattr__(m, "m", mm)
        world = wsim.World(device=device)
        world.add(rec)
        for f in (0, 1, 3, 4, 6, 8):
            np.testing.assert_allclose(rec.evaluate(f).numpy(), rec.model.evaluate(f), atol=2e-6, rtol=1e-6)


# ----------------------------------------------------------------------------- World, USD, bad input
def test_reconstruction_plays_back_in_a_world_and_exports(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    sim_world = wsim.World(device="cpu")
    sim_world.add_collider(wsim.GroundPlane())
    body = sim_world.add(wsim.PbdBody(sphere, name="ball", position=(0, 0.5, 0)))
    rec = wsim.record(sim_world, body, 12)
    assert rec.frames.shape == (13, len(sphere.vertices), 3)

    world = wsim.World(device="cpu")
    recon = world.add(wsim.PbdReconstruction(rec, stride=4, points_per_curve=6))
    out = tmp_path / "rec.usda"
    world.run(12, out, progress=False)
    stage = Usd.Stage.Open(str(out))
    pts = np.array(UsdGeom.Mesh(stage.GetPrimAtPath("/World/ball_reconstructed")).GetPointsAttr().Get(8))
    np.testing.assert_allclose(pts, recon.model.evaluate(8), atol=1e-5)
    assert wsim.pbd.reconstruction.relative_error(pts, rec.frames[8]) < 0.05
    with pytest.raises(wsim.InvalidParameter, match="covers frames 0..12"):
        world.step()


def test_reconstruction_simulates_its_own_body():
    """With an unbound PbdBody, the reconstruction simulates it privately (with the World's
    colliders) and with stride 1 reproduces the simulated frames within the spatial fit error."""
    sphere = wmesh.bumpy_sphere(radius=0.2, subdivisions=2)
    kw = dict(name="ball", position=(0, 0.4, 0), velocity=(1.0, 0.0, 0.0))
    world = wsim.World(device="cpu")
    world.add_collider(wsim.GroundPlane())
    sim = world.add(wsim.PbdBody(sphere, **kw))
    recon = world.add(wsim.PbdReconstruction(wsim.PbdBody(sphere, **kw), stride=1, frames=10, points_per_curve=6))
    # read before the first step (the World attaches its colliders then): the start, and no
    # private run without the ground (it used to simulate there and then, through the ground)
    np.testing.assert_array_equal(recon.points(), sim.points())
    worst = 0.0
    simulated = [sim.points()]
    for _ in range(10):
        world.step()
        simulated.append(sim.points())
        worst = max(worst, wsim.pbd.reconstruction.relative_error(recon.points(), sim.points()))
    # the private run saw the same ground: its frames are the World's frames, bit for bit (CPU)
    assert np.array_equal(recon.recording.frames, np.array(simulated))
    assert worst < 0.05  # stride 1: only the spatial fit error of 6-point curves remains


def test_bad_reconstruction_input_is_named():
    frames, rest, faces = smooth_motion(9)
    n = len(rest)
    with pytest.raises(wsim.InvalidParameter, match="appears more than once"):
        pf.fit(frames, rest, 2, curves=[[0, 1, 1, 2], list(range(3, n))])
    with pytest.raises(wsim.InvalidParameter, match="out of range"):
        pf.fit(frames, rest, 2, curves=[[0, 1, n + 5]])
    with pytest.raises(wsim.InvalidParameter, match="lie on no curve"):
        pf.fit(frames, rest, 2, curves=[[0, 1, 2]])
    for bad in (0, -2, 1.5, True):
        with pytest.raises(wsim.InvalidParameter, match="stride"):
            wsim.PbdReconstruction(frames, stride=bad, faces=faces)
    with pytest.raises(wsim.InvalidParameter, match="at least 2 keyframes"):
        wsim.PbdReconstruction(frames[:1], stride=1, faces=faces)
    with pytest.raises(wsim.InvalidParameter, match="basis"):
        wsim.PbdReconstruction(frames, basis="nurbs", faces=faces)
    with pytest.raises(wsim.InvalidParameter, match="faces="):
        wsim.PbdReconstruction(frames)
    world = wsim.World(device="cpu")
    body = world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1), name="b"))
    with pytest.raises(wsim.InvalidParameter, match="already belongs to a World"):
        wsim.PbdReconstruction(body, frames=5)
    with pytest.raises(wsim.InvalidParameter, match="frames="):
        wsim.PbdReconstruction(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1)))


def test_kernel_module_compiles_once(device):
    """The reconstruction kernels live in one Warp module (compiled once per device)."""
    wp.load_module(kr, device=device)


def test_closed_user_curves():
    """Rings of a surface of revolution as closed user curves: each ring is fitted with its first
    vertex repeated at u = 1 (as the paper does) and every vertex is rebuilt."""
    mesh = wmesh.neck_body(rings=12, sectors=8)
    v = np.asarray(mesh.vertices)
    rings = [np.flatnonzero(np.isclose(v[:, 0], x)) for x in np.unique(v[:, 0])]
    curves = [Curve(r[np.argsort(np.arctan2(v[r, 2], v[r, 1]))], closed=True) for r in rings]
    assert [len(c.indices) for c in curves].count(1) == 2  # the poles: single-vertex curves, fitted exactly
    t = np.linspace(0.0, 1.0, 5)[:, None, None]
    frames = v[None] * (1.0 + 0.1 * t * np.sin(3.0 * v[None, :, 0:1])) + 0.05 * t  # swelling neck, drifting body
    for method in ("pde", "bezier"):
        r = pf.fit(frames, v, 2, method=method, curves=curves)
        assert r.layout.index.shape[1] == max(len(c.indices) for c in curves) + 1  # closing point added
        err = max(np.abs(r.evaluate(f) - frames[f]).max() for f in range(len(frames)))
        assert err < 0.05 * np.linalg.norm(np.ptp(v, axis=0))
