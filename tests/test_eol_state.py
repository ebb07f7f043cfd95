"""EolBody state (``EolState``): a restored body continues bit for bit, a foreign state is refused whole.

2N frames straight equal N frames, ``get_state``, a new body built the same way, ``set_state`` and N
more frames, bit for bit on the CPU (Warp's CPU kernels run their threads in order, so atomics add
in a fixed order; on a GPU the sums are reordered and only agree to round-off). The scenes drop a
sphere onto a ground plane hard enough to flow plastically, so the contact QP's warm start
(``active_rows``), F_p^-1 and the tracked points all carry over.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp

import wsim
from wsim.eol import EolBody, Plasticity
from wsim.state import StateMismatch

SOFT = wsim.ElasticMaterial(E=1e5, nu=0.3, rho=1000.0)
FPS = 60


def wall_pose(t):
    """A turning wall closing in on the ball along x (its velocity enters the contact rows)."""
    M = np.eye(4)
    M[:3, :3] = trimesh.transformations.rotation_matrix(0.3 * t, [0.0, 1.0, 0.0])[:3, :3]
    M[:3, 3] = (1.05 - 0.5 * t, 0.5, 0.0)
    return M


def make(lagrangian="rigid", resolution=6, plastic=True, device="cpu", wall=False, **kw):
    w = wsim.World(fps=FPS, device=device)
    w.add_collider(wsim.GroundPlane(0.0))
    if wall:
        w.add_collider(wsim.MeshCollider(trimesh.creation.box(extents=(1.0, 2.0, 2.0)), transform=wall_pose,
                                         name="wall"))
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    ball.apply_translation((0.0, 0.53, 0.0))
    b = w.add(EolBody(ball, SOFT, resolution=resolution, lagrangian=lagrangian, velocity=(0.4, -2.0, 0.2),
                      angular_velocity=(0.5, 1.0, -0.8), damping=200.0,
                      plasticity=Plasticity(yield_stress=500.0, flow_rate=200.0) if plastic else None, **kw))
    return w, b


def snapshot(b):
    F, T = b.frame
    return {"points": b.points(), "z": b.reference_map(), "v": b.eulerian_velocity(), "F": F, "T": T,
            "Fp_inv": b.plastic_strain().copy(), "contact_impulse": b.contact_impulse.copy(), "time": b.time,
            "steps": b.steps}


@pytest.mark.parametrize("lagrangian, advection, wall", [("rigid", "semi-lagrangian", False),
                                                         ("affine", "semi-lagrangian", False), ("rigid", "bfecc", True)])
def test_restored_body_continues_bit_for_bit(lagrangian, advection, wall):
    n = 3
    w1, b1 = make(lagrangian, advection=advection, wall=wall)
    for _ in range(2 * n):
        w1.step()
    w2, b2 = make(lagrangian, advection=advection, wall=wall)
    for _ in range(n):
        w2.step()
    state = b2.get_state()
    # the scene exercises what must carry over: contact with a warm start, plastic flow, Newton guesses
    assert any(r.rows > 0 for r in b2.history) and len(state["active_rows"]) > 0
    assert np.abs(state["Fp_inv"] - np.eye(3)).max() > 1e-6
    assert state["steps"] > n

    w3, b3 = make(lagrangian, advection=advection, wall=wall)
    assert len(b3.get_state()["active_rows"]) == 0  # a fresh body: the warm start differs in length
    b3.set_state(state)
    w3.frame = n
    for _ in range(n):
        w3.step()
    assert b3.history and all(r.time >= n / FPS - 1e-12 for r in b3.history)
    # the same steps: dt, contact rows, QP iterations (the warm start) and residuals
    assert b3.history == b1.history[-len(b3.history):]
    if wall:
        assert any(r.rows > 0 and r.time > n / FPS for r in b1.history)
    got, ref = snapshot(b3), snapshot(b1)
    for key in ref:
        assert np.array_equal(got[key], ref[key]), key
    s1, s3 = b1.get_state(), b3.get_state()
    assert set(s1) == set(s3)
    for key in s1:
        assert np.array_equal(s1[key], s3[key]), key


def test_state_of_another_resolution_is_refused_and_changes_nothing(device):
    w, b = make(resolution=6, plastic=False, device=device)
    w.step()
    before = b.get_state()
    points = b.points()
    _, other = make(resolution=8, plastic=False, device=device)
    assert other.signature() != b.signature()
    with pytest.raises(StateMismatch, match="z"):
        b.set_state(other.get_state())
    after = b.get_state()
    assert set(after) == set(before)
    for key in before:
        assert np.array_equal(after[key], before[key]), key
    assert np.array_equal(b.points(), points)
    # a missing field is refused the same way
    partial = dict(before)
    del partial["v"]
    with pytest.raises(StateMismatch, match="missing v"):
        b.set_state(partial)


def test_state_needs_a_bound_body_and_carries_a_failure():
    b = EolBody(trimesh.creation.icosphere(subdivisions=1, radius=0.5), SOFT, resolution=5, name="ball")
    with pytest.raises(wsim.InvalidParameter, match="World"):
        b.get_state()
    b.bind(wp.get_device("cpu"), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    b._failure = ("Eulerian velocity", "non-finite at step 7", "non-finite")
    c = EolBody(trimesh.creation.icosphere(subdivisions=1, radius=0.5), SOFT, resolution=5, name="ball")
    c.bind(wp.get_device("cpu"), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    c.set_state(b.get_state())
    with pytest.raises(wsim.SimulationDiverged, match="ball.*Eulerian velocity"):
        c.check_finite(3, 0.1)
    c.set_state(_fresh_state())
    c.check_finite(3, 0.1)  # a healthy state clears it


def _fresh_state():
    b = EolBody(trimesh.creation.icosphere(subdivisions=1, radius=0.5), SOFT, resolution=5)
    b.bind(wp.get_device("cpu"), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    return b.get_state()


def test_growing_the_grid_copies_the_state_exactly():
    """``_regrid`` enlarges the grid by whole cells: every old node is a new node, so the surface,
    the momenta, the masses and the elastic energy are unchanged, and shrinking back restores z
    and v bit for bit."""
    w, b = make(plastic=False)
    w.step()
    before = b.get_state()
    P, L, E, x = b.linear_momentum(), b.angular_momentum(), b.elastic_energy, b.points()
    m = b.node_masses().sum()
    cells = b.grid.cells
    b._regrid(np.array([1, 0, 2, 3, 1, 0]))
    assert b.grid.cells == (cells[0] + 4, cells[1] + 1, cells[2] + 2)
    assert np.array_equal(b.points(), x)
    np.testing.assert_allclose(b.linear_momentum(), P, rtol=0, atol=1e-12 * np.linalg.norm(P))
    np.testing.assert_allclose(b.angular_momentum(), L, rtol=0, atol=1e-12 * np.linalg.norm(L) + 1e-12)
    assert b.node_masses().sum() == pytest.approx(m, rel=1e-13)
    assert b.elastic_energy == pytest.approx(E, rel=1e-12)
    b._regrid(np.zeros(6, dtype=np.int64))
    after = b.get_state()
    for key in ("z", "v", "y_points", "y_vertices"):
        assert np.array_equal(after[key], before[key]), key


def test_restored_body_continues_on_its_grown_grid():
    """A body with one cell of padding squashed on landing grows its grid; its state carries the
    growth (``grid_grown``): a body built the same way takes it, regrows and continues bit for bit,
    and a state that does not fit leaves the grown body as it was."""
    n = 3
    w1, b1 = make(plastic=False, padding=1)
    for _ in range(2 * n):
        w1.step()
    w2, b2 = make(plastic=False, padding=1)
    for _ in range(n):
        w2.step()
    state = b2.get_state()
    assert state["grid_grown"].any()
    w3, b3 = make(plastic=False, padding=1)
    b3.set_state(state)
    assert b3.grid.cells == b2.grid.cells and np.array_equal(b3.grid.origin, b2.grid.origin)
    w3.frame = n
    for _ in range(n):
        w3.step()
    got, ref = snapshot(b3), snapshot(b1)
    for key in ref:
        assert np.array_equal(got[key], ref[key]), key
    grown, kept = b3.grid, b3.get_state()
    _, other = make(resolution=8, plastic=False)
    with pytest.raises(StateMismatch, match="z"):
        b3.set_state(other.get_state())
    assert b3.grid.cells == grown.cells and np.array_equal(b3.grid.origin, grown.origin)
    for key, value in b3.get_state().items():
        assert np.array_equal(value, kept[key]), key
