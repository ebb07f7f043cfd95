"""Small scenes of every method for the checkpoint tests (``tests/test_checkpoint.py``).

``WSIM_TEST_SCENE`` picks the content: "pbd" (a spinning ball hitting the ground and a kinematic
pusher), "bem" (a spinning BEM ball under a pulsing traction), "eol" (an EoL ball landing on the
ground), "recon" (a PBD reconstruction), "all" (one body of each method in one World, without
colliders).
"""

from __future__ import annotations

import os

import numpy as np
import trimesh

import wsim

FRAMES = 20


def _pbd(name: str = "pbd", position=(0.0, 0.13, 0.0)) -> wsim.PbdBody:
    return wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1, radius=0.1), name=name, position=position,
                        velocity=(0.3, -0.5, 0.0), angular_velocity=(0.0, 0.0, 3.0), substeps=4, cache=False)


def _bem() -> wsim.BemBody:
    mat = wsim.ElasticMaterial(E=2e4, nu=0.3, rho=1000.0)
    body = wsim.BemBody(trimesh.creation.icosphere(subdivisions=1, radius=0.1), mat, dt=1.0 / 240.0, name="bem",
                        position=(1.0, 0.5, 0.0), velocity=(0.0, 0.2, 0.0), angular_velocity=(0.0, 2.0, 1.0))
    n = len(body.rest_vertices)
    normals = body.rest_normals
    body.add_traction(lambda t: 200.0 * np.sin(40.0 * t) * normals[:n])
    return body


def _eol() -> wsim.EolBody:
    mat = wsim.ElasticMaterial(E=2e4, nu=0.3, rho=500.0)
    return wsim.EolBody(trimesh.creation.icosphere(subdivisions=1, radius=0.1).apply_translation((-1.0, 0.115, 0.0)),
                        mat, resolution=5, name="eol", velocity=(0.0, -0.6, 0.0), angular_velocity=(0.0, 0.0, 2.0),
                        damping=5.0)


def _recon() -> wsim.PbdReconstruction:
    return wsim.PbdReconstruction(_pbd("recon_source", (0.0, 1.0, 0.0)), stride=5, frames=FRAMES + 5,
                                  points_per_curve=6, fps=60.0, name="recon")


def build(mesh=None, device=None) -> wsim.World:
    kind = os.environ.get("WSIM_TEST_SCENE", "all")
    world = wsim.World(fps=60.0, device=device or "cpu")
    if kind in ("pbd", "eol"):
        world.add_collider(wsim.GroundPlane(height=0.0, friction=0.5))
        slide = lambda t: np.array([[1.0, 0, 0, 0.3 - 0.5 * t], [0, 1.0, 0, 0.1], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])  # noqa: E731
        world.add_collider(wsim.MeshCollider(trimesh.creation.box(extents=(0.1, 0.1, 0.3)), transform=slide, name="pusher"))
    makers = {"pbd": [_pbd], "bem": [_bem], "eol": [_eol], "recon": [_recon],
              "all": [_pbd, _bem, _eol, _recon]}[kind]
    for make in makers:
        world.add(make())
    return world
