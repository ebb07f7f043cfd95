"""Throughput of ``wsim sweep`` through Ray on one GPU against every GPU of the host (issue 22 item 1).

    python tools/bench_sweep.py                                   # 8 variants of eol_two_spheres, 1 GPU vs all
    python tools/bench_sweep.py --workers 1,2 --cpu --frames 2 --values 6,7   # the path on a CPU

The same sweep (``--scene``, ``--param`` = ``--values``, ``--frames`` each) runs through a local Ray
limited to 1 worker slot and then to all of them (``--workers``: GPUs, or CPUs with ``--cpu``),
each time into a fresh folder. The kernels are compiled once before either timing (the sweep's
warm-up, which each timed sweep then repeats against the warm cache). One JSON line per run:
workers, variants, wall seconds, variants per second, the variants' own startup (imports), build
and run seconds and devices; a last line with the throughput ratio.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=str(ROOT / "scenes" / "eol_two_spheres.py"))
    ap.add_argument("--param", default="resolution")
    ap.add_argument("--values", default="16,17,18,19,20,21,22,23")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--workers", default=None, help="comma-separated slot counts (default: 1 and every GPU)")
    ap.add_argument("--cpu", action="store_true", help="CPU tasks (one CPU a slot) instead of GPUs")
    args = ap.parse_args()

    import ray
    import warp as wp

    from wsim.device import quiet_warp
    from wsim.sweep import parse_param, sweep

    quiet_warp()
    gpus = len(wp.get_cuda_devices())
    counts = [int(c) for c in args.workers.split(",")] if args.workers else sorted({1, max(gpus, 1)})
    name, values = parse_param(f"{args.param}={args.values}")
    # the kernels compiled into Warp's cache before either timing, so that neither count pays it
    from wsim.sweep import warm_kernels
    warm_s = warm_kernels(str(Path(args.scene).resolve()), {name: values[0]}, "cpu" if args.cpu else None)
    print(json.dumps({"compile_once_s": round(warm_s, 2)}), flush=True)
    rates = {}
    for k in counts:
        with tempfile.TemporaryDirectory() as tmp:
            if args.cpu:
                ray.init(num_cpus=k, num_gpus=0, include_dashboard=False, log_to_driver=False)
            else:
                ray.init(num_cpus=max(2 * k, 2), num_gpus=k, include_dashboard=False, log_to_driver=False)
            try:
                t = time.perf_counter()
                records = sweep(args.scene, {name: values}, tmp, device="cpu" if args.cpu else None, frames=args.frames,
                                engine="ray", log=lambda s: None)
                wall = time.perf_counter() - t
            finally:
                ray.shutdown()
        rates[k] = len(records) / wall
        print(json.dumps({"workers": k, "kind": "cpu" if args.cpu else "gpu", "variants": len(records), "wall_s": round(wall, 2),
                          "variants_per_s": round(rates[k], 4), "failed": sum(r["status"] != "ok" for r in records),
                          "startup_s": [r.get("startup_s") for r in records], "build_s": [r.get("build_s") for r in records], "run_s": [r.get("run_s") for r in records],
                          "devices": sorted({str(r.get("device")) for r in records})}), flush=True)
    if len(counts) > 1:
        print(json.dumps({"throughput_ratio": round(rates[counts[-1]] / rates[counts[0]], 3),
                          "workers": [counts[0], counts[-1]]}), flush=True)


if __name__ == "__main__":
    main()
