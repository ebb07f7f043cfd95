"""Benchmark one EoL body per step, by the stages of the paper's Table II: one JSON line per case.

    python tools/bench_eol.py --resolution 8,16                       # CPU-sized
    python tools/bench_eol.py --resolution 16,32,48 --device cuda:0   # on a GPU machine

Cases: a sphere (0.6 m, E = 50 kPa) in free flight spinning at pi rad/s ("free": forces, LS,
advection, tracking; no collision), and the same sphere resting on a ground plane under gravity
("contact": plus collision, row assembly and the QP every step). Each case is warmed up (kernel
compilation, the first contact) and then stepped

* without profiling: seconds per whole step (wall clock / steps, the device synchronized at the end);
* with ``profile=True`` (the device synchronized after each stage): seconds per step by stage;
  Table II's columns are forces, collision, assembly, LS, QP (``advect`` and ``track`` are
  reported apart; the paper counts them in its LS/forces columns, it does not say);

plus dt statistics, the contact rows, the grid and material-point counts and peak memory (device
memory pool on CUDA, host max RSS). Table II (GTX 580): two 32^3 spheres, 6 Lagrangian DOF,
2.0 + 15.7 + 2.9 + 21.6 + 54.4 = 96.6 ms per step.
"""

from __future__ import annotations

import argparse
import json
import resource
import time

import numpy as np
import trimesh
import warp as wp

import wsim
from wsim.eol.body import STAGES

PAPER_TABLE_II = {"forces": 2.0e-3, "collision": 15.7e-3, "assembly": 2.9e-3, "ls": 21.6e-3, "qp": 54.4e-3,
                  "total": 96.6e-3, "note": "2 spheres of 32^3, GTX 580 (per step, both bodies)"}


def make_world(case: str, resolution: int, device: str, lagrangian: str, profile: bool, damping: float = 20.0, **body_kw):
    gravity = (0.0, -9.81, 0.0) if case == "contact" else (0.0, 0.0, 0.0)
    world = wsim.World(fps=30, gravity=gravity, device=device)
    if case == "contact":
        world.add_collider(wsim.GroundPlane(0.0))
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    ball.apply_translation((0.0, 0.3 if case == "contact" else 1.0, 0.0))
    body = world.add(wsim.EolBody(ball, wsim.ElasticMaterial(E=5e4, nu=0.3, rho=500.0), resolution=resolution,
                                  lagrangian=lagrangian, angular_velocity=(0.0, np.pi, 0.0), damping=damping,
                                  profile=profile, **body_kw))
    return world, body


def run_case(case: str, resolution: int, device: str, lagrangian: str, steps: int, **body_kw) -> dict:
    sync = (lambda: wp.synchronize_device(device))
    out: dict = {"case": case, "resolution": resolution, "lagrangian": lagrangian, "device": str(wp.get_device(device)),
                 "device_name": wp.get_device(device).name, **body_kw}
    for profile in (False, True):
        t0 = time.perf_counter()
        world, body = make_world(case, resolution, device, lagrangian, profile, **body_kw)
        setup = time.perf_counter() - t0
        world.step()  # compile, settle into contact
        world.step()
        sync()
        for k in body.timings:
            body.timings[k] = 0.0
        n0 = body.steps
        t0 = time.perf_counter()
        while body.steps - n0 < steps:  # the World's path: adaptive steps to each frame's end
            body.advance(body.time, body.time + 1.0 / 30.0)
        sync()
        wall = time.perf_counter() - t0
        n = body.steps - n0
        if not profile:
            out.update(setup_s=setup, seconds_per_step=wall / n, steps=n)
            dts = np.array([r.dt for r in body.history[n0:]])
            rows = np.array([r.rows for r in body.history[n0:]])
            out.update(dt_mean=float(dts.mean()), dt_min=float(dts.min()), dt_max=float(dts.max()),
                       dt_cap=float(body.dt_elastic), rows_mean=float(rows.mean()), rows_max=int(rows.max()),
                       active_mean=float(np.mean([r.active for r in body.history[n0:]])),
                       qp_iterations_mean=float(np.mean([r.qp_iterations for r in body.history[n0:]])),
                       qp_fallbacks=int(sum(r.qp_iterations > 50 for r in body.history[n0:])),
                       # contact accuracy: overlap with the ground relative to the body's volume,
                       # and how deep the lowest surface vertex sits [m] (h for scale)
                       overlap_rel_mean=float(np.mean([r.overlap for r in body.history[n0:]]) / body.volume()),
                       lowest_vertex=float(body.points()[:, 1].min()), h=float(body.grid.h))
        else:
            out["stage_seconds_per_step"] = {k: body.timings[k] / n for k in STAGES}
            out["profiled_seconds_per_step"] = wall / n
    out.update(grid_nodes=body.grid.n_nodes, grid_cells=list(body.grid.cells), material_points=len(body._volumes),
               surface_vertices=len(body.rest_vertices), lagrangian_dof={"rigid": 6, "affine": 12, "eulerian": 0}[lagrangian])
    dev = wp.get_device(device)
    if dev.is_cuda:
        try:
            out["device_mem_high_mb"] = wp.get_mempool_used_mem_high(dev) / 2**20
        except Exception:  # older Warp
            out["device_mem_high_mb"] = None
    out["host_max_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out["paper_table_ii"] = PAPER_TABLE_II
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", default="8,16")
    ap.add_argument("--cases", default="free,contact")
    ap.add_argument("--lagrangian", default="rigid")
    ap.add_argument("--device", default=None)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--collision-block", default="1", help="comma list of EolBody collision_block values [cells]")
    ap.add_argument("--contact-spacing", type=float, default=1.0, help="EolBody contact_spacing [h]")
    args = ap.parse_args()
    device = args.device or ("cuda:0" if wp.get_cuda_device_count() else "cpu")
    for res in (int(r) for r in args.resolution.split(",")):
        for case in args.cases.split(","):
            blocks = [int(c) for c in args.collision_block.split(",")] if case == "contact" else [1]
            for block in blocks:
                out = run_case(case, res, device, args.lagrangian, args.steps, collision_block=block,
                               contact_spacing=args.contact_spacing)
                print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
