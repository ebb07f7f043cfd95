"""Where the posed model's frame time goes on a GPU (bench_pbd.py's workload): the wall time of
``World.step`` per frame (10th/50th/90th percentiles over 300 frames after 30 warm-up frames), the
GPU span of each frame by CUDA events, and the pure GPU time of the frame's recorded substep graphs
replayed back to back (no host work between them), plus one handle motion's host cost.

    python tools/profile_pbd_frame.py [--size 15k] [--device cuda:0]
Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_pbd  # noqa: E402

import wsim  # noqa: E402
from wsim.device import quiet_warp  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="15k")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    quiet_warp()
    world = wsim.World(fps=30, device=args.device)
    body = world.add(bench_pbd.posed_body(args.size))
    dev = world.device
    if not dev.is_cuda:
        raise SystemExit("needs a CUDA device (events and recorded graphs)")
    for _ in range(30):
        world.step()
    wp.synchronize_device(dev)
    walls, spans = [], []
    for _ in range(args.frames):
        e0, e1 = wp.Event(device=dev, enable_timing=True), wp.Event(device=dev, enable_timing=True)
        t0 = time.perf_counter()
        wp.record_event(e0)
        world.step()
        wp.record_event(e1)
        wp.synchronize_event(e1)
        walls.append(time.perf_counter() - t0)
        spans.append(wp.get_event_elapsed_time(e0, e1) / 1e3)
    pure = None
    graphs = body._graph  # the pipelined frame's one graph per substep (a body with handles)
    if isinstance(graphs, list) and all(g is not None for g in graphs):
        e0, e1 = wp.Event(device=dev, enable_timing=True), wp.Event(device=dev, enable_timing=True)
        wp.record_event(e0)
        for _ in range(100):
            for g in graphs:
                wp.capture_launch(g)
        wp.record_event(e1)
        wp.synchronize_event(e1)
        pure = wp.get_event_elapsed_time(e0, e1) / 1e3 / 100
    hd = body.handles[0]
    t0 = time.perf_counter()
    for i in range(1000):
        hd.pose(0.01 * i, (len(hd.vertices), 3), body._handle_labels[0], body._frame_of(0.01 * i))
    pose_us = (time.perf_counter() - t0) / 1000 * 1e6

    def q(a: list[float], p: float) -> float:
        return round(float(np.percentile(a, p)) * 1e3, 4)

    print(json.dumps({"case": f"posed{args.size}_split", "device": dev.name, "frames": args.frames,
                      "wall_ms": {"p10": q(walls, 10), "p50": q(walls, 50), "p90": q(walls, 90)},
                      "gpu_span_ms": {"p10": q(spans, 10), "p50": q(spans, 50), "p90": q(spans, 90)},
                      "pure_graphs_ms_per_frame": None if pure is None else round(pure * 1e3, 4),
                      "handle_pose_us": round(pose_us, 2)}))


if __name__ == "__main__":
    main()
