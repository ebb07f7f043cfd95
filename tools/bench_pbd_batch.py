"""K PBD bodies in one launch set against one body (issue 21 item 5): milliseconds per frame.

    python tools/bench_pbd_batch.py --bodies 100                  # on a GPU
    python tools/bench_pbd_batch.py --device cpu --bodies 10 --frames 10

The body is a tetrahedral ball (icosphere of ``--subdivisions`` 3, R = 0.1 m, tets "auto": about
1k particles), E = 2e5, nu = 0.3, rho = 500, 10 substeps x 2 iterations at 60 fps, dropped onto a
ground plane with a spin, the bodies on a grid 0.5 m apart (none touches another). One JSON line
per case after ``--warmup`` frames, over ``--frames`` frames (device synchronized):

* ``one``: a single body;
* ``batch``: K bodies in one World, stepping as one batch (``wsim.pbd.batch``);
* ``separate``: the same K bodies with batches turned off (each its own launches or CUDA graph).

With ``--contact`` the World has body contact on (the bodies then step in lockstep and the batch
runs inside it). Fields: ms per frame, the ratio to ``one``, the particle count, and for
``batch`` the largest particle distance from ``separate`` at the end (0 on the CPU: the same
arithmetic).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--bodies", type=int, default=100)
    ap.add_argument("--subdivisions", type=int, default=3)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--contact", action="store_true")
    args = ap.parse_args()

    import trimesh
    import warp as wp

    import wsim
    from wsim.device import quiet_warp, resolve_device
    from wsim.pbd import batch as pbd_batch

    quiet_warp()
    dev = resolve_device(args.device)
    mesh = trimesh.creation.icosphere(subdivisions=args.subdivisions, radius=0.1)
    side = int(np.ceil(np.sqrt(args.bodies)))

    def run(k: int, batches: bool) -> tuple[dict, list[np.ndarray]]:
        world = wsim.World(fps=60.0, device=dev, gravity=(0.0, -9.81, 0.0), body_contact=args.contact)
        world.add_collider(wsim.GroundPlane(friction=0.5))
        bodies = [world.add(wsim.PbdBody(mesh, dict(E=2e5, nu=0.3, rho=500.0), name=f"ball_{i:03d}", tets="auto",
                                         substeps=10, iterations=2, position=(0.5 * (i % side), 0.3, 0.5 * (i // side)),
                                         angular_velocity=(0.0, 1.0 + 0.01 * i, 0.0)))
                  for i in range(k)]
        original = pbd_batch.batches
        if not batches:
            pbd_batch.batches = lambda bodies: []
        try:
            for _ in range(args.warmup):
                world.step()
            wp.synchronize_device(dev)
            t0 = time.perf_counter()
            for _ in range(args.frames):
                world.step()
            wp.synchronize_device(dev)
            ms = 1e3 * (time.perf_counter() - t0) / args.frames
        finally:
            pbd_batch.batches = original
        return ({"bodies": k, "particles_each": bodies[0].model.n_particles, "ms_per_frame": round(ms, 4),
                 "batched": bodies[0]._batch is not None}, [b.particles() for b in bodies])

    one, _ = run(1, True)
    print(json.dumps({"case": "one", "device": dev.name if dev.is_cuda else "cpu", "contact": args.contact, **one}),
          flush=True)
    sep, x_sep = run(args.bodies, False)
    print(json.dumps({"case": "separate", **sep, "ratio_to_one": round(sep["ms_per_frame"] / one["ms_per_frame"], 2)}),
          flush=True)
    bat, x_bat = run(args.bodies, True)
    diff = max(float(np.abs(a - b).max()) for a, b in zip(x_bat, x_sep))
    print(json.dumps({"case": "batch", **bat, "ratio_to_one": round(bat["ms_per_frame"] / one["ms_per_frame"], 2),
                      "speedup_over_separate": round(sep["ms_per_frame"] / bat["ms_per_frame"], 2),
                      "max_particle_difference_m": diff}), flush=True)


if __name__ == "__main__":
    main()
