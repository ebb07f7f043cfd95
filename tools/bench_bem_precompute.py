"""Benchmark the BEM precomputation: the full operator set of ``wsim.bem.build_operators``.

Cases follow the paper's Table 1 settings (material, dt, so the same n_max) on procedural meshes:

    bumpy_cube  ~3000 vertices (the paper's 3000), rho 1e3, mu 5e5, nu 0.5 (incompressible), dt 0.01
    torus       1152 vertices (the paper's), rho 500, mu 5e4, nu 0.48, dt 0.001 (n_max ~ 32)
    mesh        --mesh PATH (e.g. a ~3500-vertex model), the bunny's rho 3e3, mu 1e6, nu 0.3, dt 0.003
    *_small     the same settings on coarse meshes, for CPU runs

Each case runs in a fresh subprocess (clean peak memory) and prints one JSON line: device, case,
N (collocation nodes), triangles, n_max, samples (Laplace-domain assemblies), precision, seconds
per stage (surface: validation + r_max; setup: uploads, colouring, mass properties; assembly:
Laplace-domain quadrature + CQ accumulation; transfer: device -> host; factorization: LU of H_0,
H_0^-1, H_0^-1 G'; cache_store: HDF5 write with checksums), the factorization's backend,
total_seconds (kernels already compiled by a tiny build: Warp's, and CuPy's where the
factorization runs on the GPU, though a fresh machine's first full-size run is slower still),
cache_load_seconds (the second build, loaded), peak host RSS, peak
device memory (Warp mempool high-water), bytes stored, and the paper's dense float64 storage model
(2 + 2 n_max)(3N)^2 8 B for comparison.

The paper reports "a few minutes to a little under an hour" per scene on a GPU (no exact times).

    python tools/bench_bem_precompute.py --cases bumpy_cube_small,torus_small --device cpu
    python tools/bench_bem_precompute.py --cases bumpy_cube,torus,mesh --mesh bunny.obj
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

CASES = {
    # name: (mesh spec, (rho, mu, nu, incompressible), dt)
    "bumpy_cube": (("bumpy_cube", 22), (1e3, 5e5, 0.5, True), 0.01),
    "torus": (("torus", (48, 24)), (500.0, 5e4, 0.48, False), 0.001),
    "mesh": (("file", None), (3e3, 1e6, 0.3, False), 0.003),
    "bumpy_cube_small": (("bumpy_cube", 6), (1e3, 5e5, 0.5, True), 0.01),
    "torus_small": (("torus", (24, 8)), (500.0, 5e4, 0.48, False), 0.001),
}


def make_mesh(spec, path):
    from wsim import mesh as wmesh

    kind, arg = spec
    if kind == "bumpy_cube":
        return wmesh.bumpy_cube(size=0.45, divisions=arg, amplitude=0.04)  # diagonal ~0.78 m as the paper's r_max
    if kind == "torus":
        return wmesh.torus(major_radius=0.1, minor_radius=0.05, major_sections=arg[0], minor_sections=arg[1])
    if path is None:
        raise SystemExit("case 'mesh' needs --mesh PATH")
    return wmesh.load(path)


def run_case(name: str, device: str, precision: str, mesh_path: str | None, quadrature: dict) -> dict:
    import warp as wp

    import wsim
    from wsim.bem.factorization import resolve as factorization_backend
    from wsim.bem.operators import build_operators
    from wsim.cache import OperatorCache
    from wsim.device import quiet_warp, resolve_device

    quiet_warp()
    spec, (rho, mu, nu, incompressible), dt = CASES[name]
    mesh = make_mesh(spec, mesh_path)
    material = wsim.ElasticMaterial(mu=mu, nu=nu, rho=rho, incompressible=incompressible)
    dev = resolve_device(device)
    # compile (and load) the kernels on a tiny mesh first, so the timings are the warm path: Warp's
    # kernels, and CuPy's when the factorization runs there (its elementwise kernels compile on
    # first use, then come from CuPy's on-disk cache). Not everything: on a fresh H100 machine the
    # bunny's first full-size factorization still took 5.0 s, 1.1 s in the next run
    tiny = wsim.mesh.bumpy_cube(divisions=1)
    build_operators(tiny, material, dt, precision=precision, device=dev, cache=False)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        ops = build_operators(mesh, material, dt, precision=precision, device=dev, cache=OperatorCache(tmp), **quadrature)
        total = time.perf_counter() - t0
        t1 = time.perf_counter()
        again = build_operators(mesh, material, dt, precision=precision, device=dev, cache=OperatorCache(tmp), **quadrature)
        load = time.perf_counter() - t1
        assert again.n_max == ops.n_max
    n = ops.n_nodes
    out = {
        "case": name,
        "device": dev.alias,
        "gpu": dev.name if dev.is_cuda else None,
        "N": n,
        "triangles": int(ops.surface.faces.shape[0]),
        "n_max": ops.n_max,
        "samples": (ops.n_max + 1) // 2 + 1,  # floor(L / 2) + 1 with L = n_max + 1
        "precision": precision,
        "r_max": ops.r_max,
        "quadrature": quadrature or "default",
        "factorization": factorization_backend("auto", dev.is_cuda),
        "seconds": {k: round(v, 4) for k, v in ops.timings.items()},
        "total_seconds": round(total, 3),
        "cache_load_seconds": round(load, 3),
        "peak_host_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "peak_device_bytes": wp.get_mempool_used_mem_high(dev) if dev.is_cuda else None,
        "bytes_stored": ops.nbytes,
        "dense_float64_model_bytes": (2 + 2 * ops.n_max) * (3 * n) ** 2 * 8,
        "paper": "a few minutes to a little under an hour per scene on a GPU (Sec. 4)",
    }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="bumpy_cube_small,torus_small")
    ap.add_argument("--device", default=None)
    ap.add_argument("--precision", default="float32")
    ap.add_argument("--mesh", default=None, help="mesh file for case 'mesh'")
    ap.add_argument("--subdivision", type=int, default=None)
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    quadrature = {} if args.subdivision is None else {"subdivision": args.subdivision}
    if args.one:
        print(json.dumps(run_case(args.one, args.device, args.precision, args.mesh, quadrature)), flush=True)
        return
    for name in args.cases.split(","):
        if name not in CASES:
            raise SystemExit(f"unknown case {name!r}; known: {', '.join(CASES)}")
        cmd = [sys.executable, os.path.abspath(__file__), "--one", name, "--precision", args.precision]
        for flag, value in (("--device", args.device), ("--mesh", args.mesh), ("--subdivision", args.subdivision)):
            if value is not None:
                cmd += [flag, str(value)]
        subprocess.run(cmd, check=True)


if __name__ == "__main__":
    main()
