"""Two PBD balls colliding (issue 18, ``wsim.pbd.contact``): frame time while apart (each body its
own CUDA graph) and while in reach (the lockstep frame, one recorded graph on CUDA), 10 substeps x 2
iterations, icospheres of 2 and 3 subdivisions with tets; the pair's momentum and angular-momentum
errors after the blow. One JSON line per size.

    python tools/bench_pbd_contact.py [--device cuda:0]
"""

import argparse
import json
import time

import numpy as np
import trimesh
import warp as wp

import wsim
from wsim.pbd.contact import candidate_pairs

ap = argparse.ArgumentParser()
ap.add_argument("--device", default=None)
args = ap.parse_args()
device = wp.get_device(args.device)
for sub in ("2", "3"):
    ball = trimesh.creation.icosphere(subdivisions=int(sub), radius=0.2)
    mat = wsim.ElasticMaterial(E=2e5, nu=0.3, rho=500.0)
    w = wsim.World(fps=60, gravity=(0, 0, 0), device=device.alias)
    a = w.add(wsim.PbdBody(ball, mat, tets="auto", name="a", position=(-0.6, 0, 0), velocity=(1.0, 0, 0)))
    b = w.add(wsim.PbdBody(ball, mat, tets="auto", name="b", position=(0.6, 0.05, 0), velocity=(-1.0, 0, 0)))
    times = {"apart": [], "reach": []}
    L0 = a.angular_momentum(about=(0,0,0)) + b.angular_momentum(about=(0,0,0))
    P0 = a.linear_momentum() + b.linear_momentum()
    for f in range(60):
        reach = bool(candidate_pairs([a, b], 1 / 60))
        wp.synchronize_device(device)
        t = time.perf_counter()
        w.step()
        wp.synchronize_device(device)
        if f > 2:
            times["reach" if reach else "apart"].append(time.perf_counter() - t)
    L = a.angular_momentum(about=(0,0,0)) + b.angular_momentum(about=(0,0,0))
    P = a.linear_momentum() + b.linear_momentum()
    print(json.dumps({"case": "pbd_pair", "device": device.name, "particles": int(a.model.n_particles),
                      "surface": int(a.model.n_surface), "ms_apart": 1e3 * float(np.median(times["apart"])) if times["apart"] else None,
                      "ms_reach": 1e3 * float(np.median(times["reach"])) if times["reach"] else None, "frames_reach": len(times["reach"]),
                      "dP": float(np.abs(P - P0).max()), "dL_rel": float(np.linalg.norm(L - L0) / np.linalg.norm(L0)),
                      "vA_x": float(a.linear_momentum()[0] / a.masses.sum())}))
