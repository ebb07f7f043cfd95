"""BEM scene: a beam twisted by its ends, as one body and as five joined subdomains (paper Fig. 9).

    wsim run scenes/bem_twisted_beam.py -o bem_twisted_beam.usda
    wsim run scenes/bem_twisted_beam.py -o bem_twisted_beam.usda --mesh path/to/piece.obj   # a subdomain, fitted to 0.1 m

Two 0.5 m x 0.1 m x 0.1 m beams (rho = 1000 kg/m^3, shear modulus 1e5 Pa, nu = 0.45, dt = 5 ms)
float without gravity. Their end faces are driven (``BemBody.fix`` with target functions): each
end turns by 90 degrees about the beam's axis over 1.5 s, in opposite directions, then holds.
The first beam is one BEM body: linear elasticity cannot follow a rotation that large, and its
cross-sections balloon. The second is five 0.1 m cubes (one operator set) joined at their
interfaces by point joints (``wsim.bem.decompose``): each cube turns only a little relative to
its own frame, so the twist stays a twist.
"""

from __future__ import annotations

import numpy as np

import wsim
from wsim import mesh as wmesh
from wsim.bem import decompose
from wsim.rigid import rodrigues

FRAMES = 60
FPS = 30
TWIST = 1.5  # s
ANGLE = np.pi / 2.0  # each end
MATERIAL = wsim.ElasticMaterial(mu=1.0e5, nu=0.45, rho=1000.0)
DT = 0.005


def twist(body: wsim.BemBody, ids: np.ndarray, points: np.ndarray, axis_point: np.ndarray, sign: float) -> None:
    """Drive ``ids`` of ``body`` (at ``points``) about the x axis through ``axis_point``."""

    def target(t: float) -> np.ndarray:
        s = min(t / TWIST, 1.0)
        R = rodrigues(np.array([sign * ANGLE * (3.0 * s**2 - 2.0 * s**3), 0.0, 0.0]))
        return (points - axis_point) @ R.T + axis_point

    body.fix(ids, target)


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, 0.0, 0.0), device=device)
    # one body
    beam = wmesh.beam(0.5, 0.1, 0.1, (10, 2, 2))
    beam.apply_translation((-0.25, 0.6, -0.2))
    single = world.add(wsim.BemBody(beam, MATERIAL, DT, name="beam"))
    axis = np.array([0.0, 0.6, -0.2])
    x = beam.vertices[:, 0]
    for end, sign in ((x < x.min() + 1e-9, -1.0), (x > x.max() - 1e-9, 1.0)):
        ids = np.flatnonzero(end)
        twist(single, ids, beam.vertices[ids], axis, sign)
    # five subdomains
    cube = wmesh.beam(0.1, 0.1, 0.1, (2, 2, 2)) if mesh is None else wmesh.load_fitted(mesh, 0.1)
    cube.apply_translation(-cube.bounding_box.centroid)
    pieces = []
    for k in range(5):
        p = cube.copy()
        p.apply_translation((-0.2 + 0.1 * k, 0.6, 0.2))
        pieces.append(p)
    bodies, joints = decompose(pieces, MATERIAL, DT, name=wmesh.display_name(cube, "cubes"), device=world.device)
    for b in bodies:
        world.add(b)
    for j in joints:
        world.add_joint(j)
    axis = np.array([0.0, 0.6, 0.2])
    for body, piece, sign in ((bodies[0], pieces[0], -1.0), (bodies[-1], pieces[-1], 1.0)):
        xs = piece.vertices[:, 0]
        ids = np.flatnonzero(xs < xs.min() + 1e-9) if sign < 0 else np.flatnonzero(xs > xs.max() - 1e-9)
        twist(body, ids, piece.vertices[ids], axis, sign)
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
