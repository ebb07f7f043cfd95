"""BEM scene: six soft cubes dropped into a pile, colliding with each other and the ground.

    wsim run scenes/bem_pile.py -o bem_pile.usda
    wsim run scenes/bem_pile.py -o bem_pile.usda --mesh path/to/model.obj   # six copies, fitted to 0.1 m

Six 0.1 m cubes (one operator set; rho = 1000 kg/m^3, shear modulus 1e5 Pa, nu = 0.45,
dt = 5 ms) fall from staggered heights, tilted and spinning, onto the ground and onto each
other. Contact between the bodies (``wsim.contact``) and with the ground is one constraint solve
per step for the bodies that touch, with friction 0.5.
"""

from __future__ import annotations

import numpy as np
import trimesh

import wsim
from wsim import mesh as wmesh
from wsim.bem import build_operators
from wsim.rigid import rodrigues

FRAMES = 60
FPS = 30


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, -9.8, 0.0), device=device)
    world.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    shape = trimesh.creation.box(extents=(0.1, 0.1, 0.1)).subdivide() if mesh is None else wmesh.load_fitted(mesh, 0.1)
    label = wmesh.display_name(shape, "cube")  # a --mesh model's file stem: bunny_0, bunny_1, ...
    material = wsim.ElasticMaterial(mu=1.0e5, nu=0.45, rho=1000.0)
    dt = 0.005
    ops = build_operators(shape, material, dt, device=world.device)
    rng = np.random.default_rng(3)
    for k in range(6):
        x, z = 0.06 * np.cos(2.1 * k), 0.06 * np.sin(2.1 * k)
        world.add(wsim.BemBody(shape, material, dt, operators=ops, name=f"{label}_{k}", friction=0.5,
                               position=(x, 0.1 + 0.13 * k, z) - shape.bounding_box.centroid,
                               rotation=rodrigues(rng.normal(size=3) * 0.6),
                               angular_velocity=rng.normal(size=3) * 2.0))
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
