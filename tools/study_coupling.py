"""The coupling step across methods (issue 18, ``World(coupling_dt=...)``): accuracy and cost.

Two explicit-coupling cases on the CPU or a GPU, each at 1, 2, 4, 8, 16 and 32 coupling intervals
per frame (60 fps; the BEM cube steps 32 times a frame, the PBD ball takes 10 substeps a frame or
one per interval, whichever is more), one JSON line per run:

* ``throw``: a PBD ball (R = 0.1 m) and a 26-node BEM cube thrown at each other at 1 m/s in zero
  gravity: the deepest particle of the ball inside the cube [mm], the ball's rebound velocity
  (elastic bound -1.66 m/s, perfectly inelastic -0.33 m/s), the pair's momentum error [% of the
  impulse], wall time per frame.
* ``rest``: a PBD ball dropped 4 cm onto a BEM cube on the ground, 1 s: the ball's depth in the
  cube at the end [mm], its largest speed in the last 0.25 s [m/s], wall time per frame.

    python tools/study_coupling.py [--device cuda:0] [--out tools/results/study_coupling_cpu.jsonl]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import trimesh
import warp as wp

import wsim
from wsim.contact import points_inside

DT = 1.0 / 1920.0  # divides every coupling interval used (1/60 / 32)
MAT = wsim.ElasticMaterial(E=1.0e6, nu=0.3, rho=1000.0)
BOX = trimesh.creation.box(extents=(0.2, 0.2, 0.2)).subdivide()
PBD = wsim.ElasticMaterial(E=2.0e5, nu=0.3, rho=1000.0)


def depth(a, b, device) -> float:
    """How deep any surface point of b is inside a [m] (0 if none)."""
    hit, face, bary, _ = points_inside(b.points(), a.points(), a.faces, 0.0, device)
    if not len(hit):
        return 0.0
    P = np.einsum("mk,mkd->md", bary, a.points()[a.faces[face]])
    return float(np.linalg.norm(b.points()[hit] - P, axis=1).max())


def run(case: str, k: int, device: str, ops) -> dict:
    fps = 60.0
    g = (0.0, -9.81, 0.0) if case == "rest" else (0.0, 0.0, 0.0)
    w = wsim.World(fps=fps, gravity=g, device=device, coupling_dt=1.0 / (fps * k))
    if case == "rest":
        w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
        cube = w.add(wsim.BemBody(BOX, MAT, DT, operators=ops, name="cube", position=(0.0, 0.1005, 0.0)))
        ball = w.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=2, radius=0.06), PBD, tets="auto",
                                  name="ball", position=(0.01, 0.3, 0.0), damping=0.01))
        frames = 60
    else:
        cube = w.add(wsim.BemBody(BOX, MAT, DT, operators=ops, name="cube", position=(0.2, 0.03, 0.0),
                                  velocity=(-1.0, 0.0, 0.0)))
        ball = w.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=2, radius=0.1), PBD, tets="auto",
                                  name="ball", position=(-0.15, 0.0, 0.0), velocity=(1.0, 0.0, 0.0)))
        frames = 20
    dev = wp.get_device(device)
    P0 = cube.linear_momentum() + ball.linear_momentum()
    deepest, speeds = 0.0, []
    w.step()  # compile outside the timing
    t = time.perf_counter()
    for f in range(1, frames):
        w.step()
        deepest = max(deepest, depth(cube, ball, dev))
        if case == "rest" and f >= frames - 15:
            speeds.append(float(np.abs(ball.velocities()).max()))
    wall = (time.perf_counter() - t) / (frames - 1)
    out = dict(case=case, device=dev.name, intervals_per_frame=k, coupling_dt=1.0 / (fps * k), ms_per_frame=1e3 * wall,
               deepest_mm=1e3 * deepest)
    if case == "throw":
        J = cube.coupling_impulse
        P = cube.linear_momentum() + ball.linear_momentum()
        out.update(ball_vx=float(ball.linear_momentum()[0] / ball.masses.sum()),
                   momentum_error_pct=float(100.0 * np.linalg.norm(P - P0) / np.linalg.norm(J)))
    else:
        out.update(final_depth_mm=1e3 * depth(cube, ball, dev), late_speed_max=max(speeds))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    from wsim.bem import build_operators

    ops = build_operators(BOX, MAT, DT, cache=False, device=args.device)
    for case in ("throw", "rest"):
        for k in (1, 2, 4, 8, 16, 32):
            line = json.dumps(run(case, k, args.device, ops))
            print(line, flush=True)
            if args.out:
                with open(args.out, "a") as fh:
                    fh.write(line + "\n")


if __name__ == "__main__":
    main()
