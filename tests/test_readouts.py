"""The conservation read-outs every body type gives (``wsim.body.Body``): the centre of mass."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import wsim
from bem_box import BOX, DT, MAT  # noqa: E402 (tests/ is on the path; box_ops: conftest.py)


@pytest.mark.parametrize("method", ["bem", "eol", "pbd"])
def test_center_of_mass_moves_with_the_momentum_in_free_flight(box_ops, method):
    """Without gravity a spinning, translating body's centre of mass moves in a straight line at
    linear_momentum() / mass, and angular_momentum() is taken about it."""
    world = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, 0.0, 0.0), device="cpu")
    v0, w0 = (0.4, -0.2, 0.1), (0.0, 3.0, 1.0)
    if method == "bem":
        body = world.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="b", position=(0.1, 0.2, 0.3),
                                      velocity=v0, angular_velocity=w0))
        mass = body.mass
    elif method == "eol":
        body = world.add(wsim.EolBody(BOX, wsim.ElasticMaterial(E=2e5, nu=0.3, rho=800.0), resolution=6, name="b",
                                      position=(0.1, 0.2, 0.3), velocity=v0, angular_velocity=w0))
        mass = float(body.node_masses().sum())
    else:
        body = world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1, radius=0.1), name="b", tets="auto",
                                      position=(0.1, 0.2, 0.3), velocity=v0, angular_velocity=w0, cache=False))
        mass = float(body.masses.sum())
    c0 = body.center_of_mass()
    assert np.allclose(c0, (0.1, 0.2, 0.3), atol=0.02)
    v = body.linear_momentum() / mass
    for _ in range(10):
        world.step()
    np.testing.assert_allclose(body.center_of_mass(), c0 + v * world.time, atol=2e-4)
    np.testing.assert_allclose(body.angular_momentum(), body.angular_momentum(about=body.center_of_mass()),
                               rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("method", ["bem", "eol"])
def test_world_inertia_gives_the_angular_momentum_of_a_rigid_spin(box_ops, method):
    """At the start a body spins rigidly at omega: angular_momentum() = world_inertia() omega (the
    EoL body's from its lumped node masses, which it conserves), about its centre of mass; the BEM
    cube's inertia is the solid cube's, m a^2 / 6 (exact: surface integrals of a polyhedron). An
    EoL pusher takes a BEM body's give from it (``EolBody.set_moving_surfaces``)."""
    world = wsim.World(fps=1.0 / (5 * DT), gravity=(0.0, 0.0, 0.0), device="cpu")
    w0 = np.array([0.5, 3.0, 1.0])
    if method == "bem":
        body = world.add(wsim.BemBody(BOX, MAT, DT, operators=box_ops, name="b", position=(0.1, 0.2, 0.3),
                                      velocity=(0.4, 0.0, 0.0), angular_velocity=w0))
        np.testing.assert_allclose(body.world_inertia(), body.mass * 0.2**2 / 6.0 * np.eye(3), rtol=1e-9, atol=1e-12)
    else:
        body = world.add(wsim.EolBody(trimesh.creation.box(extents=(0.3, 0.2, 0.1)), wsim.ElasticMaterial(E=2e5, nu=0.3, rho=800.0),
                                      resolution=6, name="b", position=(0.1, 0.2, 0.3), velocity=(0.4, 0.0, 0.0),
                                      angular_velocity=w0))
        world.step()  # the node masses of a stepped state
        w0 = body.angular_velocity  # the frame's spin (the split leaves the rest no angular momentum)
    I = body.world_inertia()
    np.testing.assert_allclose(I, I.T, atol=1e-14)
    np.testing.assert_allclose(body.angular_momentum(), I @ w0, rtol=1e-6, atol=1e-12)
