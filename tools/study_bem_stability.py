"""BEM stability at the extremes: one JSON line per case (CPU by default).

    python tools/study_bem_stability.py                      # every case, 10^4 steps each
    python tools/study_bem_stability.py --cases soft,fast_spin --steps 2000

Each case is a 42-node sphere (radius 0.1 m; ``--subdivisions`` refines it) that spins, falls under gravity and is squeezed on
one side for the first 20 steps, then runs free. The base material is E = 1e5 Pa, nu = 0.3,
rho = 1000 kg/m^3 and the base dt is a tenth of the breathing period (2.0 ms). A case passes if
it stays bounded (the largest |u| over the last tenth of the run is no larger than the largest
over the first half, which holds the squeeze and its wave transits, and the volume is within 1 %
of rest) or stops with ``SimulationDiverged``
naming the body and quantity. The slow tests in tests/test_bem_dynamics.py run the same cases.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

CASES = {
    # name: (E factor, nu, incompressible, dt factor, spin [rev/s])
    "base": (1.0, 0.3, False, 1.0, 1.0),
    "nu_0.45": (1.0, 0.45, False, 1.0, 1.0),
    "incompressible": (1.0, 0.5, True, 1.0, 1.0),
    "stiff_x1000": (1e3, 0.3, False, 1.0, 1.0),
    "soft_div1000": (1e-3, 0.3, False, 1.0, 1.0),
    "dt_x10": (1.0, 0.3, False, 10.0, 1.0),
    "dt_div10": (1.0, 0.3, False, 0.1, 1.0),
    "fast_spin_10rev": (1.0, 0.3, False, 1.0, 10.0),
}


def run_case(name: str, steps: int = 10_000, device: str = "cpu", subdivisions: int = 1) -> dict:
    import trimesh

    import wsim
    from wsim.bem.analytic import breathing_frequency

    e_factor, nu, incompressible, dt_factor, spin = CASES[name]
    base = wsim.ElasticMaterial(E=1e5, nu=0.3, rho=1000.0)
    dt = dt_factor * 0.1 * 2.0 * math.pi / breathing_frequency(base, 0.1)
    material = wsim.ElasticMaterial(E=1e5 * e_factor, nu=nu, rho=1000.0, incompressible=incompressible)
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.1)
    t0 = time.perf_counter()
    world = wsim.World(fps=1.0 / dt, device=device, gravity=(0.0, -9.81, 0.0))
    body = world.add(wsim.BemBody(mesh, material, dt, name=name, angular_velocity=(0.3, 2.0 * math.pi * spin, 0.0),
                                  cache=False))
    build = time.perf_counter() - t0
    n, x = body.rest_normals, body.rest_vertices
    # a squeeze of 1e-3 E on the +x half: strain ~1e-3 whatever the stiffness
    squeeze = -1e-3 * material.E * n * (x[:, :1] > 0.0)
    body.add_traction(lambda t: squeeze if t <= 20 * dt + 1e-12 else np.zeros_like(squeeze))
    v0 = body.volume()
    peak_half = peak_tail = 0.0
    deciles = [0.0] * 10
    vol_tail = 0.0
    outcome, message = "bounded", ""
    t1 = time.perf_counter()
    for i in range(steps):
        try:
            body.step()
            body.check_finite(i, body.time)
        except wsim.SimulationDiverged as err:
            outcome, message = "diverged", str(err)
            break
        u = float(np.max(np.abs(body.displacement())))
        if i < steps // 2:
            peak_half = max(peak_half, u)
        deciles[10 * i // steps] = max(deciles[10 * i // steps], u)
        if i >= steps - steps // 10:
            peak_tail = max(peak_tail, u)
            vol_tail = max(vol_tail, abs(body.volume() / v0 - 1.0))
    if outcome == "bounded" and (peak_tail > peak_half or vol_tail > 0.01):
        outcome = "unbounded"
    omega = body.frame.omega
    return {
        "case": name, "device": device, "nodes": body.operators.n_nodes, "steps": body.steps, "dt": dt, "n_max": body.operators.n_max,
        "E": material.E, "nu": nu, "spin_rev_s": spin, "outcome": outcome, "message": message,
        "max_u_first_half": peak_half, "max_u_last_tenth": peak_tail, "max_u_by_decile": deciles, "max_volume_change_last_tenth": vol_tail,
        "spin_change": float(np.linalg.norm(omega) / np.linalg.norm(body.initial_angular_velocity) - 1.0),
        "build_seconds": round(build, 2), "seconds_per_step": (time.perf_counter() - t1) / max(body.steps, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--steps", type=int, default=10_000)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--subdivisions", type=int, default=1, help="icosphere subdivisions (1: 42 nodes, 2: 162, 3: 642)")
    args = ap.parse_args()
    from wsim.device import quiet_warp

    quiet_warp()
    for name in args.cases.split(","):
        if name not in CASES:
            raise SystemExit(f"unknown case {name!r}; known: {', '.join(CASES)}")
        print(json.dumps(run_case(name, args.steps, args.device, args.subdivisions)), flush=True)


if __name__ == "__main__":
    main()
