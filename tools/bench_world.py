"""Whole-World cost of the contact scenes (issue 18): one JSON line per scene with the bodies by
method, the coupling intervals (and the implicit coupling's intervals and passes,
``World.coupling_stats``), the contacts of the last frame, milliseconds per frame (median
over the timed frames, after warm-up frames that compile kernels and record graphs), the same
split by stage (each method's stepping and the explicit "coupling": surface read-backs, broad
phase, impulse exchange, grouping of EoL bodies that may touch; from a second, profiled pass that synchronizes the device after each
stage), EoL steps per frame and milliseconds per EoL step of the World (all EoL bodies one step),
and the device memory high-water mark.

    python tools/bench_world.py [--device cuda:0] [--scenes showcase,eol_two_spheres,...]
        [--frames N] [--resolution R]   # R: the EoL scenes' cells across each body
    python tools/bench_world.py --whole --scenes eol_two_spheres --resolution 32 --device cuda:0

``--whole``: every frame of the scene (its ``FRAMES``) timed, after an untimed run of the whole
scene that compiles every kernel it meets (the first contact's, the first grid growth's): the
mean milliseconds per EoL step of the World over all of the scene's steps, as the paper's Table II
reports its averages (its 96.6 ms for the two spheres is the mean over all 2773 steps of that
scene, free flight included), and per frame, with each frame's milliseconds and EoL steps.

Scenes are built by their own ``build``; ``--resolution`` goes to the EoL scenes (the paper's
Table II uses 32). Frames simulated before timing start at the scene's first frame.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scenes"))

ap = argparse.ArgumentParser()
ap.add_argument("--device", default=None)
ap.add_argument("--scenes", default="showcase,eol_two_spheres,eol_pile,bem_fish_bowl,mixed_drop")
ap.add_argument("--frames", type=int, default=10, help="timed frames per scene")
ap.add_argument("--warmup", type=int, default=2)
ap.add_argument("--skip", type=int, default=0, help="frames simulated (untimed) before the warm-up, e.g. to reach contact")
ap.add_argument("--resolution", type=int, default=None)
ap.add_argument("--whole", action="store_true", help="time every frame of the scene after an untimed run of it")
args = ap.parse_args()
device = wp.get_device(args.device)


def build(name: str):
    scene = importlib.import_module(name)
    kw = {"device": device.alias}
    if args.resolution is not None and "resolution" in scene.build.__code__.co_varnames:
        kw["resolution"] = args.resolution
    return scene.build(**kw)


def eol_steps(world) -> int:
    return sum(b.steps for b in world.bodies if type(b).__name__ == "EolBody")


def frame_times(world, n: int) -> list[float]:
    out = []
    for _ in range(n):
        wp.synchronize_device(device)
        t = time.perf_counter()
        world.step()
        wp.synchronize_device(device)
        out.append(time.perf_counter() - t)
    return out


def n_eol(world) -> int:
    return max(1, sum(type(b).__name__ == "EolBody" for b in world.bodies))


def whole(name: str) -> None:
    """``--whole``: the scene's every frame, timed on a second run (the first compiles)."""
    frames = importlib.import_module(name).FRAMES
    world = build(name)
    for _ in range(frames):
        world.step()
    world = build(name)
    rows = []
    for f in range(frames):
        s0 = eol_steps(world)
        (t,) = frame_times(world, 1)
        rows.append((f + 1, t, (eol_steps(world) - s0) / n_eol(world)))
    total = sum(t for _, t, _ in rows)
    steps = sum(n for _, _, n in rows)
    print(json.dumps({
        "scene": name, "device": device.name, "resolution": args.resolution, "whole": True,
        "bodies": dict(Counter(type(b).__name__ for b in world.bodies)), "frames": frames,
        "seconds": round(total, 3), "ms_per_frame_mean": round(1e3 * total / frames, 2),
        "ms_per_frame_median": round(1e3 * float(np.median([t for _, t, _ in rows])), 2),
        "eol_world_steps": steps, "ms_per_eol_world_step_mean": round(1e3 * total / steps, 2) if steps else None,
        "per_frame": [{"frame": f, "ms": round(1e3 * t, 1), "eol_world_steps": n} for f, t, n in rows],
        "device_mem_high_mb": round(wp.get_mempool_used_mem_high(device) / 2**20, 1) if device.is_cuda else None,
    }), flush=True)


for name in args.scenes.split(",") if args.whole else ():
    whole(name)
for name in () if args.whole else args.scenes.split(","):
    t_build = time.perf_counter()
    world = build(name)
    t_build = time.perf_counter() - t_build
    for _ in range(args.skip):
        world.step()
    frame_times(world, args.warmup)
    s0 = eol_steps(world)
    times = frame_times(world, args.frames)
    steps = (eol_steps(world) - s0) / args.frames
    world.profile = True  # a second pass, split by stage
    world.timings = {}
    frame_times(world, max(2, args.frames // 2))
    n_prof = max(2, args.frames // 2)
    stages = {k: 1e3 * v / n_prof for k, v in sorted(world.timings.items())}
    eol_rows = sum(b.history[-1].active for b in world.bodies if type(b).__name__ == "EolBody" and b.history)
    coupled = sum(len(getattr(b, "_moving", [])) for b in world.bodies if hasattr(b, "set_moving_surfaces"))
    ms = 1e3 * float(np.median(times))
    print(json.dumps({
        "scene": name, "device": device.name, "resolution": args.resolution,
        "bodies": dict(Counter(type(b).__name__ for b in world.bodies)),
        "vertices": int(sum(len(b.points()) for b in world.bodies)),
        "coupling_steps_per_frame": world.coupling_steps, "frame": world.frame,
        # intervals whose push on a BEM body was found implicitly, their passes, those ended unconverged
        "implicit_coupling": dict(world.coupling_stats),
        "contacts_last_frame": {"eol_active_rows": int(eol_rows), "coupled_surfaces": int(coupled),
                                "pbd_lockstep_bodies": len(world._lockstep)},
        "build_s": round(t_build, 3), "ms_per_frame": round(ms, 2),
        "ms_per_frame_by_stage_profiled": {k: round(v, 2) for k, v in stages.items()},
        "eol_steps_per_frame": steps,
        "ms_per_eol_world_step": round(ms / (steps / n_eol(world)), 2)
        if steps else None,
        "device_mem_high_mb": round(wp.get_mempool_used_mem_high(device) / 2**20, 1) if device.is_cuda else None,
    }), flush=True)
