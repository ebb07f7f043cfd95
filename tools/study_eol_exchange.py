"""The explicit exchange between EoL bodies on fine grids (issue 18): the first layers of
``scenes/eol_pile.py`` at a given resolution, with the World's exchange on (the pusher's push is
handed to the pushed body over the next interval) or off (nobody is handed it: momentum is not
kept, only to show where the growth comes from). One JSON line per frame: each body's steps, its
largest Eulerian residual |v*| [m/s] and contact rows; a final line with the outcome.

    python tools/study_eol_exchange.py --resolution 16 --bodies 8 --frames 7 --device cpu
    python tools/study_eol_exchange.py --resolution 32 --bodies 8 --frames 7 --no-exchange

Measured (README, known limits of contact between bodies): with the exchange treating the partner
as rigid, 16 cells on the CPU reached v* = 96,000 m/s by frame 6 and 32 cells on an H100 left a
grid in frame 6; with the rows sharing the push with the partner's give, 280 m/s at 16 cells and
7.6e5 m/s by frame 8 at 32 cells (``tools/results/study_eol_exchange_pile32_h100.jsonl``);
without the exchange the 32-cell run stays below 8 m/s.
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
ap.add_argument("--no-exchange", action="store_true", help="hand nobody the pushes (diagnosis only)")
args = ap.parse_args()

world = eol_pile.build(device=args.device, resolution=args.resolution)
world.bodies[:] = world.bodies[:args.bodies]
if args.no_exchange:
    world._exchange = lambda interval: None  # the World's hand-over, switched off for the study
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
print(json.dumps({"resolution": args.resolution, "bodies": args.bodies, "exchange": not args.no_exchange,
                  "device": device.name, "outcome": outcome, "seconds": round(time.perf_counter() - start, 1)}))
