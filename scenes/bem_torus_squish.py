"""BEM scene: a torus squished from both sides by driven points, then held (paper Fig. 4).

    wsim run scenes/bem_torus_squish.py -o bem_torus_squish.usda
    wsim run scenes/bem_torus_squish.py -o bem_torus_squish.usda --mesh path/to/model.obj   # fitted to 0.3 m

A torus (R = 0.1 m, r = 0.05 m; the paper's material: rho = 500, shear modulus 5e4 Pa, nu = 0.48;
dt = 2 ms) floats without gravity. The vertices of its two outer sides along x are driven
inwards by 2 cm each over 0.3 s (``BemBody.fix`` with a target function), then held still: the
rest of the ring keeps moving, the dynamic secondary motion of Fig. 4. As in the paper, the
frame update is off for this scene.
"""

from __future__ import annotations

import numpy as np

import wsim
from wsim import mesh as wmesh

FRAMES = 45
FPS = 30
SQUISH = 0.3  # s
DEPTH = 0.02  # m per side


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, 0.0, 0.0), device=device)
    if mesh is None:
        ring = wmesh.torus(major_radius=0.1, minor_radius=0.05, major_sections=24, minor_sections=8)
    else:
        ring = wmesh.load_fitted(mesh, 0.3)
    ring.apply_translation((0.0, 0.5, 0.0))
    body = world.add(wsim.BemBody(ring, wsim.ElasticMaterial(mu=5.0e4, nu=0.48, rho=500.0), 0.002,
                                  name=wmesh.display_name(ring, "torus"),
                                  frame_update=False))
    x = ring.vertices[:, 0]
    span = x.max() - x.min()
    sides = np.flatnonzero(np.abs(x - 0.5 * (x.max() + x.min())) > 0.42 * span)
    start = ring.vertices[sides].copy()
    inward = -np.sign(start[:, 0] - 0.5 * (x.max() + x.min()))

    def target(t: float) -> np.ndarray:
        s = min(t / SQUISH, 1.0)
        out = start.copy()
        out[:, 0] += inward * DEPTH * (3.0 * s**2 - 2.0 * s**3)  # eased in and out
        return out

    body.fix(sides, target)
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
