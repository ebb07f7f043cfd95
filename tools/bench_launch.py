"""Host cost of one kernel launch: ``wp.launch`` against a ``wsim.launch.Launcher`` replay.

    python tools/bench_launch.py [--device cuda:0] [--resolution 32] [--n 1000]

The kernel is an EoL step's ``node_velocities`` (13 arguments: a ``Grid`` struct, four 3x3
matrices, arrays of a 32^3 grid's nodes) on a bound body's own arrays. Prints one JSON line: microseconds
per call for ``wp.launch``, a replay with nothing changed, a replay with two small arguments
changed (what an EoL step does), a device-to-host read of one number (a synchronization's round
trip), and the kernel alone (launches replayed back to back in a CUDA graph; GPU only).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_eol import make_world  # noqa: E402

from wsim.device import quiet_warp  # noqa: E402
from wsim.eol.body import _mat  # noqa: E402
from wsim.kernels import eol_step as ks  # noqa: E402
from wsim.launch import Launcher  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--device", default=None)
ap.add_argument("--resolution", type=int, default=32)
ap.add_argument("--n", type=int, default=1000)
args = ap.parse_args()
quiet_warp()
device = wp.get_device(args.device)
world, b = make_world("free", args.resolution, device.alias, "rigid", False)
world.step()
n_nodes = b.grid.n_nodes


def inputs(i: int) -> list:
    return [b.state.v, b._mass, b._forces, b._grid, _mat(0.1 * np.eye(3)), wp.vec3d(1.0, 2.0, float(i)), _mat(np.eye(3)),
            wp.vec3d(0.0, -9.8, 0.0), 1, _mat(np.eye(3) * (1.0 + i)), b._mass_real, b._w, b._a]


def per_call_us(fn) -> float:
    wp.synchronize_device(device)
    t = time.perf_counter()
    for i in range(args.n):
        fn(i)
    wp.synchronize_device(device)
    return 1e6 * (time.perf_counter() - t) / args.n


launch = Launcher(device)
fixed = inputs(0)
out = {"device": device.name, "nodes": n_nodes, "calls": args.n,
       "wp_launch_us": per_call_us(lambda i: wp.launch(ks.node_velocities, dim=n_nodes, inputs=inputs(i), device=device)),
       "replay_unchanged_us": per_call_us(lambda i: launch(ks.node_velocities, n_nodes, fixed)),
       "replay_two_changed_us": per_call_us(lambda i: launch(ks.node_velocities, n_nodes, inputs(i))),
       "readback_us": per_call_us(lambda i: b._mass[:1].numpy())}
if device.is_cuda:
    cmd = wp.launch(ks.node_velocities, dim=n_nodes, inputs=fixed, device=device, record_cmd=True)
    with wp.ScopedCapture(device=device) as cap:
        for _ in range(100):
            cmd.launch()
    out["kernel_gpu_us"] = per_call_us(lambda i: wp.capture_launch(cap.graph)) / 100
print(json.dumps(out))
