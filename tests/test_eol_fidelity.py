"""EoL fidelity (issue 16, items 1, 5, 6): frictionless contact pushes along the normal only, the
angular-momentum read-out and its convergence, flat faces, edges and corners landing on the ground.

Scaled from the issue's scenarios (``tools/study_eol_fidelity.py`` runs them at full size) so that
each runs in seconds on the CPU: the same materials and contact, coarser grids, shorter times.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import wsim
from wsim.eol import EolBody

BALL = wsim.ElasticMaterial(E=1e5, nu=0.3, rho=1000.0)
SCENE = wsim.ElasticMaterial(E=5e4, nu=0.3, rho=500.0)  # scenes/eol_spinning_sphere.py


def test_frictionless_plane_pushes_along_its_normal_only():
    """Issue 16 item 1: a ball released 2 mm above a frictionless plane slid sideways (7.6 cm in 3 s
    at resolution 8): the rows' coefficients were the body's own surface normals, whose tangential
    parts do not cancel between collision cells with different multipliers. At resolution 6 for 1 s
    the contact impulse had a horizontal part of 1.4e-4 of the vertical and the horizontal momentum
    reached 0.05 kg m/s; now the impulse is normal to round-off and the momentum stays at the level
    of advection round-off (< 2e-3 kg m/s, 1e-4 of the ball's weight impulse)."""
    w = wsim.World(fps=30, gravity=(0.0, -9.81, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.0))
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    m.apply_translation((0.0, 0.202, 0.0))
    b = w.add(EolBody(m, BALL, resolution=6, damping=200.0))
    x0 = b.points().mean(axis=0)
    for _ in range(30):
        w.step()
    J = b.contact_impulse
    P = b.linear_momentum()
    assert J[1] > 0.5 * b.mass * 9.81 * w.time  # it rested on the plane
    assert np.hypot(J[0], J[2]) < 1e-12 * J[1]
    assert np.hypot(P[0], P[2]) < 1e-4 * J[1]
    drift = b.points().mean(axis=0) - x0
    assert np.hypot(drift[0], drift[2]) < 1e-4  # m


def _contact_rows_tangential(body):
    rows = body.contact_rows()
    J = rows.J.toarray().reshape(rows.m, -1, 3)
    return np.abs(J[:, :, [0, 2]]).max() / np.abs(J[:, :, 1]).max()


def test_contact_rows_against_a_plane_are_normal_only():
    """Each row's coefficients are (n_A . n_B) n_B dGamma: the body's area elements projected on the
    plane normal (world up here; the body's frame is turned, so the velocity axes are not world)."""
    w = wsim.World(fps=30, gravity=(0.0, -9.81, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.0))
    m = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    m.apply_translation((0.0, 0.17, 0.0))  # 3 cm into the plane
    rot = trimesh.transformations.rotation_matrix(0.5, [1, 2, 3])[:3, :3]
    b = w.add(EolBody(m, BALL, resolution=6, rotation=rot))
    w.step()  # bound, colliders attached
    rows = b.contact_rows()
    R = b.frame[0]
    J = rows.J.toarray().reshape(rows.m, -1, 3) @ R.T  # velocity (body) axes -> world
    assert rows.m > 4
    assert np.abs(J[:, :, [0, 2]]).max() < 1e-12 * np.abs(J[:, :, 1]).max()


def test_angular_momentum_of_a_free_spinning_sphere_converges_to_the_rigid_value():
    """``angular_momentum()`` (about the centre of mass by default) and ``kinetic_energy()`` of a
    sphere spinning rigidly against 2/5 M R^2 omega. The node masses (the ones the step conserves
    momentum with) overestimate the second moment by O(h^2): mass lumped at the corners of the
    cells and the ``mass_floor``; measured +11 % at 8 cells across, +3.2 % at 12, +1.3 % at 16."""
    R, omega = 0.2, 2.0
    M = BALL.rho * 4.0 / 3.0 * np.pi * R**3
    errs = {}
    for res in (6, 12):
        w = wsim.World(fps=30, gravity=(0.0, 0.0, 0.0), device="cpu")
        m = trimesh.creation.icosphere(subdivisions=4, radius=R)
        m.apply_translation((0.3, -0.1, 0.2))
        axis = np.array([0.2, 1.0, 0.3]) / np.linalg.norm([0.2, 1.0, 0.3])
        b = w.add(EolBody(m, BALL, resolution=res, angular_velocity=omega * axis, velocity=(0.5, 0.0, 0.0)))
        w.step()
        L = b.angular_momentum()
        I_w = 0.4 * M * R**2 * omega
        errs[res] = np.linalg.norm(L) / I_w - 1.0
        assert np.linalg.norm(np.cross(L, axis)) < 1e-4 * np.linalg.norm(L)  # along the spin axis (grid anisotropy)
        # about another point: L_p = L_com + (com - p) x P
        mass = b.node_masses()
        com = mass @ b.node_world_positions() / mass.sum()
        p = np.array([1.0, 2.0, -0.5])
        np.testing.assert_allclose(b.angular_momentum(about=p), L + np.cross(com - p, b.linear_momentum()),
                                   rtol=1e-10, atol=1e-10 * np.linalg.norm(L))
        KE_rigid = 0.5 * b.mass * 0.25 + 0.5 * 0.4 * M * R**2 * omega**2  # |v| = 0.5 m/s
        assert b.kinetic_energy() == pytest.approx(KE_rigid, rel=2.0 * abs(errs[res]) + 0.02)
    assert 0.0 < errs[12] < 0.05
    assert errs[12] < 0.5 * errs[6]  # converges with resolution


def _box(orientation: str, size: float = 0.6, gap: float = 0.02) -> trimesh.Trimesh:
    m = trimesh.creation.box(extents=(size, size, size))
    if orientation in ("edge", "corner"):
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 4, [0, 0, 1]))
    if orientation == "corner":
        m.apply_transform(trimesh.transformations.rotation_matrix(np.arctan(1.0 / np.sqrt(2.0)), [1, 0, 0]))
    m.apply_translation((0.0, gap - m.bounds[0, 1], 0.0))
    return m


# deepest surface vertex allowed below the plane, in cells: the rows bind the overlap volume per
# collision cell, so a sharp tip (its overlap ~ depth^3) dips further than a flat face
PENETRATION = {"face": 0.1, "edge": 0.5, "corner": 0.75}


@pytest.mark.parametrize("orientation", ["face", "edge", "corner"])
def test_box_lands_on_a_face_an_edge_and_a_corner(orientation):
    """Issue 16 item 6 (scaled: resolution 6, 1.5 s, damping 200): a box of the scene's soft
    material landing flat, on an edge and on a corner does not diverge, stays within the stated
    depth below the plane, gains no energy (kinetic + elastic + gravity; the edge landing: see
    below), and its momentum changes by gravity
    and contact alone (advection of the Eulerian velocity is not conservative: below 3 % of the
    contact impulse)."""
    w = wsim.World(fps=30, gravity=(0.0, -9.81, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.0))
    b = w.add(EolBody(_box(orientation), SCENE, resolution=6, damping=200.0))
    P0 = b.linear_momentum()
    def total_energy():  # kinetic + elastic + gravitational (node masses)
        m = b.node_masses()
        return b.kinetic_energy() + b.elastic_energy + 9.81 * float(m @ b.node_world_positions()[:, 1])

    E0 = total_energy()
    lowest, energy = [], []
    for _ in range(45):
        w.step()
        lowest.append(float(b.points()[:, 1].min()))
        energy.append(total_energy())
    h = b.grid.h
    assert min(lowest) > -PENETRATION[orientation] * h
    assert b.steps < 45 * 40  # no collapse of dt
    if orientation != "edge":
        assert max(energy) < E0 + 0.02 * b.mass * 9.81 * 0.6  # nothing pumps energy in
    else:  # known (issue 16, left open): pushing out an existing overlap at vol / tau (the
        # relaxation term b) adds kinetic energy: +28 J (6 % of m g size) on this edge landing
        assert max(energy) < E0 + 0.1 * b.mass * 9.81 * 0.6
    impulse = b.contact_impulse
    assert impulse[1] > 0.3 * b.mass * 9.81 * w.time
    resid = b.linear_momentum() - P0 - b.gravity_impulse - impulse
    assert np.abs(resid).max() < 0.03 * np.linalg.norm(impulse)
    assert np.hypot(impulse[0], impulse[2]) < 1e-9 * impulse[1]


def test_box_landing_flat_at_speed_grows_its_grid():
    """Issue 16 item 6: the spinning-sphere scene's box (0.6 m, E = 50 kPa, rho = 500, damping 20)
    lands flat at 3.8 m/s (0.72 m of fall), resolution 8. It squashes by about a quarter and bulges
    sideways past its 2-cell padding: that used to stop the run ("material left the grid") two
    frames after impact. The grid now grows on the sides the material reaches, so the landing runs
    through the rebound, the body stays within a cell of the plane and its momentum changes by
    gravity and contact alone."""
    w = wsim.World(fps=30, gravity=(0.0, -9.81, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.0))
    b = w.add(EolBody(_box("face", gap=0.72), SCENE, resolution=12, damping=20.0))
    cells0 = b.grid.cells
    P0 = b.linear_momentum()
    lowest, vol = [], []
    for _ in range(20):
        w.step()
        lowest.append(float(b.points()[:, 1].min()))
        vol.append(b.volume())
    assert any(c > c0 for c, c0 in zip(b.grid.cells, cells0))  # it grew
    assert b.linear_momentum()[1] > 0.0  # it rebounded
    assert min(lowest) > -1.0 * b.grid.h
    assert min(vol) > 0.7 * 0.216
    resid = b.linear_momentum() - P0 - b.gravity_impulse - b.contact_impulse
    assert np.abs(resid).max() < 0.03 * np.linalg.norm(b.contact_impulse)


def test_thin_fin_landing_at_speed_stays_bounded():
    """Issue 16 item 6 (the bunny's failure, on a procedural shape): a fish (0.6 m, its tail fin
    14 mm thick, half a cell at 20 cells across) of the scene's soft material, spinning at pi
    rad/s, lands at about 4 m/s and bounces. The fin's cells hold one or two material points.

    - Before the reference-map extension, the empty nodes around them kept stale z: thin-part
      nodes reached 300 m/s and the run stopped at frame 10 ("material left the grid").
    - Before the contact rows pushed out from both faces of a part crossing the ground
      (``pushed_area``), rows holding a fin's upper face alone pulled it in, and rows holding both
      faces cancelled: at these settings the fin went 6 cells deep, the energy rose by 18 % of the
      start in a frame and the body's momentum missed its impulses by 188 kg m/s in a frame (the
      contact impulse over the run pointed down).

    Now the energy (kinetic, elastic, gravitational) never rises, each frame's momentum change
    matches gravity plus contact (up to the non-conservative advection, ~1 % of the contact
    impulse), the fin dips less than two cells and only for a frame or two. On a frictionless
    ground, as measured: with the ground's default friction (0.5, which EoL bodies feel since
    2026-11-28) the fin dips past a cell in three frames (1.24, 1.95 and 1.24 cells), the energy
    still never rising."""
    from wsim.mesh import shapes

    w = wsim.World(fps=30, gravity=(0.0, -9.81, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.0))  # as measured (EoL contact was frictionless)
    m = shapes.fish(0.6, 3)
    m.apply_translation((0.0, 0.75, 0.0))
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    b = w.add(EolBody(m, SCENE, resolution=20, damping=20.0, angular_velocity=np.pi * axis,
                      velocity=(0.4, -3.0, 0.0), name="fish"))

    def total_energy():
        mass = b.node_masses()
        return b.kinetic_energy() + b.elastic_energy + 9.81 * float(mass @ b.node_world_positions()[:, 1])

    E0, h = total_energy(), b.grid.h
    energy, depth, budget = [E0], [], []
    P, impulse = b.linear_momentum(), np.zeros(3)
    for _ in range(30):
        w.step()  # raises SimulationDiverged if it blows up
        energy.append(total_energy())
        depth.append(-b.points()[:, 1].min() / h)
        P1, impulse1 = b.linear_momentum(), b.gravity_impulse + b.contact_impulse
        budget.append(np.linalg.norm((P1 - P) - (impulse1 - impulse)))
        P, impulse = P1, impulse1
    energy = np.array(energy)
    assert np.max(energy - np.minimum.accumulate(energy)) < 0.01 * abs(E0)
    assert b.contact_impulse[1] > 0.0
    assert max(budget) < 0.03 * np.linalg.norm(b.contact_impulse)
    assert max(depth) < 2.0
    assert sum(d > 1.0 for d in depth) <= 2  # a dip for a frame or two
    assert max(depth[-5:]) < 1.0


def test_slab_landing_edge_first_on_a_frictionless_plane_gains_no_sideways_momentum():
    """A thin slab (0.4 x 0.03 x 0.3 m, 1.2 cells thick at 16 cells) lands edge-first, tilted 60
    degrees, at 3 m/s on a frictionless plane. The plane pushes along its normal only, so nothing
    can give the slab horizontal momentum. Semi-Lagrangian advection of the Eulerian velocity
    (sharply varying at the impact) and the re-lumped masses gave the residual momentum of its own,
    which the next split handed to the frame: 0.58 kg m/s sideways in two frames, then a slide at
    0.38 m/s (an independent check). The residual is now kept free of momentum after advection
    (``EolBody._restore_momentum``): the slab gains 13x less sideways momentum (0.04 against 0.56
    kg m/s in 8 frames: 0.5 % of the vertical contact impulse; likely the re-lumped masses) and
    each frame's momentum change matches gravity plus contact within 1 % of the contact impulse."""
    w = wsim.World(fps=30, gravity=(0.0, -9.81, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.0))
    R = trimesh.transformations.rotation_matrix(np.radians(60.0), (0, 0, 1))[:3, :3]
    b = w.add(EolBody(trimesh.creation.box((0.4, 0.03, 0.3)), SCENE, resolution=16, damping=20.0, rotation=R,
                      position=(0.0, 0.25, 0.0), velocity=(0.0, -3.0, 0.0), name="slab"))
    P, impulse = b.linear_momentum(), np.zeros(3)
    horizontal, budget = [], []
    for _ in range(8):
        w.step()
        P1, impulse1 = b.linear_momentum(), b.gravity_impulse + b.contact_impulse
        budget.append(np.linalg.norm((P1 - P) - (impulse1 - impulse)))
        horizontal.append(np.hypot(P1[0], P1[2]))
        P, impulse = P1, impulse1
    assert b.contact_impulse[1] > 5.0  # it landed (about 1.5 kg at 3-4 m/s)
    assert max(horizontal) < 0.01 * b.contact_impulse[1]  # was 0.064
    assert max(budget) < 0.01 * b.contact_impulse[1]


def test_free_box_with_a_random_velocity_field_does_not_gain_energy():
    """A free, undamped box (0.3 x 0.2 x 0.15 m, E = 1e5, 8 cells), no gravity, given a small
    non-rigid velocity field: its energy (kinetic + elastic) can only be lost to advection. At the
    elastic cap 0.5 h / c1 a mode grew out of it by about 0.7 % a step, 30x the energy by 2 s
    (spinning or not; found by an independent check on a spinning box), while the steps ran to
    the cap with each frame's remainder last: a step pattern repeating every frame, which pumps
    a mode parametrically (symplectic Euler is stable at one dt, not under a periodically
    varying one). The steps now divide each frame evenly (``EolBody.advance_group``) and the box
    decays at 0.5, the default again; a damped body decays too."""
    rng = np.random.default_rng(0)
    noise = {}

    def field(x):  # the same field for both runs
        if len(x) not in noise:
            noise[len(x)] = 0.005 * rng.standard_normal(x.shape)
        return 0.02 * np.sin(40.0 * x[:, [1, 2, 0]]) + noise[len(x)]

    def energies(**kw):
        w = wsim.World(fps=30, gravity=(0.0, 0.0, 0.0), device="cpu")
        b = w.add(EolBody(trimesh.creation.box((0.3, 0.2, 0.15)), wsim.ElasticMaterial(E=1e5, nu=0.3, rho=1000.0),
                          resolution=8, velocity_field=field, **kw))
        out = []
        for _ in range(60):
            w.step()
            out.append(b.kinetic_energy() + b.elastic_energy)
        dt = np.array([r.dt for r in b.history])  # the elastic cap binds: every step the same
        assert np.ptp(dt) < 1e-9 * dt[0] and dt[0] <= b.dt_elastic
        return np.array(out)

    E = energies()  # the default cap, 0.5 h / c1: 35x by 4 s with the remainder steps
    assert E[-1] < E[2] and E[2:].max() < 1.05 * E[2]
    # damped (10 Pa s): the same cap, or the viscous one where shorter
    w = wsim.World(fps=30, gravity=(0.0, 0.0, 0.0), device="cpu")
    mat = wsim.ElasticMaterial(E=1e5, nu=0.3, rho=1000.0)
    b = w.add(EolBody(trimesh.creation.box((0.3, 0.2, 0.15)), mat, resolution=8, velocity_field=field, damping=10.0))
    assert b.elastic_safety == 0.5 and b.dt_elastic == pytest.approx(min(0.5 * b.grid.h / mat.c1, 1000.0 * b.grid.h**2 / 120.0))
    E_damped = []
    for _ in range(60):
        w.step()
        E_damped.append(b.kinetic_energy() + b.elastic_energy)
    assert E_damped[-1] < E_damped[2] and max(E_damped[2:]) < 1.05 * E_damped[2]
