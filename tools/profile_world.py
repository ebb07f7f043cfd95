"""Where a World frame's time goes: host functions (cProfile, own and cumulative time) and, on a
GPU, the kernels' summed GPU time, for one scene after it has reached its contacts.

    python tools/profile_world.py --scene eol_two_spheres --resolution 32 --skip 4 --frames 2 --device cuda:0

Prints one JSON object: ms per frame without the profiler (median of ``--frames``), EoL world
steps per frame, the kernels' GPU ms per frame, the top host functions per frame, and (EoL
contact) wall-clock ms per EoL world step of the stages of ``wsim.eol.body._step_together``,
timed by wrappers around them without the profiler (its overhead inflates Python-heavy code).
"""

from __future__ import annotations

import argparse
import cProfile
import importlib
import json
import pstats
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scenes"))

from wsim.device import quiet_warp  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--scene", default="eol_two_spheres")
ap.add_argument("--device", default=None)
ap.add_argument("--resolution", type=int, default=None)
ap.add_argument("--skip", type=int, default=4, help="frames simulated before profiling (compilation, reaching contact)")
ap.add_argument("--frames", type=int, default=2)
ap.add_argument("--top", type=int, default=25)
ap.add_argument("--passes", default="timing,gpu,timers,profile",
                help="which passes, in this order, each over --frames further frames (contact lasts a few frames: "
                     "e.g. --passes timers)")
args = ap.parse_args()
quiet_warp()
device = wp.get_device(args.device)
scene = importlib.import_module(args.scene)
kw = {"device": device.alias}
if args.resolution is not None:
    kw["resolution"] = args.resolution
world = scene.build(**kw)
for _ in range(args.skip):
    world.step()


def eol_steps() -> int:
    return max([b.steps for b in world.bodies if type(b).__name__ == "EolBody"] or [0])


passes = args.passes.split(",")
times, steps = [], []
for _ in range(args.frames if "timing" in passes else 0):
    wp.synchronize_device(device)
    s0, t = eol_steps(), time.perf_counter()
    world.step()
    wp.synchronize_device(device)
    times.append(time.perf_counter() - t)
    steps.append(eol_steps() - s0)
out: dict = {"scene": args.scene, "resolution": args.resolution, "device": device.name, "passes": passes}
if times:
    out.update(ms_per_frame=1e3 * float(np.median(times)), eol_world_steps_per_frame=float(np.mean(steps)))
if device.is_cuda and "gpu" in passes:
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    for _ in range(args.frames):
        world.step()
    per: dict = defaultdict(lambda: [0, 0.0])
    for r in wp.timing_end():
        per[r.name][0] += 1
        per[r.name][1] += r.elapsed
    out["gpu_ms_per_frame"] = sum(v[1] for v in per.values()) / args.frames
    out["kernels"] = {k: {"launches": v[0] / args.frames, "ms": v[1] / args.frames}
                      for k, v in sorted(per.items(), key=lambda kv: -kv[1][1])[:12]}
# wall-clock timers around the EoL contact stages (no profiler: its overhead inflates Python-heavy code)
if "timers" in passes:
    from wsim.eol import body as eol_body, pairs as eol_pairs

    spent: dict = defaultdict(float)
    counted: dict = defaultdict(int)

    def timed(owner, name: str) -> None:
        fn = getattr(owner, name)

        def wrapper(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[name] += time.perf_counter() - t0
                counted[name] += 1
        setattr(owner, name, wrapper)

    for n in ("entries_device", "rows_from_entries", "joint_system", "row_friction", "moment_couples",
              "node_changes", "own_rows_at", "slip_change", "friction_changes"):
        timed(eol_pairs, n)
    for n in ("_own_rows_all", "_rows_between", "_solve", "_problems", "solve_contact"):
        timed(eol_body, n)
    for n in ("_step_forces", "_step_contact", "_split_launch", "_split_read", "_step_finish", "_pair_samples"):
        timed(eol_body.EolBody, n)
    s0, t = eol_steps(), time.perf_counter()
    for _ in range(args.frames):
        world.step()
    wp.synchronize_device(device)
    n_steps = max(eol_steps() - s0, 1)
    out["timed_ms_per_eol_step"] = round(1e3 * (time.perf_counter() - t) / n_steps, 3)
    out["stage_ms_per_eol_step"] = {k: round(1e3 * v / n_steps, 3) for k, v in sorted(spent.items(), key=lambda kv: -kv[1])}
    out["stage_calls_per_eol_step"] = {k: round(v / n_steps, 2) for k, v in counted.items()}
if "profile" in passes:
    pr = cProfile.Profile()
    pr.enable()
    for _ in range(args.frames):
        world.step()
    wp.synchronize_device(device)
    pr.disable()
    st = pstats.Stats(pr)
    rows = [(f"{Path(k[0]).name}:{k[1]}:{k[2]}", v[1], v[2], v[3]) for k, v in st.stats.items()]
    out["host_own_ms_per_frame"] = {n: [round(1e3 * own / args.frames, 3), calls // args.frames]
                                    for n, calls, own, _ in sorted(rows, key=lambda r: -r[2])[: args.top]}
    out["host_cum_ms_per_frame"] = {n: round(1e3 * cum / args.frames, 3) for n, _, _, cum in sorted(rows, key=lambda r: -r[3])[: args.top]}
print(json.dumps(out))
