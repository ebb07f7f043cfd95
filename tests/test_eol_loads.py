"""EoL loads, placement and the issue-16 checks (CPU).

Public API only: ``position=``, ``velocity_field=``, ``add_traction``, ``add_body_force``, the
``load_impulse`` read-out, the refusal of a body placed inside a collider, the stop of a body whose
material leaves its grid, and spin conservation with the fictitious loads (no phantom-mass spin-up).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import wsim
from wsim.eol import EolBody

SOFT = wsim.ElasticMaterial(E=1e5, nu=0.3, rho=1000.0)


def sphere(centre=(0.0, 0.0, 0.0), radius=0.5, subdivisions=2):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    m.apply_translation(centre)
    return m


def free_world(fps=30):
    return wsim.World(fps=fps, gravity=(0, 0, 0), device="cpu")


def test_position_moves_the_body():
    w = free_world()
    a = w.add(EolBody(sphere(), SOFT, resolution=6, name="a"))
    b = w.add(EolBody(sphere(), SOFT, resolution=6, name="b", position=(1.0, -2.0, 0.5)))
    np.testing.assert_allclose(b.points(), a.points() + [1.0, -2.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(b.frame[1], a.frame[1] + [1.0, -2.0, 0.5], atol=1e-12)
    with pytest.raises(wsim.InvalidParameter, match="body 'c': position"):
        EolBody(sphere(), SOFT, resolution=6, name="c", position=(0.0, np.nan, 0.0))


@pytest.mark.parametrize("lagrangian", ["rigid", "affine"])
def test_uniform_body_force_accelerates_at_exactly_a(lagrangian):
    """A free body under a uniform acceleration a(t): momentum = load impulse = m int a dt, the frame
    moves as the discrete ballistic path, and nothing deforms (a uniform field goes to the frame)."""
    w = free_world()
    b = w.add(EolBody(sphere(), SOFT, resolution=6, lagrangian=lagrangian, velocity=(0.1, 0.0, 0.0)))
    P0 = b.linear_momentum()
    b.add_body_force(lambda t: np.array([2.0, 0.0, -1.0]) * (1.0 + t))
    for _ in range(6):
        w.step()
    imp = b.load_impulse
    m = b.node_masses().sum()
    # forward Euler in the step's start time: sum dt a(t_k)
    expected = m * sum(r.dt * np.array([2.0, 0.0, -1.0]) * (1.0 + r.time) for r in b.history)
    np.testing.assert_allclose(imp, expected, rtol=1e-12)
    np.testing.assert_allclose(b.linear_momentum() - P0, imp, rtol=1e-9, atol=1e-9 * np.abs(imp).max())
    np.testing.assert_allclose(b.linear_momentum() / m, [0.1, 0.0, 0.0] + imp / m, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(b.state.Tdot, [0.1, 0.0, 0.0] + imp / m, rtol=1e-9, atol=1e-12)  # a = F / m
    assert np.abs(b.eulerian_velocity()).max() < 1e-9
    np.testing.assert_allclose(b.gravity_impulse, 0.0)


def test_per_point_body_force_momentum_equals_impulse():
    """fn(t, x) per material point: the momentum changes by exactly the delivered load impulse, and a
    force field that differs across the body deforms it."""
    w = free_world()
    b = w.add(EolBody(sphere(), SOFT, resolution=6))
    b.add_body_force(lambda t, x: np.column_stack([50.0 * x[:, 1], np.zeros(len(x)), np.ones(len(x))]),
                     per_point=True)
    for _ in range(3):
        w.step()
    imp = b.load_impulse
    np.testing.assert_allclose(imp, [0.0, 0.0, b.mass * w.time], rtol=1e-9, atol=1e-9)  # sum rho w_p a_p dt
    # the split conserves sum m w with the step's lumped masses; the read-out re-lumps them after the
    # material moved (node masses of the new state): 1e-3 here
    np.testing.assert_allclose(b.linear_momentum(), imp, rtol=1e-3, atol=1e-3 * np.linalg.norm(imp))
    assert np.abs(b.eulerian_velocity()).max() > 1e-3  # the shear field deforms it


def test_opposite_tractions_leave_momentum_unchanged_and_squeeze():
    """Equal and opposite forces on the two poles (tractions = force / lumped area): momentum stays at
    zero to round-off, the load impulse is zero, and the body is squeezed along x."""
    w = free_world(fps=60)
    b = w.add(EolBody(sphere(), SOFT, resolution=6))
    x0 = b.points()
    i, j = int(np.argmax(x0[:, 0])), int(np.argmin(x0[:, 0]))

    def squeeze(t):
        tr = np.zeros_like(x0)
        area = b.vertex_areas()
        tr[i] = [-200.0 / area[i], 0.0, 0.0]
        tr[j] = [200.0 / area[j], 0.0, 0.0]
        return tr

    b.add_traction(squeeze)
    width0 = np.ptp(b.points()[:, 0])
    for _ in range(4):
        w.step()
    scale = 200.0 * w.time  # the impulse of one of the two forces
    assert np.abs(b.linear_momentum()).max() < 1e-9 * scale
    assert np.abs(b.load_impulse).max() < 1e-9 * scale
    assert np.ptp(b.points()[:, 0]) < width0 - 1e-4


def test_pressure_pulse_rings_at_the_breathing_frequency():
    """A uniform pressure pulse (half-sine, 15 ms, along the deformed normals) on a free sphere
    excites its first breathing mode: the mean radius oscillates at the closed-form frequency
    (measured: -5.1 % at 8 cells, -0.86 % at 12), and the net load impulse is ~0."""
    from scipy.optimize import minimize_scalar

    from wsim.bem.analytic import breathing_frequency

    w = free_world(fps=240)
    b = w.add(EolBody(sphere(subdivisions=3), SOFT, resolution=12))
    T = 0.015
    b.add_traction(lambda t: -2e3 * np.sin(np.pi * t / T) * (t < T) * b.vertex_normals())
    r_rest = np.linalg.norm(b.rest_vertices, axis=1).mean()
    ts, rs = [], []
    while w.time < T + 0.2:
        w.step()
        if w.time > T:
            ts.append(w.time)
            rs.append(np.linalg.norm(b.points() - b.frame[1], axis=1).mean() - r_rest)
    ts, rs = np.array(ts), np.array(rs)
    assert rs.min() < -1e-5  # compressed by the pulse

    def misfit(om: float) -> float:
        X = np.column_stack([np.sin(om * ts), np.cos(om * ts), np.ones_like(ts)])
        return float(np.sum((X @ np.linalg.lstsq(X, rs, rcond=None)[0] - rs) ** 2))

    scan = np.linspace(30.0, 90.0, 601)
    om = scan[np.argmin([misfit(o) for o in scan])]
    om = minimize_scalar(misfit, bracket=(om - 0.1, om, om + 0.1)).x
    exact = breathing_frequency(SOFT, 0.5)
    assert abs(om / exact - 1.0) < 0.02
    assert np.linalg.norm(b.load_impulse) < 1e-9 * 2e3 * 4 * np.pi * 0.25 * T


@pytest.mark.parametrize("lagrangian", ["rigid", "affine"])
def test_rigid_velocity_field_goes_into_the_frame(lagrangian):
    """velocity_field = a rigid motion: the split puts it all in the frame (Eulerian v = 0), the same
    state as velocity= / angular_velocity=; a non-affine field stays Eulerian with zero net momentum."""
    v0, om = np.array([0.3, -0.1, 0.2]), np.array([0.5, 1.0, -2.0])
    w = free_world()
    c = np.array([0.1, 0.7, -0.2])
    a = w.add(EolBody(sphere(c), SOFT, resolution=6, lagrangian=lagrangian, name="field",
                      velocity_field=lambda x: v0 + np.cross(om, x - c)))
    ref = w.add(EolBody(sphere(c), SOFT, resolution=6, lagrangian=lagrangian, name="ref", velocity=v0,
                        angular_velocity=om))
    assert np.abs(a.eulerian_velocity()).max() < 1e-12
    np.testing.assert_allclose(a.angular_velocity, om, atol=1e-12)
    np.testing.assert_allclose(a.state.Tdot, v0, atol=1e-12)
    np.testing.assert_allclose(a.node_world_velocities(), ref.node_world_velocities(), atol=1e-12)
    br = w.add(EolBody(sphere(c), SOFT, resolution=6, lagrangian=lagrangian, name="breathe",
                       velocity_field=lambda x: 2.0 * (x - c) * np.sum((x - c) ** 2, axis=1, keepdims=True)))
    assert np.abs(br.eulerian_velocity()).max() > 0.02
    np.testing.assert_allclose(br.linear_momentum(), 0.0, atol=1e-10)
    np.testing.assert_allclose(br.angular_momentum(), 0.0, atol=1e-10)


def test_bad_loads_raise_naming_body_quantity_and_time():
    with pytest.raises(wsim.InvalidParameter, match="body 'ball': velocity_field must be a callable"):
        EolBody(sphere(), SOFT, resolution=6, name="ball", velocity_field=np.zeros(3))
    w = free_world()
    with pytest.raises(wsim.InvalidParameter, match=r"body 'ball': velocity_field \[m/s\] at t = 0 s has shape"):
        w.add(EolBody(sphere(), SOFT, resolution=6, name="ball", velocity_field=lambda x: np.zeros(3)))
    b = w.add(EolBody(sphere(), SOFT, resolution=6, name="ball"))
    for bad in (None, 3.0, "x"):
        with pytest.raises(wsim.InvalidParameter, match="body 'ball': add_traction takes a callable"):
            b.add_traction(bad)
        with pytest.raises(wsim.InvalidParameter, match="body 'ball': add_body_force takes a callable"):
            b.add_body_force(bad)
    w.step()
    state = b.get_state()
    b.add_traction(lambda t: np.zeros((5, 3)))
    with pytest.raises(wsim.InvalidParameter, match=r"body 'ball': a traction \[Pa\] at t = 0.0333333 s has shape"):
        w.step()
    for k, v in b.get_state().items():  # a refused load leaves the state as it was
        np.testing.assert_array_equal(v, state[k])
    b._tractions.clear()
    b.add_body_force(lambda t: np.array([0.0, np.inf, 0.0]))
    with pytest.raises(wsim.InvalidParameter, match=r"body 'ball': a body force .* at t = .* is not finite"):
        w.step()


def test_state_round_trips_with_loads_attached():
    """Loads are functions of time, not state: get_state/set_state continue bit for bit."""
    def make():
        w = free_world()
        b = w.add(EolBody(sphere(), SOFT, resolution=6, angular_velocity=(0, 0, 2.0)))
        b.add_traction(lambda t: 300.0 * np.sin(20 * t) * b.vertex_normals())
        b.add_body_force(lambda t: np.array([0.0, -1.0, 0.5 * t]))
        return w, b

    w1, b1 = make()
    for _ in range(2):
        w1.step()
    saved, frame = b1.get_state(), w1.frame
    for _ in range(2):
        w1.step()
    w2, b2 = make()
    b2.set_state(saved)
    w2.frame = frame
    for _ in range(2):
        w2.step()
    assert "load_impulse" in saved
    for k, v in b1.get_state().items():
        np.testing.assert_array_equal(v, b2.get_state()[k], err_msg=k)


def test_initial_overlap_with_a_collider_is_refused_or_resolved():
    """A body placed deeper than half a cell inside a collider is refused with the body, collider,
    depth and a hint; a shallower overlap is left to contact."""
    w = wsim.World(fps=30, device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, name="ground"))
    w.add(EolBody(sphere(), SOFT, resolution=6, name="ball", position=(0.0, 0.3, 0.0)))  # 0.2 m deep
    with pytest.raises(wsim.InvalidParameter, match=r"body 'ball': starts 0.2\d* m inside collider 'ground'.*position="):
        w.step()
    w = wsim.World(fps=30, device="cpu")
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    w.add_collider(wsim.MeshCollider(box, transform=np.eye(4), name="crate"))
    w.add(EolBody(sphere(), SOFT, resolution=6, name="ball", position=(0.0, 0.8, 0.0)))  # 0.2 m into the box
    with pytest.raises(wsim.InvalidParameter, match=r"body 'ball': starts 0.\d+ m inside collider 'crate'"):
        w.step()
    w = wsim.World(fps=30, device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, name="ground"))
    b = w.add(EolBody(sphere(), SOFT, resolution=6, damping=200.0, position=(0.0, 0.48, 0.0)))  # 2 cm: contact
    w.step()
    assert b.contact_impulse[1] > 0.0


def test_material_leaving_the_grid_stops_the_run():
    """E = 1e3 spun at 10 rev/s flies apart (centrifugal stress ~1000x E). The grid grows with the
    spreading disc up to 3x its first size across, then the run stops with SimulationDiverged
    naming the body and 'material left the grid' (without the check it ran until dt collapsed,
    frames later). E = 1e5 at the same spin stretches to about 1.8x its radius and stays bounded:
    the grid grows once and the run goes on."""
    w = free_world()
    b = w.add(EolBody(sphere(), wsim.ElasticMaterial(E=1e3, nu=0.3, rho=1000.0), resolution=6, name="spinner",
                      angular_velocity=(0, 2 * np.pi * 10, 0)))
    cells = b.grid.cells
    with pytest.raises(wsim.SimulationDiverged, match="body 'spinner'.*material left the grid") as err:
        for _ in range(10):
            w.step()
    assert err.value.step <= 8
    assert b.grid.cells[0] == 3 * cells[0] and b.grid.cells[2] == 3 * cells[2]
    w = free_world()
    b = w.add(EolBody(sphere(), SOFT, resolution=6, name="spinner", angular_velocity=(0, 2 * np.pi * 10, 0)))
    for _ in range(6):
        w.step()
    assert cells[0] < b.grid.cells[0] < 3 * cells[0]


def test_spin_keeps_angular_momentum_and_energy():
    """Issue 16's undamped spin (pi rad/s, 6 cells, fictitious loads, default dt cap) over 10 s
    instead of 20: the phantom mass of the mass floor took the centrifugal and Coriolis loads and
    spun the body up, +6.2 % L and +16.8 % energy here before the fix (+21 % / +51 % in 20 s);
    after it -1.5 % and +0.4 % at the cap 0.25 h / c1, and -0.23 % and -0.69 % at 0.5 with equal
    steps (2026-11-28; advection dissipates a little)."""
    w = free_world()
    b = w.add(EolBody(sphere(), SOFT, resolution=6, angular_velocity=(0, 0, np.pi)))
    L0, E0 = np.linalg.norm(b.angular_momentum(b.frame[1])), b.kinetic_energy() + b.elastic_energy
    for _ in range(300):
        w.step()
    L1, E1 = np.linalg.norm(b.angular_momentum(b.frame[1])), b.kinetic_energy() + b.elastic_energy
    assert abs(L1 / L0 - 1.0) < 0.025
    assert abs(E1 / E0 - 1.0) < 0.03
