"""The first layers of ``scenes/eol_pile.py`` at a resolution (issue 18: the pile at the paper's 32
cells): per frame, each body's steps, largest v* and contact rows, the frame's seconds and the
QP's size (rows and bodies of the largest joint QP of the frame).

    python tools/study_eol_pile.py --resolution 16 --bodies 8 --frames 7 --device cpu
    python tools/study_eol_pile.py --resolution 32 --bodies 16 --frames 9 --device cuda:0

With the explicit exchange between EoL bodies (before one QP joined them) v* climbed to
7.6e5 m/s by frame 8 at 32 cells on an H100 (``tools/results/study_eol_exchange_pile32_h100.jsonl``)
and body_01 reached 280 m/s at 16 cells (8 bodies, CPU).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scenes"))

import eol_pile  # noqa: E402

from wsim.errors import SimulationDiverged  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--resolution", type=int, default=16)
ap.add_argument("--bodies", type=int, default=8, help="the first N bodies of the pile (4 a layer)")
ap.add_argument("--frames", type=int, default=7)
ap.add_argument("--device", default=None)
args = ap.parse_args()

world = eol_pile.build(device=args.device, resolution=args.resolution)
world.bodies[:] = world.bodies[:args.bodies]
device = wp.get_device(args.device)
start = time.perf_counter()
outcome = "ran"
try:
    for f in range(args.frames):
        seen = {b.name: len(b.history) for b in world.bodies}
        t = time.perf_counter()
        world.step()
        wp.synchronize_device(device)
        bodies = {}
        for b in world.bodies:
            h = b.history[seen[b.name]:]
            bodies[b.name] = {"steps": len(h), "v_star_max": round(max((r.v_star for r in h), default=0.0), 2),
                              "rows_max": max((r.rows for r in h), default=0)}
        print(json.dumps({"frame": f + 1, "seconds": round(time.perf_counter() - t, 2), "bodies": bodies}), flush=True)
except SimulationDiverged as e:
    outcome = str(e)
print(json.dumps({"resolution": args.resolution, "bodies": args.bodies,
                  "device": device.name, "outcome": outcome, "seconds": round(time.perf_counter() - start, 1)}))
