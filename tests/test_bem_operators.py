"""BEM operators: rigid-body identities, the analytic pressurized sphere, quadrature convergence,
double nodes and the free term, storage precision, GPU = CPU, mass properties, cache, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import wsim
from wsim import mesh as wmesh
from wsim.bem import assembly
from wsim.bem.assembly import laplace_matrices, laplace_operators
from wsim.bem.mass import mass_properties, traction_maps
from wsim.bem.operators import build_operators
from wsim.bem.surface import free_term, prepare_surface
from wsim.cache import OperatorCache

import warp as wp

HAS_CUDA = wp.get_cuda_device_count() > 0

MAT = wsim.ElasticMaterial(mu=5e5, nu=0.3, rho=1000.0)
INCOMPRESSIBLE = wsim.ElasticMaterial(mu=5e5, nu=0.5, rho=1000.0, incompressible=True)


def sphere(sub: int = 1, radius: float = 0.5) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=sub, radius=radius)


def box(div: int = 2, size: float = 0.4) -> tuple[np.ndarray, np.ndarray]:
    m = wmesh.beam(size, size, size, (div, div, div))
    v = np.asarray(m.vertices)
    return v - 0.5 * (v.min(axis=0) + v.max(axis=0)), np.asarray(m.faces)


def rigid_fields(nodes: np.ndarray, com: np.ndarray) -> list[np.ndarray]:
    """The three translations and three rotations about com, each (3N,)."""
    n = len(nodes)
    out = [np.tile(e, n) for e in np.eye(3)]
    out += [np.cross(e, nodes - com).ravel() for e in np.eye(3)]
    return out


@pytest.mark.parametrize("material", [MAT, INCOMPRESSIBLE], ids=["nu0.3", "incompressible"])
@pytest.mark.parametrize("shape", ["sphere", "box"])
def test_H_annihilates_rigid_motions_as_s_goes_to_zero(device, material, shape):
    """H(s) r = -s^2 (D or Q) theta -> 0: the static rows of H (free term included) kill rigid motion."""
    v, f = (sphere().vertices, sphere().faces) if shape == "sphere" else box()
    ops = laplace_operators(v, f, material, 1e-3, device=device)
    scale = np.abs(ops.H).max()
    for r in rigid_fields(ops.surface.nodes, ops.com):
        assert np.abs(ops.H @ r).max() < 1e-6 * scale * np.abs(r).max()
    # not vacuous: a field with a rigid part plus a stretch is not annihilated
    stretch = (ops.surface.nodes * [1.0, 0.0, 0.0]).ravel()
    assert np.abs(ops.H @ stretch).max() > 1e-2 * scale * np.abs(stretch).max()


@pytest.mark.parametrize("s", [40.0 + 25.0j, 400.0 - 150.0j])
def test_rigid_acceleration_identities_at_finite_s(device, s):
    """A uniform acceleration of the frame, u = e t^2/2 with a = -e, solves the BIE with p = 0:
    H(1 x e) = -s^2 D e; likewise a rotation field: H r_theta = -s^2 Q theta (spec test 4). This
    checks d, q, the free term and the singular quadrature together, at |s r/c2| up to ~9."""
    m = sphere(1)
    ops = laplace_operators(m.vertices, m.faces, MAT, s, device=device)
    r = rigid_fields(ops.surface.nodes, ops.com)
    for k in range(3):
        lhs_t, rhs_t = ops.H @ r[k], -(s**2) * ops.D[:, k]
        lhs_r, rhs_r = ops.H @ r[3 + k], -(s**2) * ops.Q[:, k]
        assert np.abs(lhs_t - rhs_t).max() < 2e-5 * np.abs(rhs_t).max()
        assert np.abs(lhs_r - rhs_r).max() < 2e-5 * np.abs(rhs_r).max()
        # the right-hand sides are O(1) parts of H r, not round-off: the identity could fail
        assert np.abs(rhs_t).max() > 1e-3 * np.abs(ops.H).max()


def analytic_sphere_radial_displacement(s: complex, material: wsim.ElasticMaterial, a: float, P: float) -> complex:
    """Solid sphere, uniform pressure P (traction -P n) in the Laplace domain: u = grad phi with
    phi = A sinh(k r)/r, k = s/c1; sigma_rr(a) = lambda k^2 phi + 2 mu phi'' = -P."""
    k = s / material.c1
    lam, mu = material.lam, material.mu
    sh, ch = np.sinh(k * a), np.cosh(k * a)
    A = -P / (lam * k**2 * sh / a + 2 * mu * (k**2 * a**2 * sh - 2 * k * a * ch + 2 * sh) / a**3)
    return A * (k * a * ch - sh) / a**2


@pytest.mark.parametrize(("s", "tol"), [(40.0 + 25.0j, 5e-3), (150.0 + 60.0j, 2e-2)])
def test_pressurized_sphere_matches_the_analytic_solution(device, s, tol):
    """Solve H u = G p with p = -P n; the radial displacement converges to the analytic one
    (about second order: at s = 150 + 60j the errors are 8.4 %, 1.4 %, 0.28 % for 42, 162, 642 nodes)."""
    a, P = 0.5, 1000.0
    exact = analytic_sphere_radial_displacement(s, MAT, a, P)
    # the static limit of the formula is -P a / (3 lambda + 2 mu): the helper is right at s -> 0
    assert analytic_sphere_radial_displacement(1.0, MAT, a, P).real == pytest.approx(-P * a / (3 * MAT.lam + 2 * MAT.mu), rel=1e-3)
    errors = []
    for sub in (1, 2):
        m = sphere(sub, a)
        H, G = laplace_matrices(m.vertices, m.faces, MAT, s, device=device)
        normal = m.vertices / np.linalg.norm(m.vertices, axis=1, keepdims=True)
        u = np.linalg.solve(H, G @ (-P * normal).ravel()).reshape(-1, 3)
        ur = np.sum(u * normal, axis=1)
        errors.append(np.abs(ur - exact).max() / abs(exact))
    assert errors[1] < 0.4 * errors[0]
    assert errors[1] < tol


def test_quadrature_refinement_converges():
    m = sphere(1)
    s = 200.0 + 50.0j
    ref = laplace_operators(m.vertices, m.faces, MAT, s, subdivision=6, singular_order=16)
    diffs = []
    for sub in (1, 2, 4):
        ops = laplace_operators(m.vertices, m.faces, MAT, s, subdivision=sub)
        diffs.append(max(np.abs(ops.H - ref.H).max() / np.abs(ref.H).max(), np.abs(ops.G - ref.G).max() / np.abs(ref.G).max()))
    assert diffs[2] < diffs[1] < diffs[0]
    assert diffs[2] < 0.2 * diffs[0]


def test_double_nodes_make_the_pressurized_box_exact():
    """A box under uniform pressure: u = -P x / (3K) is linear (exact in the elements) and the traction
    -P n is constant per face, exactly representable only with double nodes at edges and corners.
    Near s = 0 the BIE residual H u - G p is then quadrature error only."""
    v, f = box(3)
    P = 1000.0
    K = MAT.lam + 2.0 * MAT.mu / 3.0
    residual = {}
    for dn in (None, 30.0):
        ops = laplace_operators(v, f, MAT, 1e-2, double_nodes=dn)
        surf = ops.surface
        normal = np.zeros((surf.n_nodes, 3))
        np.add.at(normal, surf.faces.ravel(), np.repeat(surf.normals * surf.areas[:, None], 3, axis=0))
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        u = (-P / (3.0 * K)) * surf.nodes
        Gp = ops.G @ (-P * normal).ravel()
        residual[dn] = np.abs(ops.H @ u.ravel() - Gp).max() / np.abs(Gp).max()
        if dn is not None:
            assert surf.n_nodes == len(v) + 8 * 2 + 12 * 2 * 1  # corners x3, edge-interior vertices x2
            sv_G = np.linalg.svd(ops.G, compute_uv=False)
            sv_H = np.linalg.svd(ops.H, compute_uv=False)
            assert sv_G[-1] < 1e-12 * sv_G[0]  # copies' G rows coincide (paper: G_0 singular) ...
            assert sv_H[-1] > 1e-10 * sv_H[0]  # ... H rows differ by the free term: H stays regular
    assert residual[30.0] < 1e-5
    assert residual[None] > 0.1


def test_free_term_closed_form():
    """c = I/2 at a smooth point; at a cube corner 1/8 on the diagonal and 1/(8 pi (1 - nu)) off it
    (the known octant value)."""
    v, f = box(3)
    surf = prepare_surface(v, f, double_nodes=30.0)
    kappa = assembly.kappa_of(MAT)
    corner = int(np.argmin(np.linalg.norm(surf.nodes - v.min(axis=0), axis=1)))
    face_centre = int(np.argmin(np.linalg.norm(surf.nodes - [v.max() / 3.0, v.max() / 3.0, v.max()], axis=1)))
    c = free_term(surf, np.array([corner, face_centre]), kappa)
    off = 1.0 / (8.0 * np.pi * (1.0 - MAT.nu))
    np.testing.assert_allclose(c[0], np.full((3, 3), off) + (0.125 - off) * np.eye(3), atol=1e-12)
    np.testing.assert_allclose(c[1], 0.5 * np.eye(3), atol=1e-12)


def test_storage_precisions_agree_and_history_decays(tmp_path):
    m = sphere(1)
    ops64 = build_operators(m, MAT, 0.01, precision="float64", cache=False)
    ops32 = build_operators(m, MAT, 0.01, precision="float32", cache=False)
    assert ops32.H.dtype == np.float32 and ops64.H.dtype == np.float64
    for name in ("H", "G", "H0_inv", "H0_inv_Gp"):
        a, b = getattr(ops64, name), getattr(ops32, name)
        assert np.abs(a - b).max() <= 1e-6 * np.abs(a).max(), name
    # H_0^-1 really inverts H_0 and G' is G_0 + D_0 A + Q_0 C
    assert np.abs(ops64.H0_inv @ ops64.H[0] - np.eye(3 * 42)).max() < 1e-9
    np.testing.assert_allclose(ops64.Gp, ops64.G[0] + ops64.D[0] @ ops64.A + ops64.Q[0] @ ops64.C)
    # the time-domain kernels fade after r_max / c2 (n_max): weights beyond it are < 1 % of H_0
    longer = build_operators(m, MAT, 0.01, precision="float64", cache=False, n_max=2 * ops64.n_max)
    tail = np.abs(longer.H[ops64.n_max + 1 :]).max()
    assert tail < 1e-2 * np.abs(longer.H[0]).max()
    assert np.abs(longer.H[: ops64.n_max + 1] - ops64.H).max() < 1e-7 * np.abs(ops64.H).max()


def test_row_blocks_give_the_same_operators():
    m = sphere(1)
    whole = build_operators(m, MAT, 0.01, precision="float64", cache=False)
    n_max = whole.n_max
    blocked = build_operators(m, MAT, 0.01, precision="float64", cache=False,
                              memory_limit=9 * 3 * 42 * 8 * (4 + 2 * (n_max + 1)) * 5)  # 5 rows at a time
    for name in ("H", "G", "D", "Q"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(blocked, name))


@pytest.mark.skipif(not HAS_CUDA, reason="no CUDA device")
def test_gpu_matches_cpu(rng):
    """Same quadrature, same float64 arithmetic up to FMA contraction. The vertices are jittered:
    on a regular icosphere hundreds of (node, triangle) pairs sit exactly at a near-field threshold
    (distance = edge length), where one rounding difference picks another rule on each device and
    the results then differ by the quadrature error (1e-7) instead of round-off."""
    m = sphere(2)
    v = m.vertices + 0.01 * 0.1 * rng.normal(size=m.vertices.shape)
    s = 90.0 + 40.0j
    cpu = laplace_operators(v, m.faces, MAT, s, device="cpu")
    gpu = laplace_operators(v, m.faces, MAT, s, device="cuda:0")
    for name in ("H", "G", "D", "Q"):
        a, b = getattr(cpu, name), getattr(gpu, name)
        assert np.abs(a - b).max() < 1e-11 * np.abs(a).max(), name


def test_mass_properties_of_box_and_sphere():
    lo, hi = np.array([0.1, -0.2, 0.3]), np.array([0.5, 0.4, 0.5])
    m = wmesh.beam(1.0, 1.0, 1.0, (2, 3, 2))
    v = lo + (np.asarray(m.vertices) - [0.0, -0.5, -0.5]) * (hi - lo)
    props = mass_properties(v, m.faces, 700.0)
    size = hi - lo
    mass = 700.0 * np.prod(size)
    assert props.mass == pytest.approx(mass, rel=1e-12)
    np.testing.assert_allclose(props.com, 0.5 * (lo + hi), atol=1e-14)
    expected = mass / 12.0 * np.diag([size[1] ** 2 + size[2] ** 2, size[0] ** 2 + size[2] ** 2, size[0] ** 2 + size[1] ** 2])
    np.testing.assert_allclose(props.inertia, expected, atol=1e-12 * mass)
    # an icosphere: exact for its polyhedron (trimesh's independent integrals), close to the ball
    ball = sphere(4, 0.3)
    p = mass_properties(ball.vertices, ball.faces, 1000.0)
    ball.density = 1000.0
    assert p.mass == pytest.approx(ball.mass, rel=1e-12)
    np.testing.assert_allclose(p.inertia, ball.moment_inertia, atol=1e-12 * np.abs(p.inertia).max())
    assert p.mass == pytest.approx(1000.0 * 4.0 / 3.0 * np.pi * 0.3**3, rel=5e-3)
    np.testing.assert_allclose(np.diag(p.inertia), 0.4 * p.mass * 0.3**2, rtol=1e-2)


def test_traction_maps_give_force_and_torque(rng):
    """A p is the net force / m and C p = I^-1 torque for any nodal traction field p."""
    m = sphere(1)
    surf = prepare_surface(m.vertices, m.faces)
    props = mass_properties(surf.nodes, surf.faces, MAT.rho)
    A, C = traction_maps(surf, props)
    p = rng.normal(size=(surf.n_nodes, 3))
    # reference: fine quadrature of the linear interpolant over every face
    from wsim.bem.quadrature import subdivided_rule

    bary, w = subdivided_rule(3, 2)
    y = np.einsum("qk,fkj->fqj", bary, surf.nodes[surf.faces])
    py = np.einsum("qk,fkj->fqj", bary, p[surf.faces])
    wa = w[None, :, None] * surf.areas[:, None, None]
    force = (wa * py).sum(axis=(0, 1))
    torque = (wa * np.cross(y - props.com, py)).sum(axis=(0, 1))
    np.testing.assert_allclose(A @ p.ravel(), force / props.mass, rtol=1e-12)
    np.testing.assert_allclose(C @ p.ravel(), np.linalg.solve(props.inertia, torque), rtol=1e-10)


def test_operator_cache_loads_the_second_build(tmp_path):
    store = OperatorCache(tmp_path)
    m = sphere(1)
    first = build_operators(m, MAT, 0.01, cache=store)
    second = build_operators(m, MAT, 0.01, cache=store)
    assert (store.misses, store.hits) == (1, 1)
    assert "cache_load" in second.timings and "build" not in second.timings
    for name in ("H", "G", "D", "Q", "H0_inv", "H0_inv_Gp", "A", "C"):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
    assert second.n_max == first.n_max and second.mass == first.mass
    build_operators(m, MAT, 0.02, cache=store)  # another dt is another operator
    assert store.misses == 2


def test_bad_meshes_and_parameters_fail_before_any_assembly(monkeypatch):
    def no_assembly(*args, **kwargs):
        raise AssertionError("assembly started on bad input")

    monkeypatch.setattr(assembly.LaplaceAssembler, "__init__", no_assembly)  # the class both modules use
    m = sphere(1)
    open_mesh = (m.vertices, m.faces[1:])
    with pytest.raises(wsim.InvalidMesh, match="boundary"):
        laplace_matrices(*open_mesh, MAT, 10.0)
    with pytest.raises(wsim.InvalidMesh, match="boundary"):
        build_operators(open_mesh, MAT, 0.01, cache=False)
    v = np.array(m.vertices)
    a, b = m.faces[0][:2]
    v[b] = v[a]  # collapse an edge: two zero-area faces
    with pytest.raises(wsim.InvalidMesh, match="degenerate"):
        build_operators((v, m.faces), MAT, 0.01, cache=False)
    for bad in (dict(dt=0.0), dict(dt=-1e-3), dict(dt=0.01, precision="float16"), dict(dt=0.01, method="bdf3"),
                dict(dt=0.01, double_nodes=200.0), dict(dt=0.01, subdivision=0)):
        with pytest.raises(wsim.InvalidParameter):
            build_operators(m, MAT, cache=False, **bad)
    monkeypatch.undo()
    with pytest.raises(wsim.InvalidParameter, match="positive real part"):
        laplace_matrices(m.vertices, m.faces, MAT, -1.0 + 2j)


def test_assembly_over_several_devices_gives_the_same_operators(monkeypatch):
    """Row blocks spread over a device list (the CPU twice: the blocks take turns, launched before
    any is read back, as on several GPUs) give the operators of one device, bit for bit."""
    import numpy as np
    import trimesh

    import wsim
    from wsim.bem.operators import assembly_devices, build_operators
    from wsim.errors import InvalidParameter

    shape = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    material = wsim.ElasticMaterial(mu=1.0e5, nu=0.45, rho=1000.0)
    kw = dict(device="cpu", cache=False, n_max=4, memory_limit=1)  # one row a block: 12 blocks
    one = build_operators(shape, material, 0.01, **kw)
    two = build_operators(shape, material, 0.01, devices=["cpu", "cpu"], **kw)
    for name in ("H", "G", "D", "Q", "H0_inv", "H0_inv_Gp", "Gp"):
        np.testing.assert_array_equal(getattr(two, name), getattr(one, name), err_msg=name)
    # without a memory limit all rows fit one block; two devices still get a block each
    from wsim.bem.assembly import LaplaceAssembler

    seen: dict[int, set] = {}
    plain = LaplaceAssembler.assemble

    def spy(self, s, row0, rows, out):
        seen.setdefault(id(self), set()).add((row0, rows))
        return plain(self, s, row0, rows, out)

    monkeypatch.setattr(LaplaceAssembler, "assemble", spy)
    whole = build_operators(shape, material, 0.01, device="cpu", cache=False, n_max=4, devices=["cpu", "cpu"])
    assert sorted(map(sorted, seen.values())) == [[(0, 21)], [(21, 21)]]  # 42 nodes, halved
    np.testing.assert_allclose(whole.H, one.H, rtol=0, atol=1e-6 * np.abs(one.H).max())
    assert [d.alias for d in assembly_devices("cpu", None)] == ["cpu"]
    for bad in ("cuda:0,cuda:1", [], 3):
        with pytest.raises(InvalidParameter, match="devices"):
            assembly_devices(None, bad)
