"""Coupling-step study: a PBD ball thrown at a BEM cube (``tools/study_coupling.py``'s ``throw``).

A tetrahedral PBD ball (icosphere subdivisions 2, R = 0.1 m, E = 2e5 Pa, nu = 0.3, rho = 1000
kg/m^3, 10 substeps a frame) and a 26-node BEM cube (0.2 m, E = 1e6 Pa, nu = 0.3, dt = 1/1920 s:
32 steps a frame) fly at each other at 1 m/s in zero gravity and meet after ~3 frames; 60 fps,
20 frames. They touch through the World's explicit coupling: the ball keeps itself out of the
cube's moving surface and the cube gets the opposite impulse one coupling interval later, so the
interval (``World(coupling_dt=...)``) sets the lag. The signature is the positions of every vertex
of both bodies after every frame.

Knob: ``coupling_dt`` [s] (None: the World's automatic choice). The reference is the shortest
interval there is, one BEM step (1/1920 s).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import trimesh

import wsim
from wsim.studies.common import Mode, StudySpec, StudyWorld

FRAMES = 20
FPS = 60.0
BEM_DT = 1.0 / 1920.0  # [s] divides every interval studied
BALL_RADIUS = 0.1  # [m]

SPEC = StudySpec(
    name="coupling",
    title="Coupling step across methods (PBD ball against a BEM cube)",
    scenario="A tetrahedral PBD ball (R = 0.1 m) and a 26-node BEM cube (0.2 m, 32 steps a frame) thrown at each "
             "other at 1 m/s in zero gravity; 60 fps, 20 frames.",
    error="the largest distance, over every vertex of both bodies and every frame, between a setting's positions "
          "and the reference's, over the ball's diameter (0.2 m)",
    scale=2.0 * BALL_RADIUS,
    costs={"ms_per_frame": "ms per frame"},
    knobs={"coupling_dt": "World(coupling_dt=...) [s]: the interval at which the bodies exchange contact "
                          "(None: automatic)"},
    quick=Mode(default={}, grid={"coupling_dt": [1.0 / FPS, 1.0 / (4 * FPS), 1.0 / (16 * FPS)]},
               reference={"coupling_dt": BEM_DT}, frames=FRAMES),
    full=Mode(default={}, grid={"coupling_dt": [1.0 / (k * FPS) for k in (1, 2, 4, 8, 16)]},
              reference={"coupling_dt": BEM_DT}, frames=FRAMES),
    check_note="none possible: the reference's interval is one BEM step, the shortest the World exchanges contact at, "
               "and a shorter BEM dt would change the cube itself",
    notes="The reference's own error is unknown (no reference check exists). The errors need not fall as "
          "coupling_dt shrinks, and they do not: each interval times the contact differently (the step at which "
          "the bodies are found touching and the impulse lands), so the rebound's timing, and with it the "
          "positions, shift by an amount that is not monotone in the interval. Read the errors as how far each "
          "interval's contact lands from the shortest one's, not as convergence.",
)


def build(mesh: Any = None, device: str | None = None, coupling_dt: float | None = None) -> StudyWorld:
    if mesh is not None:
        raise wsim.InvalidParameter("the coupling study runs its own bodies (mesh=None)")

    def signature(world: wsim.World) -> np.ndarray:
        return np.concatenate([b.points() for b in world.bodies])

    world = StudyWorld(fps=FPS, gravity=(0.0, 0.0, 0.0), device=device, coupling_dt=coupling_dt,
                       signature=signature)
    cube = trimesh.creation.box(extents=(0.2, 0.2, 0.2)).subdivide()
    world.add(wsim.BemBody(cube, wsim.ElasticMaterial(E=1.0e6, nu=0.3, rho=1000.0), BEM_DT, name="cube",
                           position=(0.2, 0.03, 0.0), velocity=(-1.0, 0.0, 0.0), cache=False, progress=False))
    world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=2, radius=BALL_RADIUS),
                           wsim.ElasticMaterial(E=2.0e5, nu=0.3, rho=1000.0), tets="auto", name="ball",
                           position=(-0.15, 0.0, 0.0), velocity=(1.0, 0.0, 0.0), cache=False))
    return world


def metrics(world: StudyWorld) -> dict:
    out = world.measures()
    ball = world.bodies[1]
    out["ball_vx"] = float(ball.linear_momentum()[0] / ball.masses.sum())  # rebound [m/s]; elastic bound -1.66
    out["coupling_steps"] = int(world.coupling_steps)
    return out
