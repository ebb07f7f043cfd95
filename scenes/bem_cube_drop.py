"""BEM scene: a soft cube dropped on the ground (the BEM authors' cube_drop settings).

    wsim run scenes/bem_cube_drop.py -o bem_cube_drop.usda
    wsim run scenes/bem_cube_drop.py -o bem_cube_drop.usda --mesh path/to/model.obj   # fitted to 0.1 m

A 0.1 m cube (rho = 1000 kg/m^3, shear modulus 1e5 Pa, nu = 0.45, dt = 5 ms, double nodes at its
edges) falls 5 cm, tilted by 20 degrees so that it lands on an edge, and settles on a ground with
friction 0.5. Contact and friction are solved each step (paper Sec. 3.4).
"""

from __future__ import annotations

import numpy as np
import trimesh

import wsim
from wsim import mesh as wmesh
from wsim.rigid import rodrigues

FRAMES = 60
FPS = 30


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, -9.8, 0.0), device=device)
    world.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    if mesh is None:
        shape = trimesh.creation.box(extents=(0.1, 0.1, 0.1)).subdivide().subdivide()
    else:
        shape = wmesh.load_fitted(mesh, 0.1)
    world.add(wsim.BemBody(shape, wsim.ElasticMaterial(mu=1.0e5, nu=0.45, rho=1000.0), 0.005,
                           name=wmesh.display_name(shape, "cube"),
                           position=(0.0, 0.15, 0.0), rotation=rodrigues(np.radians(20.0) * np.array([0.0, 0.0, 1.0])),
                           double_nodes=30.0 if mesh is None else None))
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
