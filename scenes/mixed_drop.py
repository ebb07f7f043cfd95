"""All three methods in one World: soft PBD balls dropped onto a BEM cube, an EoL block and each other.

    wsim run scenes/mixed_drop.py -o mixed_drop.usda
    wsim run scenes/mixed_drop.py -o mixed_drop.usda --mesh path/to/model.obj   # the balls, fitted to 0.16 m

A BEM cube (0.2 m, shear modulus 1e5 Pa) and an EoL block (0.3 x 0.15 x 0.3 m, E = 50 kPa) rest on
the ground; three PBD balls (0.16 m, tetrahedral, E = 200 kPa) fall onto them, one onto the cube,
one onto the block and one onto the first ball. PBD bodies collide with each other in lockstep
substeps (``wsim.pbd.contact``); a PBD body and a BEM or EoL body meet through the World's
explicit coupling (each pushes the other, one frame late, momentum exact:
``World._couple_surfaces``). Friction 0.5 everywhere.
"""

from __future__ import annotations

import trimesh

import wsim
from wsim import mesh as wmesh

FRAMES = 60
FPS = 30


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, -9.81, 0.0), device=device)
    world.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    cube = trimesh.creation.box(extents=(0.2, 0.2, 0.2)).subdivide()
    world.add(wsim.BemBody(cube, wsim.ElasticMaterial(mu=1.0e5, nu=0.45, rho=1000.0), 1.0 / (FPS * 8), name="bem_cube",
                           position=(-0.25, 0.1005, 0.0), friction=0.5))
    block = trimesh.creation.box(extents=(0.3, 0.15, 0.3)).subdivide().subdivide()
    world.add(wsim.EolBody(block, wsim.ElasticMaterial(E=5.0e4, nu=0.3, rho=500.0), resolution=8, name="eol_block",
                           position=(0.25, 0.0755, 0.0), damping=50.0))
    ball = (trimesh.creation.icosphere(subdivisions=2, radius=0.08) if mesh is None
            else wmesh.load_fitted(mesh, 0.16))
    label = wmesh.display_name(ball, "ball")  # a --mesh model's file stem: bunny_on_cube, ...
    ball = ball.copy()
    ball.apply_translation(-ball.bounding_box.centroid)
    material = wsim.ElasticMaterial(E=2.0e5, nu=0.3, rho=600.0)
    for target, at in (("cube", (-0.23, 0.45, 0.02)), ("block", (0.22, 0.4, -0.03)), ("ball", (-0.2, 0.75, 0.0))):
        world.add(wsim.PbdBody(ball, material, tets="auto", name=f"{label}_on_{target}", position=at, damping=0.01))
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
