"""BEM time stepping (paper Eqs. 9-12, Sec. 3.2.1): BemBody against analytic results.

Small meshes (42- and 162-node icospheres, a 98-node box) keep the CPU run short; every operator set
is built once per module.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from scipy.optimize import curve_fit

import warp as wp

import wsim
from wsim.bem import build_operators
from wsim.bem.analytic import breathing_frequency, breathing_xi, static_radial_displacement
from wsim.rigid import rodrigues

import bem_box  # noqa: E402 (tests/ is on the path: the contact tests' 26-node cube, ``box_ops``)

RADIUS = 0.1
MAT = wsim.ElasticMaterial(E=1.0e5, nu=0.3, rho=1000.0)
PERIOD = 2.0 * math.pi / breathing_frequency(MAT, RADIUS)  # 20.3 ms


def sphere(subdivisions: int) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=RADIUS)


@pytest.fixture(scope="module")
def ops_cache():
    """Operator sets by (subdivisions, steps per breathing period, precision), built on demand once."""
    built: dict = {}

    def get(subdivisions: int, per_period: int, precision: str = "float32"):
        key = (subdivisions, per_period, precision)
        if key not in built:
            built[key] = build_operators(sphere(subdivisions), MAT, PERIOD / per_period, precision=precision,
                                         cache=False, device="cpu")
        return built[key]

    return get


def make_body(ops, mesh, gravity=(0.0, 0.0, 0.0), **kwargs):
    world = wsim.World(fps=1.0 / ops.dt, device="cpu", gravity=gravity)
    body = world.add(wsim.BemBody(mesh, ops.material, ops.dt, operators=ops, **kwargs))
    return world, body


def radial(body) -> float:
    """Mean radial displacement of the surface [m]."""
    return float(np.mean(np.einsum("ij,ij->i", body.vertex_displacement(), body.rest_normals)))


# --------------------------------------------------------------------------------------------
def test_free_fall_follows_discrete_ballistic_trajectory(ops_cache):
    ops = ops_cache(1, 10)
    v0 = np.array([0.5, 2.0, -0.3])
    world, body = make_body(ops, sphere(1), gravity=(0.0, -9.81, 0.0), velocity=v0, position=(0.0, 1.0, 0.0))
    T0 = body.frame.T.copy()
    for _ in range(40):
        body.step()
    n, dt = body.steps, body.dt
    expected = T0 + n * dt * v0 + dt * dt * np.array([0.0, -9.81, 0.0]) * n * (n + 1) / 2  # Eq. (11d, f)
    np.testing.assert_allclose(body.frame.T, expected, rtol=0, atol=1e-12)
    assert np.max(np.abs(body.displacement())) < 1e-15  # a = g': no body force, no deformation
    # the exported points are the rest shape carried by the frame
    np.testing.assert_allclose(body.points(), body.rest_vertices + body.frame.T, atol=1e-12)


def test_free_spin_about_principal_axis_keeps_omega(ops_cache):
    ops = ops_cache(1, 10)
    omega = np.array([0.0, 0.0, 2.0 * math.pi * 3])  # 3 rev/s about z (an icosphere is isotropic)
    _, body = make_body(ops, sphere(1), angular_velocity=omega)
    for _ in range(100):
        body.step()
    np.testing.assert_allclose(body.frame.omega, omega, rtol=0, atol=1e-12)
    assert np.max(np.abs(body.displacement())) < 1e-15  # round-off: centrifugal force is omitted by the paper
    R_expected = rodrigues(omega * body.time)
    np.testing.assert_allclose(body.frame.R, R_expected, atol=1e-9)


def box_mesh() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(0.3, 0.2, 0.1)).subdivide()


def test_torque_free_spin_about_a_general_axis(tmp_path):
    """A box spun off its principal axes: gyroscopic=True keeps L exactly and the energy bounded; the
    paper's Eq. (11e) (gyroscopic=False) keeps omega instead and lets L wander."""
    mat = wsim.ElasticMaterial(E=1e7, nu=0.3, rho=1000.0)
    ops = build_operators(box_mesh(), mat, 2e-3, cache=False, device="cpu")
    omega0 = np.array([1.0, 4.0, 0.5])
    runs = {}
    for gyro in (True, False):
        _, body = make_body(ops, box_mesh(), angular_velocity=omega0, gyroscopic=gyro)
        L0, E0 = body.angular_momentum(), body.kinetic_energy()
        energies = []
        for _ in range(300):
            body.step()
            energies.append(body.kinetic_energy())
        runs[gyro] = (L0, E0, body.angular_momentum(), np.array(energies), body.frame.omega)
    L0, E0, L1, energies, omega1 = runs[True]
    np.testing.assert_allclose(L1, L0, rtol=1e-12, atol=1e-15)
    assert np.max(np.abs(energies / E0 - 1.0)) < 0.05  # explicit R lags a step: bounded, not conserved
    assert np.linalg.norm(omega1 - omega0) > 0.1  # it precesses
    L0p, _, L1p, _, omega1p = runs[False]
    np.testing.assert_allclose(omega1p, omega0, atol=1e-12)
    assert np.linalg.norm(L1p - L0p) > 1e-3 * np.linalg.norm(L0p)


# --------------------------------------------------------------------------------------------
def damped_cosine(t, A, sigma, omega, phi, c):
    return A * np.exp(-sigma * t) * np.cos(omega * t + phi) + c


def ring_sphere(ops, subdivisions: int, periods: float = 5.0):
    """Uniform pressure for a quarter period, then free: returns (t, mean radial displacement) after release."""
    _, body = make_body(ops, sphere(subdivisions))
    n = body.rest_normals
    pulse = 0.25 * PERIOD
    body.add_traction(lambda t: -1000.0 * n if t <= pulse + 1e-12 else 0.0 * n)
    ts, ur = [], []
    while body.time < periods * PERIOD:
        body.step()
        ts.append(body.time)
        ur.append(radial(body))
    ts, ur = np.array(ts), np.array(ur)
    keep = ts > pulse + 2.0 * ops.dt
    return ts[keep], ur[keep]


def fitted_mode(ts, ur):
    omega0 = 2.0 * math.pi / PERIOD
    p0 = (np.max(np.abs(ur)), 10.0, omega0, 0.0, 0.0)
    (A, sigma, omega, phi, c), _ = curve_fit(damped_cosine, ts - ts[0], ur, p0=p0, maxfev=20000)
    return omega, sigma


def bdf1_mode(dt: float) -> tuple[float, float]:
    """The breathing mode as BDF1-CQ reproduces it: pole s = i omega maps to zeta = 1 / (1 - i omega dt)
    per step, so omega_d = atan(omega dt) / dt and decay rate sigma_d = ln(1 + (omega dt)^2) / (2 dt)."""
    w = 2.0 * math.pi / PERIOD
    return math.atan(w * dt) / dt, math.log1p((w * dt) ** 2) / (2.0 * dt)


def test_breathing_xi_solves_the_frequency_equation():
    for nu in (0.0, 0.25, 0.3, 0.45):
        m = wsim.ElasticMaterial(E=1.0, nu=nu, rho=1.0)
        xi = breathing_xi(m)
        assert 0.0 < xi < math.pi
        assert abs(xi / math.tan(xi) - (1.0 - (m.c1 / (2.0 * m.c2)) ** 2 * xi * xi)) < 1e-10


def test_sphere_rings_at_its_breathing_frequency(ops_cache):
    """Frequency and damping of the released sphere match the breathing mode as BDF1 discretizes it;
    the remaining (spatial) error shrinks with the mesh, and the total error with dt."""
    omega = 2.0 * math.pi / PERIOD
    errors = {}
    for sub, per in ((1, 10), (1, 20), (2, 10)):
        ops = ops_cache(sub, per)
        w_fit, s_fit = fitted_mode(*ring_sphere(ops, sub))
        w_d, s_d = bdf1_mode(ops.dt)
        errors[(sub, per)] = (w_fit / w_d - 1.0, w_fit / omega - 1.0, s_fit / s_d - 1.0)
    # against the BDF1-discretized mode: only the mesh error is left, and it shrinks with h
    assert abs(errors[(1, 10)][0]) < 0.05 and abs(errors[(1, 20)][0]) < 0.05
    assert abs(errors[(2, 10)][0]) < 0.015
    assert abs(errors[(2, 10)][0]) < 0.5 * abs(errors[(1, 10)][0])
    # against the continuous frequency: halving dt cuts the error
    assert abs(errors[(1, 20)][1]) < 0.5 * abs(errors[(1, 10)][1])
    assert abs(errors[(1, 20)][1]) < 0.06
    # the numerical damping is BDF1's
    for key, (_, _, damping) in errors.items():
        assert abs(damping) < 0.25, (key, damping)


def test_slow_pressure_reaches_the_elastostatic_sphere(ops_cache):
    expected = static_radial_displacement(MAT, RADIUS, 1000.0)
    errs = []
    for sub in (1, 2):
        ops = ops_cache(sub, 10)
        _, body = make_body(ops, sphere(sub))
        n = body.rest_normals
        ramp = 3.0 * PERIOD
        body.add_traction(lambda t: -1000.0 * min(t / ramp, 1.0) * n)
        while body.time < 8.0 * PERIOD:
            body.step()
        errs.append(abs(radial(body) / expected - 1.0))
        # uniform pressure has no net force or torque: the frame stays put
        assert np.linalg.norm(body.frame.T - body._T0) < 1e-6
        assert np.linalg.norm(body.frame.velocity) < 1e-5
    assert errs[0] < 0.04 and errs[1] < 0.005 and errs[1] < errs[0]


# --------------------------------------------------------------------------------------------
def test_frame_update_removes_the_volume_gain_of_large_rotations():
    # Without the frame, rigid motion lives in u, and the paper's n_max (17 here) truncates the BDF1
    # history tail enough to make the rigid modes grow (|u - rigid| 0.03 -> 3.7 m in 0.25 s, measured);
    # at n_max = 40 the free rigid motion is reproduced to 4 mm. The frame run is unaffected either way.
    ops = build_operators(sphere(1), MAT, PERIOD / 10, n_max=40, cache=False, device="cpu")
    volumes = {}
    for frame_update in (True, False):
        _, body = make_body(ops, sphere(1), velocity=(2.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, 6.0),
                            frame_update=frame_update)
        v0 = body.volume()
        change = 0.0
        while body.time < 0.25:  # 1.5 rad and 0.5 m: several body sizes
            body.step()
            change = max(change, abs(body.volume() / v0 - 1.0))
        volumes[frame_update] = change
        # both runs move the body the same way
        centre = body.points().mean(axis=0)
        assert abs(centre[0] - 2.0 * body.time) < 0.02
    assert volumes[True] < 1e-6
    assert volumes[False] > 0.5  # linearized rotation by 1.5 rad: det(I + [theta]x) - 1 = theta^2


def test_internal_pinch_leaves_the_frame_at_rest(ops_cache):
    """Equal and opposite tractions: A p = C p = 0, so the frame never moves, and the error correction
    keeps the deformation's centroid at the origin."""
    ops = ops_cache(1, 10)
    _, body = make_body(ops, sphere(1))
    x = body.rest_vertices
    side = np.sign(x[:, 0])[:, None] * np.array([1.0, 0.0, 0.0])
    weights = np.abs(x[:, 0]) > 0.05
    body.add_traction(lambda t: -2000.0 * side * weights[:, None] * (t < 0.01))
    for _ in range(60):
        body.step()
    assert np.linalg.norm(body.frame.velocity) < 1e-6 and np.linalg.norm(body.frame.omega) < 1e-5
    u = body.displacement()
    w = body._so.correction.w
    assert np.linalg.norm(w @ u / w.sum()) < 1e-3 * np.max(np.abs(u))


def test_traction_pulse_transfers_momentum_to_the_frame(ops_cache):
    """A uniform push of total impulse J ends as frame momentum J (Eq. 10, 11d) to 1e-5 (measured
    1.1e-7) once the body has rung down. The error correction hands the drift to the frame's
    acceleration; without the loads' balance (``correction.load_balance``) the push's drift was
    systematic and the frame ended at +1.9 % here."""
    ops = ops_cache(1, 10)
    _, body = make_body(ops, sphere(1))
    areas = wsim.mesh.vertex_areas(*body._mesh)
    traction = np.array([300.0, 0.0, 0.0])
    steps = 5
    body.add_traction(lambda t: np.tile(traction, (len(areas), 1)) if t <= steps * body.dt + 1e-12 else np.zeros((len(areas), 3)))
    for _ in range(200):
        body.step()
    impulse = traction * areas.sum() * steps * body.dt
    np.testing.assert_allclose(body.linear_momentum(), impulse, rtol=1e-5, atol=1e-5 * impulse[0])
    assert np.max(np.abs(body.displacement())) < 1e-6  # rung down, no drift left in u


def test_load_balance_makes_the_static_limit_drift_free(box_ops):
    """``correction.load_balance``: with the frame terms (A p, C p) + X p, the static limit of the
    step (the CQ weights summed) has a solution u free of the correction's rigid modes (weighted
    centroid and linearized rotation), for any traction p; with (A p, C p) alone it has not: a
    uniform traction on the 26-node cube's bottom face needs 4.7 % more than A p."""
    import scipy.linalg

    from wsim.bem.correction import Correction, load_balance

    ops = box_ops
    E = scipy.linalg.lu_solve(ops.H0_lu, np.concatenate([ops.D[0], ops.Q[0]], axis=1))
    c = Correction.from_operators(ops, E)
    X = load_balance(ops, c)
    n = ops.n_nodes
    Hs = np.asarray(ops.H, dtype=np.float64).sum(axis=0)
    Gs = np.asarray(ops.G, dtype=np.float64).sum(axis=0)
    DQs = np.concatenate([ops.D.sum(axis=0), ops.Q.sum(axis=0)], axis=1)
    AC = np.vstack([ops.A, ops.C])

    def rigid_part(p: np.ndarray, beta: np.ndarray) -> np.ndarray:  # (t, theta) of the static u
        u = np.linalg.solve(Hs, Gs @ p + DQs @ beta).reshape(n, 3)
        t = c.w @ u / c.w_sum
        J = np.einsum("n,nab->ab", c.w, (c.q * c.q).sum(axis=1)[:, None, None] * np.eye(3)
                      - c.q[:, :, None] * c.q[:, None, :])
        theta = np.linalg.solve(J, (c.w[:, None] * np.cross(c.q, u - t)).sum(axis=0))
        return np.concatenate([t, theta])

    rng = np.random.default_rng(3)
    for p in rng.normal(size=(3, 3 * n)):
        scale = np.abs(rigid_part(p, AC @ p)).max()
        assert np.abs(rigid_part(p, AC @ p + X @ p)).max() < 1e-8 * scale
    bottom = ops.surface.nodes[:, 1] < ops.surface.nodes[:, 1].min() + 1e-9
    p = (bottom[:, None] * np.array([0.0, 1.0, 0.0])).reshape(-1)
    assert (ops.A @ p + X[:3] @ p)[1] / (ops.A @ p)[1] == pytest.approx(1.047, abs=0.002)


@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs CUDA")
def test_load_balance_on_the_gpu_matches_the_host(box_ops):
    """The loads' balance summed and solved through CuPy (``StepOperators.load_balance`` on a CUDA
    set) is the host's to round-off (skipped without CuPy)."""
    import scipy.linalg

    from wsim.bem.correction import Correction, load_balance
    from wsim.bem.factorization import cupy_module

    cp = cupy_module()
    if cp is None:
        pytest.skip("CuPy (the gpu extra) not installed")
    ops = box_ops
    c = Correction.from_operators(ops, scipy.linalg.lu_solve(ops.H0_lu, np.concatenate([ops.D[0], ops.Q[0]], axis=1)))
    host = load_balance(ops, c)
    with cp.cuda.Device(0):
        gpu = load_balance(ops, c, cp)
    np.testing.assert_allclose(gpu, host, rtol=1e-8, atol=1e-10 * np.abs(host).max())


@pytest.mark.parametrize("where", ["corner", "face"])
@pytest.mark.parametrize("path", ["host", "device"])
def test_a_held_vertex_load_changes_momentum_by_its_impulse(box_ops, where, path):
    """A 26-node cube under gravity held up by its weight as a vertex load (``add_vertex_impulses``,
    renewed every frame: the World's push from other bodies) on one bottom corner or spread over
    the bottom face: over 1 s its momentum changes by the impulse handed to it minus m g t to
    0.5 % of m g t (measured 0.04 % and 0.11 %) and its centre of mass stays within 2 cm (4 and
    12 mm). Without the loads' balance (``correction.load_balance``) the error correction turned
    the discrete response's drift into frame acceleration: the face load lifted the cube at
    0.49 m/s^2 (0.25 m in the second), the corner load at 0.64 m/s^2 with a sideways drift.
    ``device``: the free steps kept on the device (Warp's kernels, here on the CPU)."""
    T = 10 * bem_box.DT
    w = wsim.World(fps=1.0 / T, device="cpu", gravity=(0.0, -9.81, 0.0))
    body = w.add(wsim.BemBody(bem_box.BOX, bem_box.MAT, bem_box.DT, operators=box_ops, name="cube", **(
        {"matvec": "warp", "device_step": True} if path == "device" else {})))
    V = body.points()
    F = np.zeros_like(V)
    low = np.flatnonzero(V[:, 1] < V[:, 1].min() + 1e-9)
    if where == "corner":
        low = low[[np.argmin(V[low].sum(axis=1))]]
    F[low, 1] = body.mass * 9.81 / len(low)
    p0, x0 = body.linear_momentum(), body.center_of_mass()
    for _ in range(50):
        body.add_vertex_impulses(F * T, T)
        w.step()
    expected = body.coupling_impulse + body.mass * np.array([0.0, -9.81, 0.0]) * w.time
    assert np.linalg.norm(body.linear_momentum() - p0 - expected) < 5e-3 * body.mass * 9.81 * w.time
    assert np.linalg.norm(body.center_of_mass() - x0) < 0.02


@pytest.mark.parametrize("path", ["host", "device", "uncorrected"])
def test_a_corner_push_turns_the_body_by_r_cross_j(box_ops, path):
    """A push J along z at one corner of a free 26-node cube, delivered over one frame of 10 steps
    (``add_vertex_impulses``): 0.2 s later the momentum has changed by J to 0.1 % (measured 0.006 %)
    and the angular momentum by r x J to 1 % (measured 0.48 %: the corner moves while the push
    acts). The frame takes the push's moment at the vertex (``BemBody._push_torque``) and the BEM
    the loads' balance (``correction.load_balance``); before both, the moment acted at the hat
    function's centroid (C p, Eq. 10): the cube turned by 14 % less about one axis and its
    momentum changed by 9 % more, partly sideways. ``uncorrected``: without the error correction
    the frame takes the push's moment at the vertex all the same (checked after 2 frames: the
    uncorrected drift grows, and stops the body at 0.28 s)."""
    T = 10 * bem_box.DT
    w = wsim.World(fps=1.0 / T, device="cpu", gravity=(0.0, 0.0, 0.0))
    kw = {"device": {"matvec": "warp", "device_step": True}, "uncorrected": {"error_correction": False}}.get(path, {})
    body = w.add(wsim.BemBody(bem_box.BOX, bem_box.MAT, bem_box.DT, operators=box_ops, name="cube", **kw))
    V = body.points()
    i = int(np.argmax(V.sum(axis=1)))
    J = np.zeros_like(V)
    J[i] = (0.0, 0.0, 0.5)
    r = V[i] - body.center_of_mass()
    L0 = body.angular_momentum()
    body.add_vertex_impulses(J, T)
    for _ in range(2 if path == "uncorrected" else 21):
        w.step()
    assert np.linalg.norm(body.linear_momentum() - J[i]) < 1e-3 * np.linalg.norm(J[i])
    assert np.linalg.norm(body.angular_momentum() - L0 - np.cross(r, J[i])) < 0.01 * np.linalg.norm(np.cross(r, J[i]))


def test_error_correction_is_what_keeps_the_rigid_drift_bounded(ops_cache):
    """Sec. 3.2.1: "left untreated, this drift can become a source of instability" - measured here."""
    ops = ops_cache(1, 10)
    peaks = {}
    for correction in (True, False):
        _, body = make_body(ops, sphere(1), error_correction=correction)
        n_v = len(body.rest_vertices)
        body.add_traction(lambda t: np.tile([300.0, 0.0, 0.0], (n_v, 1)) * (t <= 5 * body.dt + 1e-12))
        for _ in range(150):
            body.step()
        peaks[correction] = float(np.max(np.abs(body.displacement())))
    assert peaks[True] < 1e-5  # still ringing down (4e-4 m at the end of the push)
    assert peaks[False] > 1e-2  # grows exponentially (1.5 m after 200 steps)


# --------------------------------------------------------------------------------------------
def pushed_trajectory(ops, mesh, steps=40, **kwargs):
    _, body = make_body(ops, mesh, gravity=(0.0, -9.81, 0.0), angular_velocity=(0.0, 3.0, 1.0), **kwargs)
    n = body.rest_normals
    x = body.rest_vertices
    body.add_traction(lambda t: (-800.0 * n * (x[:, :1] > 0) + np.array([0.0, 100.0, 0.0])) * (t < 0.01))
    out = []
    for _ in range(steps):
        body.step()
        out.append(body.points())
    return np.array(out), body


def test_warp_kernels_match_blas_on_cpu(ops_cache):
    """The CUDA code path (Warp kernels) runs on the CPU device too and matches numpy BLAS."""
    ops = ops_cache(1, 10)
    a, _ = pushed_trajectory(ops, sphere(1), matvec="warp")
    b, _ = pushed_trajectory(ops, sphere(1), matvec="blas")
    scale = np.max(np.abs(a - a[:1]))
    assert np.max(np.abs(a - b)) < 1e-5 * scale


def test_float32_storage_tracks_float64(ops_cache):
    a, body_a = pushed_trajectory(ops_cache(1, 10, "float32"), sphere(1))
    b, body_b = pushed_trajectory(ops_cache(1, 10, "float64"), sphere(1))
    u_a, u_b = body_a.displacement(), body_b.displacement()
    assert np.max(np.abs(u_a - u_b)) < 1e-4 * np.max(np.abs(u_b))
    assert np.max(np.abs(a - b)) < 1e-6


def test_world_run_exports_usd(tmp_path, ops_cache):
    from pxr import Usd, UsdGeom

    ops = ops_cache(1, 10)
    world = wsim.World(fps=50, device="cpu")
    body = world.add(wsim.BemBody(sphere(1), MAT, ops.dt, operators=ops, name="ball", velocity=(1.0, 0.0, 0.0)))
    summary = world.run(frames=3, out=tmp_path / "bem.usda", progress=False)
    assert summary.frames == 3
    assert abs(body.time - 3 / 50) <= 0.5 * ops.dt + 1e-12
    stage = Usd.Stage.Open(str(tmp_path / "bem.usda"))
    pts = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ball")).GetPointsAttr().Get(3)
    np.testing.assert_allclose(np.asarray(pts), body.points(), atol=1e-6)


# --------------------------------------------------------------------------------------------
def test_bad_input_is_refused_before_any_build(ops_cache, monkeypatch):
    import wsim.bem.body as bb

    def no_build(*a, **k):  # nothing may be assembled for rejected input
        raise AssertionError("operators were built for invalid input")

    monkeypatch.setattr(bb, "build_operators", no_build)
    open_mesh = sphere(1)
    open_mesh = trimesh.Trimesh(open_mesh.vertices, open_mesh.faces[:-3], process=False)
    with pytest.raises(wsim.InvalidMesh):
        wsim.BemBody(open_mesh, MAT, 1e-3)
    for dt in (0.0, -1.0, float("nan")):
        with pytest.raises(wsim.InvalidParameter, match="dt"):
            wsim.BemBody(sphere(1), MAT, dt)
    with pytest.raises(wsim.InvalidParameter, match="rotation"):
        wsim.BemBody(sphere(1), MAT, 1e-3, rotation=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(wsim.InvalidParameter, match="precision"):
        wsim.BemBody(sphere(1), MAT, 1e-3, precision="float16")
    with pytest.raises(wsim.InvalidParameter, match="another mesh"):
        wsim.BemBody(sphere(2), MAT, ops_cache(1, 10).dt, operators=ops_cache(1, 10))
    with pytest.raises(wsim.InvalidParameter, match="dt"):
        wsim.BemBody(sphere(1), MAT, 1e-3, operators=ops_cache(1, 10))


def test_bad_traction_load_names_the_body(ops_cache):
    ops = ops_cache(1, 10)
    _, body = make_body(ops, sphere(1), name="ball")
    body.add_traction(lambda t: np.zeros((5, 3)))
    with pytest.raises(wsim.InvalidParameter, match="ball.*shape"):
        body.step()
    _, body = make_body(ops, sphere(1), name="ball")
    body.add_traction(lambda t: np.full((42, 3), np.nan))
    with pytest.raises(wsim.InvalidParameter, match="non-finite"):
        body.step()
    with pytest.raises(wsim.InvalidParameter):
        body.add_traction("not callable")


@pytest.mark.parametrize("matvec", ["blas", "warp"])  # the host path, and the step kept on the device
def test_divergence_stops_with_the_body_and_quantity_named(tmp_path, ops_cache, matvec):
    ops = ops_cache(1, 10)
    world = wsim.World(fps=50, device="cpu", gravity=(0.0, 0.0, 0.0))
    body = world.add(wsim.BemBody(sphere(1), MAT, ops.dt, operators=ops, name="ball", divergence_limit=1e-5,
                                  matvec=matvec))
    n = body.rest_normals
    body.add_traction(lambda t: -1000.0 * n * (t > 0.03))  # |u| ~ 4e-4 m > limit, from the 2nd frame on
    with pytest.raises(wsim.SimulationDiverged, match="ball.*displacement") as err:
        world.run(frames=5, out=tmp_path / "div.usda", progress=False)
    assert err.value.step == 2
    from pxr import Usd

    stage = Usd.Stage.Open(str(tmp_path / "div.usda"))
    assert stage.GetEndTimeCode() == 1.0  # frames before the failure are written


def test_an_overflowing_step_is_a_named_divergence_not_a_crash(ops_cache):
    """A solve that returns non-finite u (an unstable setting overflowing in one step) skips the
    error correction - whose SVD cannot take NaN - and stops the body with the quantity named."""
    ops = ops_cache(1, 10)
    world = wsim.World(fps=50, device="cpu", gravity=(0.0, 0.0, 0.0))
    body = world.add(wsim.BemBody(sphere(1), MAT, ops.dt, operators=ops, name="ball"))
    world.step()
    u, a, alpha = body.unconstrained_solve()
    u[3] = np.inf
    body._finish_step(u, a, alpha, 0.0)  # the stage a real overflow reaches
    assert body.failed
    with pytest.raises(wsim.SimulationDiverged, match="ball.*non-finite displacement"):
        body.check_finite(1, body.time)


@pytest.mark.parametrize("device_step", [True, False])
def test_a_non_finite_history_stops_the_body_at_its_step(ops_cache, device_step):
    """Non-finite values anywhere in the step (here the displacement ring) stop the body at the step
    that produced them, with the quantity named, on the device path (its per-step log, read after
    the batch) as on the host path."""
    ops = ops_cache(1, 10)
    world, body = make_body(ops, sphere(1), name="ball", matvec="warp", device_step=device_step)
    x0 = body.points()
    # a load that reads the state: after the failing step it would see NaN and be refused; the body
    # must stop before, not blame the load (on the device path it runs a step ahead of the checks)
    body.add_traction(lambda t: -10.0 * (body.points() - x0))
    body.advance(0.0, 3 * ops.dt)
    body.state.U.fill_(float("inf"))
    body.advance(body.time, body.time + 40 * ops.dt)
    assert body.failed and body.steps == 4  # stopped at the failing step
    with pytest.raises(wsim.SimulationDiverged, match="ball.*non-finite displacement") as err:
        body.check_finite(1, body.time)
    assert "step 4 " in str(err.value)
    assert np.all(np.isfinite(body.frame.T)) and np.all(np.isfinite(body.frame.velocity))  # no correction of NaN


def test_growth_stop_on_the_device_path_is_at_its_step(ops_cache, monkeypatch):
    """The growth check runs on the device batch's log after the batch: a batch ends where the
    check could first stop the body, so a body it stops is left at the step the message names.
    The log's peaks are replaced by a mode growing 30 % a window (a real one takes thousands of
    steps to show): counted from the second window boundary, the fifth growing window ends at
    6 windows."""
    from wsim.bem.device_step import ResidentStep

    ops = ops_cache(1, 10)
    world, body = make_body(ops, sphere(1), name="ringer", matvec="warp")
    L = body._window_length
    real = ResidentStep.read_log

    def growing_log(self):
        log = real(self)
        first = body.state.steps - len(log)  # the batch's steps are first + 1 .. body.state.steps
        log[:, 0] = 1e-6 * 1.3 ** ((np.arange(first + 1, first + 1 + len(log)) - 1) // L)
        return log

    monkeypatch.setattr(ResidentStep, "read_log", growing_log)
    body.advance(0.0, (6 * L + 300) * ops.dt)
    assert body.failed and body._failure[2] == "growing"
    assert body.steps == 6 * L
    with pytest.raises(wsim.SimulationDiverged, match="ringer.*growing") as err:
        body.check_finite(1, body.time)
    assert f"at step {6 * L} " in str(err.value)
    # the horizon: the (5 - g)-th window boundary ahead, at least the next one (a checkpoint may
    # hold a count of 5 or more once the failure is cleared by a restore)
    for steps, g, horizon in ((0, 0, 5 * L), (L - 1, 0, 5 * L), (L, 0, 6 * L), (3 * L + 1, 3, 5 * L),
                              (3 * L + 1, 4, 4 * L), (3 * L, 5, 4 * L), (3 * L + 2, 7, 4 * L)):
        body.state.steps, body.state.window_growing = steps, g
        assert body._growth_horizon() == horizon


def test_device_step_matches_the_host_path(device, ops_cache):
    """A free step kept on the device (``wsim.bem.device_step``: correction and frame update in one
    float64 kernel, CUDA graphs, one read-back per advance) follows the host path's numpy correction
    to round-off: float64 storage, a spinning body under gravity and a pulsing one-sided load, through
    one-step batches, batches longer than the device's log (LOG_ROWS steps) and the frame's
    re-orthonormalization (every 100 steps). A load that reads the frame mid-batch sees that step's."""
    from wsim.bem.device_step import LOG_ROWS

    ops = ops_cache(1, 10, "float64")
    runs = []
    for on_device in (True, False):
        world = wsim.World(fps=1.0 / ops.dt, device=device, gravity=(0.0, -9.81, 0.0))
        body = world.add(wsim.BemBody(sphere(1), MAT, ops.dt, operators=ops, matvec="warp", device_step=on_device,
                                      angular_velocity=(0.0, 3.0, 1.0), velocity=(0.2, 0.0, 0.0)))
        n, x = body.rest_normals, body.rest_vertices
        seen = []

        def load(t, body=body, n=n, x=x, seen=seen):
            if 100 * ops.dt < t < 103.5 * ops.dt:
                seen.append(body.frame.T.copy())
            return -400.0 * n * (x[:, :1] > 0) * (1.0 + np.sin(300.0 * t))

        body.add_traction(load)
        pts = []
        for _ in range(5):
            body.step()
            pts.append(body.points())
        body.advance(body.time, body.time + (LOG_ROWS + 40) * ops.dt)
        pts.append(body.points())
        f = body.frame
        runs.append((np.array(pts), np.array(seen), np.concatenate([f.velocity, f.omega, f.L]), body.displacement()))
        if on_device:
            assert body.steps == LOG_ROWS + 45
            assert bool(body._resident.graphs) == wp.get_device(device).is_cuda  # replayed as graphs on CUDA
    (pa, sa, fa, ua), (pb, sb, fb, ub) = runs
    scale = np.max(np.abs(pb - pb[:1]))
    assert scale > 0.1 and np.max(np.abs(ub)) > 1e-6  # it moved and deformed
    assert np.max(np.abs(pa - pb)) < 1e-11 * scale
    assert len(sa) == 3 and np.max(np.abs(sa - sb)) < 1e-11 * scale
    assert np.max(np.abs(fa - fb)) < 1e-11 * np.max(np.abs(fb))
    assert np.max(np.abs(ua - ub)) < 1e-9 * np.max(np.abs(ub))


@pytest.mark.parametrize("bodies", [1, 2, "set"])
def test_device_steps_hand_over_to_the_contact_solve(device, ops_cache, bodies):
    """Balls dropped onto the ground (the second onto the first): free flight runs on the device
    (``BemBody.device_window``) until the bound on their motion brings them within reach of the
    ground or each other, then the constraint solve takes over. Fall, landing, bounce and the
    impact between the balls follow the all-host run to round-off. "set": the two balls on one
    operator set (an instance set on CUDA with CuPy, whose small members step on the device one
    body at a time, ``Instances.steps_apart``)."""
    ops = ops_cache(1, 10, "float64")
    same = bodies == "set"
    bodies = 2 if same else bodies
    meshes = [sphere(1), sphere(1) if same else trimesh.creation.icosphere(subdivisions=1, radius=0.9 * RADIUS)]
    sets = [ops] + ([ops if same else build_operators(meshes[1], MAT, ops.dt, precision="float64", cache=False,
                                                      device="cpu")] if bodies == 2 else [])
    runs = []
    for on_device in (True, False):
        world = wsim.World(fps=50, device=device, gravity=(0.0, -9.81, 0.0))
        world.add_collider(wsim.GroundPlane(0.0, friction=0.3))
        balls = [world.add(wsim.BemBody(meshes[k], MAT, ops.dt, operators=sets[k], matvec="warp", device_step=on_device,
                                        name=f"ball{k}", position=(0.04 * k, 0.3 + 0.3 * k, 0.0), velocity=(0.3, 0.0, 0.0),
                                        angular_velocity=(0.0, 0.0, 2.0))) for k in range(bodies)]
        on = [0]
        for b in balls:
            def counted(target, b=b, run=b._device_steps):
                first = b.steps
                run(target)
                on[0] += b.steps - first
            b._device_steps = counted
        pts = []
        for _ in range(25 if bodies == 1 else 32):
            world.step()
            pts.append(np.concatenate([b.points() for b in balls]))
        runs.append((np.array(pts), np.array([b.state.contact_impulse for b in balls]), on[0], balls[0].steps * bodies))
    (pa, ja, on_device, steps), (pb, jb, on_host, _) = runs
    # the falls run on the device (a group only while all of it is free), the contact steps not
    assert on_host == 0 and 0.3 * steps < on_device < steps
    assert np.abs(jb[:, 1]).min() > 0.1 * MAT.rho * 3.05e-3 * 9.81 * 0.1  # every ball was pushed up
    assert pb[:, :, 1].min() > -1e-5  # landed, within 10 um of the ground
    assert bodies == 2 or pb[-1, :, 1].min() > 1e-3  # and the lone ball bounced
    assert np.max(np.abs(pa - pb)) < 1e-10
    assert np.max(np.abs(ja - jb)) < 1e-9 * np.abs(jb).max()


def test_device_trajectory_matches_cpu_blas(device, ops_cache):
    """The same pushed, spinning body on each device (Warp kernels on CUDA) against the CPU BLAS run."""
    ops = ops_cache(1, 10)
    ref, _ = pushed_trajectory(ops, sphere(1), matvec="blas")
    world = wsim.World(fps=1.0 / ops.dt, device=device, gravity=(0.0, -9.81, 0.0))
    body = world.add(wsim.BemBody(sphere(1), MAT, ops.dt, operators=ops, angular_velocity=(0.0, 3.0, 1.0)))
    n, x = body.rest_normals, body.rest_vertices
    body.add_traction(lambda t: (-800.0 * n * (x[:, :1] > 0) + np.array([0.0, 100.0, 0.0])) * (t < 0.01))
    out = []
    for _ in range(len(ref)):
        body.step()
        out.append(body.points())
    assert np.max(np.abs(np.array(out) - ref)) < 1e-5 * np.max(np.abs(ref - ref[:1]))


# --------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("case", ["base", "nu_0.45", "incompressible", "stiff_x1000", "soft_div1000", "dt_x10",
                                  "dt_div10", "fast_spin_10rev"])
def test_stability_at_the_extremes(case):
    """10^4 steps per case (tools/study_bem_stability.py): bounded, or a clear SimulationDiverged. All are
    bounded except soft_div1000 (c2 dt / h ~ 0.007), whose second breathing mode grows slowly (BDF1's
    damping ~ (omega dt)^2 falls below the coarse mesh's spurious anti-damping) until the growth check
    stops it at step ~6350 with |u| = 9e-5 m."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    from study_bem_stability import run_case

    result = run_case(case, steps=10_000)
    assert result["outcome"] in ("bounded", "diverged"), result
    if result["outcome"] == "diverged":
        assert case in result["message"] and ("displacement" in result["message"] or "velocity" in result["message"])
    else:
        assert result["max_volume_change_last_tenth"] < 0.01


def test_growth_check_stops_an_unstable_run_early(ops_cache):
    """Without the error correction the rigid drift grows exponentially (a discrete instability): the
    growth check stops it while |u| is still far below divergence_limit, with the cause named."""
    ops = ops_cache(1, 10)
    _, body = make_body(ops, sphere(1), error_correction=False, name="drifter")
    n_v = len(body.rest_vertices)
    body.add_traction(lambda t: np.tile([300.0, 0.0, 0.0], (n_v, 1)) * (t <= 5 * body.dt + 1e-12))
    while body._failure is None and body.steps < 1000:
        body.step()
    with pytest.raises(wsim.SimulationDiverged, match="drifter.*growing displacement.*no load"):
        body.check_finite(0, body.time)
    assert np.max(np.abs(body.displacement())) < 0.2 * body.divergence_limit
