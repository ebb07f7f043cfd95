"""K BEM bodies on one operator set against one body (issue 21 item 5): seconds per step.

    python tools/bench_bem_instances.py --divisions 22 --instances 25        # N = 2906, on a GPU
    python tools/bench_bem_instances.py --device cpu --divisions 4 --instances 5 --steps 10

The body is the bumpy cube of ``bench_bem_step.py`` (0.45 m, jelly mu 5e5, nu 0.5, rho 1e3,
dt 0.01; ``--divisions`` 22: N = 2906). Every body falls free under gravity with its own spin and
a traction pulse on one of them (so the solve's p-product runs too), in one World at 1/dt fps,
``body_contact`` off unless ``--contact`` (then all bodies are one contact group, set apart so
that none touches: the contact detection's cost between them is in the time). One JSON line per
case, each after ``--warmup`` steps and over ``--steps`` steps:

* ``one``: a single body;
* ``one_host_path``: the single body with ``device_step=False``: its UNCNST stages (history,
  loads, solve) are timed on the host as a set's are, the like-for-like baseline of the issue's
  "≤ 4× one instance per unconstrained step" (the device path runs them inside its replayed
  step, where they are not split out);
* ``set``: K bodies stepping as one instance set (``wsim.bem.instances``: each matrix read once a
  step for all K);
* ``separate``: the same K bodies with the sets turned off (each body its own passes), the
  baseline of what K bodies cost before.

Fields: seconds per step (the whole World step, device synchronized), per-body UNCNST seconds
(history + loads + solve, ``BemBody.timings``, summed over bodies), the ratio to ``one``, the
device memory high-water mark, and for ``set`` the largest difference of any surface point from
``separate`` at the end (the same trajectories to round-off) and ``uncnst_ratio_to_one``, its
UNCNST seconds over ``one_host_path``'s.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--divisions", type=int, default=22)
    ap.add_argument("--instances", type=int, default=25)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--precision", default="float32")
    ap.add_argument("--contact", action="store_true", help="body_contact on: the bodies are one contact group")
    args = ap.parse_args()

    import warp as wp

    import wsim
    from wsim import mesh as wmesh
    from wsim.bem import build_operators, instances, stepper
    from wsim.device import quiet_warp, resolve_device

    quiet_warp()
    dev = resolve_device(args.device)
    jelly = wsim.ElasticMaterial(mu=5e5, nu=0.5, rho=1e3, incompressible=True)
    dt = 0.01
    cube = wmesh.bumpy_cube(size=0.45, divisions=args.divisions, amplitude=0.04)
    t = time.perf_counter()
    ops = build_operators(cube, jelly, dt, precision=args.precision, device=dev, cache=False, progress=False)
    so_backend = stepper.step_operators(ops, dev, stepper.resolve_backend("auto", dev)).many_backend
    print(json.dumps({"device": dev.name if dev.is_cuda else "cpu", "N": ops.n_nodes, "n_max": ops.n_max,
                      "precision": args.precision, "build_s": round(time.perf_counter() - t, 2),
                      "many_backend": so_backend, "contact": args.contact}), flush=True)

    def pulse(t: float) -> np.ndarray:
        p = np.zeros((len(cube.vertices), 3))
        p[cube.vertices[:, 0] > 0.15, 0] = -1e3 * np.sin(np.pi * min(t, 0.1) / 0.1)
        return p

    def run(k: int, sets: bool, device_step: bool = True) -> tuple[dict, list[np.ndarray]]:
        world = wsim.World(fps=1.0 / dt, device=dev, gravity=(0.0, -9.81, 0.0), body_contact=args.contact)
        bodies = []
        for i in range(k):
            b = world.add(wsim.BemBody(cube, jelly, dt, operators=ops, name=f"cube_{i:02d}",
                                       position=(1.0 * (i % 5), 0.0, 1.0 * (i // 5)),
                                       angular_velocity=(0.3 * i, 1.0, 0.0), device_step=device_step))
            if i == 0:
                b.add_traction(pulse)
            bodies.append(b)
        original = instances.instance_sets
        if not sets:  # the baseline: every body its own passes
            instances.instance_sets = lambda bodies: []
        try:
            for _ in range(args.warmup):
                world.step()
            wp.synchronize_device(dev)
            for b in bodies:
                b.timings = {s: 0.0 for s in b.timings}
            t0 = time.perf_counter()
            for _ in range(args.steps):
                world.step()
            wp.synchronize_device(dev)
            seconds = (time.perf_counter() - t0) / args.steps
        finally:
            instances.instance_sets = original
        uncnst = sum(b.timings.get(s, 0.0) for b in bodies for s in ("history", "loads", "solve")) / args.steps
        mem = wp.get_mempool_used_mem_high(dev) / 2**20 if dev.is_cuda else None
        return ({"instances": k, "seconds_per_step": round(seconds, 6), "uncnst_seconds_per_step": round(uncnst, 6),
                 "sets": len(world._sets) + sum(len(s) for s in world._group_sets),
                 "device_mem_high_mb": None if mem is None else round(mem, 1)}, [b.points() for b in bodies])

    one, _ = run(1, True)
    print(json.dumps({"case": "one", **one}), flush=True)
    one_host, _ = run(1, True, device_step=False)
    print(json.dumps({"case": "one_host_path", **one_host}), flush=True)
    sep, x_sep = run(args.instances, False)
    print(json.dumps({"case": "separate", **sep, "ratio_to_one": round(sep["seconds_per_step"] / one["seconds_per_step"], 2)}),
          flush=True)
    together, x_set = run(args.instances, True)
    diff = max(float(np.max(np.abs(a - b))) for a, b in zip(x_set, x_sep))
    print(json.dumps({"case": "set", **together,
                      "ratio_to_one": round(together["seconds_per_step"] / one["seconds_per_step"], 2),
                      "speedup_over_separate": round(sep["seconds_per_step"] / together["seconds_per_step"], 2),
                      "uncnst_ratio_to_one": round(together["uncnst_seconds_per_step"] / one_host["uncnst_seconds_per_step"], 2),
                      "max_point_difference_m": diff}), flush=True)


if __name__ == "__main__":
    main()
