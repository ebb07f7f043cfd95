"""Benchmark the XPBD body: seconds per frame and memory from ~1k to ~50k vertices.

The workload is the posed-model scene (scenes/posed_neck.py) at several resolutions: an
elongated creature with its torso pinned and its head driven by a kinematic handle, gravity on,
surface-only (edge stretch, dihedral bending, global volume) and, at small sizes, tetrahedral.
Each case runs in a fresh subprocess (clean peak memory, compilation counted separately) and
prints one JSON object per line:

    case, device, gpu, vertices, particles, constraints, colours, substeps, iterations, frames,
    build_seconds (model + colouring), first_frame_seconds (compile/load + graph capture),
    seconds_per_frame (median of the timed frames, synchronized), seconds_100_frames,
    peak_memory_bytes (GPU: Warp mempool high-water mark; CPU: process max RSS), state_bytes
    (the body's device arrays), and, with --reference, the numpy implementation of the same frame
    (wsim.pbd.reference, float64, vectorized per colour) timed in the same run, with the max
    deviation of the positions after its frames.

The PBD-reconstruction paper (Fang et al. 2021) reports 6.42 s for 100 frames of its
15,389-vertex horse on an i7-6700 CPU; the 15k case prints that beside its own time.

    python tools/bench_pbd.py                       # default device, all sizes
    python tools/bench_pbd.py --device cpu --sizes 1k,5k --reference
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time

SIZES = {"1k": (52, 24), "5k": (104, 48), "15k": (320, 48), "50k": (530, 96)}  # neck_body rings, sectors
PAPER_15K_SECONDS_100_FRAMES = 6.42


def posed_body(size: str, *, tets: bool = False, substeps: int = 10, iterations: int = 2, use_graph: bool = True):
    """The posed-model workload at ``size``: the creature of scenes/posed_neck.py at another
    resolution, torso pinned, head raised and twisted by a handle (shared by the tools)."""
    import numpy as np

    import wsim
    from wsim import mesh as wmesh

    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "scenes"))
    import posed_neck

    rings, sectors = SIZES[size]
    shape = wmesh.neck_body(length=1.6, rings=rings, sectors=sectors)
    u = np.asarray(shape.vertices)[:, 0]
    motion = posed_neck.head_motion(np.array([0.45 * 1.6, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    return wsim.PbdBody(
        shape,
        wsim.ElasticMaterial(E=3.0e5, nu=0.4, rho=1000.0),
        name="creature",
        tets="auto" if tets else None,
        pinned=np.flatnonzero(u < 0.40 * 1.6),
        handles=[wsim.Handle(np.flatnonzero(u > 0.85 * 1.6), motion, name="head")],
        substeps=substeps,
        iterations=iterations,
        cache=False,
        use_graph=use_graph,
    )


def run_case(size: str, tets: bool, device: str | None, frames: int, reference_frames: int) -> dict:
    import numpy as np
    import warp as wp

    import wsim
    from wsim.device import quiet_warp
    from wsim.pbd import reference

    quiet_warp()
    world = wsim.World(fps=30, device=device)
    t0 = time.perf_counter()
    body = world.add(posed_body(size, tets=tets))
    build = time.perf_counter() - t0
    dev = world.device
    t0 = time.perf_counter()
    world.step()
    wp.synchronize_device(dev)
    first = time.perf_counter() - t0
    times = []
    for _ in range(frames):
        t0 = time.perf_counter()
        world.step()  # includes the per-frame NaN check, which synchronizes
        times.append(time.perf_counter() - t0)
    spf = statistics.median(times)
    state_bytes = sum(
        a.capacity for a in vars(body).values() if isinstance(a, wp.array)
    ) + sum(f.indices.capacity + f.rest.capacity + f.compliance.capacity + f.lam.capacity for f in body._families)
    out = {
        "case": f"posed-{size}" + ("-tets" if tets else ""),
        "device": dev.alias,
        "gpu": dev.name if dev.is_cuda else None,
        "vertices": int(body.model.n_surface),
        "particles": int(body.model.n_particles),
        "constraints": {f.kind: f.count for f in body.model.families} | ({"volume": 1} if body.model.volume else {}),
        "colours": {f.kind: f.colours for f in body.model.families},
        # the colours holding a constraint with a free particle (ConstraintFamily.active), and those
        # launched (a surface body's hinges project their edges: no distance colours of their own)
        "colours_projected": {f.kind: f.colours for f in body._active_families},
        "colours_launched": {f.kind: len(f.offsets) - 1 for f in body._families},
        "substeps": 10,
        "iterations": 2,
        "frames": frames,
        "build_seconds": round(build, 4),
        "first_frame_seconds": round(first, 4),
        "seconds_per_frame": spf,
        "seconds_100_frames": 100 * spf,
        "peak_memory_bytes": (
            wp.get_mempool_used_mem_high(dev) if dev.is_cuda else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        ),
        "peak_memory_kind": "gpu mempool high-water" if dev.is_cuda else "process max RSS",
        "state_bytes": int(state_bytes),
    }
    if size == "15k" and not tets:
        out["paper_seconds_100_frames"] = PAPER_15K_SECONDS_100_FRAMES
        out["paper_device"] = "Intel i7-6700 CPU (PositionBasedDynamics library), 15,389-vertex horse"
    if reference_frames > 0:
        x = body.particles()
        vel = body.velocities()
        inv_mass = np.where(body._kinematic_mask, 0.0, 1.0 / body.masses)
        head = body.handles[0].vertices
        rest_head = body.rest_points[head]
        f0 = world.frame

        def ref_frame(k: int) -> None:
            t_start = (f0 + k) / 30.0
            targets = lambda s: body.handles[0].targets(t_start + s / (30.0 * 10), rest_head)  # noqa: E731
            reference.run_frame(
                body.model, x, vel, inv_mass, world.gravity, 1 / 30, 10, 2, body.damping, (), 0.0, (head, targets),
                hinge_edges=any(f.edge is not None for f in body._families),  # the body's projection order
            )

        t0 = time.perf_counter()
        for k in range(reference_frames):
            ref_frame(k)
        ref_spf = (time.perf_counter() - t0) / reference_frames
        for _ in range(reference_frames):
            world.step()
        out["reference"] = {
            "impl": "numpy float64, vectorized per colour (wsim.pbd.reference)",
            "seconds_per_frame": ref_spf,
            "speedup_of_warp": ref_spf / spf,
            "frames_compared": reference_frames,
            "max_deviation_m": float(np.abs(body.particles() - x).max()),
        }
    return out


SWEEP = [(5, 1), (10, 1), (5, 2), (10, 2), (20, 1), (20, 2), (40, 1)]
SWEEP_REFERENCE = (160, 2)  # successive refinements converge ~first order; (80,2) vs (160,2) differ ~0.3 %


def run_sweep(size: str, device: str | None, frames: int) -> list[dict]:
    """Speed/accuracy of (substeps, iterations) on the posed model: max vertex error at frames
    frames/4, frames/2, 3 frames/4 and frames against a 160-substep, 2-iteration run, relative to
    the bounding-box diagonal, beside seconds per frame."""
    import numpy as np
    import warp as wp

    import wsim
    from wsim.device import quiet_warp

    quiet_warp()
    shape_vertices = posed_body(size).rest_points
    checks = {frames // 4, frames // 2, 3 * frames // 4, frames}

    def simulate(substeps: int, iterations: int) -> tuple[dict[int, np.ndarray], float, str]:
        world = wsim.World(fps=30, device=device)
        world.add(posed_body(size, substeps=substeps, iterations=iterations))
        body = world.bodies[0]
        world.step()
        wp.synchronize_device(world.device)
        snaps, times = {}, []
        for f in range(2, frames + 1):
            t0 = time.perf_counter()
            world.step()
            times.append(time.perf_counter() - t0)
            if f in checks:
                snaps[f] = body.points()
        return snaps, statistics.median(times), world.device.alias

    ref, _, dev = simulate(*SWEEP_REFERENCE)
    diag = float(np.linalg.norm(np.ptp(shape_vertices, axis=0)))
    out = []
    for substeps, iterations in SWEEP:
        snaps, spf, _ = simulate(substeps, iterations)
        err = max(float(np.abs(snaps[f] - ref[f]).max()) for f in checks) / diag
        out.append(
            {
                "case": f"sweep-{size}",
                "device": dev,
                "vertices": len(shape_vertices),
                "substeps": substeps,
                "iterations": iterations,
                "seconds_per_frame": spf,
                "error_vs_reference": err,
                "reference": {"substeps": SWEEP_REFERENCE[0], "iterations": SWEEP_REFERENCE[1]},
                "error_kind": "max vertex distance over 4 frames / bounding-box diagonal",
            }
        )
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default=None)
    p.add_argument("--sizes", default="1k,5k,15k,50k")
    p.add_argument("--tets", default="1k,5k", help="sizes also run as tetrahedral bodies ('' for none)")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--reference", action="store_true", help="time the numpy reference in the same run")
    p.add_argument("--reference-frames", type=int, default=3)
    p.add_argument("--sweep", default=None, metavar="SIZE", help="speed/accuracy sweep of substeps x iterations at SIZE")
    p.add_argument("--case", default=None, help=argparse.SUPPRESS)  # internal: run one case here
    args = p.parse_args()
    if args.sweep:
        for row in run_sweep(args.sweep, args.device, args.frames):
            print(json.dumps(row), flush=True)
        return
    if args.case:
        size, _, kind = args.case.partition(":")
        res = run_case(size, kind == "tets", args.device, args.frames, args.reference_frames if args.reference else 0)
        print(json.dumps(res), flush=True)
        return
    cases = [f"{s}:surface" for s in args.sizes.split(",") if s]
    cases += [f"{s}:tets" for s in args.tets.split(",") if s and s in args.sizes.split(",")]
    for case in cases:
        cmd = [sys.executable, __file__, "--case", case, "--frames", str(args.frames)]
        if args.device:
            cmd += ["--device", args.device]
        if args.reference:
            cmd += ["--reference", "--reference-frames", str(args.reference_frames)]
        res = subprocess.run(cmd, capture_output=True, text=True)
        line = res.stdout.strip().splitlines()[-1] if res.stdout.strip() else ""
        if res.returncode != 0 or not line.startswith("{"):
            print(json.dumps({"case": case, "error": res.stderr.strip().splitlines()[-1:]}), flush=True)
        else:
            print(line, flush=True)


if __name__ == "__main__":
    main()
