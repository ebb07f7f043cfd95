"""Before/after figures for issue 16's EoL items (loads, Coriolis energy gain, material leaving the grid).

Cases (CPU, each prints one JSON line; ``--case all`` runs them in turn):

- ``spin20``: the issue's undamped spin (icosphere R = 0.5 m, E = 1e5, nu = 0.3, rho = 1000, 6 cells,
  pi rad/s about z, ``fictitious=True``, damping 0, no gravity, 30 fps) for 20 s at the default dt
  cap; angular momentum (node masses, about the frame origin) and kinetic + elastic energy change
  in %. ``--dt-scale`` multiplies the cap (``dt_max = s * dt_elastic``); ``--fictitious 0`` turns
  the loads off; ``--coriolis`` picks the Coriolis update where the body has that knob.
- ``flyapart``: E = 1e5 spun at 10 rev/s with damping 1000 (``tools/study_eol.py``'s
  fast_spin_10rev) for 1 s: how and when the run stops.

    python tools/study_eol_loads.py --case all --tag after > tools/results/study_eol_loads_cpu.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time

import numpy as np


def _L(body) -> np.ndarray:
    F, T = body.frame
    x = body.grid.node_positions() @ F.T + T
    return np.cross(x - T, body.node_world_velocities()).T @ body.node_masses()


def build(E: float, omega: float, damping: float, resolution: int, fictitious: bool, dt_scale: float | None,
          extra: dict):
    import trimesh

    import wsim

    world = wsim.World(fps=30.0, gravity=(0.0, 0.0, 0.0), device="cpu")
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    ball.apply_translation((0.0, 0.7, 0.0))
    kw = dict(resolution=resolution, damping=damping, fictitious=fictitious, **extra)
    probe = wsim.EolBody(ball, wsim.ElasticMaterial(E=E, nu=0.3, rho=1000.0), **kw)
    if dt_scale is not None:
        kw["dt_max"] = dt_scale * probe.dt_elastic
    body = world.add(wsim.EolBody(ball, wsim.ElasticMaterial(E=E, nu=0.3, rho=1000.0),
                                  angular_velocity=(0.0, 0.0, omega) if resolution == 6 else (0.0, omega, 0.0), **kw))
    return world, body


def spin20(args) -> dict:
    extra = {"coriolis": args.coriolis} if args.coriolis else {}
    if args.mass_floor is not None:
        extra["mass_floor"] = args.mass_floor
    if args.lagrangian:
        extra["lagrangian"] = args.lagrangian
    if args.breathe:  # a radial velocity field (zero net momentum) on top of the spin
        extra["velocity_field"] = lambda x: args.breathe * (x - x.mean(axis=0))
    world, body = build(1e5, math.pi, 0.0, 6, bool(args.fictitious), args.dt_scale, extra)

    L0, e0 = _L(body), body.kinetic_energy() + body.elastic_energy
    t0 = time.perf_counter()
    frames = round(args.seconds * 30)
    status = "ok"
    try:
        for _ in range(frames):
            world.step()
    except Exception as exc:  # noqa: BLE001 - report it
        status = f"{type(exc).__name__}: {exc}"
    wall = time.perf_counter() - t0
    L1, e1 = _L(body), body.kinetic_energy() + body.elastic_energy
    return {"case": "spin20", "seconds": args.seconds, "dt_scale": args.dt_scale, "fictitious": bool(args.fictitious),
            "coriolis": args.coriolis, "mass_floor": args.mass_floor, "lagrangian": args.lagrangian, "breathe": args.breathe, "status": status, "steps": body.steps, "wall_s": wall,
            "ms_per_step": 1e3 * wall / max(body.steps, 1), "dt_elastic": body.dt_elastic,
            "L_change_pct": 100.0 * (np.linalg.norm(L1) / np.linalg.norm(L0) - 1.0),
            "energy_change_pct": 100.0 * (e1 / e0 - 1.0),
            "omega_final": float(np.linalg.norm(body.angular_velocity))}


def flyapart(args) -> dict:
    world, body = build(1e5, 2 * math.pi * 10, 1000.0, 8, True, None, {})

    t0 = time.perf_counter()
    status, msg = "bounded", ""
    try:
        for _ in range(30):
            world.step()
    except Exception as exc:  # noqa: BLE001 - report it
        status, msg = type(exc).__name__, str(exc)
    return {"case": "flyapart", "status": status, "message": msg, "steps": body.steps, "sim_time": body.time,
            "wall_s": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", default="all", choices=["all", "spin20", "flyapart"])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--dt-scale", type=float, default=None)
    ap.add_argument("--fictitious", type=int, default=1)
    ap.add_argument("--coriolis", default=None)
    ap.add_argument("--lagrangian", default=None)
    ap.add_argument("--mass-floor", type=float, default=None)
    ap.add_argument("--breathe", type=float, default=0.0, help="radial velocity field rate [1/s] on top of the spin")
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    from wsim.device import quiet_warp

    quiet_warp()
    try:
        git = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False).stdout.strip()
    except OSError:
        git = None
    for case in (["spin20", "flyapart"] if args.case == "all" else [args.case]):
        row = {"spin20": spin20, "flyapart": flyapart}[case](args)
        row.update(tag=args.tag, git=git, device="cpu")
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    sys.exit(main())
