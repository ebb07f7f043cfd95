"""BEM scene: two cubes glued face to face by point joints, dropped on the ground.

    wsim run scenes/bem_glued_cubes.py -o bem_glued_cubes.usda
    wsim run scenes/bem_glued_cubes.py -o bem_glued_cubes.usda --mesh path/to/model.obj   # fitted to 0.1 m

Two 0.1 m cubes (the BEM authors' glued_cubes material: rho = 1000, shear modulus 1e5 Pa,
nu = 0.45, dt = 5 ms) share a face; every vertex of that face is a point joint (equal positions,
equal and opposite forces). Thrown sideways from 0.25 m, the pair lands and settles. Both
cubes use one operator set. With ``--mesh``, two copies of the model stand side by side and are
joined where they touch (their facing sides must have coincident vertices, so this is meant for
models cut in two).
"""

from __future__ import annotations

import numpy as np
import trimesh

import wsim
from wsim import mesh as wmesh
from wsim.bem import decompose

FRAMES = 60
FPS = 30


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, -9.8, 0.0), device=device)
    world.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    left = trimesh.creation.box(extents=(0.1, 0.1, 0.1)).subdivide() if mesh is None else wmesh.load_fitted(mesh, 0.1)
    width = left.extents[0]
    left.apply_translation(np.array([-0.5 * width, 0.3, 0.0]) - left.bounding_box.centroid)
    right = left.copy()
    right.apply_translation((left.extents[0], 0.0, 0.0))
    bodies, joints = decompose([left, right], wsim.ElasticMaterial(mu=1.0e5, nu=0.45, rho=1000.0), 0.005,
                               name=wmesh.display_name(left, "cube"), device=world.device,
                               velocity=(0.3, 0.0, 0.0))
    for b in bodies:
        world.add(b)
    for j in joints:
        world.add_joint(j)
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
