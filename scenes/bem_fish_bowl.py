"""BEM scene: soft fish fall into a bowl and onto each other (James & Pai's surface-only BEM paper, Fig. 1).

    wsim run scenes/bem_fish_bowl.py -o fish_bowl.usda
    wsim run scenes/bem_fish_bowl.py -o fish_bowl.usda --mesh path/to/fish.obj   # your model, 0.2 m long

Six procedural fish (a stretched sphere with a flattened, flaring tail, 0.2 m long; rho = 1000
kg/m^3, shear modulus 30 kPa, nu = 0.45, dt = 5 ms) fall, tilted and spinning, into a bowl (a
static, closed mesh collider, 0.64 m across) and onto each other. They are instances of one
operator set: the dense history matrices are built (or loaded from the cache) once and shared.
Contact between fish (``wsim.contact``) and with the bowl is one constraint solve per step for the
fish that touch, friction 0.4. ``build(count=..., detail=...)`` is the knob: the default is
scaled to run on a CPU in minutes (42-vertex fish); the paper's 25 fish at ``detail=3``
(642 vertices each) are a GPU's job.
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
R_OUT, R_IN = 0.32, 0.25  # the bowl's outer and inner radius [m]: a wall thicker than a fall in one step


def fish(detail: int = 1, length: float = 0.2) -> trimesh.Trimesh:
    """A closed fish-like surface along x: an ellipsoid whose rear third flattens (z) and flares
    (y) into a tail."""
    m = trimesh.creation.icosphere(subdivisions=detail, radius=1.0)
    v = m.vertices.copy()
    s = np.clip(-v[:, 0] - 0.35, 0.0, None)  # 0 ahead of the tail, growing towards its end
    v[:, 1] *= 0.4 * (1.0 + 2.5 * s)
    v[:, 2] *= 0.25 / (1.0 + 3.0 * s)
    m.vertices = v * (0.5 * length)
    return m


def bowl(sections: int = 32) -> trimesh.Trimesh:
    """A closed, thick-walled hemispherical bowl standing on y = 0, rim up."""
    a = np.linspace(-np.pi / 2, 0.0, 12)
    outer = np.column_stack([R_OUT * np.cos(a), R_OUT * np.sin(a)])
    inner = np.column_stack([R_IN * np.cos(a), R_IN * np.sin(a)])[::-1]
    profile = np.vstack([outer, inner])
    profile[[0, -1], 0] = 0.0  # both ends on the axis: a closed solid of revolution
    m = trimesh.creation.revolve(profile, sections=sections)
    m.vertices = m.vertices @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]) + [0.0, R_OUT, 0.0]  # z -> y
    return m


def build(mesh: str | None = None, device: str | None = None, count: int = 6, detail: int = 1) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, -9.8, 0.0), device=device)
    world.add_collider(wsim.GroundPlane(0.0, friction=0.4))
    world.add_collider(wsim.MeshCollider(bowl(), friction=0.4, name="bowl"))
    shape = fish(detail) if mesh is None else wmesh.load_fitted(mesh, 0.2)
    label = wmesh.display_name(shape, "fish")  # a --mesh model's file stem: bunny_00, bunny_01, ...
    shape = shape.copy()
    shape.apply_translation(-shape.bounding_box.centroid)
    material = wsim.ElasticMaterial(mu=3.0e4, nu=0.45, rho=1000.0)
    dt = 0.005
    ops = build_operators(shape, material, dt, device=world.device)
    rng = np.random.default_rng(5)
    for k in range(count):
        angle = 2.4 * k
        r = 0.08 * np.sqrt(k % 6) / 2.0
        world.add(wsim.BemBody(shape, material, dt, operators=ops, name=f"{label}_{k:02d}", friction=0.4,
                               position=(r * np.cos(angle), 0.42 + 0.1 * k, r * np.sin(angle)),
                               rotation=rodrigues(rng.normal(size=3) * 0.8),
                               angular_velocity=rng.normal(size=3) * 1.5))
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
