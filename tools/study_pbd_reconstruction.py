"""Study: keyframe-curve reconstruction of a PBD animation, error versus stored data.

The posed-model scene (scenes/posed_neck.py: a creature's neck bent and twisted by kinematic
handles, tetrahedral XPBD) is simulated for 100 frames; each method then keeps every K-th frame
as a keyframe and rebuilds all frames. One JSON object per line:

    method (pde, bezier, bspline, linear; pde_joint in the full study), stride, points_per_curve,
    mode, data_ratio (stored floats / raw per-frame vertex floats), keyframe_err and inbetween_err
    (max over vertices and frames of |x_rec - x_pbd| / bounding-box diagonal), inbetween_rms,
    paper_EA and paper_Em (the paper's Eqs. 23-24 at the keyframes, mean and max),
    seconds_per_frame (reconstruction of one frame by the Warp kernel, synchronized), fit_seconds,
    device, vertices, frames.

    python tools/study_pbd_reconstruction.py --quick          # CPU, < 2 minutes
    python tools/study_pbd_reconstruction.py                  # full sweep + PNG plot
    python tools/study_pbd_reconstruction.py --size 15k --device cuda:0 --stride 10   # GPU timing, 15k vertices
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "scenes"))
sys.path.insert(0, HERE)

import wsim  # noqa: E402
from wsim.device import quiet_warp  # noqa: E402
from wsim.pbd import fit as pf  # noqa: E402
from wsim.pbd.reconstruction import paper_errors  # noqa: E402


def posed_recording(size: str | None, device: str | None, frames: int) -> wsim.PbdRecording:
    """Simulate the posed-model scene (default resolution, tets) or its surface-only version at ``size``."""
    import posed_neck

    if size is None:
        world = posed_neck.build(device=device)
    else:
        import bench_pbd

        world = wsim.World(fps=30, device=device)
        world.add(bench_pbd.posed_body(size, substeps=20))
    return wsim.record(world, world.bodies[0], frames)


def evaluate(rec: wsim.PbdRecording, method: str, stride: int, device: str | None, **opts) -> dict:
    frames = rec.frames
    diag = float(np.linalg.norm(np.ptp(frames[0], axis=0)))
    t0 = time.perf_counter()
    recon = wsim.PbdReconstruction(rec, stride=stride, basis=method, **opts)
    fit_seconds = time.perf_counter() - t0
    world = wsim.World(fps=rec.fps, device=device)
    world.add(recon)
    recon.evaluate(0)  # compile / load the kernels outside the timing
    wp.synchronize_device(world.device)
    n = len(frames)
    t0 = time.perf_counter()
    for f in range(n):
        recon.evaluate(f)
    wp.synchronize_device(world.device)
    spf = (time.perf_counter() - t0) / n
    model = recon.model
    keys = model.keyframes
    inner = np.setdiff1d(np.arange(n), keys)
    rebuilt = np.array([recon.evaluate(f).numpy().astype(np.float64) for f in range(n)])
    err = np.linalg.norm(rebuilt - frames, axis=2).max(axis=1) / diag
    rms = np.sqrt((((rebuilt[inner] - frames[inner]) ** 2).sum(axis=2)).mean()) / diag if inner.size else 0.0
    paper = np.array([paper_errors(rebuilt[k], frames[k]) for k in keys])
    return {
        "method": method,
        "stride": stride,
        "points_per_curve": opts.get("points_per_curve", 12) if method != "linear" else None,
        "mode": opts.get("mode", "displacement") if method != "linear" else None,
        "data_ratio": model.data_ratio,
        "keyframe_err": float(err[keys].max()),
        "inbetween_err": float(err[inner].max()) if inner.size else 0.0,
        "inbetween_rms": float(rms),
        "paper_EA": float(paper[:, 0].mean()),
        "paper_Em": float(paper[:, 1].max()),
        "seconds_per_frame": spf,
        "fit_seconds": fit_seconds,
        "device": world.device.alias,
        "vertices": int(frames.shape[1]),
        "frames": n,
    }


def joint(rec: wsim.PbdRecording, stride: int) -> dict:
    frames = rec.frames
    diag = float(np.linalg.norm(np.ptp(frames[0], axis=0)))
    rebuilt, stored = pf.fit_joint_pde(frames, rec.rest, stride)
    keys = pf.keyframe_indices(len(frames), stride)
    inner = np.setdiff1d(np.arange(len(frames)), keys)
    err = np.linalg.norm(rebuilt - frames, axis=2).max(axis=1) / diag
    return {"method": "pde_joint", "stride": stride, "points_per_curve": 12, "mode": "displacement",
            "data_ratio": stored / frames.size, "keyframe_err": float(err[keys].max()),
            "inbetween_err": float(err[inner].max()) if inner.size else 0.0, "device": "cpu (numpy)", "vertices": int(frames.shape[1]), "frames": len(frames)}


def plot(rows: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    styles = {"pde": ("o-", "C0"), "bezier": ("s--", "C1"), "bspline": ("x:", "C2"), "linear": ("^-", "C3"), "pde_joint": ("*", "C4")}
    for method, (fmt, color) in styles.items():
        for ppc in sorted({r.get("points_per_curve") or 0 for r in rows if r["method"] == method}):
            pts = sorted((r["data_ratio"], r["inbetween_err"]) for r in rows
                         if r["method"] == method and (r.get("points_per_curve") or 0) == ppc
                         and r.get("mode") in (None, "displacement") and r["inbetween_err"] > 0)  # stride 1: no in-betweens
            if not pts:
                continue
            x, y = zip(*pts)
            label = method if method in ("linear", "pde_joint") else f"{method}, {ppc} pts/curve"
            width = {6: 0.8, 12: 1.8, 24: 0.8}.get(ppc, 1.5)
            dash = {6: (0, (1, 1)), 24: (0, (5, 2))}.get(ppc)
            line, = ax.loglog(x, y, fmt, color=color, alpha=0.45 + 0.55 * (ppc in (0, 12)), label=label, markersize=4, linewidth=width)
            if dash and method != "pde_joint":
                line.set_linestyle(dash)
    ax.set_xlabel("stored data / raw per-frame vertex data")
    ax.set_ylabel("max in-between error / bounding-box diagonal")
    ax.set_title("PBD posed model: reconstruction in-between error vs data (100 frames)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="CPU-sized run: a few strides, default curves")
    p.add_argument("--device", default=None, help="device of the simulation and the reconstruction kernels")
    p.add_argument("--size", default=None, help="use the surface-only posed model at this size (bench_pbd sizes: 1k, 5k, 15k, 50k)")
    p.add_argument("--stride", type=int, action="append", help="strides to run (repeatable)")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--plot", default="pbd_reconstruction_study.png", help="PNG written by the full study")
    args = p.parse_args()
    quiet_warp()
    device = "cpu" if args.quick and args.device is None else args.device
    rec = posed_recording(args.size, device, args.frames)
    rows: list[dict] = []

    def emit(row: dict) -> None:
        rows.append(row)
        print(json.dumps(row), flush=True)

    if args.quick or args.size:
        for stride in args.stride or [5, 10, 25]:
            for method in pf.METHODS:
                emit(evaluate(rec, method, stride, device))
        return
    strides = args.stride or [1, 2, 3, 5, 10, 20, 50, 100]
    for stride in strides:
        emit(evaluate(rec, "linear", stride, device))
        for method in ("pde", "bezier", "bspline"):
            for ppc in (6, 12, 24):
                emit(evaluate(rec, method, stride, device, points_per_curve=ppc))
        for method in ("pde", "bezier"):
            emit(evaluate(rec, method, stride, device, mode="position"))
        emit(joint(rec, stride))
    plot(rows, args.plot)
    print(json.dumps({"plot": os.path.abspath(args.plot)}), flush=True)


if __name__ == "__main__":
    main()
