"""Showcase: bodies of all three methods and a PDE reconstruction fall onto each other and are
swept by a kinematic paddle - what wsim is.

    wsim run scenes/showcase.py -o showcase.usda
    wsim run scenes/showcase.py -o showcase.usda --mesh path/to/model.obj   # the PBD creatures, 0.3 m

On the ground: a BEM jelly cube (0.25 m, surface-only elastodynamics, shear modulus 50 kPa) and
an EoL block (0.4 x 0.15 x 0.3 m, E = 50 kPa, Eulerian grid in a rigid frame). Falling onto them
and onto each other: an EoL ball (0.24 m), two PBD fish (0.3 m, tetrahedral XPBD) and a PBD
ball. From 1 s a kinematic paddle sweeps in and pushes the cube, the fish and the ball into the
block. Beside
them, a PDE reconstruction (Fang et al. 2021) replays a third PBD fish dropped on the ground from
14 keyframes (every 8th frame) and the closed-form curves between them; it is playback of its own
private simulation, so it meets the ground and the paddle only as that simulation did.

Every pair touches: PBD with PBD in lockstep substeps, the two EoL bodies in one contact QP with
one dt (Eqs. 27-29 of the EoL paper across objects), EoL keeping out of BEM with its contact rows
and PBD keeping out of BEM and EoL; across methods the pushed body is handed the opposite impulse
one coupling interval later (explicit coupling, momentum exact; ``World(coupling_dt=None)`` picks
the interval). Friction 0.5.
"""

from __future__ import annotations

import numpy as np
import trimesh

import wsim
from wsim import mesh as wmesh

FRAMES = 105
FPS = 30


def paddle_pose(t: float) -> np.ndarray:
    """A box paddle that waits at x = -1.2 m until 1 s, then sweeps +x at 0.6 m/s."""
    m = np.eye(4)
    m[0, 3] = -1.2 + 0.6 * max(t - 1.0, 0.0)
    m[1, 3] = 0.2  # its bottom edge 5 cm above the ground: a cube pinched at its base edge by both fights the solver
    return m


def _creature(mesh: str | None) -> trimesh.Trimesh:
    shape = wmesh.fish(length=0.3, subdivisions=2) if mesh is None else wmesh.load_fitted(mesh, 0.3)
    shape = shape.copy()
    shape.apply_translation(-shape.bounding_box.centroid)
    return shape


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, -9.81, 0.0), device=device)
    world.add_collider(wsim.GroundPlane(0.0, friction=0.5, size=4.0))
    world.add_collider(wsim.MeshCollider(trimesh.creation.box(extents=(0.1, 0.3, 1.4)), transform=paddle_pose,
                                         friction=0.3, name="paddle"))
    jelly = wsim.ElasticMaterial(mu=5.0e4, nu=0.45, rho=1000.0)
    world.add(wsim.BemBody(trimesh.creation.box(extents=(0.25, 0.25, 0.25)).subdivide(), jelly, 1.0 / (FPS * 8),
                           name="bem_cube", position=(-0.35, 0.1255, 0.0), friction=0.5))
    soft = wsim.ElasticMaterial(E=5.0e4, nu=0.3, rho=500.0)
    world.add(wsim.EolBody(trimesh.creation.box(extents=(0.4, 0.15, 0.3)).subdivide().subdivide(), soft, resolution=8,
                           name="eol_block", position=(0.25, 0.0755, 0.0), damping=30.0, friction=0.5))
    world.add(wsim.EolBody(trimesh.creation.icosphere(subdivisions=2, radius=0.12), soft, resolution=6, name="eol_ball",
                           position=(0.28, 0.5, 0.02), velocity=(0.0, -0.5, 0.0), damping=30.0, friction=0.5))
    creature = _creature(mesh)
    fish = wmesh.display_name(creature, "fish")  # a --mesh model's file stem: pbd_bunny_a, ...
    rubber = wsim.ElasticMaterial(E=2.0e5, nu=0.3, rho=600.0)
    for name, at, spin in ((f"pbd_{fish}_a", (-0.33, 0.45, 0.03), (0.0, 2.0, 1.0)),
                           (f"pbd_{fish}_b", (0.2, 0.85, -0.04), (1.5, 0.0, 0.0))):
        world.add(wsim.PbdBody(creature, rubber, tets="auto", name=name, position=at, angular_velocity=spin,
                               damping=0.01))
    world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=2, radius=0.08), rubber, tets="auto", name="pbd_ball",
                           position=(-0.3, 0.8, -0.02), damping=0.01))
    twin = wsim.PbdBody(creature, rubber, name=f"{fish}_replayed", position=(0.0, 0.5, 0.6),
                        angular_velocity=(0.0, 1.0, 2.5), damping=0.01)
    world.add(wsim.PbdReconstruction(twin, stride=8, basis="pde", frames=FRAMES, fps=FPS))
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
