"""The loads' balance of a BEM operator set (``wsim.bem.correction.load_balance``): seconds on the
host (numpy/scipy, every core) against the GPU (CuPy, the ``gpu`` extra), and their difference.

    python tools/bench_bem_load_balance.py --divisions 22                 # N = 2906, on a GPU
    python tools/bench_bem_load_balance.py --device cpu --divisions 6

The body is the bumpy cube of ``bench_bem_instances.py`` (0.45 m; here E 2e5 Pa, nu 0.45,
rho 1e3, dt 0.01: n_max 13 at N = 2906). The balance is
built once per operator set, when a body on it first takes a load (``StepOperators.load_balance``):
a sum of the n_max + 1 history matrices H_k, a dense float64 solve with its transpose and six
products with each G_k. One JSON line: N, n_max, the build's seconds, the host's seconds, the
GPU's (twice: the first pays CuPy's first use) and the largest difference relative to the
largest entry.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--divisions", type=int, default=22)
    args = ap.parse_args()

    import warp as wp

    import wsim
    from wsim import mesh as wmesh
    from wsim.bem import build_operators, stepper
    from wsim.bem.correction import load_balance
    from wsim.bem.factorization import cupy_module

    wp.config.quiet = True
    dev = wp.get_device(args.device)
    cube = wmesh.bumpy_cube(size=0.45, divisions=args.divisions, amplitude=0.04)
    jelly = wsim.ElasticMaterial(E=2e5, nu=0.45, rho=1000.0)
    t = time.perf_counter()
    ops = build_operators(cube, jelly, 0.01, device=dev, cache=False, progress=False)
    out = {"device": dev.name if dev.is_cuda else "cpu", "N": ops.n_nodes, "n_max": ops.n_max,
           "build_s": round(time.perf_counter() - t, 2)}
    c = stepper.step_operators(ops, dev, stepper.resolve_backend("auto", dev)).correction
    t = time.perf_counter()
    host = load_balance(ops, c)
    out["host_s"] = round(time.perf_counter() - t, 3)
    cp = cupy_module() if dev.is_cuda else None
    if cp is not None:
        for r in range(2):
            t = time.perf_counter()
            with cp.cuda.Device(dev.ordinal):
                gpu = load_balance(ops, c, cp)
            out[f"gpu_s_{r}"] = round(time.perf_counter() - t, 3)
        out["max_rel_diff"] = float(np.abs(gpu - host).max() / np.abs(host).max())
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
