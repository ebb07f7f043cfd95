"""Default scene: a soft fish-like body dropped on the ground, then pushed along by a paddle.

    wsim run scenes/soft_drop.py -o soft_drop.usda
    wsim run scenes/soft_drop.py -o soft_drop.usda --mesh path/to/model.obj   # your own closed mesh

The body is a surface-only XPBD soft body (edge stretch, dihedral bending, global volume);
the paddle is a kinematic box collider that sweeps in from the side after the landing.
"""

from __future__ import annotations

import numpy as np
import trimesh

import wsim
from wsim import mesh as wmesh

FRAMES = 90


def paddle_pose(t: float) -> np.ndarray:
    """Box paddle: waits at x = -0.9 m for 1 s, then sweeps +x at 0.6 m/s (reaches the body at ~2 s)."""
    m = np.eye(4)
    m[0, 3] = -0.9 + 0.6 * max(t - 1.0, 0.0)
    m[1, 3] = 0.2
    return m


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=30, gravity=(0.0, -9.81, 0.0), device=device)
    world.add_collider(wsim.GroundPlane(height=0.0, friction=0.6))
    paddle = trimesh.creation.box(extents=(0.1, 0.4, 1.2))
    world.add_collider(wsim.MeshCollider(paddle, transform=paddle_pose, friction=0.3, name="paddle"))
    if mesh is None:
        shape = wmesh.fish(length=0.8, subdivisions=3)
    else:
        shape = wmesh.load_fitted(mesh, 0.8)  # a user model: 0.8 m long, centred above the origin
    lift = 0.5 - float(np.min(shape.vertices[:, 1]))
    world.add(
        wsim.PbdBody(
            shape,
            wsim.ElasticMaterial(E=2.0e5, nu=0.4, rho=800.0),
            name=wmesh.display_name(shape, "fish"),
            position=(0.0, lift, 0.0),
            velocity=(0.0, -1.0, 0.0),
            angular_velocity=(0.0, 1.5, 2.0),
            substeps=10,
            iterations=2,
        )
    )
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
