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

Between EoL bodies, at 1, 4, 16 and 64 intervals per frame (60 fps). Touching EoL bodies share one
QP (``wsim.eol.pairs``), so the interval only groups them; with the explicit exchange between EoL
bodies it replaced (``tools/results/study_coupling_eol_cpu.jsonl``) the interval set the lag:

* ``eol_throw``: two EoL spheres (R = 0.15 m, 6 cells, the second 10x denser) thrown at each
  other at 1 m/s in zero gravity, 0.4 s: the light one's velocity after (perfectly inelastic
  -0.82 m/s, elastic -2.64 m/s), kinetic energy kept, the pair's momentum error [% of the sum of
  the momenta], the deepest vertex [cells].
* ``eol_rest``: an EoL box set on an EoL box on the ground, 2 s: the mean speed of the two over the
  last second [m/s] (jitter) and how far the top box's bottom moved over it [mm].

Global against lagged on one scene (``pbd_pair``): two tet PBD balls (R = 0.2 m) thrown at each
other at 2 m/s, 5 cm off centre, in zero gravity, 0.4 s at 60 fps and 10 substeps a frame, once
with the World's PBD-PBD contact (substeps in lockstep, both bodies in every projection: the
global, implicit exchange) and once with the explicit exchange the World uses across methods,
driven by hand at 1 and 10 intervals a frame (ball b keeps out of ball a's moving surface, ball a
gets b's push as a velocity change at the start of the next interval): pair momentum and
angular momentum errors, deepest particle, rebound velocities, kinetic energy kept, cost.

    python tools/study_coupling.py [--device cuda:0] [--cases throw,rest,eol_throw,eol_rest,pbd_pair]
        [--out tools/results/study_coupling_cpu.jsonl]
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


def run_eol(case: str, k: int, device: str) -> dict:
    fps = 60.0
    dev = wp.get_device(device)
    if case == "eol_throw":
        w = wsim.World(fps=fps, gravity=(0.0, 0.0, 0.0), device=device, coupling_dt=1.0 / (fps * k))
        ball = trimesh.creation.icosphere(subdivisions=2, radius=0.15)
        a = w.add(wsim.EolBody(ball, wsim.ElasticMaterial(E=1e5, nu=0.3, rho=500.0), resolution=6, name="light",
                               position=(-0.2, 0.0, 0.0), velocity=(1.0, 0.0, 0.0), damping=50.0))
        b = w.add(wsim.EolBody(ball, wsim.ElasticMaterial(E=1e5, nu=0.3, rho=5000.0), resolution=6, name="heavy",
                               position=(0.2, 0.02, 0.0), velocity=(-1.0, 0.0, 0.0), damping=50.0))
        P0 = a.linear_momentum() + b.linear_momentum()
        scale = np.linalg.norm(a.linear_momentum()) + np.linalg.norm(b.linear_momentum())
        E0 = a.kinetic_energy() + b.kinetic_energy()
        deepest = 0.0
        t = time.perf_counter()
        for _ in range(24):
            w.step()
            deepest = max(deepest, depth(a, b, dev), depth(b, a, dev))
        wall = (time.perf_counter() - t) / 24
        P = a.linear_momentum() + b.linear_momentum()
        return dict(case=case, device=dev.name, intervals_per_frame=k, coupling_dt=1.0 / (fps * k), ms_per_frame=1e3 * wall,
                    light_vx=float(a.linear_momentum()[0] / a.mass), heavy_vx=float(b.linear_momentum()[0] / b.mass),
                    kinetic_energy_kept=float((a.kinetic_energy() + b.kinetic_energy()) / E0),
                    momentum_error_pct=float(100.0 * np.linalg.norm(P - P0) / scale), deepest_cells=deepest / a.grid.h)
    w = wsim.World(fps=fps, device=device, coupling_dt=1.0 / (fps * k))
    w.add_collider(wsim.GroundPlane(name="ground"))
    mat = wsim.ElasticMaterial(E=2e5, nu=0.3, rho=500.0)
    box = trimesh.creation.box(extents=(0.3, 0.2, 0.3)).subdivide().subdivide()
    low = w.add(wsim.EolBody(box, mat, resolution=5, name="low", position=(0, 0.101, 0), damping=100.0))
    top = w.add(wsim.EolBody(box, mat, resolution=5, name="top", position=(0.03, 0.305, 0), damping=100.0))
    bottom, speeds = [], []
    t = time.perf_counter()
    for f in range(120):
        w.step()
        if f >= 60:
            bottom.append(top.points()[:, 1].min())
            speeds.append(np.mean([np.linalg.norm(x.linear_momentum()) / x.mass for x in (low, top)]))
    wall = (time.perf_counter() - t) / 120
    return dict(case=case, device=dev.name, intervals_per_frame=k, coupling_dt=1.0 / (fps * k), ms_per_frame=1e3 * wall,
                mean_speed=float(np.mean(speeds)), bottom_moved_mm=1e3 * float(np.ptp(bottom)))


def run_pbd_pair(mode: str, k: int, device: str) -> dict:
    """``mode`` "lockstep" (the World's PBD-PBD contact) or "explicit" (k intervals a frame)."""
    fps = 60.0
    dev = wp.get_device(device)
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    mat = wsim.ElasticMaterial(E=2.0e5, nu=0.3, rho=500.0)
    explicit = mode == "explicit"
    w = wsim.World(fps=fps * (k if explicit else 1), gravity=(0.0, 0.0, 0.0), device=device, body_contact=not explicit)
    sub = 10 // k if explicit else 10
    a = w.add(wsim.PbdBody(ball, mat, tets="auto", name="a", position=(-0.3, 0.0, 0.0), velocity=(2.0, 0, 0), substeps=sub))
    b = w.add(wsim.PbdBody(ball, mat, tets="auto", name="b", position=(0.3, 0.05, 0.0), velocity=(-2.0, 0, 0), substeps=sub))
    P0 = a.linear_momentum() + b.linear_momentum()
    L0 = a.angular_momentum(about=(0, 0, 0)) + b.angular_momentum(about=(0, 0, 0))
    E0 = a.kinetic_energy() + b.kinetic_energy()
    deepest = 0.0
    frames = 24
    w.step()  # binds, compiles (the balls are apart)
    t = time.perf_counter()
    for f in range(1, frames):
        if not explicit:
            w.step()
        else:
            for i in range(k):
                t0, t1 = w.time, w.time + w.frame_dt
                start = a.points()
                a.advance(t0, t1)
                b.set_moving_surfaces([(id(a), start, a.points(), a.faces, 0.5)])
                b.advance(t0, t1)
                J = b.moving_surface_impulses()[id(a)]
                v = a.velocities()
                n = len(J)
                m = a.masses[:n]
                free = m > 0.0
                v[:n][free] += J[free] / m[free, None]
                a.set_velocities(v)
                w.frame += 1
        deepest = max(deepest, depth(a, b, dev), depth(b, a, dev))
    wall = (time.perf_counter() - t) / (frames - 1)
    P = a.linear_momentum() + b.linear_momentum()
    L = a.angular_momentum(about=(0, 0, 0)) + b.angular_momentum(about=(0, 0, 0))
    scale = float(np.linalg.norm(a.linear_momentum()) + np.linalg.norm(b.linear_momentum()))
    return dict(case="pbd_pair", mode=mode, device=dev.name, intervals_per_frame=k if explicit else None,
                ms_per_frame=1e3 * wall, momentum_error_pct=float(100.0 * np.linalg.norm(P - P0) / scale),
                angular_momentum_error_pct=float(100.0 * np.linalg.norm(L - L0) / np.linalg.norm(L0)),
                kinetic_energy_kept=float((a.kinetic_energy() + b.kinetic_energy()) / E0), deepest_mm=1e3 * deepest,
                a_vx=float(a.linear_momentum()[0] / a.masses.sum()), b_vx=float(b.linear_momentum()[0] / b.masses.sum()))


def emit(row: dict, out: str | None) -> None:
    """Print one JSON line, and append it to ``out`` if given."""
    line = json.dumps(row)
    print(line, flush=True)
    if out:
        with open(out, "a") as fh:
            fh.write(line + "\n")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    ap.add_argument("--cases", default="throw,rest,eol_throw,eol_rest")
    args = ap.parse_args()
    from wsim.bem import build_operators

    cases = args.cases.split(",")
    ops = build_operators(BOX, MAT, DT, cache=False, device=args.device) if {"throw", "rest"} & set(cases) else None
    if "pbd_pair" in cases:
        cases.remove("pbd_pair")
        for mode, k in (("lockstep", 1), ("explicit", 1), ("explicit", 10)):
            emit(run_pbd_pair(mode, k, args.device), args.out)
    for case in cases:
        for k in ((1, 4, 16, 64) if case.startswith("eol") else (1, 2, 4, 8, 16, 32)):
            emit(run_eol(case, k, args.device) if case.startswith("eol") else run(case, k, args.device, ops), args.out)


if __name__ == "__main__":
    main()
