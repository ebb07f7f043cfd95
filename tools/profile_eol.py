"""Where an EoL step's time goes: GPU time per kernel (CUDA activity timing) and host time per
Python function (cProfile), for the cases of bench_eol.py.

    python tools/profile_eol.py --resolution 32 --cases free,contact --collision-block 1,2 --device cuda:0

Prints one JSON object per case: wall ms per step (no profiler) and of it the host's waits in
device-to-host reads (``wp.array.numpy``, which synchronizes: wall - wait is the host's own Python
and launch work), the kernels' summed GPU ms per step and launches per step (CUDA activity timing:
a replayed graph counts as one), the top kernels, and the top host functions by own time. Each
case first steps ``--warmup`` steps (the contact case settles into its patch).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import sys
import time
from collections import defaultdict

import numpy as np
import warp as wp

sys.path.insert(0, os.path.dirname(__file__))
from bench_eol import make_world  # noqa: E402

from wsim.device import quiet_warp  # noqa: E402
from wsim.eol.body import _step_together  # noqa: E402


def steps(body, n: int) -> None:
    for _ in range(n):
        _step_together([body], [0], min(body.dt_elastic, body.dt_max or np.inf))


def profile_case(case: str, resolution: int, block: int, device: str, warmup: int, n: int, top: int,
                 damping: float) -> dict:
    # damping: bench_eol's 20 Pa s lets the ball hop off the ground; a larger value keeps the
    # profiled window in contact
    world, body = make_world(case, resolution, device, "rigid", False, damping=damping, collision_block=block)
    world.step()  # binds the colliders, compiles the kernels
    steps(body, warmup)
    wp.synchronize_device(device)
    real_numpy, waited = wp.array.numpy, [0.0]

    def timed_numpy(self):
        t = time.perf_counter()
        try:
            return real_numpy(self)
        finally:
            waited[0] += time.perf_counter() - t

    wp.array.numpy = timed_numpy
    try:
        t0 = time.perf_counter()
        steps(body, n)
        wp.synchronize_device(device)
        wall = (time.perf_counter() - t0) / n
    finally:
        wp.array.numpy = real_numpy
    out: dict = {"case": case, "resolution": resolution, "collision_block": block, "damping": damping, "device": wp.get_device(device).name,
                 "wall_ms_per_step": 1e3 * wall, "wait_ms_per_step": 1e3 * waited[0] / n,
                 "rows_mean": float(np.mean([r.rows for r in body.history[-n:]])),
                 "qp_iterations_mean": float(np.mean([r.qp_iterations for r in body.history[-n:]]))}
    if wp.get_device(device).is_cuda:
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        steps(body, n)
        results = wp.timing_end()
        per: dict = defaultdict(lambda: [0, 0.0])
        for r in results:
            per[r.name][0] += 1
            per[r.name][1] += r.elapsed
        out["gpu_ms_per_step"] = sum(v[1] for v in per.values()) / n
        out["launches_per_step"] = sum(v[0] for v in per.values()) / n
        out["kernels"] = {k: {"launches": v[0] / n, "ms": v[1] / n}
                          for k, v in sorted(per.items(), key=lambda kv: -kv[1][1])[:top]}
    pr = cProfile.Profile()
    pr.enable()
    steps(body, n)
    wp.synchronize_device(device)
    pr.disable()
    st = pstats.Stats(pr)
    rows = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:top]  # by own time
    out["host_own_ms_per_step"] = {f"{os.path.basename(f)}:{line}:{fn}": 1e3 * v[2] / n for (f, line, fn), v in rows}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", default="32")
    ap.add_argument("--cases", default="free,contact")
    ap.add_argument("--collision-block", default="1")
    ap.add_argument("--device", default=None)
    ap.add_argument("--warmup", type=int, default=150)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--damping", type=float, default=1000.0, help="EolBody damping [Pa s]")
    args = ap.parse_args()
    quiet_warp()
    device = args.device or ("cuda:0" if wp.get_cuda_device_count() else "cpu")
    for res in (int(r) for r in args.resolution.split(",")):
        for case in args.cases.split(","):
            for block in ([int(b) for b in args.collision_block.split(",")] if case == "contact" else [1]):
                print(json.dumps(profile_case(case, res, block, device, args.warmup, args.steps, args.top,
                                                      args.damping)), flush=True)


if __name__ == "__main__":
    main()
