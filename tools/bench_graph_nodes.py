"""GPU cost of one dependent step of a PBD frame: kernels replayed back to back in a CUDA graph.

    python tools/bench_graph_nodes.py [--device cuda:0] [--nodes 400]

A Gauss-Seidel PBD frame is a chain of small launches, each waiting for the one before (one per
colour, iteration and substep: ~560 for the posed 15k model). This measures what one link of that
chain costs on its own: a trivial kernel (the graph's floor), a memset, and wsim's edge-stretch
projection (``wsim.kernels.pbd.solve_distance``, launched as the body launches it: 32 threads a
block) over one colour of disjoint particle pairs of several sizes. One JSON line per case:
microseconds per node (median of 20 replays of a graph of ``--nodes`` such launches).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import warp as wp

from wsim.device import quiet_warp
from wsim.kernels import pbd as kp


@wp.kernel
def _trivial(a: wp.array(dtype=float)):
    i = wp.tid()
    a[i] = a[i] + 1.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--nodes", type=int, default=400)
    args = ap.parse_args()
    quiet_warp()
    dev = wp.get_device(args.device)
    if not dev.is_cuda:
        raise SystemExit("bench_graph_nodes measures CUDA graph replays: give a CUDA device")
    rng = np.random.default_rng(0)
    n = 15000
    with wp.ScopedDevice(dev):
        a = wp.zeros(1 << 16, dtype=float)
        x = wp.array(rng.random((n, 3)), dtype=wp.vec3)
        dx, x_prev = wp.zeros(n, dtype=wp.vec3), wp.array(rng.random((n, 3)), dtype=wp.vec3)
        inv_mass = wp.ones(n, dtype=float)
        m = n // 2
        pairs = wp.array(rng.permutation(n)[: 2 * m].reshape(m, 2).astype(np.int32), dtype=wp.vec2i)  # one colour
        rest, compliance, lam = wp.ones(m, dtype=float), wp.full(m, 1e-6, dtype=float), wp.zeros(m, dtype=float)
        count = wp.zeros(1, dtype=float)

        def case(name: str, launch, **extra) -> None:
            wp.synchronize_device(dev)
            with wp.ScopedCapture() as cap:
                for _ in range(args.nodes):
                    launch()
            wp.capture_launch(cap.graph)
            wp.synchronize_device(dev)
            times = []
            for _ in range(20):
                t0 = time.perf_counter()
                wp.capture_launch(cap.graph)
                wp.synchronize_device(dev)
                times.append(time.perf_counter() - t0)
            print(json.dumps({"case": name, "device": dev.name, "nodes": args.nodes, **extra,
                              "us_per_node": round(1e6 * float(np.median(times)) / args.nodes, 3)}), flush=True)

        for threads in (1, 1024, 8192):
            case("trivial kernel", lambda t=threads: wp.launch(_trivial, dim=t, inputs=[a]), threads=threads)
        case("memset", lambda: lam.zero_(), floats=m)
        for size in (256, 2000, 6000):
            case("solve_distance colour", lambda s=size: wp.launch(
                kp.solve_distance, dim=s, inputs=[x, dx, x_prev, inv_mass, pairs, rest, compliance, lam, 0, 0.0,
                                                  1.0 / 600.0, dx, count, 0.0], block_dim=32), constraints=size)


if __name__ == "__main__":
    main()
