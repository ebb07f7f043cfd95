"""A large BEM body with compressed operators (issue 20): build, memory and step time, one JSON line
per stage as it finishes (a long run that stops early still reports what it did).

    python tools/bench_bem_large.py --device cuda:0 --divisions 41 --ratio 32   # N = 10088 on a GPU
    python tools/bench_bem_large.py --device cpu --divisions 6 --ratio 8        # the same on a CPU

The body is the bumpy cube of the paper's Table 1 (jelly, dt 0.01) at ``divisions`` (N = 6 d^2 + 2
nodes), built without the cache (a 10k-node set is ~80 GB), the factorization on the GPU when
CuPy is there (``wsim.bem.factorization``), compressed at CR ``ratio`` on the device. It then
falls freely for ``steps`` steps with a traction pulse on one side: the check is physical (the
frame falls as the frame integrator's g dt^2 n (n + 1) / 2 after n steps - the pulse pushes
sideways -, the displacement stays finite and rings down). Reported: the build's stages, the dense operator bytes a step would read against the
compressed ones, seconds per step and per unconstrained solve, the device's peak memory.
"""

from __future__ import annotations

import argparse
import json
import resource
import time

import numpy as np


def emit(**fields) -> None:
    print(json.dumps(fields), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--divisions", type=int, default=41)
    ap.add_argument("--ratio", type=float, default=32.0)
    ap.add_argument("--steps", type=int, default=40)
    args = ap.parse_args()

    import warp as wp

    import wsim
    from wsim import mesh as wmesh
    from wsim.bem import build_operators, stepper
    from wsim.device import quiet_warp, resolve_device

    quiet_warp()
    dev = resolve_device(args.device)
    cube = wmesh.bumpy_cube(size=0.45, divisions=args.divisions, amplitude=0.04)
    jelly = wsim.ElasticMaterial(mu=5e5, nu=0.5, rho=1e3, incompressible=True)
    dt = 0.01
    t0 = time.perf_counter()
    ops = build_operators(cube, jelly, dt, device=dev, cache=False, progress=False)
    n3 = 3 * ops.n_nodes
    dense_step_bytes = (2 * ops.n_max + 2) * n3 * n3 * 4  # H_k, G_k, H_0^-1, H_0^-1 G' in float32
    from wsim.bem import factorization

    emit(stage="build", factorization=factorization.resolve("auto", dev.is_cuda), device=dev.alias, gpu=dev.name if dev.is_cuda else None, N=ops.n_nodes, n_max=ops.n_max,
         seconds=round(time.perf_counter() - t0, 2), timings={k: round(v, 2) for k, v in ops.timings.items()},
         dense_step_bytes=dense_step_bytes, host_peak_bytes=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)

    backend = "warp" if dev.is_cuda else "blas"
    t0 = time.perf_counter()
    so = stepper.step_operators(ops, dev, backend, ("ratio", args.ratio), cache=False)
    wp.synchronize_device(dev)
    emit(stage="compress", ratio=args.ratio, seconds=round(time.perf_counter() - t0, 2),
         kept_ratio=so.compressed.ratio, history_bytes=so.history_bytes, step_bytes=so.matrix_bytes,
         dense_over_compressed=dense_step_bytes / so.matrix_bytes,
         H0_inv_Gp_dense_bytes=int(so.H0_inv_Gp.capacity),
         relative_frobenius_error_H1=so.compressed.H[0].relative_error)

    world = wsim.World(fps=1.0 / dt, device=dev.alias, gravity=(0.0, -9.81, 0.0))
    body = world.add(wsim.BemBody(cube, jelly, dt, operators=ops, matvec=backend, compression=args.ratio, cache=False))
    x, nrm = body.rest_vertices, body.rest_normals
    body.add_traction(lambda t: -2e3 * nrm * (x[:, :1] > 0) * (t < 0.05))
    body.step()
    wp.synchronize_device(dev)
    t0 = time.perf_counter()
    peak_u = 0.0
    taken = 0
    for _ in range(args.steps):
        body.step()
        taken += 1
        peak_u = max(peak_u, float(np.abs(body.displacement()).max()))
        if body.failed:  # a diverging run is reported, not timed
            try:
                body.check_finite(0, body.time)
            except wsim.SimulationDiverged as exc:
                emit(stage="step", failed=str(exc), steps=taken + 1, peak_displacement_m=peak_u)
            return
    wp.synchronize_device(dev)
    per_step = (time.perf_counter() - t0) / args.steps
    t0 = time.perf_counter()
    for _ in range(10):
        body.unconstrained_solve()
    wp.synchronize_device(dev)
    uncnst = (time.perf_counter() - t0) / 10
    n = args.steps + 1
    fall = float(body.state.frame.T[1] - body._T0[1])
    emit(stage="step", steps=args.steps + 1, seconds_per_step=per_step, uncnst_seconds=uncnst,
         frame_drop_m=fall, free_fall_m=-9.81 * dt * dt * n * (n + 1) / 2, peak_displacement_m=peak_u,
         final_displacement_m=float(np.abs(body.displacement()).max()),
         device_peak_bytes=wp.get_mempool_used_mem_high(dev) if dev.is_cuda else None,
         host_peak_bytes=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)


if __name__ == "__main__":
    main()
