"""EoL scene: 16 soft objects dropped into a bin pile up (Fan et al., Table II, "16 Penguins").

    wsim run scenes/eol_pile.py -o eol_pile.usda
    wsim run scenes/eol_pile.py -o eol_pile.usda --mesh path/to/model.obj   # 16 of your model, 0.2 m

Sixteen soft bodies (spheres, boxes, capsules and cylinders of about 0.2 m; E = 50 kPa,
nu = 0.3, rho = 500 kg/m^3, light damping; friction 0.4 between them) fall in four layers of four
into a 0.6 x 0.6 m bin (a ground plane and four static wall meshes) and settle into a pile. Bodies
that may touch step together with one dt and one contact QP (Eqs. 27-29 across objects, as in the
paper); the walls and ground hold them with friction 0.4 too (the paper's colliders are
frictionless; EoL bodies feel a collider's friction since 2026-11-28). ``resolution`` (cells
across each body) is the knob: 6 here so a CPU runs it in
minutes; the paper's Table II uses 32 (``build(resolution=32)``, a GPU's job).
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

import wsim
from wsim import mesh as wmesh

FRAMES = 45
FPS = 30
RESOLUTION = 6
BIN = 0.6  # inner width of the bin [m]


def _shapes(mesh: str | None) -> list[trimesh.Trimesh]:
    if mesh is not None:
        return [wmesh.load_fitted(mesh, 0.2)]
    return [trimesh.creation.icosphere(subdivisions=2, radius=0.1),
            trimesh.creation.box(extents=(0.17, 0.17, 0.17)).subdivide(),
            trimesh.creation.capsule(height=0.1, radius=0.07, count=(12, 12)),
            trimesh.creation.cylinder(radius=0.09, height=0.15, sections=16)]


def build(mesh: str | None = None, device: str | None = None, resolution: int = RESOLUTION) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, -9.81, 0.0), device=device)
    world.add_collider(wsim.GroundPlane(0.0, friction=0.4, size=2.0))
    t, h = 0.05, 0.5  # wall thickness and height [m]
    for name, centre, extents in (("wall_x0", (-(BIN + t) / 2, h / 2, 0.0), (t, h, BIN + 2 * t)),
                                  ("wall_x1", ((BIN + t) / 2, h / 2, 0.0), (t, h, BIN + 2 * t)),
                                  ("wall_z0", (0.0, h / 2, -(BIN + t) / 2), (BIN, h, t)),
                                  ("wall_z1", (0.0, h / 2, (BIN + t) / 2), (BIN, h, t))):
        wall = trimesh.creation.box(extents=extents)
        wall.apply_translation(centre)
        world.add_collider(wsim.MeshCollider(wall, friction=0.4, name=name))
    rng = np.random.default_rng(7)
    shapes = _shapes(mesh)
    label = wmesh.display_name(shapes[0], "body")  # a --mesh model's file stem: bunny_00, bunny_01, ...
    material = wsim.ElasticMaterial(E=5.0e4, nu=0.3, rho=500.0)
    for i in range(16):
        layer, slot = divmod(i, 4)
        shape = shapes[i % len(shapes)].copy()
        shape.apply_translation(-shape.bounds.mean(axis=0))
        x = (slot % 2 - 0.5) * 0.27 + rng.uniform(-0.02, 0.02)
        z = (slot // 2 - 0.5) * 0.27 + rng.uniform(-0.02, 0.02)
        world.add(wsim.EolBody(shape, material, resolution=resolution, name=f"{label}_{i:02d}",
                               position=(x, 0.15 + 0.27 * layer, z), rotation=Rotation.random(random_state=rng).as_matrix(),
                               damping=20.0, friction=0.4))
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
