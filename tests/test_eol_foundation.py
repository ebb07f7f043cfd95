"""EoL foundation (issue 7, first step): grid quadrature, mass blocks (Eq. 11, 20), momentum split (Eqs. 23-25).

Spec tests T1 (Eq. 20 and its O(h^2) lumping error), T2 (least squares), T3 (velocity
preservation), T11 (mass).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import wsim
from wsim.eol import (
    consistent_blocks,
    lagrangian_jacobian,
    lumped_masses,
    make_grid,
    mass_blocks,
    material_samples,
    momentum_split,
)

RHO = 800.0


def body(kind="box"):
    if kind == "box":  # a box that fills whole cells at every resolution below
        m = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    else:
        m = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    m.apply_translation((0.05, -0.02, 0.03))  # off the origin: the moments are not trivial
    return m


def setup(resolution, kind="box", lagrangian="rigid"):
    m = body(kind)
    grid = make_grid(m.vertices, resolution)
    samples = material_samples(grid, m.vertices, m.faces)
    masses = lumped_masses(grid, samples, RHO)
    return m, grid, samples, masses, mass_blocks(lagrangian, grid, samples, masses, RHO)


def test_grid_quadrature_and_mass_t11():
    m, grid, samples, masses, blocks = setup(8)
    assert samples.volume == pytest.approx(0.4 * 0.3 * 0.2, rel=1e-12)  # cells align with the box
    assert masses.sum() == pytest.approx(RHO * samples.volume, rel=1e-12)
    np.testing.assert_allclose(blocks.M1[3:, 3:], RHO * samples.volume * np.eye(3), rtol=1e-12)
    nodes, phi = grid.shape_functions(samples.points)
    np.testing.assert_allclose(phi.sum(axis=1), 1.0)
    np.testing.assert_allclose(np.einsum("pc,pci->pi", phi, grid.node_positions()[nodes]), samples.points, atol=1e-12)
    sphere, _, s_sphere, _, _ = setup(16, "sphere")  # a staircase of Gauss points: converges with h
    assert s_sphere.volume == pytest.approx(sphere.volume, rel=0.01)


def test_inside_surface_matches_the_direct_winding_number(device, rng):
    """The BVH classification of material points agrees with the direct winding-number sum, for a
    non-convex surface far from the origin (float32 relative to the surface's centre)."""
    from wsim.eol.grid import inside_surface
    from wsim.mesh import winding_number

    m = trimesh.creation.torus(0.5, 0.2)
    m.apply_translation((1000.0, 2.0, -3.0))
    lo, hi = m.bounds
    pts = lo - 0.1 + (hi - lo + 0.2) * rng.random((4000, 3))
    got = inside_surface(m.vertices, m.faces, pts, device)
    assert 0.1 < got.mean() < 0.9
    np.testing.assert_array_equal(got, winding_number(m.vertices, m.faces, pts) > 0.5)


@pytest.mark.parametrize("lagrangian", ["rigid", "affine"])
def test_eq20_holds_to_roundoff_with_consistent_mass(lagrangian):
    _, grid, samples, masses, blocks = setup(4, lagrangian=lagrangian)
    M12, M2 = consistent_blocks(lagrangian, grid, samples, RHO, blocks.active)
    rhs = M12 @ np.linalg.solve(M2, M12.T)
    np.testing.assert_allclose(rhs, blocks.M1, atol=1e-10 * np.abs(blocks.M1).max())
    # the nullspace of Eq. (22): M (I; -M_2^-1 M_12^T) = 0
    n1 = blocks.M1.shape[0]
    M = np.block([[blocks.M1, M12], [M12.T, M2]])
    basis = np.vstack([np.eye(n1), -np.linalg.solve(M2, M12.T)])
    assert np.abs(M @ basis).max() < 1e-10 * np.abs(M).max()
    assert np.allclose(M, M.T) and np.linalg.eigvalsh(M).min() > -1e-9 * np.abs(M).max()


@pytest.mark.parametrize("lagrangian", ["rigid", "affine"])
def test_eq20_with_lumped_mass_exact_translation_second_order_rest(lagrangian):
    errors = []
    for resolution in (4, 8, 16):
        _, _, _, _, blocks = setup(resolution, lagrangian=lagrangian)
        M2 = blocks.dense_M2()
        rhs = blocks.M12 @ np.linalg.solve(M2, blocks.M12.T)
        diff = rhs - blocks.M1
        t = slice(blocks.M1.shape[0] - 3, None)  # translation block
        assert np.abs(diff[t, t]).max() < 1e-9 * np.abs(blocks.M1[t, t]).max()
        errors.append(np.abs(diff).max() / np.abs(blocks.M1).max())
    ratios = [errors[i] / errors[i + 1] for i in range(2)]
    assert all(3.5 < r < 4.5 for r in ratios), (errors, ratios)  # O(h^2): 4x per halving of h


@pytest.mark.parametrize("lagrangian", ["rigid", "affine"])
def test_least_squares_split_t2_t3(lagrangian, rng):
    _, grid, _, _, blocks = setup(6, "sphere", lagrangian)
    M_C = blocks.M_C
    V = rng.standard_normal(M_C.shape[0])
    q1, v_star = momentum_split(M_C, V)
    assert np.abs(M_C.T @ v_star).max() < 1e-9 * np.abs(M_C.T @ V).max()  # orthogonal to the modes
    for _ in range(20):  # never larger than any other split
        other = rng.standard_normal(M_C.shape[1])
        assert np.linalg.norm(v_star) <= np.linalg.norm(V - M_C @ other) + 1e-12
    W = rng.standard_normal(M_C.shape[0])
    _, w_star = momentum_split(M_C, W)
    _, vw = momentum_split(M_C, V + 0.3 * W)
    np.testing.assert_allclose(vw, v_star + 0.3 * w_star, atol=1e-10)  # linear (Eq. 32b)
    # T3: the velocity rebuilt by Eq. (2) / (9) at the nodes is the input
    y = grid.node_positions()[blocks.active]
    rebuilt = np.einsum("sin,n->si", lagrangian_jacobian(lagrangian, y), q1) + v_star.reshape(-1, 3)
    np.testing.assert_allclose(rebuilt.ravel(), V, atol=1e-12)


def test_rigid_velocity_goes_entirely_to_the_lagrangian_modes(rng):
    """A rigid (or affine) velocity field is carried with v* = 0 (spec T4's first half)."""
    for lagrangian in ("rigid", "affine"):
        _, grid, _, _, blocks = setup(6, "sphere", lagrangian)
        q_true = rng.standard_normal(blocks.M1.shape[0])
        y = grid.node_positions()[blocks.active]
        V = np.einsum("sin,n->si", lagrangian_jacobian(lagrangian, y), q_true).ravel()
        q1, v_star = momentum_split(blocks.M_C, V)
        np.testing.assert_allclose(q1, q_true, atol=1e-10)
        assert np.abs(v_star).max() < 1e-10


def test_bad_grid_resolution():
    m = body()
    for bad in (3, 0, 2.5, True):
        with pytest.raises(wsim.InvalidParameter, match="resolution"):
            make_grid(m.vertices, bad)


# -- elastic forces from the reference map (spec T13) ----------------------------------------
def elastic_setup():
    m, grid, samples, masses, _ = setup(6)
    return grid, samples, masses


MATERIAL = wsim.ElasticMaterial(E=1e5, nu=0.3, rho=RHO)


def forces_of(grid, samples, z, device, **kw):
    from wsim.eol.elastic import elastic_forces

    return elastic_forces(grid, z, samples.points, samples.weights, MATERIAL, device, **kw)


def test_rigidly_rotated_reference_map_has_no_force(device):
    from wsim.rigid import rodrigues

    grid, samples, masses = elastic_setup()
    y = grid.node_positions()
    R = rodrigues(np.array([0.4, -1.1, 0.7]))
    f_rot, m_rot, e_rot = forces_of(grid, samples, (y - 0.1) @ R + 0.1, device)  # z = R^T (y - c) + c
    f_str, _, _ = forces_of(grid, samples, y / 1.05, device)
    assert np.abs(f_rot).max() < 1e-9 * np.abs(f_str).max()
    assert abs(e_rot) < 1e-12
    np.testing.assert_allclose(m_rot, masses, rtol=1e-12, atol=1e-15)  # lumped masses of the kernel
    # a rotation in the Lagrangian part (F_L = R) costs nothing either
    f_L, _, e_L = forces_of(grid, samples, y, device, F_L=R)
    assert np.abs(f_L).max() < 1e-9 * np.abs(f_str).max() and abs(e_L) < 1e-12


def test_uniform_stretch_patch_test(device):
    grid, samples, masses = elastic_setup()
    y = grid.node_positions()
    lam_s = 1.05
    f, _, energy = forces_of(grid, samples, y / lam_s, device)  # F = lam_s I
    mu, lam = MATERIAL.mu, MATERIAL.lam
    logJ = 3.0 * np.log(lam_s)
    W = 0.5 * mu * (3 * lam_s**2 - 3) - mu * logJ + 0.5 * lam * logJ**2
    assert energy == pytest.approx(samples.volume * W, rel=1e-10)  # material volumes
    # interior nodes (every surrounding cell full): zero net force; whole body: no net force or torque
    counts = np.zeros(grid.n_nodes)
    np.add.at(counts, samples.nodes.ravel(), 1.0)
    interior = counts == counts.max()
    assert interior.sum() > 0
    assert np.abs(f[interior]).max() < 1e-9 * np.abs(f).max()
    assert np.abs(f.sum(axis=0)).max() < 1e-9 * np.abs(f).max()
    assert np.abs(np.cross(y, f).sum(axis=0)).max() < 1e-9 * np.abs(f).max() * np.abs(y).max()
    # the same stretch carried by the Lagrangian deformation gradient gives the same energy
    _, _, e_L = forces_of(grid, samples, y, device, F_L=lam_s * np.eye(3))
    assert e_L == pytest.approx(energy, rel=1e-10)


def test_forces_are_the_power_conjugate_of_affine_velocities(device, rng):
    """sum_s g_s (y_s, 1)^T = -dV/d(A, b) exactly (trilinear nodes reproduce affine velocities):
    what makes the Lagrangian forces consistent with the nodal ones (Eqs. 18-22)."""
    grid, samples, masses = elastic_setup()
    y = grid.node_positions()
    z = y - 0.01 * np.sin(3.0 * y[:, [1, 2, 0]]) - 0.004 * rng.standard_normal(y.shape) * (masses > 0)[:, None]
    A = np.eye(3) + 0.05 * rng.standard_normal((3, 3))
    Fp_inv = np.eye(3) + 0.03 * rng.standard_normal((len(samples.weights), 3, 3))
    for fp in (None, Fp_inv):
        f, _, _ = forces_of(grid, samples, z, device, F_L=A, Fp_inv=fp)
        dVdA = -f.T @ y
        np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=1e-9 * np.abs(f).max())
        eps = 1e-6
        for i, j in [(0, 0), (0, 2), (1, 0), (2, 1), (2, 2)]:
            Ap, Am = A.copy(), A.copy()
            Ap[i, j] += eps
            Am[i, j] -= eps
            dV = (forces_of(grid, samples, z, device, F_L=Ap, Fp_inv=fp)[2]
                  - forces_of(grid, samples, z, device, F_L=Am, Fp_inv=fp)[2]) / (2 * eps)
            assert dVdA[i, j] == pytest.approx(dV, rel=1e-5, abs=1e-8 * np.abs(dVdA).max())


# -- advection (Eq. 15) -------------------------------------------------------------------------
def interior_mask(grid, margin):
    ijk = np.stack(np.meshgrid(*(np.arange(n) for n in grid.node_shape), indexing="ij"), axis=-1).reshape(-1, 3)
    return np.all((ijk >= margin) & (ijk <= np.array(grid.node_shape) - 1 - margin), axis=1)


@pytest.mark.parametrize("scheme", ["semi-lagrangian", "bfecc"])
def test_advection_is_exact_for_linear_fields_and_whole_cell_shifts(device, scheme):
    from wsim.eol.advection import advect

    grid = make_grid(body().vertices, 8)
    y = grid.node_positions()
    v = np.tile([0.7, -0.3, 0.2], (grid.n_nodes, 1))
    inner = interior_mask(grid, 3)
    # the reference map z = y (and any affine field) moves exactly: trilinear reproduces it
    z = advect(grid, y, v, 0.01, scheme, device)
    np.testing.assert_allclose(z[inner], (y - 0.01 * v)[inner], atol=1e-12)
    # a whole-cell shift moves any field node to node
    q = np.sin(7.0 * y) + y[:, [2, 0, 1]] ** 2
    shifted = advect(grid, q, np.tile([grid.h, 0.0, 0.0], (grid.n_nodes, 1)), 1.0, scheme, device)
    src = y - np.array([grid.h, 0.0, 0.0])
    expected = np.sin(7.0 * src) + src[:, [2, 0, 1]] ** 2
    np.testing.assert_allclose(shifted[inner], expected[inner], atol=1e-12)


def test_bfecc_is_second_order_semi_lagrangian_first(device):
    """A smooth field carried a fixed distance at fixed CFL 0.5: error ~ h (SL) and ~ h^2 (BFECC)."""
    from wsim.eol.advection import advect
    from wsim.eol.grid import EolGrid

    errors = {"semi-lagrangian": [], "bfecc": []}
    for n in (16, 32, 64):
        grid = EolGrid(origin=np.zeros(3), h=1.0 / n, cells=(n, 4, 4))
        y = grid.node_positions()
        v = np.tile([1.0, 0.0, 0.0], (grid.n_nodes, 1))
        dt = 0.5 * grid.h
        steps = int(round(0.25 / dt))
        inner = (y[:, 0] > 0.45) & (y[:, 0] < 0.95)
        exact = np.sin(2 * np.pi * (y - 0.25 * v))
        for scheme in errors:
            q = np.sin(2 * np.pi * y)
            for _ in range(steps):
                q = advect(grid, q, v, dt, scheme, device)
            errors[scheme].append(np.abs(q - exact)[inner, 0].max())
    sl, bf = errors["semi-lagrangian"], errors["bfecc"]
    assert all(1.7 < sl[i] / sl[i + 1] < 2.3 for i in range(2)), sl
    assert all(bf[i] / bf[i + 1] > 3.5 for i in range(2)), bf
    assert bf[-1] < 0.05 * sl[-1]


def test_limited_bfecc_adds_no_extrema_and_beats_semi_lagrangian(device):
    """The limited BFECC EolBody uses: a step profile keeps its range (no over- or undershoot), and a
    smooth field is still far more accurate than semi-Lagrangian."""
    from wsim.eol.advection import advect
    from wsim.eol.grid import EolGrid

    n = 32
    grid = EolGrid(origin=np.zeros(3), h=1.0 / n, cells=(n, 4, 4))
    y = grid.node_positions()
    v = np.tile([1.0, 0.0, 0.0], (grid.n_nodes, 1))
    dt = 0.5 * grid.h
    step = np.where(y < 0.3, 1.0, 0.0)
    smooth = np.sin(2 * np.pi * y)
    q_step, q_sl, q_lim = step.copy(), smooth.copy(), smooth.copy()
    for _ in range(16):
        q_step = advect(grid, q_step, v, dt, "bfecc", device, limit=True)
        q_sl = advect(grid, q_sl, v, dt, "semi-lagrangian", device)
        q_lim = advect(grid, q_lim, v, dt, "bfecc", device, limit=True)
    assert q_step.min() >= -1e-12 and q_step.max() <= 1.0 + 1e-12
    assert advect(grid, step, v, dt, "bfecc", device).min() < -1e-3  # unlimited BFECC undershoots
    inner = (y[:, 0] > 0.45) & (y[:, 0] < 0.95)
    exact = np.sin(2 * np.pi * (y - 16 * dt * v))
    assert np.abs(q_lim - exact)[inner, 0].max() < 0.5 * np.abs(q_sl - exact)[inner, 0].max()


def test_bad_advection_scheme():
    from wsim.eol.advection import advect

    grid = make_grid(body().vertices, 4)
    with pytest.raises(wsim.InvalidParameter, match="advection"):
        advect(grid, grid.node_positions(), np.zeros((grid.n_nodes, 3)), 0.1, "maccormack", "cpu")


# -- adaptive time step (Eqs. 30-33, spec T9) -------------------------------------------------
def test_adaptive_dt_root_satisfies_the_cfl_rule(rng):
    from wsim.eol.timestep import adaptive_dt, cfl_gamma

    h = np.array([0.02, 0.03, 0.025])
    alpha = 0.5
    for _ in range(20):
        v0, v1 = rng.standard_normal((50, 3)), 30.0 * rng.standard_normal((50, 3))
        dt = adaptive_dt(v0, v1, h, alpha, dt_max=1.0)
        gamma = cfl_gamma(v0 + dt * v1, h)
        assert dt * gamma <= alpha * (1 + 1e-12)  # Eq. (33) with its sum: Eq. (30) holds a fortiori
        # and it is the largest such step: gamma_i enter linearly, so equality holds when the
        # per-axis maxima of v0 and v1 sit on the same node; always dt * max-rule <= alpha
        v = np.abs(v0 + dt * v1)
        assert dt * np.max(v / h) <= alpha + 1e-12
    same = np.tile([1.0, 0.0, 0.0], (4, 1))
    dt = adaptive_dt(same, 2.0 * same, h, alpha, dt_max=1.0)
    assert dt * (1.0 + 2.0 * dt) / h[0] == pytest.approx(alpha, rel=1e-12)


def test_adaptive_dt_limits():
    from wsim.eol.timestep import adaptive_dt, elastic_dt_limit

    z = np.zeros((5, 3))
    v = np.tile([2.0, 0.0, 0.0], (5, 1))
    assert adaptive_dt(z, z, 0.1, 0.5, dt_max=1 / 30) == 1 / 30  # v* = 0: the cap (frame time)
    assert adaptive_dt(v, z, 0.1, 0.5, dt_max=1.0) == pytest.approx(0.5 * 0.1 / 2.0)  # gamma_1 = 0: alpha / gamma_0
    for bad in (0.0, 1.0, -0.2):
        with pytest.raises(wsim.InvalidParameter, match="cfl"):
            adaptive_dt(v, z, 0.1, bad, dt_max=1.0)
    mat = wsim.ElasticMaterial(E=1e5, nu=0.3, rho=1000.0)
    assert elastic_dt_limit(0.01, mat) == pytest.approx(0.25 * 0.01 / mat.c1)
    with pytest.raises(wsim.InvalidParameter, match="compressible"):
        elastic_dt_limit(0.01, wsim.ElasticMaterial(E=1e5, nu=0.5, rho=1000.0, incompressible=True))


# -- surface tracking (Algorithm 2, spec T12) -------------------------------------------------
def test_surface_tracking(device, rng):
    from wsim.eol.tracking import track_surface
    from wsim.rigid import rodrigues

    m = body("sphere")
    grid = make_grid(m.vertices, 12, padding=3)
    y = grid.node_positions()
    zv = m.vertices
    # no displacement: every vertex is exactly where it was, with no iteration
    out, iters = track_surface(grid, y, zv, zv, device=device)
    np.testing.assert_array_equal(out, zv)
    assert iters.max() == 0
    # an affine reference map z = A^-1 (y - b): one Newton step from the rest guess
    A = rodrigues(np.array([0.1, 0.2, -0.1])) @ np.diag([1.05, 0.97, 1.02])
    b = np.array([0.01, -0.02, 0.015])
    out, iters = track_surface(grid, (y - b) @ np.linalg.inv(A).T, zv, zv, device=device)
    np.testing.assert_allclose(out, zv @ A.T + b, atol=1e-12)
    assert iters.max() == 1
    # a smooth nonlinear map: converges to the tolerance in a few (Newton) iterations
    def phi_inv(q):  # z(y): a small smooth wobble
        return q - 0.01 * np.sin(4.0 * q[:, [1, 2, 0]])

    out, iters = track_surface(grid, phi_inv(y), zv, zv, tol=1e-10, device=device)
    # the trilinear field is the one being inverted: the residual through it is below the tolerance
    nodes, phi = grid.shape_functions(out)
    z_at = np.einsum("pc,pci->pi", phi, phi_inv(y)[nodes])
    assert np.linalg.norm(z_at - zv, axis=1).max() < 1e-10
    assert 1 <= iters.min() and iters.max() <= 6
    assert np.abs(out - zv).max() > 1e-3  # it moved
    assert np.abs(phi_inv(out) - zv).max() < 0.05 * np.abs(out - zv).max()  # near the smooth inverse (h^2 error)


@pytest.mark.parametrize("lagrangian", ["rigid", "affine"])
@pytest.mark.parametrize("split", ["mass", "uniform"])
def test_body_moment_split_is_the_least_squares_split(device, rng, lagrangian, split):
    """What EolBody runs each step (moments reduced and the fields solved on the device,
    ``split.split_on_device``; ``split.lagrangian_fields`` its host form)
    is ``momentum_split`` (Eq. 23, T2/T3 above) on the same nodal velocities, in the body's norm
    (uniform: the paper's 2-norm; mass: weighted by the lumped masses)."""
    import warp as wp

    from wsim.eol import EolBody
    from wsim.eol.split import fields_of, lagrangian_fields, moments, unpack_fields

    b = EolBody(body("sphere"), MATERIAL, resolution=6, lagrangian=lagrangian, split=split,
                rotation=trimesh.transformations.rotation_matrix(0.5, [1, 2, 3])[:3, :3])
    b.bind(wp.get_device(device), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    mass = b.node_masses()
    active = mass > 0.0
    y = b.grid.node_positions()[active]
    w0 = rng.standard_normal((b.grid.n_nodes, 3))
    w1 = 10.0 * rng.standard_normal((b.grid.n_nodes, 3))
    b._w.assign(w0)
    b._a.assign(w1)
    b._split(b._w, b._a)  # on the device (``split_fields``), read back here
    fields = unpack_fields(b._fields.numpy())[:2]
    k = mass[active] if split == "mass" else np.ones(int(active.sum()))
    M_C = lagrangian_jacobian(lagrangian, y).reshape(-1, 6 if lagrangian == "rigid" else 12)
    sq = np.repeat(np.sqrt(k), 3)
    for (L, c), w in zip(fields, (w0, w1)):
        q1, _ = momentum_split(sq[:, None] * M_C, sq * w[active].ravel())
        L_ref, c_ref = fields_of(lagrangian, q1)
        scale = np.abs(w).max()
        np.testing.assert_allclose(L, L_ref, atol=1e-9 * scale / np.abs(y).max())
        np.testing.assert_allclose(c, c_ref, atol=1e-9 * scale)
        # the host moments give the same fields
        L_h, c_h = lagrangian_fields(lagrangian, *moments(y, w[active], k))
        np.testing.assert_allclose(L_h, L, atol=1e-9 * scale / np.abs(y).max())
        np.testing.assert_allclose(c_h, c, atol=1e-9 * scale)


# -- robustness of thin parts (issue 16 item 6) -----------------------------------------------
def test_reference_map_extension_continues_an_affine_map(device):
    """z is continued from the nodes with material into the empty layers around them: an affine
    map (any A, b) is reproduced exactly there; the material nodes and the nodes beyond the
    layers are untouched."""
    import warp as wp

    from wsim.eol.advection import extend_reference_map

    m = body("sphere")
    grid = make_grid(m.vertices, 8, padding=4)
    samples = material_samples(grid, m.vertices, m.faces)
    mass = lumped_masses(grid, samples, RHO)
    y = grid.node_positions()
    A = np.array([[0.9, 0.1, 0.0], [-0.05, 1.1, 0.08], [0.02, 0.0, 0.95]])
    z_affine = y @ A.T + np.array([0.01, -0.02, 0.03])
    z0 = np.where((mass > 0)[:, None], z_affine, 7.0)  # stale values off the material
    shape = grid.node_shape
    za = wp.array(z0.reshape(*shape, 3), dtype=wp.vec3d, device=device)
    layer = wp.zeros(shape, dtype=wp.int32, device=device)
    G = wp.zeros(shape, dtype=wp.mat33d, device=device)
    extend_reference_map(za, wp.array(mass.reshape(shape), dtype=wp.float64, device=device), grid.h, 2, layer,
                         G, device)
    z, lay = za.numpy().reshape(-1, 3), layer.numpy().ravel()
    assert set(np.unique(lay)) == {0, 1, 2, 3}
    np.testing.assert_array_equal(z[lay == 1], z0[lay == 1])
    np.testing.assert_allclose(z[lay >= 2], z_affine[lay >= 2], atol=1e-12)
    np.testing.assert_array_equal(z[lay == 0], 7.0)


def test_hourglass_control_acts_on_under_integrated_cells_only(device, rng):
    """Hourglass control (kernel ``hourglass_forces``): no force or energy for an affine reference
    map or in fully integrated cells; on a perturbed map the forces sum to zero with no moment
    (momentum untouched) and push each corner along F r_c, back toward the cell's affine fit."""
    import warp as wp

    from wsim.eol.elastic import hourglass_forces
    from wsim.kernels.eol_grid import grid_struct

    def run(kind, z):
        m = body(kind)
        grid = make_grid(m.vertices, 8 if kind == "box" else 6)  # the box fills whole cells at 8
        samples = material_samples(grid, m.vertices, m.faces)
        shape = grid.node_shape
        forces = wp.zeros(shape, dtype=wp.vec3d, device=device)
        energy = wp.zeros(1, dtype=wp.float64, device=device)
        hourglass_forces(grid_struct(grid), wp.array(z(grid).reshape(*shape, 3), dtype=wp.vec3d, device=device),
                         wp.array(samples.points, dtype=wp.vec3d, device=device),
                         wp.array(samples.weights, dtype=wp.float64, device=device), grid.h**3, np.eye(3),
                         0.1 * MATERIAL.mu, wp.zeros(grid.cells, dtype=wp.float64, device=device), forces, energy,
                         device)
        return grid, forces.numpy().reshape(-1, 3), float(energy.numpy()[0])

    A = np.eye(3) + 0.1 * rng.standard_normal((3, 3))
    _, f, e = run("sphere", lambda g: g.node_positions() @ A.T + 0.03)
    assert np.abs(f).max() < 1e-9 and abs(e) < 1e-12
    noise = {}

    def wobbly(g):
        if g.n_nodes not in noise:
            noise[g.n_nodes] = 0.01 * g.h * rng.standard_normal((g.n_nodes, 3))
        return g.node_positions() + noise[g.n_nodes]

    _, f_full, e_full = run("box", wobbly)  # the box fills whole cells: nothing under-integrated
    assert np.abs(f_full).max() == 0.0 and e_full == 0.0
    grid, f, e = run("sphere", wobbly)
    y = grid.node_positions()
    assert e > 0.0 and np.abs(f).max() > 0.0
    assert np.abs(f.sum(axis=0)).max() < 1e-12 * np.abs(f).sum()
    assert np.abs(np.cross(y, f).sum(axis=0)).max() < 1e-12 * np.abs(f).sum() * np.abs(y).max()
    # the forces oppose the perturbation: moving nodes along f lowers the hourglass energy
    step = 1e-3 * grid.h / np.abs(f).max()
    _, _, e_moved = run("sphere", lambda g: wobbly(g) - step * f)  # dz = -G dy, G ~ I here
    assert e_moved < e


def test_tracking_is_safeguarded_on_a_folded_field(device):
    """Where z folds (grad z singular in a cell) a plain Newton step is unbounded and threw
    vertices hundreds of cells away (issue 16 item 6). The safeguarded step never raises the
    residual, stays finite and moves at most MAX_STEP cells per iteration."""
    from wsim.eol.tracking import track_surface
    from wsim.kernels.eol_track import MAX_STEP

    m = body("sphere")
    grid = make_grid(m.vertices, 8, padding=3)
    y = grid.node_positions()
    z = y.copy()
    cell, _ = grid.locate(np.zeros((1, 3)))
    from wsim.eol.grid import CORNERS
    corners = grid.node_index(cell[0] + CORNERS)
    z[corners] = z[corners].mean(axis=0) + 1e-9 * (y[corners] - y[corners].mean(axis=0))  # collapsed: G ~ 1e-9
    guess = np.array([[0.2, 0.3, 0.4]]) * grid.h + y[corners[0]]
    target = guess + np.array([[0.3, 0.0, 0.0]]) * grid.h  # not reachable inside the collapsed cell
    out, iters = track_surface(grid, z, target, guess, max_iter=20, device=device)
    nodes, phi = grid.shape_functions(np.vstack([guess, out]))
    r = np.linalg.norm(np.einsum("pc,pci->pi", phi, z[nodes]) - target, axis=1)
    assert np.all(np.isfinite(out))
    assert r[1] <= r[0]
    assert np.linalg.norm(out - guess) <= MAX_STEP * grid.h * max(int(iters[0]), 1) + 1e-12


def test_kelvin_voigt_damping_is_stable_on_light_nodes(device, rng):
    """Explicit Kelvin-Voigt damping at its cap rho h^2 / (12 eta) (kernels ``viscous_row_bound``,
    ``viscous_forces``). A box of whole cells (Gauss points): dt lambda_max(M^-1 K) = 2/3 and the
    damping is untouched. The same box with its bottom layer squashed into the top tenth of its
    cells (what a landing does): its bottom nodes hold slivers of material (at the 0.02 rho h^3
    mass floor) under nearly the full stiffness of their cells, and with the full viscosity on
    every node dt lambda_max exceeds 2, the forward-Euler instability that spiked a landing box's
    Eulerian velocity and collapsed its dt in the pile scene. Limited, dt lambda_max stays below 1,
    and forward Euler never gains kinetic energy (the M-norm of a stable explicit step of a
    symmetric dissipative operator never grows). The forces sum to zero with no moment."""
    import warp as wp

    from wsim.eol.elastic import viscous_forces
    from wsim.eol.grid import MaterialSamples
    from wsim.kernels.eol_grid import grid_struct

    m = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    grid = make_grid(m.vertices, 4)
    h, shape, full = grid.h, grid.node_shape, RHO * grid.h**3
    eta = 50.0
    dt = RHO * h**2 / (12.0 * eta)
    lo = np.round((m.bounds[0] - grid.origin) / h)
    gauss = 0.5 + 0.5 / np.sqrt(3.0) * np.array([-1.0, 1.0])
    local = np.stack(np.meshgrid(gauss, gauss, gauss, indexing="ij"), axis=-1).reshape(-1, 3)
    cells = np.stack(np.meshgrid(*(np.arange(4),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    gs = grid_struct(grid)
    forces = wp.zeros(shape, dtype=wp.vec3d, device=device)
    bound = wp.zeros(shape, dtype=wp.float64, device=device)

    def setting(squash):
        t = np.repeat(local[None], len(cells), axis=0)
        bottom = cells[:, 1] == 0
        t[bottom, :, 1] = 1.0 - squash * (1.0 - t[bottom, :, 1])
        points = grid.origin + h * (lo + cells[:, None, :] + t).reshape(-1, 3)
        nodes, phi = grid.shape_functions(points)
        real = lumped_masses(grid, MaterialSamples(points, np.full(len(points), h**3 / 8), nodes, phi), RHO)
        mass = np.where(real > 0.0, np.maximum(real, 0.02 * full), 0.0)
        arrays = (wp.array(points, dtype=wp.vec3d, device=device),
                  wp.array(np.full(len(points), h**3 / 8), dtype=wp.float64, device=device),
                  wp.array(mass.reshape(shape), dtype=wp.float64, device=device))
        return real, mass, arrays

    def f(w, arrays, step):  # step 0: no limit (the full viscosity on every node)
        y, vol, m3 = arrays
        viscous_forces(gs, wp.array(w.reshape(*shape, 3), dtype=wp.vec3d, device=device), y, vol, np.eye(3), eta,
                       m3, step, forces, bound, device)
        return forces.numpy().reshape(-1, 3)

    def lambda_max(mass, arrays, step, iterations=200):  # power iteration on M^-1 K (M-self-adjoint)
        has = mass > 0.0
        w = np.where(has[:, None], rng.standard_normal((grid.n_nodes, 3)), 0.0)
        for _ in range(iterations):
            Aw = np.zeros_like(w)
            Aw[has] = -f(w, arrays, step)[has] / mass[has, None]
            lam = np.sqrt((mass[:, None] * Aw**2).sum() / (mass[:, None] * w**2).sum())
            w = Aw / np.abs(Aw).max()
        return lam

    real, mass, arrays = setting(1.0)
    w0 = np.where((mass > 0.0)[:, None], rng.standard_normal((grid.n_nodes, 3)), 0.0)
    # whole cells: the full viscosity (exactly the same sums on the CPU; a GPU adds the points'
    # forces to a node in no set order, so two launches agree to round-off)
    full_eta, unlimited = f(w0, arrays, dt), f(w0, arrays, 0.0)
    np.testing.assert_allclose(full_eta, unlimited, rtol=0.0, atol=1e-13 * np.abs(unlimited).max())
    assert dt * lambda_max(mass, arrays, dt) == pytest.approx(2.0 / 3.0, rel=1e-3)
    real, mass, arrays = setting(0.1)
    assert ((real > 0.0) & (real < 0.02 * full)).any()  # the sliver nodes the test is about
    assert dt * lambda_max(mass, arrays, 0.0) > 2.0
    assert dt * lambda_max(mass, arrays, dt) < 1.0
    fw = f(w0, arrays, dt)
    x = grid.node_positions()
    assert np.abs(fw.sum(axis=0)).max() < 1e-12 * np.abs(fw).sum()
    assert np.abs(np.cross(x, fw).sum(axis=0)).max() < 1e-12 * np.abs(fw).sum() * np.abs(x).max()
    has = mass > 0.0
    w, energy = w0.copy(), []
    for _ in range(60):
        energy.append(0.5 * float((mass * (w * w).sum(axis=1)).sum()))
        w[has] += dt * f(w, arrays, dt)[has] / mass[has, None]
    assert np.all(np.diff(energy) <= 1e-12 * energy[0]) and energy[-1] < 0.5 * energy[0]  # stable, and it damps
