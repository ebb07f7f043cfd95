"""EoL scene: a plastic cylinder pressed by a kinematic rod (Fan et al., Fig. 1c).

    wsim run scenes/eol_plastic_cylinder.py -o eol_cylinder.usda
    wsim run scenes/eol_plastic_cylinder.py -o eol_cylinder.usda --mesh path/to/model.obj   # your closed mesh

A cylinder (0.5 m across, 0.8 m long; E = 50 kPa, nu = 0.3, rho = 500 kg/m^3) stands on the
ground. A rod lying across it presses down 35 % of its height over 1 s, holds, and lifts away.
Above a yield stress of 3 kPa the material flows (Eqs. 34-37, F_p stored per material point):
the cylinder keeps a dent and a bulge, its volume within a few percent. The rigid Lagrangian frame
carries the body; the Eulerian grid (16 cells along the height) the dent. Surface triangles are
split to the grid spacing so the exported surface shows the dent (trimesh's cylinder has long
slivers; contact samples would be subdivided by EolBody anyway).
"""

from __future__ import annotations

import numpy as np
import trimesh

import wsim
from wsim import mesh as wmesh

FRAMES = 75
FPS = 30
RESOLUTION = 16
HEIGHT = 0.8


def rod_pose(t: float) -> np.ndarray:
    """Rod along z, above the cylinder's top: down 35 % over 1 s, hold 0.5 s, up at 0.5 m/s."""
    press = 0.35 * HEIGHT * min(t / 1.0, 1.0) if t < 1.5 else max(0.35 * HEIGHT - 0.5 * (t - 1.5), -0.3)
    M = np.eye(4)
    M[1, 3] = HEIGHT + 0.06 - press
    return M


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, -9.81, 0.0), device=device)
    world.add_collider(wsim.GroundPlane(0.0))
    rod = trimesh.creation.cylinder(radius=0.06, height=1.2, sections=24)  # along z
    world.add_collider(wsim.MeshCollider(rod, transform=rod_pose, name="rod"))
    if mesh is None:
        shape = trimesh.creation.cylinder(radius=0.25, height=HEIGHT, sections=32)
        shape.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))  # axis up
    else:
        shape = wmesh.load_fitted(mesh, HEIGHT).copy()
    label = wmesh.display_name(shape, "cylinder")  # before the remesh below, which drops the file's name
    shape.apply_translation(np.array([0.0, HEIGHT / 2, 0.0]) - shape.bounds.mean(axis=0))
    # triangles below the grid spacing: the exported surface can follow the dent
    shape = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(shape.vertices, shape.faces, HEIGHT / RESOLUTION))
    world.add(
        wsim.EolBody(
            shape,
            wsim.ElasticMaterial(E=5.0e4, nu=0.3, rho=500.0),
            resolution=RESOLUTION,
            lagrangian="rigid",
            name=label,
            plasticity=wsim.Plasticity(yield_stress=3.0e3, flow_rate=100.0),
            damping=20.0,
        )
    )
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
