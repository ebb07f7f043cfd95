"""BEM scene: a beam-like bar and a torus set ringing by a brief squeeze (paper Figs. 4-5 bodies).

    wsim run scenes/bem_squeeze.py -o bem_squeeze.usda
    wsim run scenes/bem_squeeze.py -o bem_squeeze.usda --mesh path/to/model.obj   # replaces the torus

Both float in zero gravity (no ground: BEM contact comes with the constraints issue). For the
first 0.1 s a pressure squeezes each from two opposite sides: the bar (0.6 x 0.1 x 0.1 m,
mu = 3e4 Pa, nu = 0.45) across its middle third, the torus (R = 0.1, r = 0.05 m, the paper's
Table 1 material: rho = 500, mu = 5e4, nu = 0.48) across its ring. Released, they ring with
their own modes, damped by BDF1. The squeeze is balanced, so the frames stay put and the
error correction only removes drift.
"""

from __future__ import annotations

import numpy as np

import wsim
from wsim import mesh as wmesh

FRAMES = 45
FPS = 30
SQUEEZE = 0.1  # s


def squeeze(body: wsim.BemBody, axis: int, pressure: float, region) -> None:
    """Pressure on the vertices in ``region`` whose normals face +/- ``axis``, for the first SQUEEZE s."""
    n, x = body.rest_normals, body.rest_vertices
    facing = (np.abs(n[:, axis]) > 0.5) & region(x)
    load = -pressure * n * facing[:, None]
    body.add_traction(lambda t: load if t <= SQUEEZE else np.zeros_like(load))


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, 0.0, 0.0), device=device)
    bar = wmesh.beam(length=0.6, width=0.1, height=0.1, divisions=(12, 2, 2))
    bar.apply_translation((-0.3, 0.0, 0.0))
    bar_body = world.add(wsim.BemBody(bar, wsim.ElasticMaterial(mu=3.0e4, nu=0.45, rho=1000.0), 1.0 / 300.0,
                                      name="bar", position=(0.0, 0.5, -0.3), double_nodes=60.0))
    squeeze(bar_body, 1, 3.0e3, lambda x: np.abs(x[:, 0]) < 0.1)
    if mesh is None:
        ring = wmesh.torus(major_radius=0.1, minor_radius=0.05, major_sections=24, minor_sections=8)
    else:
        ring = wmesh.load_fitted(mesh, 0.3)
    ring_body = world.add(wsim.BemBody(ring, wsim.ElasticMaterial(mu=5.0e4, nu=0.48, rho=500.0), 1.0 / 600.0,
                                       name=wmesh.display_name(ring, "torus"), position=(0.0, 0.5, 0.3)))
    squeeze(ring_body, 0, 4.0e3, lambda x: np.ones(len(x), dtype=bool))
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
