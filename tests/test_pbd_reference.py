"""The Warp XPBD kernels against the independent numpy implementation of the same frame."""

from __future__ import annotations

import numpy as np
import pytest

import wsim
from wsim import mesh as wmesh
from wsim.pbd import reference


@pytest.mark.parametrize("tets", [None, "auto"], ids=["surface", "tets"])
def test_warp_frame_matches_numpy_reference(device, tets):
    """Same model, same colour order, float32 (Warp) vs float64 (numpy): a bumpy body with a pinned
    vertex falls onto the ground and bounces for 8 frames; positions agree to float32 accuracy."""
    world = wsim.World(fps=30, device=device)
    world.add_collider(wsim.GroundPlane(height=0.0, friction=0.4))
    body = world.add(
        wsim.PbdBody(
            wmesh.bumpy_sphere(radius=0.25, subdivisions=2, amplitude=0.2, seed=3),
            wsim.ElasticMaterial(E=5e4, nu=0.35, rho=600.0),
            name="b",
            position=(0.0, 0.3, 0.0),
            velocity=(0.4, -1.0, 0.0),
            angular_velocity=(0.0, 2.0, 4.0),
            tets=tets,
            substeps=6,
            iterations=2,
            damping=2e-3,
        )
    )
    x = body.particles()
    v = body.velocities()
    inv_mass = np.where(body.masses > 0, 1.0 / body.masses, 0.0)
    planes = [(np.array([0.0, 1.0, 0.0]), 0.0, 0.4)]
    diag = np.linalg.norm(np.ptp(x, axis=0))
    for _ in range(8):
        world.step()
        reference.run_frame(
            body.model, x, v, inv_mass, world.gravity, world.frame_dt, 6, 2, 2e-3, planes, body.contact_margin
        )
    assert x[:, 1].min() >= -1e-9  # the reference also keeps the body above ground
    err = np.abs(body.particles() - x).max()
    assert err < 2e-5 * diag, err  # measured 1e-6 m on a 0.94 m body
    assert np.abs(body.particles() - body.rest_points).max() > 0.05 * diag  # it really moved and deformed
