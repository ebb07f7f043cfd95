"""EoL knob study: a spinning ball thrown sideways onto the ground (``tools/study_eol.py``'s drop).

An icosphere (subdivisions 2, radius 0.5 m; E = 1e5 Pa, nu = 0.3, rho = 1000 kg/m^3, Kelvin-Voigt
damping 20 Pa s, the damping of ``tools/bench_eol.py``, at which the CFL bound sets dt in contact)
with its centre at y = 0.7 m, moving sideways at 0.5 m/s and spinning at 2 rad/s about z, falls
onto a ground plane; 30 fps, 0.5 s (the fall, the impact at ~0.2 s and the rebound). The surface
mesh lives in material space, so vertex i is the same material point at every grid resolution;
the signature is the positions of the 42 vertices of the subdivision-1 icosphere (kept by the
subdivision-2 one) after every frame.

Knobs (``EolBody``'s): ``resolution`` (grid cells across the body), ``advection`` ("semi-lagrangian"
or "bfecc"), ``cfl`` and ``dt_max`` (the cap on the step) [s].
"""

from __future__ import annotations

from typing import Any

import trimesh

import wsim
from wsim.studies.common import Mode, StudySpec, StudyWorld, match_points

FRAMES = 15
RADIUS = 0.5  # [m]
MATERIAL = dict(E=1.0e5, nu=0.3, rho=1000.0)

SPEC = StudySpec(
    name="eol",
    title="EoL: grid resolution, advection, CFL number, step cap",
    scenario="An elastic ball (R = 0.5 m, E = 100 kPa, damping 20 Pa s) thrown sideways at 0.5 m/s, spinning at "
             "2 rad/s, dropped 0.2 m onto the ground; 30 fps, 0.5 s.",
    error="the largest distance, over 42 material points of the surface and every frame, between a setting's "
          "positions and the reference's, over the ball's diameter (1 m)",
    scale=2.0 * RADIUS,
    costs={"ms_per_frame": "ms per frame", "model_mb": "grid and state, host + device [MB]"},
    knobs={"resolution": "EolBody(resolution=...): grid cells across the body",
           "advection": "EolBody(advection=...): 'semi-lagrangian' or 'bfecc'",
           "cfl": "EolBody(cfl=...): CFL number of the step (Eq. 30)",
           "dt_max": "EolBody(dt_max=...): cap on the step [s] (None: the elastic and viscous caps only)"},
    # the check halves dt_max. Measured on the CPU (15 frames, all surface points, over the diameter):
    # semi-Lagrangian at 12 cells, cfl 0.2: dt_max 3e-4 against 1.5e-4 0.17 %, 1.5e-4 against 7.5e-5
    # 0.41 %, while the default (6 cells) lies 3.0 % from the 7.5e-5 run. BFECC does not converge in
    # the step here: at 12 cells, cfl 0.2, 3e-4 against 1.5e-4 moved 3.44 %, and 7.5e-5 stopped with
    # the step collapsed at frame 15 (16 cells at 3e-4 too). So the references advect semi-Lagrangian.
    quick=Mode(default={}, grid={"resolution": [8], "advection": ["bfecc"], "cfl": [0.2, 0.8], "dt_max": [1e-3]},
               reference={"resolution": 12, "advection": "semi-lagrangian", "cfl": 0.2, "dt_max": 3e-4},
               frames=FRAMES, check={"dt_max": 1.5e-4}),
    full=Mode(default={"resolution": 16},
              grid={"resolution": [8, 12, 24], "advection": ["bfecc"], "cfl": [0.2, 0.8], "dt_max": [1e-3, 3e-4]},
              reference={"resolution": 32, "advection": "semi-lagrangian", "cfl": 0.2, "dt_max": 3e-4},
              frames=FRAMES, check={"dt_max": 1.5e-4}),
    check_note="the reference with dt_max halved",
    notes="The reference advects semi-Lagrangian: BFECC did not converge in the step on this scene (at 12 "
          "cells, cfl 0.2, halving dt_max from 3e-4 moved it 3.44 % of the diameter, and 7.5e-5 stopped with the "
          "step collapsed after the impact), where semi-Lagrangian moved 0.17 % and 0.41 % at the next two "
          "halvings. The bfecc row is therefore judged against a semi-Lagrangian reference.",
)


def build(mesh: Any = None, device: str | None = None, resolution: int = 6, advection: str = "semi-lagrangian",
          cfl: float = 0.5, dt_max: float | None = None) -> StudyWorld:
    if mesh is not None:
        raise wsim.InvalidParameter("the EoL study runs its own ball (mesh=None)")
    ball = trimesh.creation.icosphere(subdivisions=2, radius=RADIUS)
    probes = match_points(ball.vertices, trimesh.creation.icosphere(subdivisions=1, radius=RADIUS).vertices,
                          "eol study")
    ball.apply_translation((0.0, 0.7, 0.0))
    world = StudyWorld(fps=30.0, gravity=(0.0, -9.81, 0.0), device=device,
                       signature=lambda w: w.bodies[0].points()[probes])
    world.add_collider(wsim.GroundPlane(0.0))
    world.add(wsim.EolBody(ball, wsim.ElasticMaterial(**MATERIAL), name="ball", resolution=resolution,
                           advection=advection, cfl=cfl, dt_max=dt_max, damping=20.0, velocity=(0.5, 0.0, 0.0),
                           angular_velocity=(0.0, 0.0, 2.0)))
    return world


def metrics(world: StudyWorld) -> dict:
    out = world.measures()
    body = world.bodies[0]
    out["steps"] = int(body.steps)
    return out
