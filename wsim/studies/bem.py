"""BEM knob study: a soft ball squeezed and released while it spins, rung by the squeeze.

An icosphere of radius 0.1 m (mu = 3e4 Pa, nu = 0.45, rho = 1000 kg/m^3; ``subdivisions`` 1, 2, 3:
42, 162, 642 nodes) spins at 3 rad/s in zero gravity; for the first 20 ms a 3 kPa pressure
squeezes its two caps |x| > 0.03 m (frame axes), then it rings freely. 50 fps. The signature is
the displacement of the 12 icosahedron vertices (on every subdivision) from the rigidly moved rest
shape, in world axes, after every frame (``R u``: the deformation the knobs act on; the frame's
rigid motion is the same torque-free ODE for every setting). Without material damping the exact
answer rings on; BDF1 damps it numerically, the more the longer dt, so the reference is BDF1 at a
short dt (BDF2 grows on this ball: 2.3 mm to 12 mm over 0.9 s at dt = 1 ms, 42 nodes; measured
on the CPU, so it is a variant, not the reference).

Knobs (``BemBody``'s): ``dt``, ``method`` (CQ: "bdf1" or "bdf2"), ``precision`` ("float32" or
"float64" storage), ``compression`` (Haar compression ratio CR), the quadrature's ``order`` and
``singular_order``, and the mesh (``subdivisions``). Operators are built uncached when the body
joins the World; ``setup_s`` times that (assembly, CQ weights, factorization; compression and
upload happen there too).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import trimesh

import wsim
from wsim.studies.common import Mode, StudySpec, StudyWorld, match_points

FRAMES = 15
FPS = 50.0
RADIUS = 0.1  # [m]
SQUEEZE = 0.02  # [s]
PRESSURE = 3.0e3  # [Pa]
MATERIAL = dict(mu=3.0e4, nu=0.45, rho=1000.0)

SPEC = StudySpec(
    name="bem",
    title="BEM: time step, CQ order, precision, compression, quadrature, mesh",
    scenario="A soft ball (R = 0.1 m, mu = 30 kPa, nu = 0.45) spinning at 3 rad/s in zero gravity, its caps "
             "squeezed by 3 kPa for 20 ms, then ringing freely; 50 fps.",
    error="the largest distance, over the 12 icosahedron vertices and every frame, between a setting's "
          "deformation (displacement from the rigidly moved rest shape, world axes) and the reference's, "
          "over the reference's largest displacement",
    scale="reference_peak",
    costs={"ms_per_frame": "ms per frame", "setup_s": "operator build [s]", "model_mb": "operators and state, host + device [MB]"},
    knobs={"dt": "BemBody(dt=...) [s]", "method": "BemBody(method=...): CQ multistep method",
           "precision": "BemBody(precision=...): storage of the operators",
           "compression": "BemBody(compression=CR): Haar compression ratio (None: dense)",
           "order": "BemBody(order=...): Gauss points per direction, regular quadrature",
           "singular_order": "BemBody(singular_order=...): polar rule at a triangle's own vertex",
           "subdivisions": "icosphere subdivisions: 1, 2, 3 = 42, 162, 642 nodes"},
    quick=Mode(default={},
               grid={"dt": [0.001, 0.004], "method": ["bdf2"], "precision": ["float64"], "compression": [4],
                     "order": [2], "subdivisions": [2]},
               reference={"subdivisions": 2, "dt": 0.0005, "precision": "float64"},
               frames=FRAMES),
    full=Mode(default={"subdivisions": 2},
              grid={"dt": [0.001, 0.004], "method": ["bdf2"], "precision": ["float64"],
                    "compression": [2, 4, 8, 16], "order": [1, 2, 5], "singular_order": [4, 16],
                    "subdivisions": [1, 3]},
              # n_max is 83 at dt = 0.5 ms (162 nodes, measured): H_k and G_k of 642 nodes in float64, ~5 GB
              reference={"subdivisions": 3, "dt": 0.0005, "precision": "float64", "order": 5, "singular_order": 16},
              frames=FRAMES),
    notes="BDF2 grows on this ball once the squeeze is released (the largest displacement went from 2.3 mm to "
          "12 mm over 0.9 s at dt = 1 ms, 42 nodes, CPU), where BDF1 decays; the reference is BDF1 at a short dt "
          "for that reason. With compression the body steps with the compressed operators instead of a stepping "
          "copy of the dense ones (on a GPU, their device copy), but keeps the dense operators it was built from "
          "in host memory, which the memory column counts.",
)


def build(mesh: Any = None, device: str | None = None, subdivisions: int = 1, dt: float = 0.002,
          method: str = "bdf1", precision: str = "float32", compression: float | None = None, order: int = 3,
          singular_order: int = 8) -> StudyWorld:
    if mesh is not None:
        raise wsim.InvalidParameter("the BEM study runs its own icospheres (mesh=None)")
    ball = trimesh.creation.icosphere(subdivisions=subdivisions, radius=RADIUS)
    probes = match_points(ball.vertices, trimesh.creation.icosphere(subdivisions=0, radius=RADIUS).vertices,
                          "bem study")
    body: wsim.BemBody | None = None

    def signature(world: wsim.World) -> np.ndarray:
        # R u at the probes: the deformation, in world axes
        return body.vertex_displacement()[probes] @ body.frame.R.T

    world = StudyWorld(fps=FPS, gravity=(0.0, 0.0, 0.0), device=device, signature=signature)
    t = time.perf_counter()
    body = world.add(wsim.BemBody(ball, wsim.ElasticMaterial(**MATERIAL), dt, name="ball",
                                  angular_velocity=(0.0, 3.0, 0.0), method=method, precision=precision,
                                  compression=compression, order=order, singular_order=singular_order,
                                  cache=False, progress=False))
    world.extra["setup_s"] = time.perf_counter() - t  # the operators are built (uncached) as the body joins
    n, x = body.rest_normals, body.rest_vertices
    load = -PRESSURE * n * (np.abs(x[:, :1]) > 0.3 * RADIUS)  # both caps: no net force
    body.add_traction(lambda t: load if t <= SQUEEZE + 1e-9 else np.zeros_like(load))
    return world


def metrics(world: StudyWorld) -> dict:
    out = world.measures()
    body = world.bodies[0]
    out.update(nodes=int(body.operators.n_nodes), n_max=int(body.operators.n_max))
    return out
