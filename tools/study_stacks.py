"""Stacks of two bodies of different methods, as light as or heavier than the body they rest on
(issue 18's "a stack of two bodies of different methods rests on the ground"): what holds and
what does not, one JSON line per stack.

Each stack: a 0.2 m cube of one method (8 kg, E = 1e6 Pa, nu = 0.3) on the ground (friction
0.5), and on it, set 1.5 mm above and ``--offset`` off centre (2 cm), a 0.2 m cube of another
method, ``--ratios`` times as heavy (its density scaled; same E). BEM: the 26-node cube, dt = 2 ms
(one BEM step a coupling interval); PBD: 386 surface vertices, tets, the default 10 substeps of 2
iterations a frame; EoL: 8 cells, damping 20. 100 fps, friction 0.5 between the bodies, the
World's default coupling. Measured over the last second of ``--seconds`` (3) and the second
before it: each body's mean and peak speed (|momentum| / mass) [mm/s], how much the gap between
the top body's lowest point and the bottom body's highest changed [mm] (negative: it sank or
tilted in), how far the top's centre moved relative to the bottom's [mm], and the kinetic plus
gravitational energy of the two at the start of the last two seconds and its largest value in the
last one [J] (it should not grow: nothing drives the stack; the bodies' elastic energy is not in
it). ``fell``: the top's centre ended below the bottom's top face. ``--coupling``: the World's
(``World(coupling=...)``).

    python tools/study_stacks.py [--pairs bem/pbd,pbd/bem,...] [--ratios 1,5] [--device cpu]
        [--coupling auto] [--out tools/results/study_stacks_cpu.jsonl]

``bottom/top`` names a pair (``--pairs``; default: the six of different methods). ``--pusher eol``
or ``pbd`` makes that method push between PBD and EoL bodies whatever ``wsim.world._eol_pushes_pbd``
would choose (the study of ``wsim.world.PBD_PUSHER_MASS_RATIO``:
``tools/results/study_stacks_pusher_cpu.jsonl``, ``--pairs eol/pbd --ratios 2,1,0.5,0.33,0.2,0.125,0.0625``).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import trimesh

import wsim
from wsim.bem import build_operators

G = 9.81
DT = 2e-3
SIZE = 0.2
PAIRS = ("bem/pbd", "pbd/bem", "bem/eol", "eol/bem", "pbd/eol", "eol/pbd")


def cube(world: wsim.World, method: str, rho: float, name: str, position: tuple, device: str):
    """A 0.2 m cube of ``method`` (bem, pbd, eol) of density ``rho`` added to ``world``."""
    mat = wsim.ElasticMaterial(E=1.0e6, nu=0.3, rho=rho)
    box = trimesh.creation.box(extents=(SIZE, SIZE, SIZE))
    if method == "bem":
        mesh = box.subdivide()
        ops = build_operators(mesh, mat, DT, cache=False, device=device)
        return world.add(wsim.BemBody(mesh, mat, DT, operators=ops, name=name, position=position, friction=0.5))
    if method == "pbd":
        mesh = box.subdivide().subdivide().subdivide()
        return world.add(wsim.PbdBody(mesh, mat, tets="auto", name=name, position=position, friction=0.5))
    if method == "eol":
        return world.add(wsim.EolBody(box.subdivide().subdivide(), mat, resolution=8, name=name, position=position,
                                      damping=20.0, friction=0.5))
    raise ValueError(f"unknown method {method!r}")


def mass(body) -> float:
    """A body's mass [kg], whatever its method (PBD: its particles'; EoL: its lumped nodes')."""
    if isinstance(body, wsim.PbdBody):
        return float(body.masses.sum())
    return float(body.mass if isinstance(body, wsim.BemBody) else body.node_masses().sum())


def energy(bodies, masses) -> float:
    """Kinetic plus gravitational energy of the bodies [J] (rigid kinetic energy for BEM bodies)."""
    return float(sum(b.kinetic_energy() + G * m * b.center_of_mass()[1] for b, m in zip(bodies, masses)))


def stack(bottom: str, top: str, ratio: float, seconds: float, offset: float, device: str,
          coupling: str = "auto") -> dict:
    """One stack, stepped ``seconds``; its measures (module docstring)."""
    fps = 1.0 / (5 * DT)
    w = wsim.World(fps=fps, gravity=(0.0, -G, 0.0), device=device, coupling=coupling)
    w.add_collider(wsim.GroundPlane(0.0, friction=0.5))
    lo = cube(w, bottom, 1000.0, "bottom", (0.0, 0.1005, 0.0), device)
    hi = cube(w, top, 1000.0 * ratio, "top", (offset, 0.3015, 0.0), device)
    masses = (mass(lo), mass(hi))
    n, second = int(round(seconds * fps)), int(round(fps))
    rows, energies = [], []
    t0 = time.perf_counter()
    for _ in range(n):
        w.step()
        rows.append((np.linalg.norm(lo.linear_momentum()) / masses[0], np.linalg.norm(hi.linear_momentum()) / masses[1],
                     hi.points()[:, 1].min() - lo.points()[:, 1].max(), *(hi.center_of_mass() - lo.center_of_mass())))
        energies.append(energy((lo, hi), masses))
    wall = time.perf_counter() - t0
    r = np.asarray(rows)
    last, before = r[-second:], r[-2 * second:-second]
    e = np.asarray(energies)
    return {
        "bottom": bottom, "top": top, "ratio": ratio, "masses_kg": [round(m, 2) for m in masses],
        "device": device, "seconds": seconds, "offset_m": offset, "coupling": coupling,
        "coupling_stats": dict(w.coupling_stats),
        "mean_speed_last_s_mm_s": [round(1e3 * float(last[:, k].mean()), 2) for k in (0, 1)],
        "peak_speed_last_s_mm_s": [round(1e3 * float(last[:, k].max()), 1) for k in (0, 1)],
        "mean_speed_second_before_mm_s": [round(1e3 * float(before[:, k].mean()), 2) for k in (0, 1)],
        "gap_change_mm": round(1e3 * float(last[-1, 2] - before[0, 2]), 3),
        "top_moved_mm": round(1e3 * float(np.linalg.norm(last[-1, 3:] - before[0, 3:])), 2),
        "energy_J": {"start_of_last_two_s": round(float(e[-2 * second]), 4), "start_of_last_s": round(float(e[-second]), 4),
                     "max_last_s": round(float(e[-second:].max()), 4), "end": round(float(e[-1]), 4)},
        "fell": bool(r[-1, 4] < 0.5 * SIZE), "wall_s": round(wall, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", default=",".join(PAIRS))
    ap.add_argument("--ratios", default="1,5")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--offset", type=float, default=0.02)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--coupling", default="auto", help="World(coupling=...): auto, explicit or implicit")
    ap.add_argument("--pusher", choices=("rule", "eol", "pbd"), default="rule",
                    help="between PBD and EoL bodies: the World's rule (wsim.world._eol_pushes_pbd), or always this method")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    if args.pusher != "rule":  # a study of the rule itself: this process's World only
        import wsim.world

        wsim.world._eol_pushes_pbd = lambda *a, **k: args.pusher == "eol"
    for ratio in (float(x) for x in args.ratios.split(",")):
        for pair in args.pairs.split(","):
            bottom, top = pair.split("/")
            result = stack(bottom, top, ratio, args.seconds, args.offset, args.device, args.coupling)
            line = json.dumps(result | ({"pusher": args.pusher} if args.pusher != "rule" else {}))
            print(line, flush=True)
            if args.out:
                with open(args.out, "a") as f:
                    f.write(line + "\n")


if __name__ == "__main__":
    main()
