"""BEM operator assembly on one GPU against every GPU of the host (issue 22 item 2).

    python tools/bench_bem_multigpu.py --divisions 24,41          # N = 3458 and 10088 on a 2-GPU host
    python tools/bench_bem_multigpu.py --device cpu --divisions 2 --devices cpu,cpu --repeat 1   # the path on a CPU

The body is the bumpy cube of ``bench_bem_large.py`` (0.45 m, the paper's jelly: mu 5e5, nu 0.5,
rho 1e3, dt 0.01) at each ``--divisions``. Per size, after a tiny build that compiles the kernels
on every device, ``build_operators`` (no cache) runs ``--repeat`` times on the first device alone
and on ``--devices`` (default "all"), alternating. One JSON line per build: the devices, the
stages' seconds (assembly = Laplace-domain quadrature + CQ accumulation, the part spread over the
devices; transfer; factorization, on the first device), and checksums of H_1 and G' (sums of
absolute values: the multi-device build must give the single-device operators, to the last bit
up to the CUDA assembly's atomic sums). A last line per size: the assembly speed-up (median over
the repeats). The operator sets are not held side by side: a 10k-node set is ~80 GB of host memory.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None, help="the single device (default: cuda:0 if present)")
    ap.add_argument("--devices", default="all", help='"all" or a comma-separated list (cuda:0,cuda:1)')
    ap.add_argument("--divisions", default="24,41", help="bumpy cube divisions: 24 -> N = 3458, 41 -> N = 10088")
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()

    import numpy as np
    import warp as wp

    import wsim
    from wsim import mesh as wmesh
    from wsim.bem import build_operators
    from wsim.bem.operators import assembly_devices
    from wsim.device import quiet_warp, resolve_device

    quiet_warp()
    one = [resolve_device(args.device)]
    many = args.devices if args.devices == "all" else args.devices.split(",")
    names = [d.alias for d in assembly_devices(None, many)]
    jelly = wsim.ElasticMaterial(mu=5e5, nu=0.5, rho=1e3, incompressible=True)
    dt = 0.01
    tiny = wmesh.bumpy_cube(size=0.45, divisions=1, amplitude=0.04)
    t = time.perf_counter()
    build_operators(tiny, jelly, dt, devices=many, cache=False, progress=False)
    print(json.dumps({"warm_up_s": round(time.perf_counter() - t, 2), "devices": names,
                      "gpus": [d.name for d in wp.get_cuda_devices()]}), flush=True)
    for div in (int(d) for d in args.divisions.split(",")):
        cube = wmesh.bumpy_cube(size=0.45, divisions=div, amplitude=0.04)
        seconds: dict[str, list[float]] = {"one": [], "many": []}
        sums: dict[str, tuple[float, float]] = {}
        for _ in range(args.repeat):
            for label, devs in (("one", one), ("many", many)):
                t = time.perf_counter()
                ops = build_operators(cube, jelly, dt, devices=devs, cache=False, progress=False)
                total = time.perf_counter() - t
                sums[label] = (float(np.abs(ops.H[1]).sum(dtype=np.float64)), float(np.abs(ops.Gp).sum()))
                seconds[label].append(ops.timings["assembly"])
                print(json.dumps({"divisions": div, "N": ops.n_nodes, "n_max": ops.n_max, "run": label,
                                  "devices": [d.alias for d in assembly_devices(None, devs)], "total_s": round(total, 3),
                                  **{k: round(v, 3) for k, v in ops.timings.items()},
                                  "H1_abs_sum": sums[label][0], "Gp_abs_sum": sums[label][1]}), flush=True)
                del ops
        a, b = statistics.median(seconds["one"]), statistics.median(seconds["many"])
        print(json.dumps({"divisions": div, "assembly_s_one": round(a, 3), "assembly_s_many": round(b, 3),
                          "speedup": round(a / b, 3), "devices": names,
                          "same_checksums": sums["one"] == sums["many"],
                          "checksum_rel_diff": max(abs(x - y) / max(abs(x), 1e-300) for x, y in zip(sums["one"], sums["many"]))}),
              flush=True)


if __name__ == "__main__":
    main()
