"""Contact between bodies (``wsim.contact``): BEM bodies of one dt collide with each other through
the same constraint solve as their colliders and joints; the impulses are equal and opposite."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp

import wsim
from wsim.bem import build_operators
from wsim.contact import points_inside

from bem_box import BOX, DT, G, MAT  # noqa: E402 (tests/ is on the path; box_ops: conftest.py)


def _depth(a, b) -> float:
    """How deep any node of b is inside a [m] (0 if none)."""
    hit, face, bary, _ = points_inside(b.points(), a.points(), a.faces, 0.0, wp.get_device("cpu"))
    if not len(hit):
        return 0.0
    P = np.einsum("mk,mkd->md", bary, a.points()[a.faces[face]])
    return float(np.linalg.norm(b.points()[hit] - P, axis=1).max())


def _frames_momenta(bodies) -> tuple[np.ndarray, np.ndarray]:
    """The BEM bodies' frames' momentum and angular momentum about the origin (what contact
    impulses move; the read-outs add a constrained step's pose transfer)."""
    p, L = np.zeros(3), np.zeros(3)
    for body in bodies:
        f = body.state.frame
        p += body.mass * f.velocity
        L += body.world_inertia() @ f.omega + np.cross(f.T, body.mass * f.velocity)
    return p, L


def _collide(ops, mesh, device, offset: float = 0.05, steps: int = 150) -> dict:
    """Two cubes thrown at each other at 1 m/s in zero gravity, offset by ``offset`` [m] (5 cm: the
    blow is glancing), stepped ``steps`` steps (0.3 s): the cubes ``a``, ``b``, the pair's momentum
    ``p0`` and angular momentum about the origin ``L0`` at the start, the ``depth`` of the deepest
    interpenetration seen, and the largest change of the frames' momentum ``dp`` and angular
    momentum ``dL`` while they touched (what the contact impulses move)."""
    world = wsim.World(fps=1.0 / DT, device=device, gravity=(0.0, 0.0, 0.0))
    a = world.add(wsim.BemBody(mesh, MAT, DT, operators=ops, name="a", position=(-0.15, 0.0, 0.0),
                               velocity=(1.0, 0.0, 0.0), friction=0.3))
    b = world.add(wsim.BemBody(mesh, MAT, DT, operators=ops, name="b", position=(0.15, offset, 0.0),
                               velocity=(-1.0, 0.0, 0.0), friction=0.3))
    p0 = a.linear_momentum() + b.linear_momentum()
    L0 = a.angular_momentum(about=(0, 0, 0)) + b.angular_momentum(about=(0, 0, 0))
    out = dict(a=a, b=b, p0=p0, L0=L0, depth=0.0, dp=0.0, dL=0.0)
    for _ in range(steps):
        world.step()
        out["depth"] = max(out["depth"], _depth(a, b), _depth(b, a))
        if len(a.state.point_nodes) or len(b.state.point_nodes):
            p, L = _frames_momenta((a, b))
            out["dp"] = max(out["dp"], float(np.abs(p - p0).max()))
            out["dL"] = max(out["dL"], float(np.abs(L - L0).max()))
    return out


def test_head_on_collision_conserves_momentum_and_does_not_interpenetrate(box_ops, device):
    """The cubes meet, push apart and leave: the contact impulses are equal and opposite, so the
    frames' momentum is kept through contact to round-off; after they part each rings freely and
    the paper's error correction hands its deformation's drift to its frame, which is not exactly
    momentum-neutral: the pair's momentum 0.3 s on is kept to 3e-3 of one cube's (2.0e-3
    measured, out of the blow's plane, in the first steps after they part; 0.8e-3 while nodes on
    the other's face edges took a side face's normal, ``wsim.contact.facing_faces``), and no node
    goes deeper into the other than a few times the solver's tolerance (1.0x measured, at the
    first touch: the constraint is linearized on the predicted surface)."""
    c = _collide(box_ops, BOX, device)
    a, b = c["a"], c["b"]
    assert np.linalg.norm(a.contact_impulse) > 1.0
    assert np.abs(a.contact_impulse + b.contact_impulse).max() < 1e-9 * np.linalg.norm(a.contact_impulse)
    assert c["dp"] < 1e-9 * a.mass * 1.0
    assert np.abs(a.linear_momentum() + b.linear_momentum() - c["p0"]).max() < 3e-3 * a.mass * 1.0
    assert a.frame.velocity[0] < 0.0 < b.frame.velocity[0]  # they separated
    assert c["depth"] < 3.0 * a.constraint_tolerance


def test_glancing_collision_keeps_angular_momentum(box_ops, device):
    """The frame turns by each contact force's own moment at its point (``BemBody._point_alphas``),
    so the two sides of a contact exert no net torque on the pair: through the glancing blow the
    frames' angular momentum about the origin stays within 1 % of its start (0.49 % measured at
    26 nodes a cube; with the moment of the traction, which acts at the hat functions' centroids,
    20 % was lost at 26 nodes and 7 % at 98). In the first free steps after they part, the
    paper's error correction hands each cube's drift to its frame and moves it again: the read-out
    0.3 s on is kept to 2 % (0.33 % measured; 1.0 % with the points' levers predicted for the
    step's end)."""
    c = _collide(box_ops, BOX, device)
    a, b, L0 = c["a"], c["b"], c["L0"]
    L = a.angular_momentum(about=(0, 0, 0)) + b.angular_momentum(about=(0, 0, 0))
    assert np.linalg.norm(a.contact_impulse) > 1.0
    assert c["dL"] < 1e-2 * np.linalg.norm(L0)
    assert np.abs(L - L0).max() < 2e-2 * np.linalg.norm(L0)


def test_cubes_of_one_mesh_meeting_face_to_face_part(box_ops, device):
    """Cubes of one mesh thrown face to face with no offset: every node of the touching faces but the
    centre lies on an edge of the other's face, whose nearest face is a tie. Taken as the side
    face, its normal and friction held the faces together as they sprang apart: the cubes stopped
    dead, pulled together in 35 steps (an independent check). With the face each node faces
    (``wsim.contact.facing_faces``) they part at 0.36 m/s each, like the same cubes offset by 3 cm
    (0.32 m/s) or of 98 nodes (0.39 m/s), and the contact pushes them apart."""
    c = _collide(box_ops, BOX, device, offset=0.0, steps=60)
    a, b = c["a"], c["b"]
    assert a.frame.velocity[0] < -0.2 and b.frame.velocity[0] > 0.2
    assert c["dp"] < 1e-9 * a.mass * 1.0
    assert a.contact_impulse[0] < -1.0


def test_cube_stacked_on_a_cube_rests(box_ops, device):
    """A cube set on another on the ground: it stays on top (no interpenetration beyond the
    tolerance), the upper cube's contact impulse carries its weight and the lower's carries its own
    (the ground pushes it with both weights, the upper cube with one, opposite)."""
    world = wsim.World(fps=1.0 / DT, device=device, gravity=(0.0, -G, 0.0))
    world.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    a = world.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="a", position=(0.0, 0.1002, 0.0)))
    b = world.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="b", position=(0.05, 0.3006, 0.02)))
    for _ in range(400):  # lands and settles
        world.step()
    Ja, Jb, y = a.contact_impulse, b.contact_impulse, b.points()[:, 1].min()
    for _ in range(100):
        world.step()
        assert max(_depth(a, b), _depth(b, a)) < a.constraint_tolerance
    weight = MAT.rho * 0.008 * G * 100 * DT
    # to 1 %: the upper cube still rocks gently on the lower one (only BDF1 damps it; its lowest
    # point moves 0.3 mm in this window), so the window's impulse is 0.2 % short of its weight
    assert (b.contact_impulse - Jb)[1] == pytest.approx(weight, rel=1e-2)
    assert (a.contact_impulse - Ja)[1] == pytest.approx(weight, rel=1e-2)
    assert abs(b.points()[:, 1].min() - y) < 1e-3  # it stays on top


def _slide(w, base, box, frames: int = 40) -> tuple[float, float]:
    """Step ``w`` ``frames`` frames: how far ``box`` moved along x relative to ``base`` [m] and their
    relative x velocity at the end [m/s] (centres of mass)."""
    def x() -> float:
        return float(box.center_of_mass()[0] - base.center_of_mass()[0])

    x0 = x()
    for _ in range(frames):
        w.step()
    rel_v = box.linear_momentum()[0] / _mass(box) - base.linear_momentum()[0] / _mass(base)
    return x() - x0, float(rel_v)


def _mass(body) -> float:
    """A body's mass [kg], whatever its method (PBD: the particles'; EoL: the lumped nodes')."""
    if isinstance(body, wsim.PbdBody):
        return float(body.masses.sum())
    return float(body.mass if isinstance(body, wsim.BemBody) else body.node_masses().sum())


def test_bem_cube_slides_to_the_coulomb_distance_on_a_bem_slab(box_ops):
    """The 26-node BEM cube launched at 1 m/s across a BEM slab (0.8 x 0.1 x 0.4 m, 26 nodes, on
    ground it cannot slide on; friction 0.5 both) stops within 15 % of the Coulomb distance
    v^2 / (2 mu g) relative to the slab (measured 0.1027 m against 0.1019 m). Across a second
    cube of its own mesh: ``test_bem_cube_slides_to_the_coulomb_distance_on_a_bem_cube``."""
    slab = trimesh.creation.box(extents=(0.8, 0.1, 0.4)).subdivide()
    slab_mat = wsim.ElasticMaterial(E=1e7, nu=0.3, rho=2000.0)
    w = wsim.World(fps=1.0 / (5 * DT), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.9))
    base = w.add(wsim.BemBody(slab, slab_mat, DT, operators=build_operators(slab, slab_mat, DT, cache=False, device="cpu"),
                              name="slab", position=(0.2, 0.0505, 0.0), friction=0.5))
    box = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="box", position=(0.0, 0.2015, 0.0),
                             velocity=(1.0, 0.0, 0.0), friction=0.5))
    dx, rel_v = _slide(w, base, box)
    assert abs(rel_v) < 0.02
    assert dx == pytest.approx(1.0 / (2 * 0.5 * G), rel=0.15)


def test_bem_cube_slides_to_the_coulomb_distance_on_a_bem_cube(box_ops):
    """The 26-node BEM cube launched at 0.5 m/s across a second cube of its own mesh resting on the
    ground (E = 1e6 Pa both, friction 0.5) stops within 15 % of the Coulomb distance relative to
    it (measured 0.0234 m, 0.92 of 0.0255 m; 0.93 at 98 nodes) and stays: the pair then sways
    together on the soft lower cube (the relative speed of the centres of mass swings by up to
    0.05 m/s, ringing down: BEM bodies have no material damping), which averages out over 0.2 s
    (measured -4 mm/s; 6 mm/s at 98 nodes). Launched at 1 m/s it slides to within 7 mm of the lower cube's edge and
    tips there, which the Coulomb distance does not model."""
    w = wsim.World(fps=1.0 / (5 * DT), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    low = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="low", position=(0.0, 0.1002, 0.0), friction=0.5))
    top = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="top", position=(-0.03, 0.3006, 0.0),
                             velocity=(0.5, 0.0, 0.0), friction=0.5))
    x0 = top.center_of_mass()[0] - low.center_of_mass()[0]
    rel_v = []
    for _ in range(100):
        w.step()
        rel_v.append(top.state.material_velocity[0] - low.state.material_velocity[0])
    dx = top.center_of_mass()[0] - low.center_of_mass()[0] - x0
    assert dx == pytest.approx(0.5**2 / (2 * 0.5 * G), rel=0.15)
    assert abs(np.mean(rel_v[-20:])) < 0.01


@pytest.mark.parametrize("box_method, slab_method", [("pbd", "bem"), ("eol", "bem"), ("eol", "pbd"), ("bem", "pbd")])
def test_box_slides_to_the_coulomb_distance_on_a_slab_of_another_method(box_ops, box_method, slab_method):
    """A box launched at 1 m/s across a slab of another method resting on the ground (friction 0.5
    both; the ground holds the slab) stops within 15 % of v^2 / (2 mu g) relative to the slab.
    Measured 0.1013 m (PBD box on a BEM slab), 0.1018 (EoL on BEM), 0.1030 (EoL on PBD) and 0.0895
    (the 8 kg BEM cube on a 48 kg PBD slab, whose push is found implicitly; 0.0902 handed over one
    interval late, at 2 mm/s relative to it at the end; 0.0917 and still rattling at 4 cm/s before
    the cube yielded to the slab's particles within the interval) against 0.1019 m."""
    w = wsim.World(fps=1.0 / (5 * DT), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.9))
    if slab_method == "bem":
        mesh = trimesh.creation.box(extents=(0.8, 0.1, 0.4)).subdivide()
        mat = wsim.ElasticMaterial(E=1e7, nu=0.3, rho=2000.0)
        base = w.add(wsim.BemBody(mesh, mat, DT, operators=build_operators(mesh, mat, DT, cache=False, device="cpu"),
                                  name="slab", position=(0.2, 0.0505, 0.0), friction=0.5))
    else:
        base = w.add(wsim.PbdBody(trimesh.creation.box(extents=(1.2, 0.1, 0.4)).subdivide(), PBD_DENSE, tets="auto",
                                  name="slab", position=(0.3, 0.05, 0.0), damping=0.01, friction=0.5))
    small = trimesh.creation.box(extents=(0.1, 0.1, 0.1)).subdivide()
    if box_method == "pbd":
        box = w.add(wsim.PbdBody(small, PBD_DENSE, tets="auto", name="box", position=(0.0, 0.1505, 0.0),
                                 velocity=(1.0, 0.0, 0.0)))
    elif box_method == "eol":
        box = w.add(wsim.EolBody(small.subdivide(), wsim.ElasticMaterial(E=1e5, nu=0.3, rho=500.0), resolution=5,
                                 name="box", position=(0.0, 0.1505, 0.0), velocity=(1.0, 0.0, 0.0), damping=50.0,
                                 friction=0.5))
    else:
        box = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="box", position=(0.0, 0.2005, 0.0),
                                 velocity=(1.0, 0.0, 0.0), friction=0.5))

    dx, _ = _slide(w, base, box)
    assert dx == pytest.approx(1.0 / (2 * 0.5 * G), rel=0.15)


@pytest.mark.parametrize("slab_rho, iterations, bound", [(1000.0, 6, 5e-3), (1000.0, 2, 0.1), (167.0, 6, 5e-3)],
                         ids=["48kg_slab", "48kg_slab_2_passes", "8kg_slab"])
def test_bem_cube_rests_on_a_pbd_slab(box_ops, slab_rho, iterations, bound):
    """The 8 kg BEM cube set on the PBD slab of the slide above (48 kg, or 8 kg), with the World's
    default coupling, which finds the slab's push within each interval: the 48 kg slab is over
    twice the cube's mass, and the 8 kg one carries its weight (``wsim.world._supports``). Over the
    second half second the cube's speed relative to the slab averages under 5 mm/s (measured 1.1
    on both; handed over one interval late it is kicked at 17-19 and 10 mm/s by each interval's
    push, from a few of its nine bottom nodes' contacts). With ``coupling_iterations=2`` the
    intervals end unconverged and what the guess missed is handed over after them: it must not
    fling the cube (under 0.1 m/s; measured 40 mm/s). When the first guess was the slab's last
    push alone, with that leftover pending on top, the cube was flung at 4-6 m/s
    (``World._advance_implicit``)."""
    w = wsim.World(fps=1.0 / (5 * DT), device="cpu", coupling_iterations=iterations)
    w.add_collider(wsim.GroundPlane(0.0, friction=0.9))
    base = w.add(wsim.PbdBody(trimesh.creation.box(extents=(1.2, 0.1, 0.4)).subdivide(),
                              wsim.ElasticMaterial(E=PBD_DENSE.E, nu=PBD_DENSE.nu, rho=slab_rho), tets="auto",
                              name="slab", position=(0.3, 0.05, 0.0), damping=0.01, friction=0.5))
    box = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="box", position=(0.0, 0.2005, 0.0), friction=0.5))
    rel = []
    for _ in range(100):
        w.step()
        rel.append(np.linalg.norm(box.state.material_velocity - base.linear_momentum() / _mass(base)))
    assert w.coupling_stats["implicit_intervals"] > 400
    assert np.mean(rel[50:]) < bound, np.mean(rel[50:])


def test_pending_push_is_shared_by_the_pushers_that_pushed_where_it_is():
    """``World._advance_implicit``'s first guess takes each pusher's share of what is still pending
    on the target out of its last push (``wsim.world._pending_shares``): at each vertex in
    proportion to the pushers' last pushes there, among the pushers that pushed at all where none
    pushed that vertex, and among those near the target where none pushed it; the shares add up
    to what is pending, and a pusher that did not push and is not near holds none."""
    from wsim.world import _pending_shares

    a, b, far = object(), object(), object()
    pairs = [(a, 0), (b, 0), (far, 0)]
    last = [np.array([[0.0, 2.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]),
            np.array([[0.0, 0.0, 0.0], [0.0, 3.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]),
            np.zeros((4, 3))]
    pending = {0: np.array([[0.0, 0.4, 0.0], [0.0, 0.8, 0.0], [0.2, 0.0, 0.0], [0.0, 0.0, 0.6]])}
    shares = _pending_shares(pairs, last, pending, lambda j: j == 2)
    assert np.allclose(sum(shares), pending[0])
    assert np.allclose(shares[0][:, 1], [0.4, 0.2, 0.0, 0.0]) and np.allclose(shares[1][:, 1], [0.0, 0.6, 0.0, 0.0])
    assert np.allclose(shares[1][2], [0.2, 0.0, 0.0]) and not shares[2].any()
    assert np.allclose(shares[0][3], [0.0, 0.0, 0.3]) and np.allclose(shares[1][3], [0.0, 0.0, 0.3])  # none pushed it
    none = _pending_shares(pairs, [np.zeros((4, 3))] * 3, pending, lambda j: j == 2)  # a bounce: the near one
    assert np.allclose(none[2], pending[0]) and not none[0].any() and not none[1].any()


def test_body_contact_can_be_switched_off(box_ops):
    world = wsim.World(fps=1.0 / DT, device="cpu", gravity=(0.0, 0.0, 0.0), body_contact=False)
    a = world.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="a", position=(-0.15, 0.0, 0.0),
                               velocity=(1.0, 0.0, 0.0)))
    b = world.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="b", position=(0.15, 0.0, 0.0),
                               velocity=(-1.0, 0.0, 0.0)))
    for _ in range(150):
        world.step()
    assert a.frame.velocity[0] == pytest.approx(1.0) and b.frame.velocity[0] == pytest.approx(-1.0)  # passed through


@pytest.mark.parametrize("offset", [(0.0, 0.0), (0.02, 0.01)], ids=["corner_over_corner", "off_centre"])
def test_coarse_bem_boxes_stack(offset):
    """Two 8-node BEM boxes (``trimesh.creation.box``, 12 faces), one set 1.5 mm above the other on
    the ground. Contact at nodes alone let the top one slide down the edges of the other when set
    corner over corner (on the edge planes no face holds a node) until it lay on the ground
    inside it, and tip in when set 2 cm off (two supports on a diagonal); with the faces'
    centroids pressing too (``wsim.contact.surface_points``, surfaces of fewer than
    ``CENTROID_FACES`` faces) it rests: after 0.6 s its centre is within 1 mm of where it rests
    and no node of it is more than 1 mm below the other's top (measured 0.1 mm and 0.3-0.4 mm)."""
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    ops = build_operators(box, MAT, DT, cache=False, device="cpu")
    w = wsim.World(fps=100, gravity=(0.0, -G, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    low = w.add(wsim.BemBody(box, MAT, DT, operators=ops, name="low", position=(0.0, 0.1005, 0.0), friction=0.5))
    top = w.add(wsim.BemBody(box, MAT, DT, operators=ops, name="top", position=(offset[0], 0.3015, offset[1]),
                             friction=0.5))
    for _ in range(60):
        w.step()
    assert len(top.points()) == 8
    assert abs(top.center_of_mass()[1] - 0.2995) < 1e-3
    assert top.points()[:, 1].min() > low.points()[:, 1].max() - 1e-3


def test_coarse_bem_box_rests_on_a_box_collider():
    """An 8-node BEM box set corner over corner on an 8-vertex box collider (a pedestal): its
    nodes lie on the pedestal's edges, where no face holds them, and it slid down them to the
    ground; its faces' centroids press on the collider too (surfaces of fewer than
    ``CENTROID_FACES`` faces), and it rests on top (centre within 1 mm of where it rests, lowest
    node less than 3 mm into the pedestal's top: measured 0.4 and 1.9 mm). Set 2 cm off centre
    it still tips, slowly (README, known limits)."""
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    ops = build_operators(box, MAT, DT, cache=False, device="cpu")
    w = wsim.World(fps=100, gravity=(0.0, -G, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    w.add_collider(wsim.MeshCollider(trimesh.creation.box(extents=(0.2, 0.2, 0.2)), transform=np.array(
        [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.1], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]), name="pedestal"))
    top = w.add(wsim.BemBody(box, MAT, DT, operators=ops, name="top", position=(0.0, 0.3015, 0.0), friction=0.5))
    for _ in range(60):
        w.step()
    assert abs(top.center_of_mass()[1] - 0.2995) < 1e-3
    assert top.points()[:, 1].min() > 0.2 - 3e-3


def test_bem_bodies_of_different_dt_raise_before_they_may_touch(box_ops, tmp_path):
    """BEM bodies touch only bodies of their own dt (one constraint solve per step): a cube of
    another dt dropped on one passed through it unnoticed. The World raises before the frame in
    which they may meet, naming both and their dts, and the frames before it stay in the file;
    bodies of different dt far apart step on."""
    dt2 = 2.0 * DT
    ops2 = build_operators(BOX, MAT, dt2, cache=False, device="cpu")
    world = wsim.World(fps=1.0 / dt2, device="cpu", gravity=(0.0, -G, 0.0))
    world.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    world.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="low", position=(0.0, 0.1005, 0.0)))
    world.add(wsim.BemBody(BOX, MAT, dt2, operators=ops2, name="far", position=(2.0, 0.1005, 0.0)))
    world.add(wsim.BemBody(BOX, MAT, dt2, operators=ops2, name="high", position=(0.0, 0.35, 0.0)))
    out = tmp_path / "apart.usda"
    with pytest.raises(wsim.InvalidParameter, match=r"'low' \(dt = 0.002 s\) and 'high' \(dt = 0.004 s\) may touch"):
        world.run(60, out, progress=False)
    assert 0 < world.frame < 60  # it fell freely for some frames first (no pass-through): 4.8 cm take ~25
    from pxr import Usd

    stage = Usd.Stage.Open(str(out))
    assert stage.GetEndTimeCode() == world.frame  # the frames stepped before it were written
    alone = wsim.World(fps=1.0 / dt2, device="cpu", gravity=(0.0, -G, 0.0))
    alone.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    alone.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="low", position=(0.0, 0.1005, 0.0)))
    alone.add(wsim.BemBody(BOX, MAT, dt2, operators=ops2, name="far", position=(2.0, 0.1005, 0.0)))
    for _ in range(5):
        alone.step()


# -- PBD bodies (wsim.pbd.contact) ------------------------------------------------------------

PBD_MAT = wsim.ElasticMaterial(E=2.0e5, nu=0.3, rho=500.0)
BALL = trimesh.creation.icosphere(subdivisions=2, radius=0.2)


def _pbd_pair(device, contact=True, substeps=10):
    """Two tetrahedral PBD balls thrown at each other at 2 m/s in zero gravity, 5 cm off centre;
    after 0.4 s: the bodies, the pair's momentum and angular momentum about the origin at the
    start, and the deepest interpenetration seen."""
    w = wsim.World(fps=60, gravity=(0.0, 0.0, 0.0), device=device, body_contact=contact)
    a = w.add(wsim.PbdBody(BALL, PBD_MAT, tets="auto", name="a", position=(-0.3, 0.0, 0.0), velocity=(2.0, 0, 0),
                           substeps=substeps))
    b = w.add(wsim.PbdBody(BALL, PBD_MAT, tets="auto", name="b", position=(0.3, 0.05, 0.0), velocity=(-2.0, 0, 0),
                           substeps=substeps))
    P0 = a.linear_momentum() + b.linear_momentum()
    L0 = a.angular_momentum(about=(0, 0, 0)) + b.angular_momentum(about=(0, 0, 0))
    depth = 0.0
    for _ in range(24):
        w.step()
        depth = max(depth, _depth(a, b), _depth(b, a))
    return a, b, P0, L0, depth


def test_pbd_contact_by_ray_parity_matches_the_winding_number(monkeypatch):
    """A watertight PBD surface is queried by ray parity (``wsim.mesh.inside_test``, a third of the
    winding number's cost); the collision of two balls comes out as with the winding number."""
    from wsim import mesh as wm

    a, b, *_ = _pbd_pair("cpu")
    assert a._contact_test == b._contact_test == 2  # ray parity
    monkeypatch.setattr(wm, "inside_test", lambda faces: 1)
    a1, b1, *_ = _pbd_pair("cpu")
    assert a1._contact_test == 1
    assert a.linear_momentum()[0] < -10.0  # they met and bounced apart (a flew in along +x)
    for x, y in ((a, a1), (b, b1)):  # measured: identical on the CPU
        assert np.abs(x.particles() - y.particles()).max() < 1e-6
        assert np.allclose(x.linear_momentum(), y.linear_momentum(), rtol=1e-6, atol=1e-6)


def _spin_error(a, b, L0) -> float:
    L = a.angular_momentum(about=(0, 0, 0)) + b.angular_momentum(about=(0, 0, 0))
    return float(np.linalg.norm(L - L0) / np.linalg.norm(L0))


def test_pbd_balls_collide_with_equal_and_opposite_impulses(device):
    """The balls meet, push apart and leave with their relative velocity reversed. The pair's
    momentum is kept to float32 round-off (point-triangle constraints with both inverse masses:
    equal and opposite corrections), and no surface particle goes deeper into the other ball than
    1 cm (5 % of the radius). Angular momentum is kept to first order in the substep: a position
    correction acts at the end-of-substep positions, so the lever arm is off by the tangential
    slip over one substep (1.75 % at 10 substeps, 0.96 % at 20, 0.47 % at 40). With
    ``body_contact=False`` they pass through each other."""
    a, b, P0, L0, depth = _pbd_pair(device)
    scale = float(a.masses.sum()) * 2.0
    P = a.linear_momentum() + b.linear_momentum()
    assert np.abs(P - P0).max() < 1e-4 * scale
    assert _spin_error(a, b, L0) < 0.025
    assert a.linear_momentum()[0] < -0.5 * float(a.masses.sum())  # a rebounds along -x
    assert b.center_of_mass()[0] - a.center_of_mass()[0] > 0.6  # and they part
    assert depth < 0.01
    a, b, *_ = _pbd_pair(device, contact=False)
    assert a.center_of_mass()[0] > b.center_of_mass()[0]  # passed through each other


def test_pbd_contact_angular_momentum_error_is_first_order_in_the_substep():
    errors = [_spin_error(a, b, L0) for a, b, _, L0, _ in (_pbd_pair("cpu", substeps=n) for n in (10, 20))]
    assert errors[1] < 0.65 * errors[0]


def test_pbd_box_rests_on_a_pbd_box_on_the_ground():
    """A box dropped 5 cm onto a box resting on the ground stays on top (two layers of contact in
    one lockstep solve: ground-box and box-box) and comes to rest there."""
    w = wsim.World(fps=60, gravity=(0.0, -G, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.8))
    box = trimesh.creation.box(extents=(0.4, 0.2, 0.4)).subdivide().subdivide()
    low = w.add(wsim.PbdBody(box, PBD_MAT, tets="auto", name="low", position=(0.0, 0.1, 0.0), damping=0.01))
    top = w.add(wsim.PbdBody(box, PBD_MAT, tets="auto", name="top", position=(0.05, 0.35, 0.0), damping=0.01))
    for _ in range(60):
        w.step()
    assert top.center_of_mass()[1] > low.center_of_mass()[1] + 0.15
    assert _depth(low, top) < 0.01 and _depth(top, low) < 0.01
    assert np.abs(top.velocities()).max() < 0.1


def test_pbd_box_is_carried_by_a_driven_pbd_slab_and_rides_a_sliding_one(device):
    """Friction between PBD bodies follows the other surface's own motion: (1) a box on a slab
    whose top and bottom particles a handle accelerates at 1.5 m/s^2 (< mu g = 2.9) on
    frictionless ground is carried along (a version that took the slab's velocity after its
    prediction, zero for handle-driven particles, did not drag it at all); (2) a box riding a slab
    that slides down a frictionless 30 degree incline stays put on it (a version that took the
    slab's velocity before gravity let it fall behind at h g sin(theta) = 8.2 mm/s). The slabs set
    friction 0: the box's acts between the bodies (the larger of the two) and none on the
    ground (the larger of the ground's and the slab's)."""
    mat = wsim.ElasticMaterial(E=1e6, nu=0.3, rho=500.0)
    flat = trimesh.creation.box(extents=(0.12, 0.05, 0.12)).subdivide()
    A, T = 1.5, 0.4
    w = wsim.World(fps=60, gravity=(0.0, -G, 0.0), device=device)
    w.add_collider(wsim.GroundPlane(0.0, friction=0.0))
    slab_mesh = trimesh.creation.box(extents=(1.2, 0.08, 0.4)).subdivide().subdivide()
    driven = np.nonzero(np.abs(slab_mesh.vertices[:, 1]) > 0.039)[0]

    def motion(t: float) -> np.ndarray:
        m = np.eye(4)
        m[0, 3] = 0.5 * A * t * t if t < T else 0.5 * A * T * T + A * T * (t - T)
        return m

    slab = w.add(wsim.PbdBody(slab_mesh, mat, tets="auto", name="slab", position=(0.2, 0.04, 0.0), friction=0.0,
                              mass=10.0, handles=[wsim.Handle(driven, motion)]))
    top = w.add(wsim.PbdBody(flat, mat, tets="auto", name="top", position=(0.7, 0.1055, 0.0), friction=0.3, mass=1.0))
    x0 = top.center_of_mass()[0] - slab.particles()[:, 0].mean()
    for _ in range(36):
        w.step()
    slip = top.center_of_mass()[0] - slab.particles()[:, 0].mean() - x0
    assert abs(slip) < 5e-3  # the slab went 0.5 A t^2 + ... = 0.24 m
    assert top.velocities()[:, 0].mean() == pytest.approx(A * T, rel=0.02)

    th = np.radians(30.0)
    w = wsim.World(fps=60, gravity=(G * np.sin(th), -G * np.cos(th), 0.0), device=device)
    w.add_collider(wsim.GroundPlane(0.0, friction=0.0))
    slab = w.add(wsim.PbdBody(trimesh.creation.box(extents=(1.6, 0.08, 0.4)).subdivide(), mat, tets="auto",
                              name="slab", position=(0.0, 0.04, 0.0), friction=0.0, mass=20.0))
    top = w.add(wsim.PbdBody(flat, mat, tets="auto", name="top", position=(-0.6, 0.1055, 0.0), friction=0.5, mass=1.0))
    rel = []
    for _ in range(60):
        w.step()
        rel.append(top.center_of_mass()[0] - slab.center_of_mass()[0])
    assert slab.velocities()[:, 0].mean() == pytest.approx(G * np.sin(th), rel=0.01)  # 1 s of free sliding
    assert abs(rel[-1] - rel[29]) < 1e-3


def test_pbd_box_slides_to_the_coulomb_distance_on_a_pbd_slab_with_its_own_friction():
    """``PbdBody(friction=...)``: a box launched at 1 m/s across a slab resting on the ground, both
    at friction 0.3 (below the 0.5 a body that sets none has), stops within 15 % of
    v0^2 / (2 mu g) with mu = 0.3; a negative coefficient is refused."""
    with pytest.raises(wsim.InvalidParameter, match="body 'b': friction"):
        wsim.PbdBody(trimesh.creation.box(), name="b", friction=-0.1, cache=False)
    mu, v0 = 0.3, 1.0
    w = wsim.World(fps=60, gravity=(0.0, -G, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.8))
    slab = trimesh.creation.box(extents=(1.2, 0.1, 0.4)).subdivide()
    w.add(wsim.PbdBody(slab, PBD_MAT, tets="auto", name="slab", position=(0.3, 0.05, 0.0), damping=0.01, friction=mu))
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1)).subdivide()
    top = w.add(wsim.PbdBody(box, PBD_MAT, tets="auto", name="top", position=(0.0, 0.151, 0.0), damping=0.01,
                             friction=mu, velocity=(v0, 0.0, 0.0)))
    x0 = top.center_of_mass()[0]
    for _ in range(45):
        w.step()
    expected = v0**2 / (2.0 * mu * G)
    assert abs(np.linalg.norm(top.velocities().mean(axis=0))) < 0.02  # stopped
    assert top.center_of_mass()[0] - x0 == pytest.approx(expected, rel=0.15)


def test_pbd_ball_landing_on_a_thin_tetrahedral_fish_does_not_fling_it(device):
    """The showcase's draft (issue 18): a tetrahedral PBD fish (0.3 m, thin tail and fins) lands
    on the ground spinning, and a PBD ball (r = 8 cm) falls onto it at about 3.4 m/s, at 40
    substeps. Contact asked which side of the other body's surface a particle is on by the
    normal of the nearest face, which misjudges points near sharp edges: particles outside were
    projected onto the fin from afar, and the fish reached 111 m/s within a frame (400-1600 m/s
    in the full scene). By the winding number (``kernels/mesh.py`` ``query_inside``) no particle
    moves faster than the impact, and the bodies end apart."""
    from wsim.mesh import shapes

    w = wsim.World(fps=30, gravity=(0.0, -G, 0.0), device=device)
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    rubber = wsim.ElasticMaterial(E=2.0e5, nu=0.3, rho=600.0)
    fish = shapes.fish(length=0.3, subdivisions=2)
    fish.apply_translation(-fish.bounding_box.centroid)
    a = w.add(wsim.PbdBody(fish, rubber, tets="auto", name="fish", position=(-0.33, 0.45, 0.03),
                           angular_velocity=(0.0, 2.0, 1.0), damping=0.01, substeps=40))
    b = w.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=2, radius=0.08), rubber, tets="auto", name="ball",
                           position=(-0.3, 0.8, -0.02), damping=0.01, substeps=40))
    fastest = 0.0
    for _ in range(20):
        w.step()
        fastest = max(fastest, np.abs(a.velocities()).max(), np.abs(b.velocities()).max())
    assert fastest < 5.0
    assert _depth(a, b) < 0.01 and _depth(b, a) < 0.01
    assert b.center_of_mass()[1] > a.center_of_mass()[1]  # the ball on top of the fish or beside it


def test_bodies_rest_on_an_open_terrain_sheet(box_ops):
    """An open mesh collider (a terrain sheet, normals up) is one-sided. Inside/outside by the
    winding number does not hold for it (about 1/2 on either side near the sheet: bodies fell
    through), so an open collider keeps the nearest face's normal (``query_inside``). A PBD ball,
    an EoL ball and a BEM cube dropped on it come to rest on it; the cube lands at 1.7 m/s, fast
    enough to carry its nodes several contact margins past the sheet in one step (a box-shaped
    prefilter of the queried nodes once lost those: they sank 6-18 mm)."""
    g = np.linspace(-1.0, 1.0, 5)
    X, Z = np.meshgrid(g, g, indexing="ij")
    V = np.column_stack([X.ravel(), np.zeros(X.size), Z.ravel()])
    F = []
    for i in range(4):
        for k in range(4):
            a, b, c, d = 5 * i + k, 5 * i + k + 1, 5 * (i + 1) + k, 5 * (i + 1) + k + 1
            F += [[a, b, d], [a, d, c]]  # (b - a) x (d - a) points up (+y)
    sheet = trimesh.Trimesh(V, np.array(F), process=False)
    assert np.all(sheet.face_normals[:, 1] > 0.99)
    w = wsim.World(fps=60, gravity=(0.0, -G, 0.0), device="cpu")
    w.add_collider(wsim.MeshCollider(sheet, name="terrain"))
    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    p = w.add(wsim.PbdBody(ball, PBD_MAT, tets="auto", name="pbd", position=(-0.4, 0.3, 0.0)))
    e = w.add(wsim.EolBody(ball, EOL_MAT, resolution=6, damping=20.0, name="eol", position=(0.4, 0.3, 0.0)))
    c = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="bem", position=(0.0, 0.25, -0.5)))
    lowest = np.inf
    for _ in range(40):
        w.step()
        lowest = min(lowest, c.points()[:, 1].min())
    assert lowest > -1e-3  # no node of the cube more than 1 mm through the sheet at any frame
    for b in (p, e, c):
        assert b.points()[:, 1].min() > -0.02, b.name  # on the sheet, not through it
        assert b.points()[:, 1].mean() > 0.05, b.name  # its centre above the sheet (it may still bounce)


@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs CUDA")
def test_pbd_lockstep_graph_matches_direct_launches():
    """On CUDA the lockstep frame is recorded once and replayed: same motion as launching it every
    frame (to the reordering of float32 atomics on shared triangles)."""
    out = []
    for graph in (True, False):
        w = wsim.World(fps=60, gravity=(0.0, 0.0, 0.0), device="cuda:0")
        a = w.add(wsim.PbdBody(BALL, PBD_MAT, tets="auto", name="a", position=(-0.3, 0.0, 0.0), velocity=(2.0, 0, 0),
                               use_graph=graph))
        b = w.add(wsim.PbdBody(BALL, PBD_MAT, tets="auto", name="b", position=(0.3, 0.05, 0.0), velocity=(-2.0, 0, 0),
                               use_graph=graph))
        for _ in range(24):
            w.step()
        out.append(np.concatenate([a.particles(), b.particles()]))
    assert np.abs(out[0] - out[1]).max() < 1e-3


# -- across methods: PBD against BEM (explicit coupling, wsim.world._couple_surfaces) -----------

SMALL_BALL = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
PBD_DENSE = wsim.ElasticMaterial(E=2.0e5, nu=0.3, rho=1000.0)


def test_pbd_ball_and_bem_cube_collide(box_ops):
    """A PBD ball and a BEM cube thrown at each other in zero gravity, 3 cm off centre. The ball is
    kept out of the cube's surface as it moves over the frame; what that takes is handed to the
    cube over the next frame (``add_vertex_impulses``). They part; the ball's momentum changes by
    exactly minus what the cube was handed (float32 round-off) and the cube's by that to 0.1 %
    (measured 0.016 %; 1.8 % more before the loads' balance, ``correction.load_balance``: the
    error correction handed the systematic drift of the BEM body's response to a point load to its
    frame's acceleration); no particle of the ball goes deeper than 5 mm into the cube. Without
    body contact they pass through each other."""
    def run(contact: bool):
        w = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, 0.0, 0.0), device="cpu", body_contact=contact)
        cube = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="cube", position=(0.2, 0.03, 0.0),
                                  velocity=(-1.0, 0.0, 0.0)))
        ball = w.add(wsim.PbdBody(SMALL_BALL, PBD_DENSE, tets="auto", name="ball", position=(-0.15, 0.0, 0.0),
                                  velocity=(1.0, 0.0, 0.0)))
        pc, pb = cube.linear_momentum(), ball.linear_momentum()
        depth = 0.0
        for _ in range(30):
            w.step()
            depth = max(depth, _depth(cube, ball))
        return cube, ball, pc, pb, depth

    cube, ball, pc, pb, depth = run(True)
    J = cube.coupling_impulse
    assert np.linalg.norm(J) > 5.0
    np.testing.assert_allclose(ball.linear_momentum() - pb, -J, atol=1e-4 * np.linalg.norm(J))
    assert np.linalg.norm(cube.linear_momentum() - pc - J) < 1e-3 * np.linalg.norm(J)
    assert ball.linear_momentum()[0] < 0.0 and cube.linear_momentum()[0] > 0.0  # both rebound
    assert depth < 0.005
    cube, ball, *_ = run(False)
    assert ball.center_of_mass()[0] > cube.points().mean(axis=0)[0]


@pytest.mark.parametrize("other", ["pbd", "eol"])
def test_glancing_blow_on_a_bem_cube_keeps_angular_momentum(box_ops, other):
    """A ball (PBD, or EoL at 5 cells) and a BEM cube thrown at each other 6-7 cm off centre in zero
    gravity: the pair's angular momentum about the origin is kept to 1 % (measured 0.05 % and
    0.17 %). The cube's frame takes the push's moment at the vertices (``BemBody._push_torque``);
    as tractions on the vertices' hat functions it acted at the hats' centroids: 16 % and 9.4 %."""
    w = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, 0.0, 0.0), device="cpu")
    cube = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="cube", position=(0.2, 0.06 if other == "pbd" else 0.07, 0.0),
                              velocity=(-1.0, 0.0, 0.0)))
    if other == "pbd":
        ball = w.add(wsim.PbdBody(SMALL_BALL, PBD_DENSE, tets="auto", name="ball", position=(-0.15, 0.0, 0.0),
                                  velocity=(1.0, 0.0, 0.0)))
    else:
        ball = w.add(wsim.EolBody(SMALL_BALL, wsim.ElasticMaterial(E=1e5, nu=0.3, rho=500.0), resolution=5,
                                  name="ball", position=(-0.12, 0.0, 0.0), velocity=(1.0, 0.0, 0.0), damping=50.0))

    def L() -> np.ndarray:
        return cube.angular_momentum(about=(0, 0, 0)) + ball.angular_momentum(about=(0, 0, 0))

    L0 = L()
    for _ in range(30 if other == "pbd" else 25):
        w.step()
    assert np.linalg.norm(cube.coupling_impulse) > 1.0  # they met
    assert np.linalg.norm(L() - L0) < 0.01 * np.linalg.norm(L0)


def test_pbd_ball_rests_on_a_bem_cube_on_the_ground(box_ops):
    """A PBD ball dropped 4 cm onto a BEM cube resting on the ground comes to rest on it, and the
    cube carries its weight: what the ball hands the cube is m g t to 1 % after 1 s."""
    w = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, -G, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    cube = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="cube", position=(0.0, 0.1005, 0.0)))
    ball = w.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=2, radius=0.06), PBD_DENSE, tets="auto",
                              name="ball", position=(0.01, 0.3, 0.0), damping=0.01))
    for _ in range(100):
        w.step()
    assert ball.center_of_mass()[1] > 0.24 and _depth(cube, ball) < 0.002
    assert np.abs(ball.velocities()).max() < 0.1
    weight = float(ball.masses.sum()) * G * w.time
    assert cube.coupling_impulse[1] == pytest.approx(-weight, rel=0.01)


@pytest.mark.parametrize("rho_cube, rho_box, subdivisions", [(500.0, 3000.0, 3), (1000.0, 1000.0, 2)],
                         ids=["24kg_on_4kg", "8kg_coarse_on_8kg"])
def test_pbd_box_rests_on_a_bem_cube_as_heavy_or_heavier(box_ops, rho_cube, rho_box, subdivisions):
    """A PBD box (0.2 m, E = 1e6) set 3 cm off centre on the 26-node BEM cube resting on the
    ground stays on it and rings down, with the World's default coupling: over the second and
    third seconds its centroid moves less than 5 mm relative to the cube, its mean speed over the
    third second is under 20 mm/s and under 0.8 of the second's, and the pair's kinetic plus
    gravitational energy peaks lower in the third second than in the second (nothing drives it).
    The cube's mass, coarse (98 vertices; the push handed over one interval late): 0.1 mm, 1.2
    mm/s in the second second. Six times the cube's mass (386 vertices; the push found
    implicitly, ``World(coupling="auto")``): 2.2 mm, 23.5 then 17.3 mm/s (0.74), the energy's
    peaks 0.146 then 0.127 J above its value at 0.5 s. Handed over one interval late it rang down
    faster (13.3 then 5.9 mm/s), the lag's numerical damping, which pumps energy into other heavy
    boxes instead (``test_heavy_coarse_pbd_box_on_a_light_bem_cube_gains_no_energy``).
    With the cube kinematic within each interval the heavy box rocked off it (41 mm, 0.29 m/s)
    and the coarse one shook (9.9 mm, 73 mm/s): its particles share each correction with the
    cube's give (``kernels.pbd_contact.moving_surface_contact``)."""
    mat = wsim.ElasticMaterial(E=MAT.E, nu=MAT.nu, rho=rho_cube)
    ops = box_ops if rho_cube == MAT.rho else build_operators(BOX, mat, DT, cache=False, device="cpu")
    w = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, -G, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    cube = w.add(wsim.BemBody(BOX, mat, DT, operators=ops, name="cube", position=(0.0, 0.1005, 0.0)))
    mesh = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    for _ in range(subdivisions):
        mesh = mesh.subdivide()
    box = w.add(wsim.PbdBody(mesh, wsim.ElasticMaterial(E=1e6, nu=0.3, rho=rho_box), tets="auto", name="box",
                             position=(0.03, 0.3015, 0.0)))
    m = float(box.masses.sum())
    assert m / cube.mass == pytest.approx(rho_box / rho_cube)
    rel, speeds, energies = [], [], []
    for _ in range(300):
        w.step()
        rel.append(box.center_of_mass() - cube.center_of_mass())
        speeds.append(np.linalg.norm(box.linear_momentum()) / m)
        energies.append(box.kinetic_energy() + cube.kinetic_energy()
                        + G * (m * box.center_of_mass()[1] + cube.mass * cube.center_of_mass()[1]))
    moved = np.linalg.norm(np.asarray(rel[100:]) - rel[99], axis=1).max()
    second, third = np.mean(speeds[100:200]), np.mean(speeds[200:])
    assert moved < 5e-3 and third < 0.02 and third < 0.8 * second, (moved, second, third)
    assert max(energies[200:]) < max(energies[100:200]), (max(energies[100:200]) - energies[49],
                                                          max(energies[200:]) - energies[49])


def test_heavy_coarse_pbd_box_on_a_light_bem_cube_gains_no_energy(box_ops):
    """A 24 kg PBD box of 98 vertices set 3 cm off centre on a 4 kg BEM cube on the ground, with
    the World's default coupling (the push found implicitly: the box is over twice the cube's
    mass, ``wsim.world.IMPLICIT_MASS_RATIO``): nothing drives the pair, so their kinetic plus
    gravitational energy must not rise after the landing. Over the second second it stays within
    0.2 J of its value at 0.5 s (measured +0.08 J) and the box stays on the cube (its centre
    within 5 mm; measured 3.5 mm). Found implicitly with the BEM surface yielding elastically as
    a column of its vertex's patch (the plane-wave give over the interval), the surface's yield
    did net work on the rocking box and the pair gained 2.1 J; the push engages the half-sphere
    its P wave reaches where that is more (``kernels.pbd_contact.elastic_give``,
    ``wsim.world._wave_speed``). Handed over one interval late (``coupling="explicit"``) the pair
    gains 0.45 J by 2 s, its kinetic energy growing."""
    mat = wsim.ElasticMaterial(E=MAT.E, nu=MAT.nu, rho=500.0)
    w = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, -G, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    cube = w.add(wsim.BemBody(BOX, mat, DT, operators=build_operators(BOX, mat, DT, cache=False, device="cpu"),
                              name="cube", position=(0.0, 0.1005, 0.0)))
    box = w.add(wsim.PbdBody(trimesh.creation.box(extents=(0.2, 0.2, 0.2)).subdivide().subdivide(),
                             wsim.ElasticMaterial(E=1e6, nu=0.3, rho=3000.0), tets="auto", name="box",
                             position=(0.03, 0.3015, 0.0)))
    m = float(box.masses.sum())

    def energy() -> float:
        return (box.kinetic_energy() + cube.kinetic_energy()
                + G * (m * box.center_of_mass()[1] + cube.mass * cube.center_of_mass()[1]))

    energies, rel = [], []
    for _ in range(200):
        w.step()
        energies.append(energy())
        rel.append(box.center_of_mass() - cube.center_of_mass())
    rise = max(energies[100:]) - energies[49]
    assert rise < 0.2, f"energy rose {rise:.3f} J"
    assert np.linalg.norm(np.asarray(rel[100:]) - rel[49], axis=1).max() < 5e-3


@pytest.mark.parametrize("subdivisions, kept_out", [(2, True), (2, False), (0, True)],
                         ids=["98_vertices", "98_vertices_particles_only", "8_vertices"])
def test_bem_cube_rests_on_a_coarse_pbd_box(box_ops, monkeypatch, subdivisions, kept_out):
    """A BEM cube set on a coarse PBD box resting on the ground (98 surface vertices, or a plain
    8-vertex box whose top is two triangles): the PBD body also keeps the cube's vertices out of
    its own surface (``moving_points_contact``, the correction shared by the vertex's lumped mass
    and the triangle's particles), so no corner sinks between its particles (the deepest stays
    under 0.5 mm over 0.5 s) and the cube rests on top without being thrown (its centre within
    5 mm of where it started; after the landing its frame's speed averages under 0.05 m/s and
    peaks under 0.2 m/s: measured 0.024 / 0.049 m/s on the 98-vertex box; on the 8-particle box
    it rattles, 0.040 / 0.116 m/s, and peaks of 0.086-0.13 m/s over 0.5-2 s with and without the
    push's torque fix, 0.097-0.115 m/s before the loads' balance).
    With only the PBD particles kept out
    of the cube (``vertices_kept_out`` off) its corners sink in: the test tells the two apart.
    Measured: the 8-vertex box threw the cube at 2.3 m/s when the vertex was taken as immovable."""
    monkeypatch.setattr(wsim.BemBody, "vertices_kept_out", kept_out)
    w = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, -G, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    box = trimesh.creation.box(extents=(0.4, 0.12, 0.4))
    for _ in range(subdivisions):
        box = box.subdivide()
    low = w.add(wsim.PbdBody(box, wsim.ElasticMaterial(E=4e5, nu=0.3, rho=600.0), tets="auto", name="low",
                             position=(0.0, 0.0605, 0.0), damping=0.01))
    cube = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="cube", position=(0.03, 0.2215, 0.0)))
    assert len(low.points()) == (98 if subdivisions else 8)
    c0 = cube.points().mean(axis=0)
    deepest, speeds = 0.0, []
    for k in range(50):
        w.step()
        deepest = max(deepest, _depth(low, cube))
        if k >= 25:  # after the landing (the cube starts 1 mm above the box)
            speeds.append(float(np.linalg.norm(cube.linear_momentum())) / cube.mass)
    if kept_out:
        assert deepest < 5e-4
        assert np.linalg.norm(cube.points().mean(axis=0) - c0) < 5e-3
        assert np.mean(speeds) < 0.05 and max(speeds) < 0.2
    else:
        assert deepest > 1e-3


@pytest.mark.parametrize("rho, kept_out, pusher", [(800.0, True, None), (5000.0, True, None), (5000.0, True, "pbd"),
                                                    (5000.0, False, "pbd")],
                         ids=["eol_pushes", "heavy_eol_pushes", "pbd_pushes_kept_out", "pbd_pushes_particles_only"])
def test_eol_cube_rests_on_a_coarse_pbd_box(monkeypatch, rho, kept_out, pusher):
    """An EoL cube (5 cells) set on the 98-vertex PBD box (6.5 kg) resting on the ground. The cube
    pushes the box (``wsim.world._eol_pushes_pbd``: no PBD body lighter than an EoL body rests on
    it), its rows taking the box's give and the box's vertices inside it
    (``kernels.eol_contact.vertex_rows``). A 1.4 kg cube: no cube vertex goes 1.5 mm into the box
    over 0.5 s (measured 0.32 mm) and it stays on top (centroid within 5 mm: 2.6). An 8.6 kg cube,
    the heavier, over 1 s: 1.6 mm deep (0.07 of its 2.4 cm cells) as the soft box gives under it
    (centroid 5.6 mm down), then at rest (mean speed over the second half second 1.7 mm/s) with
    its energy flat (the kinetic, gravitational and elastic energy of the two within 0.003 J of
    what they were half a second in). Pushed by the box, as it was when the lighter body pushed
    (``pusher="pbd"``), it shook at 9-16 mm/s and the pair's energy rose 0.3 J, and a 23 kg EoL
    cube on a 7.6 kg box gained 4 J a second and walked off (an independent check). The box's
    push keeps the cube's vertices out of its surface, shared by mass as for a BEM body: 1.37 mm
    deep, centroid within 10 mm (6.0); with only the particles kept out its edges sink between
    them (45.6 mm)."""
    monkeypatch.setattr(wsim.EolBody, "vertices_kept_out", kept_out)
    if pusher == "pbd":
        monkeypatch.setattr(wsim.world, "_eol_pushes_pbd", lambda *args, **kwargs: False)
    w = wsim.World(fps=60, gravity=(0.0, -G, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    box = trimesh.creation.box(extents=(0.3, 0.12, 0.3)).subdivide().subdivide()
    low = w.add(wsim.PbdBody(box, wsim.ElasticMaterial(E=4e5, nu=0.3, rho=600.0), tets="auto", name="low",
                             position=(0.0, 0.0605, 0.0), damping=0.01))
    cube = trimesh.creation.box(extents=(0.12, 0.12, 0.12)).subdivide().subdivide()
    top = w.add(wsim.EolBody(cube, wsim.ElasticMaterial(E=2e5, nu=0.3, rho=rho), resolution=5, name="top",
                             position=(0.03, 0.1815, 0.0), damping=50.0))
    heavy = rho > 1000.0 and pusher is None
    c0 = top.points().mean(axis=0)
    m = top.node_masses().sum()

    def energy() -> float:
        return (low.kinetic_energy() + G * low.mass * low.center_of_mass()[1] + top.kinetic_energy()
                + G * m * top.center_of_mass()[1] + top.elastic_energy)

    deepest, energies, speeds = 0.0, [], []
    for f in range(60 if heavy else 30):
        w.step()
        deepest = max(deepest, _depth(low, top))
        energies.append(energy())
        speeds.append(float(np.linalg.norm(top.linear_momentum())) / m)
    moved = np.linalg.norm(top.points().mean(axis=0) - c0)
    assert set(w._eol_pushes.values()) == {pusher is None}
    if heavy:
        assert deepest < 2.5e-3 and moved < 1e-2
        assert np.mean(speeds[30:]) < 5e-3
        assert max(energies[30:]) - energies[29] < 0.05
    elif kept_out:
        assert deepest < 1.5e-3 and moved < (5e-3 if rho < 1000.0 else 1e-2)
    else:
        assert deepest > 3e-3


def test_eol_bodies_push_pbd_bodies_unless_a_light_pbd_body_rests_on_one():
    """``wsim.world._eol_pushes_pbd`` (asked before each interval per group of EoL bodies that may
    touch): a light PBD ball resting on a heavy EoL block makes the PBD bodies push, a heavy EoL
    ball resting on a light PBD box the EoL bodies; asked for both at once the EoL bodies push
    (the heavy EoL ball bounced on the box at 363 mm/s when the ball on the block let the PBD
    bodies push, an independent check), but the World asks each pair apart (below); without
    gravity the EoL bodies push (``test_heavy_eol_cube_and_light_pbd_cube_collide_without_gaining_energy``). A PBD ball less than
    ``PBD_PUSHER_MASS_RATIO`` (5) times lighter than the block it rests on leaves the push to the
    block: 0.2 m PBD cubes of 8, 4 and 2.6 kg on an 8 kg EoL box moved at 43-88, 27-74 and
    20-37 mm/s pushing it (energy rising), 0.2-3.2 mm/s pushed (``_eol_pushes_pbd``'s table); the
    strict "lighter" rule before switched the pusher between intervals for the 8 kg pair."""
    from wsim.world import PBD_PUSHER_MASS_RATIO, _eol_pushes_pbd

    soft = wsim.ElasticMaterial(E=2e5, nu=0.3, rho=1000.0)

    def scene(pair_a: bool, pair_b: bool, gravity: float = G, ball_rho: float = 1000.0) -> wsim.World:
        w = wsim.World(fps=60, gravity=(0.0, -gravity, 0.0), device="cpu")
        w.add_collider(wsim.GroundPlane(0.0))
        if pair_a:  # a 0.8 kg PBD ball (at ball_rho 1000) on a 13.5 kg EoL block
            w.add(wsim.EolBody(trimesh.creation.box(extents=(0.3, 0.15, 0.3)).subdivide(), soft, resolution=5,
                               name="block", position=(0.0, 0.0755, 0.0)))
            w.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1, radius=0.06),
                               wsim.ElasticMaterial(E=2e5, nu=0.3, rho=ball_rho), tets="auto", name="ball",
                               position=(0.02, 0.2105, 0.0)))  # touching
        if pair_b:  # a 7.3 kg EoL ball on a 1.2 kg PBD box
            w.add(wsim.PbdBody(trimesh.creation.box(extents=(0.2, 0.1, 0.2)), wsim.ElasticMaterial(E=2e5, nu=0.3, rho=300.0),
                               tets="auto", name="box", position=(1.0, 0.0505, 0.0)))
            w.add(wsim.EolBody(trimesh.creation.icosphere(subdivisions=1, radius=0.1), wsim.ElasticMaterial(
                E=2e5, nu=0.3, rho=2000.0), resolution=5, name="eball", position=(1.0, 0.2005, 0.0)))
        w._bind()
        return w

    for a, b, gravity, pushes in ((True, False, G, False), (False, True, G, True), (True, True, G, True),
                                  (True, False, 0.0, True)):
        w = scene(a, b, gravity)
        assert _eol_pushes_pbd(w._pbd, w._eol, w.gravity, 1.0 / 240.0) is pushes, (a, b, gravity)
    for rho, pushes in ((5000.0, True), (2000.0, False)):  # a ball 3.3x and 8x lighter than the block
        w = scene(True, False, ball_rho=rho)
        ratio = w._eol[0].mass / float(w._pbd[0].masses.sum())
        assert (ratio < PBD_PUSHER_MASS_RATIO) is pushes, ratio
        assert _eol_pushes_pbd(w._pbd, w._eol, w.gravity, 1.0 / 240.0) is pushes, rho

    # the World asks per group of EoL bodies that may touch: with both pairs in one World the ball
    # pushes the block and the EoL ball the box, and the ball on the block moves as it does with
    # the other pair absent (one answer for the World made the block push the ball: in this scene
    # with the EoL bodies' damping 20, its mean speed over the second half second was 260 mm/s,
    # 658 at most, against 147 and 200 alone; this soft undamped tet ball jiggles on the rigid
    # ground too, 105 mm/s)
    both, alone = scene(True, True), scene(True, False)
    for _ in range(12):
        both.step()
        alone.step()
    assert {b.name: both._eol_pushes[id(b)] for b in both._eol} == {"block": False, "eball": True}
    np.testing.assert_allclose(both.bodies[1].points(), alone.bodies[1].points(), rtol=0, atol=1e-9)


def test_light_pbd_box_between_a_heavy_eol_block_and_ball_does_not_blow_up():
    """A 1.2 kg PBD box (6 cm thick) resting on a 19 kg EoL block, a 3.5 kg EoL ball resting on
    the box (E = 2e5 Pa, 100 fps; an independent check's scene). The block and the ball meet only
    through the cell the groups of EoL bodies are grown by, and want different pushers: the box
    pushes the block (it rests on one 16x heavier) and the ball the box (a heavy EoL body on a
    lighter PBD body). One group pushed the box from both sides, one interval late, and the stack
    blew up at 0.76 s (+99 J, the box at 5.2 m/s); split (``World._update_roles``) the kinetic and
    gravitational energy never rises above its start and the box stays slow (measured 83 mm/s at
    most over the last half of a second, 48 over the second)."""
    w = wsim.World(fps=100, gravity=(0.0, -G, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    soft = dict(E=2e5, nu=0.3)
    block = w.add(wsim.EolBody(trimesh.creation.box(extents=(0.4, 0.12, 0.4)).subdivide(), dict(soft, rho=1200.0),
                               resolution=8, damping=30.0, name="block", position=(0.0, 0.0605, 0.0)))
    box = w.add(wsim.PbdBody(trimesh.creation.box(extents=(0.2, 0.06, 0.2)).subdivide().subdivide(),
                             dict(soft, rho=500.0), tets="auto", name="box", position=(0.0, 0.151, 0.0)))
    ico = trimesh.creation.icosphere(subdivisions=2, radius=0.07)
    ball = w.add(wsim.EolBody(ico, dict(soft, rho=2500.0), resolution=6, damping=30.0, name="ball",
                              position=(0.01, 0.1815 - ico.vertices[:, 1].min(), 0.0)))
    bodies = (block, box, ball)

    def energy() -> float:
        return sum(b.kinetic_energy() + G * (b.node_masses().sum() if b is not box else b.mass) * b.center_of_mass()[1]
                   for b in bodies)

    e0, rise, fastest = energy(), [], 0.0
    for _ in range(85):
        w.step()
        rise.append(energy() - e0)
        fastest = max(fastest, float(np.linalg.norm(box.linear_momentum())) / box.mass)
    assert {b.name: w._eol_pushes[id(b)] for b in (block, ball)} == {"block": False, "ball": True}
    assert max(rise) < 0.0
    assert fastest < 0.3


def test_light_eol_box_rests_on_a_heavy_pbd_slab():
    """A 1 kg EoL box (8 cells, damping 20) set 1 mm above a 32 kg PBD slab on the ground. The EoL
    body rests on the slab, so its QP pushes the slab with the slab's give (``wsim.world._eol_pushes_pbd``)
    and the slab's vertices inside the box enter its rows: the box lands and rests (mean speed
    over the last 0.2 s under 5 mm/s, measured 0.72; its bottom within 2 mm of the slab's top,
    measured 0.6 mm into the sagging slab). Pushed by the slab's particles, which took its
    surface as immovable, it bounced up to 14 mm off the slab (an independent check)."""
    w = wsim.World(fps=100, gravity=(0.0, -G, 0.0), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.9))
    slab = trimesh.creation.box(extents=(0.8, 0.1, 0.4)).subdivide().subdivide().subdivide()
    w.add(wsim.PbdBody(slab, wsim.ElasticMaterial(E=1e7, nu=0.3, rho=1000.0), tets="auto", name="slab",
                       position=(0.2, 0.0505, 0.0), friction=0.4))
    cube = trimesh.creation.box(extents=(0.1, 0.1, 0.1)).subdivide().subdivide()
    box = w.add(wsim.EolBody(cube, wsim.ElasticMaterial(E=1e6, nu=0.3, rho=1000.0), resolution=8, name="box",
                             position=(-0.05, 0.1515, 0.0), damping=20.0, friction=0.4))
    speeds = []
    for f in range(50):
        w.step()
        if f >= 30:
            speeds.append(np.linalg.norm(box.linear_momentum()) / box.node_masses().sum())
    assert np.mean(speeds) < 5e-3
    assert abs(box.points()[:, 1].min() - 0.1005) < 2e-3


def test_open_or_bare_pbd_bodies_do_not_keep_bem_vertices_out(box_ops):
    """Only a closed PBD surface keeps a BEM body's vertices out: an open sheet (a dome, whose
    winding number exceeds 1/2 in its concavity) over a BEM cube, nothing touching, leaves both at
    rest; bare particles (no faces) thrown onto the cube stop on it (a Warp mesh of no faces with
    winding numbers crashed the process)."""
    from wsim import mesh as wm

    s = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    keep = (s.vertices[s.faces][:, :, 1] > -1e-9).all(axis=1)
    dome = trimesh.Trimesh(s.vertices, s.faces[keep], process=False)
    dome.remove_unreferenced_vertices()
    assert wm.has_boundary(np.asarray(dome.faces))
    w = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, 0.0, 0.0), device="cpu")
    d = w.add(wsim.PbdBody(dome, name="dome", mass=1.0, volume=False, damping=0.01))
    cube = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="cube"))
    for _ in range(10):
        w.step()
    assert d.points()[:, 1].max() == pytest.approx(0.3, abs=1e-6) and np.abs(cube.linear_momentum()).max() < 1e-9
    pts = np.array([[0.0, 0.15, 0.0], [0.05, 0.15, 0.0], [0.0, 0.15, 0.05]])
    w = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, 0.0, 0.0), device="cpu")
    dust = w.add(wsim.PbdBody((pts, np.zeros((0, 3), dtype=np.int32)), name="dust", mass=0.01,
                              velocity=(0.0, -1.0, 0.0)))
    w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="cube"))
    for _ in range(20):
        w.step()
    assert dust._own_surface is None and dust.particles()[:, 1].min() > 0.099


def test_pbd_ball_and_eol_box_collide(monkeypatch):
    """A PBD ball and an EoL box thrown at each other in zero gravity, the ball pushing (as a light
    PBD body resting on a heavy EoL body does under gravity; without gravity the World lets the
    EoL bodies push, here overridden): the same explicit coupling as against a BEM body (the EoL
    body takes the impulses as tractions, ``add_vertex_impulses``). The ball's momentum changes by
    exactly minus what the box is handed; the box's by that to 0.5 % (measured 0.09 %: EoL
    advection is not exactly conservative); the ball rebounds and no particle goes 5 mm into the
    box."""
    monkeypatch.setattr(wsim.world, "_eol_pushes_pbd", lambda *args, **kwargs: False)
    w = wsim.World(fps=60, gravity=(0.0, 0.0, 0.0), device="cpu")
    box = trimesh.creation.box(extents=(0.3, 0.3, 0.3)).subdivide().subdivide()
    eol = w.add(wsim.EolBody(box, wsim.ElasticMaterial(E=1e5, nu=0.3, rho=500.0), resolution=6, name="box",
                             position=(0.25, 0.03, 0.0), velocity=(-1.0, 0.0, 0.0), damping=50.0))
    ball = w.add(wsim.PbdBody(SMALL_BALL, PBD_DENSE, tets="auto", name="ball", position=(-0.2, 0.0, 0.0),
                              velocity=(1.0, 0.0, 0.0)))
    pe, pb = eol.linear_momentum(), ball.linear_momentum()
    depth = 0.0
    for _ in range(30):
        w.step()
        depth = max(depth, _depth(eol, ball))
    J = eol.coupling_impulse
    assert J[0] > 5.0
    np.testing.assert_allclose(ball.linear_momentum() - pb, -J, atol=1e-5 * np.linalg.norm(J))
    np.testing.assert_allclose(eol.load_impulse, J, rtol=1e-9, atol=1e-12)
    assert np.linalg.norm(eol.linear_momentum() - pe - J) < 0.005 * np.linalg.norm(J)
    assert ball.linear_momentum()[0] < 0.0
    assert depth < 0.005


def test_eol_striker_hitting_a_pbd_box_that_carries_an_eol_cube_gains_no_energy():
    """A 3.6 kg EoL block slides at 1 m/s into the side of a 1.2 kg PBD box that carries a resting
    0.9 kg EoL cube, on frictionless ground, one coupling interval a frame (10 PBD substeps; an
    independent check's case). The box takes each push at once at the next interval's start: the
    three bodies' kinetic and gravitational energy never rises above its value before the blow
    (measured -0.0007 J). Taking a push that continued the last one (the resting cube's) over the
    interval's substeps, the blow's push reached the box too slowly, the block pushed again, and
    the energy rose 0.34 J (19 % of the block's) and stayed up."""
    w = wsim.World(fps=100, gravity=(0.0, -G, 0.0), device="cpu", coupling_dt=0.01)
    w.add_collider(wsim.GroundPlane(0.0, friction=0.0))
    soft = dict(E=5e5, nu=0.3)
    box = w.add(wsim.PbdBody(trimesh.creation.box(extents=(0.2, 0.1, 0.2)).subdivide().subdivide(), dict(soft, rho=300.0),
                             tets="auto", name="box", position=(0.0, 0.0505, 0.0), friction=0.0))

    def eol(ext, rho, pos, vel, name, mu):
        return w.add(wsim.EolBody(trimesh.creation.box(extents=ext).subdivide(), dict(soft, rho=rho), resolution=6,
                                  damping=30.0, name=name, friction=mu, position=pos, velocity=vel))

    cube = eol((0.1, 0.1, 0.1), 900.0, (0.0, 0.1515, 0.0), (0.0, 0.0, 0.0), "cube", 0.5)
    block = eol((0.12, 0.08, 0.12), 3.6 / (0.12 * 0.08 * 0.12), (-0.25, 0.0405, 0.0), (1.0, 0.0, 0.0), "block", 0.0)
    bodies = (box, cube, block)

    def energy() -> float:
        return sum(b.kinetic_energy() + G * (b.mass if b is box else float(b.node_masses().sum())) * b.center_of_mass()[1]
                   for b in bodies)

    energies, speeds = [], []
    for _ in range(30):
        w.step()
        energies.append(energy())
        speeds.append(block.linear_momentum()[0] / float(block.node_masses().sum()))
    hit = int(np.argmax(np.abs(np.diff(speeds)) > 0.02))  # the first frame the block slows
    assert 0 < hit < 20
    assert max(energies[hit + 1:]) <= energies[hit] + 0.01
    assert box.linear_momentum()[0] > 0.0  # it was hit


@pytest.mark.parametrize("coupling_dt", [None, 0.01], ids=["automatic", "frame"])
def test_heavy_eol_cube_and_light_pbd_cube_collide_without_gaining_energy(coupling_dt):
    """An 8 kg EoL cube (8 cells) and a 3.4 kg PBD cube thrown at each other at 0.5 m/s each in
    zero gravity (100 fps; an independent check's case): the EoL cube pushes
    (``wsim.world._eol_pushes_pbd``), the pair's momentum is kept to 1e-6 of either's, no frame
    has more kinetic energy than the start, and they part slower than they met (restitution
    measured 0.50). With the PBD cube pushing, as the rule before let the lighter do, they parted
    at 1.58 times their closing speed with 130 % more kinetic energy, the EoL cube's nodes at
    48 m/s within the frame of the blow. ``frame``: one coupling interval a frame, 10 PBD
    substeps; the PBD cube takes each push at once at the next interval's start
    (``PbdBody.add_vertex_impulses``: spread over the interval's substeps, the blow's push reached
    it too slowly, the EoL cube pushed again, and the pair parted faster than they met)."""
    v = 0.5
    w = wsim.World(fps=100, gravity=(0.0, 0.0, 0.0), device="cpu", coupling_dt=coupling_dt)
    mat = wsim.ElasticMaterial(E=1e6, nu=0.3, rho=1000.0)
    eol = w.add(wsim.EolBody(trimesh.creation.box(extents=(0.2, 0.2, 0.2)).subdivide(), mat, resolution=8, damping=20.0,
                             name="eol", position=(-0.16, 0.0, 0.0), velocity=(v, 0.0, 0.0)))
    pbd = w.add(wsim.PbdBody(trimesh.creation.box(extents=(0.15, 0.15, 0.15)).subdivide().subdivide(), mat,
                             tets="auto", name="pbd", position=(0.19, 0.0, 0.0), velocity=(-v, 0.0, 0.0)))
    p0 = eol.linear_momentum() + pbd.linear_momentum()
    k0 = eol.kinetic_energy() + pbd.kinetic_energy()
    energies = []
    for _ in range(40):
        w.step()
        energies.append(eol.kinetic_energy() + pbd.kinetic_energy())
    assert all(w._eol_pushes.values())
    assert np.linalg.norm(eol.linear_momentum() + pbd.linear_momentum() - p0) < 1e-6 * eol.mass * v
    assert max(energies) <= k0 * (1.0 + 1e-6)
    u_eol = eol.linear_momentum()[0] / eol.node_masses().sum()
    u_pbd = pbd.linear_momentum()[0] / pbd.masses.sum()
    assert 0.0 < u_pbd - u_eol < 2.0 * v


def test_coupling_interval_is_chosen_and_checked(box_ops):
    """``World(coupling_dt=None)`` couples PBD and BEM bodies at the shortest interval that holds a
    whole number of BEM steps and at least one PBD substep (here 5 BEM steps a frame, 10 PBD
    substeps: 5 intervals); a PBD-only World keeps the frame. An interval that does not divide the
    frame, or that a BEM body's dt does not divide, is refused by name, as is an unknown
    ``coupling`` or a tolerance or pass count out of range."""
    def world(**kw):
        w = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, 0.0, 0.0), device="cpu", **kw)
        w.add(wsim.PbdBody(SMALL_BALL, PBD_DENSE, tets="auto", name="ball", position=(-0.15, 0.0, 0.0)))
        return w

    w = world()
    w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="cube", position=(0.2, 0.0, 0.0)))
    w.step()
    assert w.coupling_steps == 5
    w = world()
    w.step()
    assert w.coupling_steps == 1
    with pytest.raises(wsim.InvalidParameter, match="coupling_dt"):
        world(coupling_dt=3 * DT)
    w = world(coupling_dt=2.5 * DT)  # divides the frame (2 intervals), not the cube's dt
    w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="cube", position=(0.2, 0.0, 0.0)))
    with pytest.raises(wsim.InvalidParameter, match="body 'cube'.*coupling interval"):
        w.step()
    for kw, what in [(dict(coupling="lagged"), "coupling = 'lagged'"), (dict(coupling_tol=0.0), "coupling_tol"),
                     (dict(coupling_tol=float("nan")), "coupling_tol"), (dict(coupling_iterations=0), "coupling_iterations")]:
        with pytest.raises(wsim.InvalidParameter, match=what):
            world(**kw)


@pytest.mark.parametrize("pusher", ["pbd", "eol"])
@pytest.mark.parametrize("coupling", ["auto", "implicit"])
def test_checkpoint_in_mid_contact_keeps_the_pending_push(box_ops, tmp_path, pusher, coupling):
    """A World saved while a ball (PBD, or EoL at 5 cells) is pushing the BEM cube (a push still
    to deliver over the next interval) and restored into a fresh World continues bit for bit on
    the CPU; with the implicit coupling too (its first guess is the ball's last push, kept in its
    state, and what the guess missed is pending on the cube). The EoL ball did not until its
    partners' yield was taken where they are at the step (``EolBody._place_moving``): it read
    them where the last step had left them, which a restored body does not know (3e-7 m apart
    after a frame)."""
    def world():
        w = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, 0.0, 0.0), device="cpu", coupling=coupling)
        w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="cube", position=(0.2, 0.03, 0.0),
                           velocity=(-1.0, 0.0, 0.0)))
        if pusher == "pbd":
            w.add(wsim.PbdBody(SMALL_BALL, PBD_DENSE, tets="auto", name="ball", position=(-0.15, 0.0, 0.0),
                               velocity=(1.0, 0.0, 0.0)))
        else:
            w.add(wsim.EolBody(SMALL_BALL, EOL_MAT, resolution=5, name="ball", position=(-0.12, 0.0, 0.0),
                               velocity=(1.0, 0.0, 0.0), damping=50.0))
        return w

    straight = _resumes_bit_for_bit(world, 9, 0, tmp_path)  # the bodies touch from frame 8 (PBD), 6 (EoL) on
    assert (straight.coupling_stats["implicit_intervals"] > 0) == (coupling == "implicit")


def test_implicit_coupling_of_bem_bodies_of_different_meshes(box_ops):
    """Two BEM cubes of different meshes (26 and 8 vertices), each hit by a PBD ball, with the
    push found implicitly: each ball's momentum changes by exactly minus what its cube is handed
    (float32 round-off), the guesses being one per (pusher, cube) pair of that cube's vertices."""
    small = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    w = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, 0.0, 0.0), device="cpu", coupling="implicit")
    cubes = [w.add(wsim.BemBody(mesh, MAT, DT, operators=ops, name=f"cube{i}", position=(0.2, 0.03, 2.0 * i),
                                velocity=(-1.0, 0.0, 0.0)))
             for i, (mesh, ops) in enumerate([(BOX, box_ops), (small, build_operators(small, MAT, DT, cache=False,
                                                                                       device="cpu"))])]
    balls = [w.add(wsim.PbdBody(SMALL_BALL, PBD_DENSE, tets="auto", name=f"ball{i}", position=(-0.15, 0.0, 2.0 * i),
                                velocity=(1.0, 0.0, 0.0))) for i in range(2)]
    p0 = [b.linear_momentum() for b in balls]
    for _ in range(20):
        w.step()
    assert w.coupling_stats["implicit_intervals"] > 0
    for cube, ball, p in zip(cubes, balls, p0):
        J = cube.coupling_impulse
        assert np.linalg.norm(J) > 5.0
        np.testing.assert_allclose(ball.linear_momentum() - p, -J, atol=1e-4 * np.linalg.norm(J))


def _resumes_bit_for_bit(world, n: int, pushed: int | None, tmp_path):
    """``world()`` stepped 2n frames straight equals one saved after n frames (body ``pushed``
    holding a push still to deliver; None: bodies holding active contact rows between them) and
    restored into a fresh ``world()``, bit for bit. Returns the straight World."""
    straight = world()
    for _ in range(2 * n):
        straight.step()
    first = world()
    for _ in range(n):
        first.step()
    if pushed is None:
        from wsim.eol.pairs import PAIR_ID

        assert any(np.any(b.state.active_rows >= PAIR_ID) for b in first.bodies)
    else:
        body = first.bodies[pushed]
        assert body.state.coupling_until > first.time and np.abs(body.state.coupling_force).max() > 0.0
    path = first.checkpoint(tmp_path / "mid.h5")
    resumed = world()
    resumed.restore(path)
    for _ in range(n):
        resumed.step()
    for a, b in zip(straight.bodies, resumed.bodies):
        assert np.array_equal(a.points(), b.points()), a.name
    if pushed is not None:
        assert np.array_equal(straight.bodies[pushed].coupling_impulse, resumed.bodies[pushed].coupling_impulse)
    return straight


# -- EoL bodies against EoL bodies (one QP, Eq. 29 across objects) and BEM bodies (explicit) ------

EOL_MAT = wsim.ElasticMaterial(E=1e5, nu=0.3, rho=500.0)
EOL_BALL = trimesh.creation.icosphere(subdivisions=2, radius=0.15)


def test_eol_pair_rows_summed_on_the_device_match_the_host(device, monkeypatch):
    """The rows between EoL bodies are summed on the device (``pairs.entries_device``: a sort by
    key and one thread per key); the host's numpy version (``pairs.entries_host``, checked equal
    to the per-cell assembly it replaced to 6e-16 on records of two 32-cell spheres in contact)
    sums the same records read back. Three spheres meeting at the origin (two pairs at once, each
    body on both sides of some rows): the same keys, sums equal to round-off, the same rows."""
    from wsim.eol import pairs

    seen = []
    device_entries = pairs.entries_device

    def both(buffers, found, infos, scratch):
        got = device_entries(buffers, found, infos, scratch)
        records = [(k, ri.numpy()[:n], rf.numpy()[:n]) for k, ri, rf, n in buffers]
        ref = pairs.entries_host(records, found, infos, pairs.key_strides(found, infos))
        seen.append((got, ref, found, infos, len(found)))
        return got

    monkeypatch.setattr(pairs, "entries_device", both)
    w = wsim.World(fps=60, gravity=(0.0, 0.0, 0.0), device=device)
    for name, x, v in (("a", (-0.2, 0.0, 0.0), (1.0, 0.0, 0.0)), ("b", (0.2, 0.02, 0.0), (-1.0, 0.0, 0.0)),
                       ("c", (0.0, 0.28, 0.02), (0.0, -1.0, 0.0))):
        w.add(wsim.EolBody(EOL_BALL, EOL_MAT, resolution=6, name=name, position=x, velocity=v, damping=50.0))
    for _ in range(8):
        w.step()
    assert max(n for *_, n in seen) >= 2  # steps with two or three pairs in reach
    checked = 0
    for got, ref, found, infos, _ in seen:
        np.testing.assert_array_equal(got.row_keys, ref.row_keys)
        np.testing.assert_array_equal(got.node_keys, ref.node_keys)
        np.testing.assert_array_equal(got.node_mass, ref.node_mass)
        np.testing.assert_allclose(got.row_values, ref.row_values, rtol=1e-12, atol=1e-14 * np.abs(ref.row_values).max())
        np.testing.assert_allclose(got.node_values, ref.node_values, rtol=1e-12,
                                   atol=1e-14 * np.abs(ref.node_values).max())
        a, b = pairs.rows_from_entries(got, found, infos), pairs.rows_from_entries(ref, found, infos)
        np.testing.assert_array_equal(a.ids, b.ids)
        assert sorted(a.sides) == sorted(b.sides)
        for k in a.sides:
            np.testing.assert_array_equal(a.sides[k].nodes, b.sides[k].nodes)
            assert abs(a.sides[k].J - b.sides[k].J).max() <= 1e-12 * abs(b.sides[k].J).max()
        checked += len(np.unique(got.row_keys // got.row_stride)) >= 2
    assert checked  # a step whose rows come from two pairs


def test_eol_spheres_collide_head_on(device):
    """Two EoL spheres (6 cells across) thrown at each other at 1 m/s in zero gravity, the second
    10x denser. Touching EoL bodies step with one dt and one QP (``wsim.eol.pairs``), so a World
    of EoL bodies alone keeps frame-long coupling intervals; each row pushes the two apart with
    equal and opposite impulses at the same points: the contact impulses are opposite to
    round-off and the pair's momentum is kept to 2 % of the sum of the two momenta (measured
    1e-5: advection is not exactly conservative); they part with the velocities of a partly
    elastic collision (the light one at -1.83 m/s, between the perfectly inelastic -0.82 and the
    elastic -2.64), kinetic energy does not grow (79 % kept), and no surface vertex goes deeper
    than one cell into the other (measured 0.13 cell)."""
    w = wsim.World(fps=60, gravity=(0.0, 0.0, 0.0), device=device)
    heavy = wsim.ElasticMaterial(E=1e5, nu=0.3, rho=5000.0)
    a = w.add(wsim.EolBody(EOL_BALL, EOL_MAT, resolution=6, name="light", position=(-0.2, 0.0, 0.0),
                           velocity=(1.0, 0.0, 0.0), damping=50.0))
    b = w.add(wsim.EolBody(EOL_BALL, heavy, resolution=6, name="heavy", position=(0.2, 0.02, 0.0),
                           velocity=(-1.0, 0.0, 0.0), damping=50.0))
    p0 = a.linear_momentum() + b.linear_momentum()
    scale = np.linalg.norm(a.linear_momentum()) + np.linalg.norm(b.linear_momentum())
    E0 = a.kinetic_energy() + b.kinetic_energy()
    depth = 0.0
    for _ in range(24):
        w.step()
        depth = max(depth, _depth(a, b), _depth(b, a))
    assert w.coupling_steps == 1
    J = b.contact_impulse
    assert J[0] > 0.5 * a.mass
    np.testing.assert_allclose(a.contact_impulse, -J, atol=1e-9 * np.linalg.norm(J))
    assert np.linalg.norm(a.linear_momentum() + b.linear_momentum() - p0) < 0.02 * scale
    va, vb = a.linear_momentum()[0] / a.mass, b.linear_momentum()[0] / b.mass
    m, M = a.mass, b.mass
    inelastic = (m - M) / (m + M)
    assert va < inelastic - 0.1 and vb > inelastic  # the light one rebounds, the heavy one slows
    assert va > ((m - M) - 2 * M) / (m + M) - 0.05  # no faster than an elastic rebound
    assert a.kinetic_energy() + b.kinetic_energy() < E0
    assert depth < a.grid.h


@pytest.mark.parametrize("mu", [0.5, 0.0])
def test_eol_spheres_glancing_blow_keeps_angular_momentum(mu):
    """Two equal EoL spheres (6 cells) thrown at each other 8 cm off centre, with friction 0.5 and
    without: the pair's angular momentum about the origin is kept to 2 % (measured 1.66 % and
    0.39 %). The contact's own moment is exact (``wsim.eol.pairs.moment_couples``; without it the
    frictionless blow gained 4.9 %); what is left is the EoL discretization's, which converges
    with the grid: 1.66 %, 1.30 % and 0.88 % with friction at 6, 8 and 10 cells."""
    w = wsim.World(fps=60, gravity=(0.0, 0.0, 0.0), device="cpu")
    a = w.add(wsim.EolBody(EOL_BALL, EOL_MAT, resolution=6, name="a", position=(-0.2, -0.04, 0.0),
                           velocity=(1.0, 0.0, 0.0), damping=50.0, friction=mu))
    b = w.add(wsim.EolBody(EOL_BALL, EOL_MAT, resolution=6, name="b", position=(0.2, 0.04, 0.0),
                           velocity=(-1.0, 0.0, 0.0), damping=50.0, friction=mu))
    L0 = a.angular_momentum(about=(0, 0, 0)) + b.angular_momentum(about=(0, 0, 0))
    for _ in range(30):
        w.step()
    L = a.angular_momentum(about=(0, 0, 0)) + b.angular_momentum(about=(0, 0, 0))
    assert np.linalg.norm(b.contact_impulse) > 0.5 * b.mass  # they met
    assert np.linalg.norm(L - L0) < 0.02 * np.linalg.norm(L0)


def test_eol_pair_checkpoint_in_mid_contact_resumes_bit_for_bit(tmp_path):
    """Two EoL spheres saved in mid-contact and restored into a fresh World continue bit for bit
    on the CPU: the warm start of the rows between them is state (``active_rows``)."""
    def world():
        w = wsim.World(fps=60, gravity=(0.0, 0.0, 0.0), device="cpu", coupling_dt=1.0 / 240.0)
        w.add(wsim.EolBody(EOL_BALL, EOL_MAT, resolution=5, name="a", position=(-0.17, 0.0, 0.0),
                           velocity=(1.0, 0.0, 0.0), damping=50.0))
        w.add(wsim.EolBody(EOL_BALL, wsim.ElasticMaterial(E=1e5, nu=0.3, rho=1000.0), resolution=5, name="b",
                           position=(0.17, 0.02, 0.0), velocity=(-1.0, 0.0, 0.0), damping=50.0))
        return w

    _resumes_bit_for_bit(world, 3, None, tmp_path)


def test_eol_box_rests_on_an_eol_box():
    """An EoL box set on another on the (frictionless) ground rests there for 2 s: its bottom
    stays put (sinks less than 2 mm over the last second; measured 0.07 mm, 0.16 when first
    measured) and neither box jitters (mean speed under 5 mm/s over the last second; measured 1.1
    mm/s, 0.85 when first measured, 1.8 with the explicit exchange between EoL bodies this QP
    replaced); the upper box's contact impulse is its weight, m g t to 0.1 % (measured 2e-5), and
    the lower box takes the opposite."""
    w = wsim.World(fps=30, device="cpu")
    w.add_collider(wsim.GroundPlane(name="ground", friction=0.0))  # as measured
    mat = wsim.ElasticMaterial(E=2e5, nu=0.3, rho=500.0)
    box = trimesh.creation.box(extents=(0.3, 0.2, 0.3)).subdivide().subdivide()
    low = w.add(wsim.EolBody(box, mat, resolution=5, name="low", position=(0, 0.101, 0), damping=100.0))
    top = w.add(wsim.EolBody(box, mat, resolution=5, name="top", position=(0.03, 0.305, 0), damping=100.0))
    bottom, speeds = [], []
    for f in range(60):
        w.step()
        if f >= 30:
            bottom.append(top.points()[:, 1].min())
            speeds.append([np.linalg.norm(b.linear_momentum()) / b.mass for b in (low, top)])
    assert bottom[0] - min(bottom) < 0.002 and bottom[-1] > 0.195
    assert np.mean(speeds) < 0.005
    assert top.contact_impulse[1] == pytest.approx(top.mass * G * w.time, rel=1e-3)
    ground = low.contact_impulse + top.contact_impulse  # what the ground gave both
    assert ground[1] == pytest.approx((top.mass + low.mass) * G * w.time, rel=1e-3)


def test_eol_joint_qp_is_the_same_sparse_and_dense(monkeypatch):
    """The joint QP of touching EoL bodies is factorized sparse past ``pairs.SPARSE_ROWS`` rows (a
    pile's thousands of rows) and dense below: a box resting on a box on the ground, its rows
    between bodies and against the ground in one QP, gives the same motion both ways (to 1e-9 m
    over 10 frames)."""
    from wsim.eol import pairs

    def run() -> np.ndarray:
        w = wsim.World(fps=30, device="cpu")
        w.add_collider(wsim.GroundPlane(name="ground"))
        mat = wsim.ElasticMaterial(E=2e5, nu=0.3, rho=500.0)
        box = trimesh.creation.box(extents=(0.3, 0.2, 0.3)).subdivide().subdivide()
        w.add(wsim.EolBody(box, mat, resolution=5, name="low", position=(0, 0.101, 0), damping=100.0))
        top = w.add(wsim.EolBody(box, mat, resolution=5, name="top", position=(0.03, 0.305, 0), damping=100.0))
        for _ in range(10):
            w.step()
        assert any(r.rows for r in top.history)
        return np.concatenate([b.points() for b in w.bodies])

    dense = run()
    monkeypatch.setattr(pairs, "SPARSE_ROWS", 0)
    np.testing.assert_allclose(run(), dense, rtol=0.0, atol=1e-9)


def test_eol_pair_friction_is_near_coulombs_minimum(monkeypatch):
    """The friction of the rows between EoL bodies (``pairs.row_friction``) is the minimum of
    1/2 P.K P + slip.P over each row's tangential disc |P_i| <= mu lambda_i |D_i| (Coulomb's law
    per row: stick where the slip can be removed, else slide at the bound). A box resting on a
    box on the ground, friction 0.5: each of the last ten solves' impulses against the minimum
    found independently (plain projected gradient with one step 1 / |K|, 2000 sweeps, checked
    converged by its own fixed-point residual). Measured: median 0.5 %, at most 2.7 % of the
    largest bound (accelerated sweeps); the plain per-row sweeps they replaced, 2.1 % and 4.2 %."""
    from wsim.eol import pairs

    seen = []
    solve = pairs.row_friction

    def kept(rows, lam, slip):
        P = solve(rows, lam, slip)
        seen.append((rows, lam.copy(), slip.copy(), P))
        return P

    monkeypatch.setattr(pairs, "row_friction", kept)
    w = wsim.World(fps=30, device="cpu")
    w.add_collider(wsim.GroundPlane(name="ground"))
    mat = wsim.ElasticMaterial(E=2e5, nu=0.3, rho=500.0)
    box = trimesh.creation.box(extents=(0.3, 0.2, 0.3)).subdivide().subdivide()
    w.add(wsim.EolBody(box, mat, resolution=5, name="low", position=(0, 0.101, 0), damping=100.0, friction=0.5))
    w.add(wsim.EolBody(box, mat, resolution=5, name="top", position=(0.03, 0.305, 0), damping=100.0, friction=0.5))
    for _ in range(10):
        w.step()
    assert len(seen) >= 10
    errors = []
    for rows, lam, slip, P in seen[-10:]:
        st = rows.stacked()
        K = (st.Gr @ st.Gr.T).toarray()
        size = np.linalg.norm(rows.D, axis=1)
        bound = rows.mu * np.maximum(lam, 0.0) * size
        n = rows.D / size[:, None]

        def disc(Q: np.ndarray) -> np.ndarray:
            Q = Q - np.sum(Q * n, axis=1)[:, None] * n
            r = np.linalg.norm(Q, axis=1)
            return Q * np.minimum(1.0, bound / np.maximum(r, 1e-300))[:, None]

        t = 1.0 / np.linalg.eigvalsh(K).max()
        ref = np.zeros_like(slip)
        for _ in range(2000):
            ref = disc(ref - t * (K @ ref + slip))
        assert np.abs(ref - disc(ref - t * (K @ ref + slip))).max() < 1e-9 * bound.max()
        assert np.all(np.linalg.norm(P, axis=1) <= bound * (1 + 1e-9) + 1e-15)  # within the discs
        assert np.abs(np.sum(P * n, axis=1)).max() <= 1e-9 * bound.max()  # tangential
        errors.append(np.abs(P - ref).max() / bound.max())
    assert np.median(errors) < 0.01
    assert np.max(errors) < 0.05


def _slab_world(mu: float, device: str):
    """A World (60 fps) with a ground and a heavy EoL slab (0.8 x 0.1 x 0.3 m, 48 kg, top at y =
    0.1005 m) of friction mu on it (16 cells: two across its thickness, where its material points
    weigh it right; at 12 it would weigh 28 kg). Since 2026-11-28 the slab's friction holds it on
    the ground (a collider's contact takes the larger of the two); before, the ground was
    frictionless for it, and the slab slid by m / M of the box's slide (2 %)."""
    w = wsim.World(fps=60, device=device)
    w.add_collider(wsim.GroundPlane(name="ground"))
    slab = trimesh.creation.box(extents=(0.8, 0.1, 0.3)).subdivide().subdivide()
    base = w.add(wsim.EolBody(slab, wsim.ElasticMaterial(E=5e5, nu=0.3, rho=2000.0), resolution=16, name="slab",
                              position=(0.2, 0.0505, 0), damping=100.0, friction=mu))
    return w, base


def test_eol_box_slides_to_a_stop_on_an_eol_slab(device):
    """An EoL box launched at 1 m/s across the flat top of a heavy EoL slab (friction 0.4 on both)
    stops within 15 % of the Coulomb distance v^2 / (2 mu g) (measured 0.1254 m against 0.1274 m),
    relative to the slab (``_slab_world``); the tangential
    impulse it took is mu times the normal one while it slid, to 1 % (measured 0.17 % above:
    Coulomb's bound holds per contact row, mu lambda |D|, and a few rows at the box's bulged
    bottom edges push sideways, 2-5 % of the load, whose bounds add to the total but whose normal
    impulses cancel; the friction is taken at the QP's dt guess, the normal impulse at the step's
    final dt where a step is shortened)."""
    mu = 0.4
    w, base = _slab_world(mu, device)
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1)).subdivide()
    cube = w.add(wsim.EolBody(box, wsim.ElasticMaterial(E=2e5, nu=0.3, rho=500.0), resolution=4, name="box",
                              position=(-0.1, 0.1505, 0), velocity=(1.0, 0.0, 0.0), damping=50.0, friction=mu))
    x0 = cube.points()[:, 0].mean() - base.points()[:, 0].mean()
    for f in range(30):
        w.step()
        if f == 5:  # sliding
            J = cube.contact_impulse
            assert -J[0] == pytest.approx(mu * J[1], rel=1e-2)
    x1 = cube.points()[:, 0].mean() - base.points()[:, 0].mean()
    rel_v = cube.linear_momentum()[0] / cube.mass - base.linear_momentum()[0] / base.mass
    assert abs(rel_v) < 0.02
    assert x1 - x0 == pytest.approx(1.0 / (2 * mu * G), rel=0.15)


@pytest.mark.parametrize("coupling", ["auto", "implicit"])
def test_eol_ball_and_bem_cube_collide(box_ops, device, coupling):
    """An EoL ball and a BEM cube thrown at each other in zero gravity: the EoL body pushes, the
    cube (4x heavier) is handed the opposite impulse (exactly) and its momentum changes by that to
    0.1 % (measured 0.004 %; 1.1 % more before the loads' balance, see the PBD-BEM test); the
    pair's momentum is kept to 2 % of the sum of the two momenta (measured 0.012 %, 0.67 % before);
    they part (ball -1.72 m/s, cube -0.31 m/s: between the inelastic -0.60 and the elastic
    -2.19 / -0.20), and no vertex goes deeper than one EoL cell into the other (measured 0.1 cell).
    The same with the push reaching the cube within its interval (``coupling="implicit"``: the
    interval stepped again until the push matches the cube's guess; what the guess missed is
    handed over after it), exactly too."""
    w = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, 0.0, 0.0), device=device, coupling=coupling)
    cube = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="cube", position=(0.2, 0.02, 0.0),
                              velocity=(-1.0, 0.0, 0.0)))
    ball = w.add(wsim.EolBody(trimesh.creation.icosphere(subdivisions=2, radius=0.1), EOL_MAT, resolution=5,
                              name="ball", position=(-0.12, 0.0, 0.0), velocity=(1.0, 0.0, 0.0), damping=50.0))
    p0, p0_cube = cube.linear_momentum() + ball.linear_momentum(), cube.linear_momentum()
    scale = np.linalg.norm(cube.linear_momentum()) + np.linalg.norm(ball.linear_momentum())
    depth = 0.0
    for _ in range(20):
        w.step()
        depth = max(depth, _depth(cube, ball), _depth(ball, cube))
    J = cube.coupling_impulse
    assert J[0] > 0.2 * ball.mass
    np.testing.assert_allclose(ball.contact_impulse, -J, atol=1e-9 * np.linalg.norm(J))
    assert np.linalg.norm(cube.linear_momentum() - p0_cube - J) < 1e-3 * np.linalg.norm(J)
    assert np.linalg.norm(cube.linear_momentum() + ball.linear_momentum() - p0) < 0.02 * scale
    v_ball, v_cube = ball.linear_momentum()[0] / ball.mass, cube.linear_momentum()[0] / cube.mass
    assert v_ball < v_cube < -0.2  # they part; the heavier cube only slows down
    assert depth < ball.grid.h
    assert (w.coupling_stats["implicit_intervals"] > 0) == (coupling == "implicit")


def test_eol_box_rests_on_a_bem_cube_on_the_ground(box_ops):
    """An EoL box set on a BEM cube resting on the ground stays there for 2 s: its bottom stays
    put (moves less than 1 mm over the last second), neither body jitters (speeds under 1 mm/s
    over the last second), and the cube is handed the box's weight, m g t to 0.1 % (measured: still
    to 1 um, 0.09 mm/s, 1e-5)."""
    w = wsim.World(fps=1.0 / (5 * DT), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    cube = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="cube", position=(0.0, 0.1005, 0.0), friction=0.5))
    top = w.add(wsim.EolBody(trimesh.creation.box(extents=(0.15, 0.1, 0.15)).subdivide().subdivide(),
                             wsim.ElasticMaterial(E=2e5, nu=0.3, rho=500.0), resolution=5, name="top",
                             position=(0.01, 0.2515, 0.0), damping=50.0, friction=0.5))
    bottom, speeds = [], []
    for f in range(200):
        w.step()
        if f >= 100:
            bottom.append(top.points()[:, 1].min())
            speeds.append(max(np.linalg.norm(top.linear_momentum()) / top.mass,
                              np.linalg.norm(cube.linear_momentum()) / cube.mass))
    assert np.ptp(bottom) < 0.001 and min(bottom) > 0.199
    assert max(speeds) < 0.001
    assert -cube.coupling_impulse[1] == pytest.approx(top.mass * G * w.time, rel=1e-3)


def test_eol_box_of_the_cubes_mass_rests_on_it(box_ops):
    """An 8 kg EoL box (0.2 m, E = 1e6 Pa, the BEM cube's material) set on the 8 kg BEM cube on the
    ground, BEM dt = 2 ms (one BEM step a coupling interval): both come to rest, mean speeds under
    1 mm/s over the last half second, and neither sinks into the other (deepest vertex under
    0.5 mm). With the cube's rigid give alone in the EoL QP the pair kept shaking in the
    exchange's period-two mode, the push alternating around the weight each interval (an
    independent check at 8 cells: 12-13 mm/s; here 3.9 and 1.6 mm/s, 0.73 and 0.78 mm deep); with
    its elastic give and the change of the push yielding (``kernels.eol_contact.partner_yield``)
    measured 0.29 and 0.46 mm/s, 0.14 and 0.03 mm deep."""
    w = wsim.World(fps=1.0 / (5 * DT), device="cpu")
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    cube = w.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="cube", position=(0.0, 0.1005, 0.0)))
    top = w.add(wsim.EolBody(trimesh.creation.box(extents=(0.2, 0.2, 0.2)).subdivide().subdivide(), MAT,
                             resolution=5, name="top", position=(0.03, 0.302, 0.0), damping=20.0))
    speeds = []
    for f in range(150):
        w.step()
        if f >= 100:
            speeds.append((np.linalg.norm(cube.linear_momentum()) / cube.mass,
                           np.linalg.norm(top.linear_momentum()) / top.mass))
    mean = np.mean(speeds, axis=0)
    assert mean.max() < 0.001, f"mean speeds (cube, box) {mean} m/s"
    assert _depth(cube, top) < 5e-4 and _depth(top, cube) < 5e-4


def _bem_box_on_eol_slab(ops, mat, velocity: float, device: str):
    """The 0.2 m BEM cube (material ``mat``, friction 0.5) set on the flat top of a heavy EoL slab
    (48 kg, ``_slab_world``'s, at 100 fps so that the frame holds whole BEM steps) on a frictionless
    ground, launched along x at ``velocity``; the World, slab and box. The slab's friction is left
    unset: the pair takes the cube's 0.5, and the ground's 0 holds for the slab (a collider's
    contact takes the larger of the collider's and the body's)."""
    w = wsim.World(fps=1.0 / (5 * DT), device=device)
    w.add_collider(wsim.GroundPlane(name="ground", friction=0.0))
    slab = trimesh.creation.box(extents=(0.8, 0.1, 0.3)).subdivide().subdivide()
    base = w.add(wsim.EolBody(slab, wsim.ElasticMaterial(E=5e5, nu=0.3, rho=2000.0), resolution=16, name="slab",
                              position=(0.2, 0.0505, 0), damping=100.0))
    box = w.add(wsim.BemBody(BOX, mat, DT, operators=ops, name="box", position=(0.0, 0.2015, 0.0),
                             velocity=(velocity, 0.0, 0.0), friction=0.5))
    return w, base, box


def _energy(w) -> float:
    """Kinetic, elastic (EoL) and gravitational energy of a World of EoL and BEM bodies [J]."""
    e = 0.0
    for b in w.bodies:
        if isinstance(b, wsim.EolBody):
            e += b.kinetic_energy() + b.elastic_energy + G * float(b.node_masses() @ b.node_world_positions()[:, 1])
        else:
            e += b.kinetic_energy() + G * b.mass * b.center_of_mass()[1]
    return e


def test_bem_box_slides_to_a_stop_on_an_eol_slab(box_ops, device):
    """The 8 kg BEM cube launched at 1 m/s across a 48 kg EoL slab (friction 0.5) on frictionless
    ground stops within 15 % of the Coulomb distance relative to the slab, v^2 / (2 mu g (1 + m/M)):
    friction slows the cube by mu g and speeds the slab up by mu g m / M (0.0874 m; measured
    0.0874 m on the CPU with the slab's push found implicitly, ``World(coupling="auto")``, and
    handed over one interval late, 0.093 m before the loads' balance, ``correction.load_balance``)."""
    w, base, box = _bem_box_on_eol_slab(box_ops, MAT, 1.0, device)
    dx, rel_v = _slide(w, base, box)
    assert abs(rel_v) < 0.05
    assert dx == pytest.approx(1.0 / (2 * 0.5 * G * (1.0 + box.mass / base.mass)), rel=0.15)


def test_light_bem_box_rests_on_a_heavy_eol_slab():
    """A 0.8 kg BEM cube set on a 48 kg EoL slab stays on it without gaining energy. The slab's rows
    (Eq. 28) keep it out of the cube; taken as a kinematic surface the cube was handed the push
    that moves the slab's heavy nodes to its velocity: it gained 3.6 J and was thrown about at
    0.86 m/s (an independent check: a 1 kg box thrown off a 43 kg slab with 5 J gained). With the
    cube's rigid give in the QP (``kernels.eol_contact.partner_compliance``) the energy never
    exceeds its start (measured: 0.027 J below it), the cube's speed relative to the slab over the
    last 0.25 s stays under 0.1 m/s (measured mean 0.0038 m/s, at most 0.010), it moves less than
    5 mm over that time (measured 0.16 mm) and its bottom stays within 5 mm of the slab's top at
    0.1005 m (measured 0.7 mm below). The slab, 60 times heavier, has its push found implicitly
    (``World(coupling="auto")``; 5.6 passes an interval, most ending at the limit of 6); handed
    over one interval late it measured 0.03 J below, 0.019 and 0.038 m/s, 0.5 mm and 0.6 mm."""
    light = wsim.ElasticMaterial(E=MAT.E, nu=MAT.nu, rho=100.0)
    w, base, box = _bem_box_on_eol_slab(build_operators(BOX, light, DT, cache=False, device="cpu"), light, 0.0, "cpu")
    e0, gain, speeds = _energy(w), -np.inf, []
    x_mid = None
    for f in range(50):
        w.step()
        gain = max(gain, _energy(w) - e0)
        if f == 24:
            x_mid = box.center_of_mass() - base.center_of_mass()
        if f >= 25:
            speeds.append(np.linalg.norm(box.linear_momentum() / box.mass - base.linear_momentum() / base.mass))
    assert gain < 0.01 * box.mass * G * 0.1  # less than a 1 mm rise of the cube
    assert np.mean(speeds) < 0.1
    assert np.linalg.norm(box.center_of_mass() - base.center_of_mass() - x_mid) < 0.005
    assert box.points()[:, 1].min() > 0.095


def test_bem_cube_rests_on_a_heavy_eol_slab_with_its_push_found_implicitly(box_ops):
    """The 8 kg BEM cube set on the 48 kg EoL slab (``_bem_box_on_eol_slab``) rests: over the
    second half second its speed relative to the slab averages under 8 mm/s (measured 2.8) and it
    walks less than 1 mm (measured 0.04). The slab is the heavier: ``coupling="auto"`` finds its
    push within each interval once they may touch (``World._advance_implicit``: 494 of the 500
    intervals, 3.2 passes each, 2 ended unconverged). Handed over one interval late (the code
    before) the cube shook at 23 mm/s relative to the slab over the second second and walked
    10 mm/s (``coupling="explicit"`` keeps that)."""
    w, base, box = _bem_box_on_eol_slab(box_ops, MAT, 0.0, "cpu")
    rel, x = [], []
    for _ in range(100):
        w.step()
        rel.append(np.linalg.norm(box.linear_momentum() / box.mass - base.linear_momentum() / base.mass))
        x.append(box.center_of_mass() - base.center_of_mass())
    stats = w.coupling_stats
    assert stats["implicit_intervals"] > 450 and stats["unconverged"] < 0.05 * stats["implicit_intervals"]
    assert np.mean(rel[50:]) < 8e-3 and np.linalg.norm(x[-1] - x[49]) < 1e-3, (np.mean(rel[50:]), x[-1] - x[49])


def test_pbd_box_slides_to_a_stop_on_an_eol_slab(device):
    """A PBD box launched at 1 m/s across the flat top of a heavy EoL slab (friction 0.5: the PBD
    default, the slab's is the same) stops within 15 % of the Coulomb distance v^2 / (2 mu g)
    (measured 0.099 m against 0.102 m), relative to the slab."""
    mu = 0.5
    w, base = _slab_world(mu, device)
    box = w.add(wsim.PbdBody(trimesh.creation.box(extents=(0.1, 0.1, 0.1)).subdivide(), PBD_DENSE, tets="auto",
                             name="box", position=(-0.1, 0.1505, 0), velocity=(1.0, 0.0, 0.0)))
    x0 = box.center_of_mass()[0] - base.points()[:, 0].mean()
    for _ in range(30):
        w.step()
    x1 = box.center_of_mass()[0] - base.points()[:, 0].mean()
    rel_v = box.linear_momentum()[0] / box.masses.sum() - base.linear_momentum()[0] / base.mass
    assert abs(rel_v) < 0.02
    assert x1 - x0 == pytest.approx(1.0 / (2 * mu * G), rel=0.15)


def test_small_pbd_ball_landing_on_an_eol_block_does_not_ring():
    """A 0.9 kg PBD ball dropped 3 cm onto an 11.6 kg EoL block (7 cells, damping 20) on the
    ground. The block's top layer of grid nodes holds a sliver of material (0.0085 kg against
    0.07 inside; the viscosity is cut there) and rings at about 150 Hz. Its steps used to run to
    the elastic cap with the coupling interval's remainder last (3.6e-4, 7.2e-4, 9.5e-4,
    1.3e-3 s, every 3.3 ms interval: half the mode's period), which pumped the mode
    parametrically: the layer reached -4 m/s within half a second, the block's kinetic energy
    4.2 J (more than the ball brought). Steps now divide each advance evenly
    (``EolBody.advance_group``). Measured: the block's kinetic energy below 0.5 mJ over the
    last 10 frames, v* at most 0.32 m/s, and the energy (kinetic, EoL elastic, gravitational;
    the ball's elastic energy left out, which only lowers the sum) never above its start."""
    w = wsim.World(fps=60, device="cpu")
    w.add_collider(wsim.GroundPlane(name="ground", friction=0.5))
    soft = wsim.ElasticMaterial(E=2e5, nu=0.3, rho=1000.0)
    block = w.add(wsim.EolBody(trimesh.creation.box(extents=(0.3, 0.15, 0.3)).subdivide().subdivide(), soft,
                               resolution=7, damping=20.0, name="block", position=(0.0, 0.0755, 0.0), friction=0.5))
    ball = w.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=2, radius=0.06), soft, tets="auto",
                              name="ball", position=(0.02, 0.241, 0.0), friction=0.5))

    def energy() -> float:
        e = block.kinetic_energy() + block.elastic_energy + G * float(block.node_masses() @ block.node_world_positions()[:, 1])
        return e + ball.kinetic_energy() + G * float(ball.masses.sum()) * ball.center_of_mass()[1]

    e0, energies, kinetic = energy(), [], []
    for _ in range(40):
        w.step()
        energies.append(energy())
        kinetic.append(block.kinetic_energy())
    assert any(r.rows for r in block.history) and ball.center_of_mass()[1] > 0.15  # it landed and rests on top
    assert max(kinetic[-10:]) < 0.005
    assert max(r.v_star for r in block.history) < 1.0
    assert max(energies) < e0 + 0.01


def test_eol_cube_landing_on_a_light_slab_does_not_ring():
    """A dense, coarse EoL cube (5.2 kg, 4 cells) dropped 4 cm onto a light, fine EoL slab (10 kg,
    16 cells) on the ground: the cube's contact rows are much heavier than the slab's surface
    nodes. The explicit exchange that one QP replaced rang here (the lighter body pushed, the
    other was handed the push one coupling interval later: the slab's v* reached 44 m/s and the
    pair gained 2.3 J of the 15 J it started with; 6 m/s once the push was shared by the slab's
    give). In one QP the slab's v* stays below 10 m/s (measured 1.2) and the energy (kinetic,
    elastic, gravitational) never exceeds its start by more than 1 % (measured: never above it)."""
    w = wsim.World(fps=60, device="cpu")
    w.add_collider(wsim.GroundPlane(name="ground"))
    slab = trimesh.creation.box(extents=(0.6, 0.1, 0.3)).subdivide().subdivide()
    w.add(wsim.EolBody(slab, wsim.ElasticMaterial(E=2e5, nu=0.3, rho=500.0), resolution=16, name="slab",
                       position=(0.0, 0.0505, 0), damping=50.0))
    cube = trimesh.creation.box(extents=(0.12, 0.12, 0.12)).subdivide()
    w.add(wsim.EolBody(cube, wsim.ElasticMaterial(E=1e6, nu=0.3, rho=3000.0), resolution=4, name="cube",
                       position=(0.05, 0.2, 0.0), damping=50.0))

    def energy() -> float:
        return sum(b.kinetic_energy() + b.elastic_energy + G * float(b.node_masses() @ b.node_world_positions()[:, 1])
                   for b in w.bodies)

    e0, energies = energy(), []
    for _ in range(30):
        w.step()
        energies.append(energy())
    v_star = max(r.v_star for b in w.bodies for r in b.history)
    assert any(r.rows for r in w.bodies[1].history)  # they met
    assert v_star < 10.0
    assert max(energies) < 1.01 * e0
