"""A large BEM body with compressed operators (issue 20): build, memory and step time, one JSON line
per stage as it finishes (a long run that stops early still reports what it did).

    python tools/bench_bem_large.py --device cuda:0 --divisions 41 --ratio 32   # N = 10088 on a GPU
    python tools/bench_bem_large.py --device cpu --divisions 6 --ratio 8        # the same on a CPU

The body is the bumpy cube of the paper's Table 1 (jelly, dt 0.01) at ``divisions`` (N = 6 d^2 + 2
nodes), built without the cache (a 10k-node set is ~80 GB), the factorization on the GPU when
CuPy is there (``wsim.bem.factorization``), compressed at CR ``ratio`` on the device. Stages:
``build``; ``compress`` (time, bytes, H_1's Frobenius error; a second one for the error set
when the 'error' variant runs); ``accuracy`` (each compressed matrix's kept ratio and relative
matvec error against the dense one on smooth surface fields, random vectors, fresh tuning
fields and the run's own load); then one ``step`` line per ``--variants`` entry (compressed,
error, dense): the body falls
freely for ``steps`` steps with a traction pulse on one side (the frame must fall as the frame
integrator's g dt^2 n (n + 1) / 2, the displacement ring down), with seconds per step and per
unconstrained solve, the bytes a step reads and the peaks of device and host memory; and a
``trajectory`` line: the compressed displacements against the dense ones. ``--watch-memory S``
reports the host memory every S seconds on stderr, with where the run is.
"""

from __future__ import annotations

import argparse
import gc
import json
import resource
import time

import numpy as np


def emit(**fields) -> None:
    print(json.dumps(fields), flush=True)


def _meminfo() -> dict[str, int]:
    """This process's resident and peak bytes and the host's available bytes (Linux /proc)."""
    out = {}
    for path, keys in (("/proc/self/status", ("VmRSS", "VmHWM")), ("/proc/meminfo", ("MemAvailable",))):
        try:
            with open(path) as f:
                for line in f:
                    name, _, rest = line.partition(":")
                    if name in keys:
                        out[name] = int(rest.split()[0]) * 1024
        except OSError:
            pass
    return out


def watch_memory(period: float) -> None:
    """Report host memory every ``period`` seconds on stderr (a 10k-node build runs close to a
    128 GB host's limit: where it dies is worth knowing)."""
    import sys
    import threading

    t0 = time.perf_counter()

    main_id = threading.main_thread().ident

    def loop() -> None:
        import traceback

        while True:
            time.sleep(period)
            frame = sys._current_frames().get(main_id)
            stack = traceback.extract_stack(frame) if frame else []
            ours = [f for f in stack if "/wsim/" in f.filename or "/tools/" in f.filename]
            where = [f"{f.filename.rsplit('/', 1)[-1]}:{f.lineno} {f.name}" for f in (ours[-4:] + stack[-2:])]
            print(json.dumps({"stage": "memory", "t": round(time.perf_counter() - t0, 1), **_meminfo(), "where": where}),
                  file=sys.stderr, flush=True)

    threading.Thread(target=loop, daemon=True).start()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--divisions", type=int, default=41)
    ap.add_argument("--ratio", type=float, default=32.0)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--error", type=float, default=0.01, help="compression_error of the 'error' variant")
    ap.add_argument("--variants", default="compressed,dense",
                    help="comma list of compressed (CR --ratio), error (compression_error --error), dense (the dense "
                         "set needs 44 GB of device memory at N = 10088)")
    ap.add_argument("--watch-memory", type=float, default=0.0, help="report host memory every this many seconds")
    args = ap.parse_args()
    if args.watch_memory > 0:
        watch_memory(args.watch_memory)

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
    ch = so.compressed
    emit(stage="compress", ratio=args.ratio, seconds=round(time.perf_counter() - t0, 2),
         kept_ratio=ch.ratio, history_bytes=so.history_bytes, step_bytes=so.matrix_bytes,
         dense_over_compressed=dense_step_bytes / so.matrix_bytes,
         relative_frobenius_error_H1=ch.H[0].relative_error)
    accuracy(ops, ch, "ratio")
    held = [so]
    if "error" in args.variants.split(","):  # the error set, shared with the 'error' variant's body
        t0 = time.perf_counter()
        so_e = stepper.step_operators(ops, dev, backend, ("error", args.error), cache=False)
        wp.synchronize_device(dev)
        emit(stage="compress", error=args.error, seconds=round(time.perf_counter() - t0, 2),
             kept_ratio=so_e.compressed.ratio, step_bytes=so_e.matrix_bytes,
             dense_over_compressed=dense_step_bytes / so_e.matrix_bytes)
        accuracy(ops, so_e.compressed, "error")
        held.append(so_e)

    results = {}
    for variant in args.variants.split(","):
        results[variant] = run_variant(variant, ops, cube, jelly, dt, dev, backend, args)
    del so, held  # held until here: the compressed variants share these sets
    if "dense" in results and results["dense"] is not None:
        ref = results["dense"]
        for name, u in results.items():
            if name != "dense" and u is not None:
                m = min(len(u), len(ref))
                scale = max(float(np.abs(ref[:m]).max()), 1e-30)
                per_step = np.linalg.norm((u[:m] - ref[:m]).reshape(m, -1), axis=1)
                ref_l2 = np.maximum(np.linalg.norm(ref[:m].reshape(m, -1), axis=1), 1e-30)
                emit(stage="trajectory", variant=name, against="dense", steps=m,
                     max_displacement_error_over_max_displacement=float(np.abs(u[:m] - ref[:m]).max()) / scale,
                     # the first 12 steps: the push (t < 0.05 s) and its release, where the history
                     # sums cancel most
                     relative_l2_error_by_step=np.round(per_step[:12] / ref_l2[:12], 4).tolist(),
                     l2_error_over_peak_l2_by_step=np.round(per_step[:12] / ref_l2.max(), 4).tolist())


def accuracy(ops, ch, spec: str) -> None:
    """Each compressed matrix's kept ratio and relative matvec error against the dense one, on
    smooth surface fields (what a step mostly multiplies), on random vectors (the worst case for a
    Haar basis), on a fresh draw of ``compression_error``'s tuning kinds (``tuning_fields``, seed 1)
    and on the run's own load (the traction -n on the side x > 0)."""
    import itertools

    from wsim.bem.compression import folded_G, smooth_fields, tuning_fields
    from wsim.mesh.surface import vertex_normals

    s = ops.surface
    rng = np.random.default_rng(1)
    n3 = 3 * ops.n_nodes
    load = (-vertex_normals(s.nodes, s.faces) * (s.nodes[:, :1] > 0)).reshape(-1, 1)  # the run's traction
    X = {"smooth": smooth_fields(s.nodes, 4, seed=7), "random": rng.standard_normal((n3, 4)),
         "tuning_kinds": tuning_fields(s, seed=1), "load": load}
    names = [*(f"H{k}" for k in range(1, ops.n_max + 1)), *(f"G{k}" for k in range(1, ops.n_max + 1)), "H0_inv",
             "H0_inv_Gp"]
    # the set stores G'_k (``compression.folded_G``), made one at a time (7 GB each at N = 10088)
    dense = itertools.chain((ops.H[k] for k in range(1, ops.n_max + 1)),
                            (folded_G(ops, k) for k in range(1, ops.n_max + 1)), (ops.H0_inv, ops.H0_inv_Gp))
    out = {}
    for name, A, m in zip(names, dense, ch.matrices):
        errs = {"ratio": round(m.ratio, 2)}
        for kind, x in X.items():
            exact = A @ x.astype(A.dtype)
            approx = np.stack([m.matvec(x[:, j]) for j in range(x.shape[1])], axis=1)
            errs[kind] = float(np.max(np.linalg.norm(approx - exact, axis=0) / np.linalg.norm(exact, axis=0)))
        out[name] = errs
    emit(stage="accuracy", set=spec, relative_matvec_error=out)


def run_variant(variant: str, ops, cube, jelly, dt: float, dev, backend: str, args):
    """Step the body ``steps`` times as ``variant`` ("compressed" at the ratio, or "dense"): one JSON
    line, and the displacement of every step (for the trajectory comparison) or None when it could
    not run."""
    import warp as wp

    import wsim

    kw = {"dense": {}, "compressed": {"compression": args.ratio}, "error": {"compression_error": args.error}}[variant]
    world = wsim.World(fps=1.0 / dt, device=dev.alias, gravity=(0.0, -9.81, 0.0))
    t_add = time.perf_counter()
    try:
        body = world.add(wsim.BemBody(cube, jelly, dt, operators=ops, matvec=backend, cache=False, name=variant, **kw))
        add_seconds = time.perf_counter() - t_add  # the compression (or the dense upload) of a new set
        x, nrm = body.rest_vertices, body.rest_normals
        body.add_traction(lambda t: -2e3 * nrm * (x[:, :1] > 0) * (t < 0.05))
        t0 = time.perf_counter()
        body.step()
        wp.synchronize_device(dev)
        first = time.perf_counter() - t0
    except (MemoryError, RuntimeError) as exc:  # dense operators that do not fit
        emit(stage="step", variant=variant, skipped=f"{type(exc).__name__}: {exc}"[:300])
        return None
    peak = []
    us = [body.displacement().copy()]
    t0 = time.perf_counter()
    failed = None
    for _ in range(args.steps):
        try:
            body.step()
        except (wsim.SimulationDiverged, np.linalg.LinAlgError) as exc:
            failed = str(exc)[:300]
            break
        u = body.displacement()
        us.append(u.copy())
        peak.append(float(np.abs(u).max()))
    wp.synchronize_device(dev)
    per_step = (time.perf_counter() - t0) / max(len(peak), 1)
    uncnst = None
    if failed is None:
        t0 = time.perf_counter()
        for _ in range(10):
            body.unconstrained_solve()
        wp.synchronize_device(dev)
        uncnst = (time.perf_counter() - t0) / 10
    n = len(us)
    fall = float(body.state.frame.T[1] - body._T0[1])
    ch = body._so.compressed
    emit(stage="step", variant=variant, steps=n, kept_ratio=None if ch is None else ch.ratio,
         add_seconds=add_seconds, failed=failed, first_step_seconds=first, seconds_per_step=per_step,
         uncnst_seconds=uncnst, frame_drop_m=fall, free_fall_m=-9.81 * dt * dt * n * (n + 1) / 2,
         max_displacement_by_step=[round(v, 9) for v in peak],
         step_matrix_bytes=body._so.matrix_bytes,
         device_peak_bytes=wp.get_mempool_used_mem_high(dev) if dev.is_cuda else None,
         host_peak_bytes=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
    del body, world
    gc.collect()
    return np.stack(us)


if __name__ == "__main__":
    main()
