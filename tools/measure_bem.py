"""Measure a BEM scene over time: volume change (paper Fig. 5 metric), energy, momentum, step timing.

    python tools/measure_bem.py scenes/bem_spinning_cube.py --frames 60 > cube.json
    python tools/measure_bem.py scenes/bem_squeeze.py --device cuda:0 --plot squeeze.png

Prints one JSON object: per BEM body, per frame, the relative volume change of the deformed
surface, the frame's kinetic energy (1/2 m |v|^2 + 1/2 omega . L), gravitational potential energy
(-m g . T), linear and angular momentum, the largest |u|, and the mean seconds per step by stage
(history, loads, solve, correction, frame; the device is synchronized between stages).
"""

from __future__ import annotations

import argparse
import json
import runpy
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--device", default=None)
    ap.add_argument("--mesh", default=None)
    ap.add_argument("--plot", default=None, help="write a PNG of volume change and energy over time")
    args = ap.parse_args()
    from wsim.device import quiet_warp

    import wsim

    quiet_warp()
    scene = runpy.run_path(args.scene)
    world = scene["build"](mesh=args.mesh, device=args.device)
    frames = args.frames or scene.get("FRAMES", 30)
    bodies = [b for b in world.bodies if isinstance(b, wsim.BemBody)]
    if not bodies:
        raise SystemExit(f"{args.scene} has no BemBody")
    for b in bodies:
        b.profile = True
    rest = {b.name: b.volume() for b in bodies}
    series: dict = {b.name: {k: [] for k in ("time", "volume_change", "kinetic_energy", "potential_energy",
                                             "linear_momentum", "angular_momentum", "max_displacement")}
                    for b in bodies}

    def record(w: wsim.World) -> None:
        for b in bodies:
            s = series[b.name]
            s["time"].append(b.time)
            s["volume_change"].append(b.volume() / rest[b.name] - 1.0)
            s["kinetic_energy"].append(b.kinetic_energy())
            s["potential_energy"].append(float(-b.mass * w.gravity @ b.frame.T))
            s["linear_momentum"].append(b.linear_momentum().tolist())
            s["angular_momentum"].append(b.angular_momentum().tolist())
            s["max_displacement"].append(float(np.max(np.abs(b.displacement()))))

    t0 = time.perf_counter()
    world.run(frames=frames, out=None, progress=False, on_frame=record)
    wall = time.perf_counter() - t0
    out = {"scene": args.scene, "device": world.device.alias, "frames": frames, "wall_seconds": wall, "bodies": {}}
    for b in bodies:
        s = series[b.name]
        out["bodies"][b.name] = {
            "N": b.operators.n_nodes, "n_max": b.operators.n_max, "dt": b.dt, "steps": b.steps,
            "max_volume_change": float(np.max(np.abs(s["volume_change"]))),
            "stage_seconds_per_step": {k: v / max(b.steps, 1) for k, v in b.timings.items()},
            **s,
        }
    print(json.dumps(out))
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        for name, s in out["bodies"].items():
            ax[0].plot(s["time"], 100.0 * np.array(s["volume_change"]), label=name)
            ax[1].plot(s["time"], np.array(s["kinetic_energy"]) + np.array(s["potential_energy"]), label=name)
        ax[0].set(xlabel="t [s]", ylabel="volume change [%]")
        ax[1].set(xlabel="t [s]", ylabel="frame kinetic + potential energy [J]")
        ax[0].legend()
        fig.tight_layout()
        fig.savefig(args.plot, dpi=120)


if __name__ == "__main__":
    main()
