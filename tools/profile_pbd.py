"""Per-kernel GPU time of one XPBD frame (CUDA activity timing, graph replay off), and the frame
time with the graph on, for the posed-model workload of bench_pbd.py.

    python tools/profile_pbd.py --size 15k
Prints one JSON object: kernel name -> {launches, total_ms} per frame, and frame totals.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import defaultdict

import warp as wp

sys.path.insert(0, os.path.dirname(__file__))
import bench_pbd  # noqa: E402

import wsim  # noqa: E402
from wsim.device import quiet_warp  # noqa: E402


def build(size: str, use_graph: bool, device: str) -> tuple[wsim.World, wsim.PbdBody]:
    world = wsim.World(fps=30, device=device)
    body = world.add(bench_pbd.posed_body(size, use_graph=use_graph))
    return world, body


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--size", default="15k")
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--frames", type=int, default=5)
    args = p.parse_args()
    quiet_warp()
    world, _ = build(args.size, False, args.device)
    for _ in range(2):
        world.step()
    wp.synchronize()
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    for _ in range(args.frames):
        world.step()
    results = wp.timing_end()
    per = defaultdict(lambda: [0, 0.0])
    for r in results:
        per[r.name][0] += 1
        per[r.name][1] += r.elapsed
    kernels = {k: {"launches": v[0] // args.frames, "total_ms": v[1] / args.frames} for k, v in sorted(per.items(), key=lambda kv: -kv[1][1])}
    world_g, _ = build(args.size, True, args.device)
    for _ in range(3):
        world_g.step()
    wp.synchronize()
    t0 = time.perf_counter()
    n = 30
    for _ in range(n):
        world_g.step()
    wp.synchronize()
    frame_ms = 1e3 * (time.perf_counter() - t0) / n
    print(json.dumps({"size": args.size, "device": args.device, "graph_frame_ms": frame_ms,
                      "sum_kernel_ms_per_frame": sum(v["total_ms"] for v in kernels.values()), "kernels": kernels}))


if __name__ == "__main__":
    main()
