"""BEM scene: three bodies launched along the floor with friction 0.2, 0.4 and 0.6 (paper Fig. 8).

    wsim run scenes/bem_friction.py -o bem_friction.usda
    wsim run scenes/bem_friction.py -o bem_friction.usda --mesh path/to/bunny.obj   # fitted to 0.15 m

Three copies of one body (one operator set) slide side by side along the ground at 1.5 m/s,
released 5 mm above it; the BEM authors' bunny_friction settings: rho = 3000 kg/m^3, shear
modulus 1e6 Pa, nu = 0.3, dt = 3 ms. The body's friction coefficient combines with the floor's
(0.1) by the maximum, as in their code; with Coulomb friction mu g decelerates each body, so
the one with 0.6 stops first and the one with 0.2 slides three times as far (v^2 / (2 mu g):
0.57, 0.29, 0.19 m). The default body is a 0.15 m bumpy block; ``--mesh`` takes a model (the
authors' bunny, say), stood on its lowest point.
"""

from __future__ import annotations


import wsim
from wsim import mesh as wmesh
from wsim.bem import build_operators

FRAMES = 45
FPS = 30
MU = (0.2, 0.4, 0.6)


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=FPS, gravity=(0.0, -9.8, 0.0), device=device)
    world.add_collider(wsim.GroundPlane(0.0, friction=0.1))
    shape = wmesh.bumpy_cube(size=0.15, divisions=3, amplitude=0.005) if mesh is None else wmesh.load_fitted(mesh, 0.15)
    model = wmesh.display_name(shape, "")  # a --mesh model's file stem: bunny_mu_0, bunny_mu_1, ...
    material = wsim.ElasticMaterial(mu=1.0e6, nu=0.3, rho=3000.0)
    dt = 0.003
    ops = build_operators(shape, material, dt, device=world.device)
    lift = 0.005 - shape.bounds[0, 1]
    for k, mu in enumerate(MU):
        world.add(wsim.BemBody(shape, material, dt, operators=ops, friction=mu,
                               name=f"{model}_mu_{k}" if model else f"mu_{k}",
                               position=(-0.4 - shape.bounding_box.centroid[0], lift, 0.25 * (k - 1)),
                               velocity=(1.5, 0.0, 0.0)))
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
