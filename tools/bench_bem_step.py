"""Benchmark the BEM time step (paper Table 1, column UNCNST): one JSON line per case.

    python tools/bench_bem_step.py --cases bumpy_cube_small                 # CPU-sized
    python tools/bench_bem_step.py --cases bumpy_cube,mesh --mesh bunny.obj  # on a GPU machine

Per case: operators built (not cached, not timed here: see bench_bem_precompute.py), then a body
spinning and pushed by a traction pulse is stepped

* with ``profile=True`` (device synchronized after each stage; the host path): seconds per step
  by stage (loads, history, solve = the paper's UNCNST; correction + frame = ERRCR);
* without profiling: seconds per whole step (``step()``: kept on the device, ``wsim.bem.device_step``,
  with one read-back per step), per step of one ``advance`` over all the steps (one read-back, as a
  World frame has), per step on the host path (``device_step=False``), and per unconstrained solve
  alone (``BemBody.unconstrained_solve``: history, loads, Eq. 12 and the copy of u_n to the host);
  and the device path's end state against the host path's after the same steps from the start;
* ``world_drop``: the body dropped onto a ground plane in a World at 30 fps, device steps on
  and off (``BemBody.device_window`` hands the fall to the device and the landing to the
  constraint solve): seconds per frame, steps taken on the device, the two runs' difference;

and the history matvec alone is timed and compared, in the same run, with the same product through
torch (``torch.mv`` over the 2 n_max matrices, on the GPU, when torch is importable) and numpy BLAS
(on the host copies). GB/s counts the matrix bytes read once per pass.

``--compression 8,32`` adds, per ratio CR, the same measurements for a body with compressed
operators (``BemBody(compression=CR)``, Warp backend: built on the GPU, or on the host on the CPU)
and, for every body (dense too), a trajectory of ``--compare-steps`` steps from the same start and
loads: the compressed body's displacement error against the dense one's, over the dense one's
largest displacement. Compressed history = the sparse pass over the wavelet-domain rings; a step
also transforms its two new ring vectors (``ring_update_seconds``, counted in
``history_with_ring_update_seconds`` and in the speed-up against dense). On CUDA the history (and
ring update) is also captured as a CUDA graph and replayed (``..._graph_seconds``): the device's
time without Python's per-launch cost, which a compressed pass (8 launches) feels and the dense
one (1 launch) does not.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_bem_precompute import CASES, make_mesh  # noqa: E402

PAPER_UNCNST = {"bumpy_cube": 0.268, "mesh": 0.0912}  # Table 1, s per step on one CPU thread


def _time(fn, repeats: int, sync) -> float:
    fn()
    sync()
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(repeats):
            fn()
        sync()
        best = min(best, (time.perf_counter() - t0) / repeats)
    return best


def _drop(mesh, material, ops, dev, sync, frames: int = 30) -> dict:
    """The body dropped from rest onto a ground plane in a World at 30 fps, device steps on and
    off: seconds per frame over the fall and the landing, the steps the device took, and the
    largest point difference between the two runs."""
    import wsim

    out: dict = {"frames": frames}
    ends = []
    for on in (None, True, False):  # None: an untimed run first (the contact kernels compile on first contact)
        world = wsim.World(fps=30, device=dev.alias, gravity=(0.0, -9.81, 0.0))
        world.add_collider(wsim.GroundPlane(0.0, friction=0.3))
        drop = 0.5 * 9.81 * (0.6 * frames / 30.0) ** 2  # lands after 60 % of the frames
        lo = float((ops.surface.nodes - ops.com)[:, 1].min())
        body = world.add(wsim.BemBody(mesh, material, ops.dt, operators=ops, device_step=bool(on), cache=False, matvec="warp",
                                      position=(0.0, drop - lo, 0.0) - ops.com))
        on_device = [0]
        run = body._device_steps

        def counted(target, run=run, body=body, on_device=on_device):
            first = body.steps
            run(target)
            on_device[0] += body.steps - first

        body._device_steps = counted
        world.step()  # compile, capture
        sync()
        t0 = time.perf_counter()
        pts = []
        for _ in range(frames - 1):
            world.step()
            pts.append(body.points())
        sync()
        if on is None:
            continue
        key = "device" if on else "host"
        out[f"{key}_seconds_per_frame"] = (time.perf_counter() - t0) / (frames - 1)
        out[f"{key}_steps_on_device"] = on_device[0]
        out["steps"] = body.steps
        out["lowest_point_m"] = float(np.array(pts)[:, :, 1].min())
        ends.append(np.array(pts))
    out["device_vs_host_points_m"] = float(np.abs(ends[0] - ends[1]).max())
    return out


def run_case(name: str, device: str | None, precision: str, mesh_path: str | None, steps: int,
             ratios: list[float] | None = None, compare_steps: int = 100) -> dict:
    import warp as wp

    import wsim
    from wsim.bem import stepper
    from wsim.bem.operators import build_operators
    from wsim.device import quiet_warp, resolve_device

    quiet_warp()
    spec, (rho, mu, nu, incompressible), dt = CASES[name]
    mesh = make_mesh(spec, mesh_path)
    material = wsim.ElasticMaterial(mu=mu, nu=nu, rho=rho, incompressible=incompressible)
    dev = resolve_device(device)
    t0 = time.perf_counter()
    ops = build_operators(mesh, material, dt, precision=precision, device=dev, cache=False)
    build_s = time.perf_counter() - t0

    def sync() -> None:
        wp.synchronize_device(dev)

    results: dict = {}
    backends = ["warp"] + (["blas"] if dev.is_cpu else [])
    cases = [(b, None) for b in backends] + [("warp", r) for r in ratios or []]
    keep_alive = []  # the shared compressed operator sets outlive the bodies of one case

    def make_body(backend: str, ratio: float | None, profile: bool):
        world = wsim.World(fps=1.0 / dt, device=dev.alias, gravity=(0.0, -9.81, 0.0))
        body = world.add(wsim.BemBody(mesh, material, dt, operators=ops, matvec=backend, profile=profile,
                                      angular_velocity=(0.0, 2.0, 1.0), compression=ratio, cache=False))
        x, nrm = body.rest_vertices, body.rest_normals
        body.add_traction(lambda t: -2e3 * nrm * (x[:, :1] > 0) * (1.0 + np.sin(40.0 * t)))  # a pulsing squeeze
        return body

    trajectories: dict[str, np.ndarray] = {}
    for backend, ratio in cases:
        label = backend if ratio is None else f"{backend} CR {ratio:g}"
        compress_s = None
        if ratio is not None:
            t0 = time.perf_counter()
            keep_alive.append(stepper.step_operators(ops, dev, backend, ("ratio", ratio), cache=False))
            sync()
            compress_s = time.perf_counter() - t0
        body = make_body(backend, ratio, True)
        body.step()  # compile / first touch
        body.timings = {k: 0.0 for k in body.timings}
        n_prof = max(steps // 2, 5)
        for _ in range(n_prof):
            body.step()
        stage = {k: v / n_prof for k, v in body.timings.items()}
        body.profile = False
        for _ in range(2 * ops.n_max + 1):  # the device path: compile, then capture each ring slot's graph
            body.step()
        sync()
        t1 = time.perf_counter()
        for _ in range(steps):
            body.step()
        sync()
        per_step = (time.perf_counter() - t1) / steps
        paths = {}
        if ratio is None and backend == "warp":  # the step kept on the device, one read-back per advance, and the host path
            t1 = time.perf_counter()
            body.advance(body.time, body.time + steps * dt)
            sync()
            paths["seconds_per_step_one_advance"] = (time.perf_counter() - t1) / steps
            body.device_step = False
            t1 = time.perf_counter()
            for _ in range(steps):
                body.step()
            sync()
            paths["seconds_per_step_host_path"] = (time.perf_counter() - t1) / steps
            body.device_step = True
            ends = []
            for on_device in (True, False):  # the same run from the start both ways: what the device path changes
                fresh = make_body(backend, None, False)
                fresh.device_step = on_device
                fresh.advance(0.0, steps * dt)
                ends.append((fresh.points(), fresh.frame.velocity.copy()))
            paths["device_vs_host_path_points_m"] = float(np.abs(ends[0][0] - ends[1][0]).max())
            paths["device_vs_host_path_velocity_m_s"] = float(np.abs(ends[0][1] - ends[1][1]).max())
            paths["compared_steps"] = steps
            paths["world_drop"] = _drop(mesh, material, ops, dev, sync)
        uncnst = _time(body.unconstrained_solve, 50, sync)  # UNCNST alone, no per-stage syncs
        so = body._so
        h = so.vectors()
        hist = _time(lambda: stepper.history(so, body._U_k, body._P_k, body.state.B, body.state.ring, h,
                                             body._scratch), 20, sync)
        ring = 0.0
        slot = (body.state.ring - 1) % so.n_max

        def history_and_ring() -> None:
            stepper.history(so, body._U_k, body._P_k, body.state.B, body.state.ring, h, body._scratch)
            stepper.ring_written(so, body._U_k, body._P_k, slot, body._scratch, body._bf_in)

        if body._scratch is not None:  # the two vectors a step adds to the wavelet-domain rings
            ring = _time(lambda: stepper.ring_written(so, body._U_k, body._P_k, slot, body._scratch, body._bf_in), 20, sync)
        graph = None
        if dev.is_cuda:  # the same launches replayed as one CUDA graph: device time without Python's launch cost
            with wp.ScopedCapture(device=dev) as capture:
                history_and_ring()
            graph = _time(lambda: wp.capture_launch(capture.graph), 50, sync)
        hist_bytes = so.history_bytes
        out = {
            "seconds_per_step": per_step,
            "stage_seconds_per_step": stage,
            "uncnst_seconds": uncnst,
            "uncnst_seconds_profiled": stage["loads"] + stage["history"] + stage["solve"],
            "errcr_seconds": stage["correction"] + stage["frame"],
            "history_matvec_seconds": hist,
            "history_matvec_GBps": hist_bytes / hist / 1e9,
            "history_bytes": int(hist_bytes),
            "history_matrix_bytes": int(so.history_matrix_bytes),
            "history_with_ring_update_graph_seconds": graph,
            "step_matrix_bytes": int(so.matrix_bytes),
            "max_displacement": float(np.max(np.abs(body.displacement()))),
            **paths,
        }
        if ratio is not None:
            dense = results["warp"]
            out.update({
                "compression_ratio": ratio, "compressed_on": dev.alias, "compress_seconds": round(compress_s, 2),
                "kept_ratio_measured": so.compressed.ratio,
                "ring_update_seconds": ring, "history_with_ring_update_seconds": hist + ring,
                "history_speedup_vs_dense": dense["history_matvec_seconds"] / (hist + ring),
                "history_speedup_vs_dense_graph": (dense["history_with_ring_update_graph_seconds"] / graph
                                                   if graph else None),
                "history_memory_ratio_vs_dense": dense["history_bytes"] / hist_bytes,
                "matrix_memory_ratio_vs_dense": dense["history_matrix_bytes"] / so.history_matrix_bytes,
                "uncnst_speedup_vs_dense": dense["uncnst_seconds"] / uncnst,
                "relative_frobenius_error_H1": so.compressed.H[0].relative_error,
            })
        if ratios and compare_steps > 0:  # the same run from the start, for the trajectory error
            fresh = make_body(backend, ratio, False)
            traj = []
            for _ in range(compare_steps):
                fresh.step()
                traj.append(fresh.displacement().copy())
            trajectories[label] = np.array(traj)
            if ratio is not None:
                ref = trajectories["warp"]
                out["trajectory_error_vs_dense"] = float(np.abs(trajectories[label] - ref).max() / np.abs(ref).max())
                out["trajectory_steps"] = compare_steps
        results[label] = out
    # the same history product through the reference a user would otherwise reach for
    n3 = 3 * ops.n_nodes
    refs: dict = {}
    U = np.random.default_rng(0).standard_normal((ops.n_max, n3)).astype(ops.H.dtype)
    Hs, Gs = ops.H[1:], ops.G[1:]

    def numpy_history():
        out = np.zeros(n3, dtype=ops.H.dtype)
        for k in range(ops.n_max):
            out += Gs[k] @ U[k]
            out -= Hs[k] @ U[k]
        return out

    t_np = _time(numpy_history, 2, lambda: None)
    refs["numpy_blas_host"] = {"history_matvec_seconds": t_np, "GBps": (Hs.nbytes + Gs.nbytes) / t_np / 1e9}
    if dev.is_cuda:
        try:
            import torch

            tdev = torch.device(f"cuda:{dev.ordinal}")
            tH = torch.from_numpy(np.ascontiguousarray(Hs)).to(tdev)
            tG = torch.from_numpy(np.ascontiguousarray(Gs)).to(tdev)
            tU = torch.from_numpy(U).to(tdev)

            def torch_history():
                out = torch.zeros(n3, dtype=tH.dtype, device=tdev)
                for k in range(ops.n_max):
                    out += torch.mv(tG[k], tU[k])
                    out -= torch.mv(tH[k], tU[k])
                return out

            def torch_one():
                return torch.mv(tH[0], tU[0])

            t_t = _time(torch_history, 20, torch.cuda.synchronize)
            t_1 = _time(torch_one, 50, torch.cuda.synchronize)
            refs["torch_mv"] = {
                "torch": torch.__version__,
                "history_matvec_seconds": t_t,
                "GBps": (Hs.nbytes + Gs.nbytes) / t_t / 1e9,
                "single_mv_GBps": Hs[0].nbytes / t_1 / 1e9,
            }
            del tH, tG
        except ImportError:
            refs["torch_mv"] = "torch not importable"
    warp_gbps = results["warp"]["history_matvec_GBps"]
    torch_gbps = refs.get("torch_mv", {}).get("GBps") if isinstance(refs.get("torch_mv"), dict) else None
    return {
        "case": name,
        "device": dev.alias,
        "gpu": dev.name if dev.is_cuda else None,
        "N": ops.n_nodes,
        "n_max": ops.n_max,
        "precision": precision,
        "dt": dt,
        "build_seconds": round(build_s, 2),
        "matrix_bytes_per_step": results["warp"]["step_matrix_bytes"],
        "backends": results,
        "references": refs,
        "warp_vs_torch_bandwidth": (warp_gbps / torch_gbps) if torch_gbps else None,
        "paper_uncnst_seconds": PAPER_UNCNST.get(name.removesuffix("_small")),
        "peak_host_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "peak_device_bytes": wp.get_mempool_used_mem_high(dev) if dev.is_cuda else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="bumpy_cube_small")
    ap.add_argument("--device", default=None)
    ap.add_argument("--precision", default="float32")
    ap.add_argument("--mesh", default=None, help="mesh file for case 'mesh'")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--compression", default="", help="compression ratios to add, e.g. 8,32")
    ap.add_argument("--compare-steps", type=int, default=100)
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        ratios = [float(r) for r in args.compression.split(",") if r]
        print(json.dumps(run_case(args.one, args.device, args.precision, args.mesh, args.steps, ratios,
                                  args.compare_steps)), flush=True)
        return
    for name in args.cases.split(","):
        if name not in CASES:
            raise SystemExit(f"unknown case {name!r}; known: {', '.join(CASES)}")
        cmd = [sys.executable, os.path.abspath(__file__), "--one", name, "--precision", args.precision,
               "--steps", str(args.steps), "--compression", args.compression, "--compare-steps", str(args.compare_steps)]
        for flag, value in (("--device", args.device), ("--mesh", args.mesh)):
            if value is not None:
                cmd += [flag, str(value)]
        subprocess.run(cmd, check=True)


if __name__ == "__main__":
    main()
