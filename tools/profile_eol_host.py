"""Where an EoL step's wall time goes on a GPU: the host's own work, the waits on the device, and the
kernels' GPU time. One JSON line per case.

    python tools/profile_eol_host.py --resolution 32 --device cuda:0 --steps 200

For the free-flight sphere of ``tools/bench_eol.py`` (and ``--case contact``), stepped as the World
steps it (``advance`` to each frame's end), three passes over the same steps:

* wall: seconds per step, the device synchronized at the end;
* wait: the seconds the host spent blocked in device-to-host reads (``wp.array.numpy``, which
  synchronizes), so wall - wait is the host's own Python and launch work per step;
* kernels: Warp's CUDA activity timing (``wp.timing_begin``), the GPU time of every kernel, copy
  and memset, summed per name; their total is the GPU's busy time per step, and the count the
  launches per step.

Also the host's top functions by own time (cProfile) over the wall pass's steps.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_eol import make_world  # noqa: E402 (the same sphere)


def _steps(body, n: int) -> int:
    n0 = body.steps
    while body.steps - n0 < n:
        body.advance(body.time, body.time + 1.0 / 30.0)
    return body.steps - n0


def profile_case(case: str, resolution: int, device: str, steps: int, top: int) -> dict:
    world, body = make_world(case, resolution, device, "rigid", profile=False)
    world.step()
    world.step()
    wp.synchronize_device(device)
    out: dict = {"case": case, "resolution": resolution, "device": str(wp.get_device(device)),
                 "device_name": wp.get_device(device).name}

    # wall and the host's waits on reads
    real_numpy = wp.array.numpy
    waited = [0.0]

    def timed_numpy(self):
        t = time.perf_counter()
        try:
            return real_numpy(self)
        finally:
            waited[0] += time.perf_counter() - t

    wp.array.numpy = timed_numpy
    prof = cProfile.Profile()
    try:
        t0 = time.perf_counter()
        prof.enable()
        n = _steps(body, steps)
        prof.disable()
        wp.synchronize_device(device)
        wall = time.perf_counter() - t0
    finally:
        wp.array.numpy = real_numpy
    out.update(steps=n, wall_s_per_step=wall / n, wait_s_per_step=waited[0] / n,
               host_s_per_step=(wall - waited[0]) / n)

    # the same steps without the profiler's overhead: wall alone
    t0 = time.perf_counter()
    n2 = _steps(body, steps)
    wp.synchronize_device(device)
    out["wall_s_per_step_unprofiled"] = (time.perf_counter() - t0) / n2

    # GPU time per kernel (CUDA events around each launch)
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    n3 = _steps(body, steps)
    wp.synchronize_device(device)
    results = wp.timing_end()
    per: dict[str, list[float]] = {}
    for r in results:
        per.setdefault(r.name, []).append(r.elapsed * 1e-3)  # ms -> s
    kernels = sorted(((k, float(np.sum(v)) / n3, len(v) / n3) for k, v in per.items()), key=lambda x: -x[1])
    out["gpu_s_per_step"] = float(sum(k[1] for k in kernels))
    out["launches_per_step"] = float(sum(k[2] for k in kernels))
    out["gpu_top"] = [{"name": k, "s_per_step": s, "per_step": c} for k, s, c in kernels[:top]]

    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("tottime").print_stats(top)
    out["host_top"] = [line.strip() for line in buf.getvalue().splitlines() if line.strip()][-top:]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", default="free", help="free, contact or both (comma-separated)")
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--top", type=int, default=25)
    args = ap.parse_args()
    for case in args.case.split(","):
        print(json.dumps(profile_case(case, args.resolution, args.device, args.steps, args.top)), flush=True)


if __name__ == "__main__":
    main()
