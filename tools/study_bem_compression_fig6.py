"""The paper's Fig. 6 scene (issue 20): a bumpy cube pulled sideways on two sides, dense against
compressed operators at CR 8, 32 and 128 (and CR 1, which must equal the dense run) and at
``compression_error`` targets: the deformation's error against the dense run over time, the
ratio kept, the bytes of the history matrices and the time per step. One JSON line per case.

    python tools/study_bem_compression_fig6.py [--divisions 10] [--steps 150] [--errors 0.01,0.1]

The paper's cube is N = 3000 (divisions 22); the default (N = 602) runs on a 2-core CPU in a few
minutes. Compressed bodies run on the CPU device for now. The deformation is the surface points
relative to the body's frame (what compression changes; the rigid motion is the frame's).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import wsim
from wsim import mesh as wmesh
from wsim.bem import build_operators


def run(cube, material, dt: float, ops, steps: int, **kw) -> tuple[np.ndarray, float, object]:
    world = wsim.World(fps=1.0 / dt, device="cpu", gravity=(0.0, 0.0, 0.0))
    body = world.add(wsim.BemBody(cube, material, dt, operators=ops, name="cube", **kw))
    x = body.rest_vertices
    side = np.where(x[:, 0] > 0.9 * x[:, 0].max(), 1.0, np.where(x[:, 0] < 0.9 * x[:, 0].min(), -1.0, 0.0))
    pull = np.zeros_like(x)
    pull[:, 0] = 2e4 * side  # outward on both x faces [Pa]

    body.add_traction(lambda t: pull * (t < 0.1))
    world.step()  # compile and first-use costs out of the timing
    out = [body.displacement().copy()]
    t = time.perf_counter()
    for _ in range(steps - 1):
        world.step()
        out.append(body.displacement().copy())
    return np.array(out), (time.perf_counter() - t) / (steps - 1), body


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--divisions", type=int, default=10)
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--ratios", default="1,8,32,128")
    ap.add_argument("--errors", default="0.01,0.03,0.1", help="compression_error targets")
    args = ap.parse_args()
    cube = wmesh.bumpy_cube(size=0.45, divisions=args.divisions, amplitude=0.04)
    material = wsim.ElasticMaterial(mu=5e5, nu=0.45, rho=1e3)
    dt = 0.01
    t = time.perf_counter()
    ops = build_operators(cube, material, dt, device="cpu")
    build_s = time.perf_counter() - t
    ref, dense_step, body = run(cube, material, dt, ops, args.steps)
    scale = float(np.abs(ref).max())
    dense_bytes = int(body._so.history_bytes)
    print(json.dumps({"case": "dense", "N": ops.n_nodes, "n_max": ops.n_max, "steps": args.steps, "build_s": round(build_s, 1),
                      "ms_per_step": 1e3 * dense_step, "history_bytes": dense_bytes,
                      "max_displacement_m": scale, "device": "cpu"}), flush=True)
    cases = [(f"CR {float(v):g}", {"compression": float(v)}) for v in args.ratios.split(",") if v]
    cases += [(f"error {float(v):g}", {"compression_error": float(v)}) for v in args.errors.split(",") if v]
    for name, kw in cases:
        got, step_s, b = run(cube, material, dt, ops, args.steps, **kw)
        err = np.abs(got - ref).max(axis=(1, 2)) / scale
        print(json.dumps({"case": name, "N": ops.n_nodes, "ms_per_step": 1e3 * step_s,
                          "history_bytes_csr": int(b._so.history_bytes), "memory_ratio": dense_bytes / b._so.history_bytes,
                          "kept_ratio": b._so.compressed.ratio,
                          "max_displacement_error_over_max_displacement": float(err.max()),
                          "error_at_steps": {str(k): float(err[k]) for k in (10, 50, 100, len(err) - 1) if k < len(err)},
                          "device": "cpu"}), flush=True)
        del b  # the next case must not find this one's shared operators


if __name__ == "__main__":
    main()
