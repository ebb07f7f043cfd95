"""PBD at the extremes (issue 16): one JSON line per case; each stays bounded and conserves what it
should (free bodies: momentum and angular momentum), or stops with SimulationDiverged.

Base case: a free tet ball (icosphere subdivision 2, R = 0.2 m, 251 particles), E = 1e5,
nu = 0.3, rho = 1000, zero gravity, 30 fps x 10 substeps x 2 iterations, spin 2 rad/s about y plus
a breathing field 0.1 m/s * r / R and a drift of 0.5 m/s, 2 s. Cases vary one thing each.

    python tools/study_pbd_extremes.py [--out tools/results/study_pbd_extremes_cpu.jsonl] [--cases ...]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import trimesh

import wsim

CASES = {
    "base": {},
    "nu_0.499": {"nu": 0.499},
    "E_x1000": {"E": 1e8},
    "E_div1000": {"E": 1e2},
    "spin_10rev_s": {"spin": 20.0 * np.pi},
    "dt_x10": {"substeps": 1},
    "dt_div10": {"substeps": 100},
    "frames_1e4": {"frames": 10000, "subdivisions": 1},
}


def run(name: str, device: str) -> dict:
    o = {"E": 1e5, "nu": 0.3, "spin": 2.0, "substeps": 10, "frames": 60, "subdivisions": 2, **CASES[name]}
    R = 0.2
    world = wsim.World(fps=30, gravity=(0.0, 0.0, 0.0), device=device)
    body = world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=o["subdivisions"], radius=R),
                                  wsim.ElasticMaterial(E=o["E"], nu=o["nu"], rho=1000.0), name="ball", tets="auto",
                                  substeps=o["substeps"], velocity=(0.5, 0.0, 0.0), angular_velocity=(0.0, o["spin"], 0.0)))
    x = body.particles()
    c = x.mean(0)
    body.set_velocities(body.velocities() + 0.1 * (x - c) / R)
    P0, L0, K0 = body.linear_momentum(), body.angular_momentum(), body.kinetic_energy()
    out = {"case": name, "device": device, "E": o["E"], "nu": o["nu"], "spin_rad_s": o["spin"], "substeps": o["substeps"],
           "frames": o["frames"], "particles": body.model.n_particles}
    t = time.perf_counter()
    max_strain = 0.0
    try:
        for f in range(o["frames"]):
            world.step()
            if f % 10 == 9 or f == o["frames"] - 1:
                p = body.particles()
                r_now = np.linalg.norm(p - p.mean(0), axis=1).max()
                max_strain = max(max_strain, r_now / R - 1.0)
        out["status"] = "ok"
    except wsim.errors.SimulationDiverged as e:
        out["status"] = f"SimulationDiverged: {e}"
    out["seconds"] = time.perf_counter() - t
    P, L, K = body.linear_momentum(), body.angular_momentum(), body.kinetic_energy()
    out["momentum_error_rel"] = float(np.linalg.norm(P - P0) / np.linalg.norm(P0))
    out["angular_momentum_error_rel"] = float(np.linalg.norm(L - L0) / np.linalg.norm(L0))
    out["energy_ratio"] = K / K0
    out["max_radial_strain"] = float(max_strain)
    out["bounded"] = bool(np.all(np.isfinite(body.particles())) and max_strain < 1.0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    device = args.device or str(wp.get_preferred_device())
    for name in args.cases.split(","):
        line = json.dumps(run(name, device))
        print(line, flush=True)
        if args.out:
            with open(args.out, "a") as fh:
                fh.write(line + "\n")


if __name__ == "__main__":
    main()
