"""PBD knob study: a cantilever released under gravity, swinging on its clamped root.

A beam 0.6 x 0.1 x 0.1 m (E = 1e6 Pa, nu = 0.3, rho = 1000 kg/m^3), tetrahedralized
(``tets="auto"``), its root face x = 0 pinned, starts straight and level and swings down under
gravity; 30 fps, 1 s. Its static tip deflection by beam theory is rho g A L^4 / (8 E I) = 0.19 m,
so the swing is a large deformation. XPBD's effective stiffness depends on substeps and iterations
(too few leave it soft: the tip falls further) and the tets' on the mesh, so all three change the
swing. The signature is the positions of the coarsest beam's 28 vertices (kept by every finer
beam) after every frame.

Knobs: ``substeps`` and ``iterations`` (``PbdBody``'s), and the mesh: ``divisions`` = cells
across the beam's width (6 times as many along it).
"""

from __future__ import annotations

from typing import Any

import numpy as np

import wsim
from wsim import mesh as wmesh
from wsim.studies.common import Mode, StudySpec, StudyWorld, match_points

FRAMES = 30
LENGTH, WIDTH = 0.6, 0.1  # [m]
MATERIAL = dict(E=1.0e6, nu=0.3, rho=1000.0)

SPEC = StudySpec(
    name="pbd",
    title="PBD: substeps, iterations, mesh",
    scenario="A tetrahedral cantilever (0.6 x 0.1 x 0.1 m, E = 1 MPa, nu = 0.3), clamped at one end, released "
             "level under gravity; 30 fps, 1 s.",
    error="the largest distance, over the coarsest beam's 28 vertices and every frame, between a setting's "
          "positions and the reference's, over the beam's length (0.6 m)",
    scale=LENGTH,
    costs={"ms_per_frame": "ms per frame", "model_mb": "model and state, host + device [MB]"},
    knobs={"substeps": "PbdBody(substeps=...): substeps per frame",
           "iterations": "PbdBody(iterations=...): constraint sweeps per substep",
           "divisions": "cells across the beam (6x along it): 1, 2, 3, 4 = 28, 114, 295, 610 particles"},
    quick=Mode(default={}, grid={"substeps": [5, 20, 60], "iterations": [1, 4], "divisions": [1, 3]},
               reference={"substeps": 100, "iterations": 4, "divisions": 3}, frames=FRAMES,
               check={"substeps": 200}),
    full=Mode(default={"divisions": 3},
              grid={"substeps": [5, 20, 40, 80, 160], "iterations": [1, 4, 8], "divisions": [1, 2, 4]},
              reference={"substeps": 400, "iterations": 8, "divisions": 4}, frames=FRAMES,
              check={"substeps": 800}),
    check_note="the reference with its substeps doubled: the substep sets XPBD's stiffness and time error",
    notes="The default's mesh is coarser than the reference's, and the mesh changes the beam's stiffness (its "
          "tets): every variant on the default mesh carries that error, so their error column is mostly the "
          "mesh's and need not fall as another knob is refined; the vs-default column shows that knob's own effect.",
)


def beam(divisions: int) -> Any:
    return wmesh.beam(LENGTH, WIDTH, WIDTH, divisions=(6 * divisions, divisions, divisions))


def build(mesh: Any = None, device: str | None = None, substeps: int = 10, iterations: int = 2,
          divisions: int = 2) -> StudyWorld:
    if mesh is not None:
        raise wsim.InvalidParameter("the PBD study runs its own beams (mesh=None)")
    shape = beam(divisions)
    probes = match_points(shape.vertices, beam(1).vertices, "pbd study")
    root = np.flatnonzero(shape.vertices[:, 0] < 1e-9 * LENGTH)
    world = StudyWorld(fps=30.0, device=device, signature=lambda w: w.bodies[0].points()[probes])
    world.add(wsim.PbdBody(shape, wsim.ElasticMaterial(**MATERIAL), name="beam", tets="auto", substeps=substeps,
                           iterations=iterations, pinned=root, cache=False))
    return world


def metrics(world: StudyWorld) -> dict:
    out = world.measures()
    out["particles"] = int(world.bodies[0].model.n_particles)
    return out
