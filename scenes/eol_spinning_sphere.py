"""EoL scene: a spinning elastic sphere dropped on the ground (Fan et al., Figs. 1b, 7, 8).

    wsim run scenes/eol_spinning_sphere.py -o eol_sphere.usda
    wsim run scenes/eol_spinning_sphere.py -o eol_sphere.usda --mesh path/to/model.obj   # your closed mesh

A soft ball (0.6 m across; E = 50 kPa, nu = 0.3, rho = 500 kg/m^3, light Kelvin-Voigt damping)
spins at pi rad/s about a tilted axis and falls 0.7 m onto a ground plane. The rigid Lagrangian
frame carries the flight and the spin; the Eulerian grid (16 cells across) carries the squash on
impact, and the adaptive step shrinks during contact and grows back in flight. Contact is
frictionless, as in the paper, so the ball keeps spinning after it lands.
"""

from __future__ import annotations

import numpy as np
import trimesh

import wsim
from wsim import mesh as wmesh

FRAMES = 90
FPS = 30
RESOLUTION = 16


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, -9.81, 0.0), device=device)
    world.add_collider(wsim.GroundPlane(0.0, friction=0.0))  # frictionless, as in the paper
    shape = trimesh.creation.icosphere(subdivisions=3, radius=0.3) if mesh is None else wmesh.load_fitted(mesh, 0.6)
    label = wmesh.display_name(shape, "ball")
    shape = shape.copy()
    shape.apply_translation(np.array([0.0, 1.0, 0.0]) - shape.bounds.mean(axis=0))
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    world.add(
        wsim.EolBody(
            shape,
            wsim.ElasticMaterial(E=5.0e4, nu=0.3, rho=500.0),
            resolution=RESOLUTION,
            name=label,
            velocity=(0.4, 0.0, 0.0),
            angular_velocity=np.pi * axis,
            damping=20.0,
        )
    )
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
