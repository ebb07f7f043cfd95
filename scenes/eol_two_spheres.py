"""EoL scene: two elastic spheres collide head-on and part (Fan et al., Fig. 1b and Table II, "2 Spheres").

    wsim run scenes/eol_two_spheres.py -o eol_two_spheres.usda
    wsim run scenes/eol_two_spheres.py -o eol_two_spheres.usda --mesh path/to/model.obj   # two of your model, 0.5 m

Two soft balls (0.5 m across; E = 50 kPa, nu = 0.3, rho = 500 kg/m^3, light Kelvin-Voigt damping)
fly at each other at 2 m/s each in zero gravity, 5 cm off centre, squash flat against each other
and part spinning. Each body's rigid Lagrangian frame carries its flight; its Eulerian grid
(``resolution`` cells across: 12 here so a CPU runs it in about a minute; the paper's Table II
uses 32, ``build(resolution=32)``) carries the squash. Once they may touch, the two step
together with one dt and one contact QP (Eqs. 27-29 across objects: every sample of either
surface inside the other makes a row on both bodies' velocities); Coulomb friction 0.3 between
them.
"""

from __future__ import annotations

import trimesh

import wsim
from wsim import mesh as wmesh

FRAMES = 36
FPS = 60
RESOLUTION = 12


def build(mesh: str | None = None, device: str | None = None, resolution: int = RESOLUTION) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, 0.0, 0.0), device=device)
    shape = trimesh.creation.icosphere(subdivisions=3, radius=0.25) if mesh is None else wmesh.load_fitted(mesh, 0.5)
    model = wmesh.display_name(shape, "")  # a --mesh model's file stem: bunny_left, bunny_right
    shape = shape.copy()
    shape.apply_translation(-shape.bounds.mean(axis=0))
    material = wsim.ElasticMaterial(E=5.0e4, nu=0.3, rho=500.0)
    for side, x, y, v in (("left", -0.4, 0.0, 2.0), ("right", 0.4, 0.05, -2.0)):
        world.add(wsim.EolBody(shape, material, resolution=resolution, name=f"{model}_{side}" if model else side,
                               position=(x, y, 0.0), velocity=(v, 0.0, 0.0), damping=20.0, friction=0.3))
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
