"""Undamped EoL bodies at an elastic cap (``elastic_safety``): does any gain energy or ring?

Each advance (a frame, or a coupling interval) is split into equal steps within the cap
(``EolBody.advance_group``, 2026-11-28). Before, the steps ran to the cap with the advance's
remainder last; that pattern, repeating every advance, pumped modes parametrically. This study ran
the cases below at 0.25 and 0.5 with the equal steps, and at 0.5 with the old steps (commit
8dea320, the same script on that tree), to choose the default cap (0.5 for every body).

Cases (CPU by default; one JSON line each; ``--cases`` picks, ``--safety`` the caps):

- ``free_box``: a free box (0.3 x 0.2 x 0.15 m, E = 1e5, 8 cells), no gravity, a small random
  velocity field (``tests/test_eol_fidelity.py``'s), 2 s at 30 fps;
- ``spin_box``: the same box spinning at (0.3, 2, 0.1) rad/s, 5 s;
- ``ball_rest``: an icosphere (R = 0.5 m, E = 1e5, 8 cells) dropped 0.2 m on the ground, 4 s;
- ``box_rest``: a box (0.3 x 0.15 x 0.3 m, E = 2e5, 7 cells) set on the ground (friction 0.5), 4 s;
- ``stack``: a 0.15 m cube (6 cells) set 2 cm off centre on that box, 4 s;
- ``two_balls``: two balls (R = 0.25 m, 8 cells) meeting head on at 2 m/s, 5 cm off axis, 2 s;
- ``spin20``: the icosphere at 6 cells spinning at pi rad/s for 20 s, no gravity;
- ``pbd_ball_on_block``: a 0.9 kg PBD ball dropped 3 cm onto the box (the scene of
  ``test_small_pbd_ball_landing_on_an_eol_block_does_not_ring``, the block undamped), 3 s.

Fields: ``dE_max`` and ``dE_end`` (kinetic + EoL elastic + gravitational energy against the
start [J]; a PBD body's elastic energy is not counted), ``vE_max`` and ``vE_last_tenth`` (largest
Eulerian node speed [m/s], over the run and its last tenth), ``steps`` (of all EoL bodies), ``wall_s``.

    python tools/study_eol_even_steps.py > tools/results/study_eol_even_steps.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import numpy as np
import trimesh
import warp as wp

import wsim
from wsim import EolBody

G = 9.81
SOFT = wsim.ElasticMaterial(E=1e5, nu=0.3, rho=1000.0)
FIRM = wsim.ElasticMaterial(E=2e5, nu=0.3, rho=1000.0)
CASES = ("free_box", "spin_box", "ball_rest", "box_rest", "stack", "two_balls", "spin20", "pbd_ball_on_block")


def _block(w: wsim.World, safety: float, **kw) -> EolBody:
    return w.add(EolBody(trimesh.creation.box((0.3, 0.15, 0.3)).subdivide().subdivide(), FIRM, resolution=7,
                         position=(0.0, 0.0755, 0.0), friction=0.5, elastic_safety=safety, **kw))


def build(case: str, safety: float, device: str) -> tuple[wsim.World, int]:
    """The case's World and its number of frames."""
    if case in ("free_box", "spin_box"):
        w = wsim.World(fps=30, gravity=(0.0, 0.0, 0.0), device=device)
        rng = np.random.default_rng(0)
        noise: dict[int, np.ndarray] = {}

        def field(x):
            if len(x) not in noise:
                noise[len(x)] = 0.005 * rng.standard_normal(x.shape)
            return 0.02 * np.sin(40.0 * x[:, [1, 2, 0]]) + noise[len(x)]

        kw = dict(velocity_field=field) if case == "free_box" else dict(angular_velocity=(0.3, 2.0, 0.1))
        w.add(EolBody(trimesh.creation.box((0.3, 0.2, 0.15)), SOFT, resolution=8, elastic_safety=safety, **kw))
        return w, 60 if case == "free_box" else 150
    if case == "spin20":
        w = wsim.World(fps=30, gravity=(0.0, 0.0, 0.0), device=device)
        w.add(EolBody(trimesh.creation.icosphere(subdivisions=2, radius=0.5), SOFT, resolution=6,
                      angular_velocity=(0.0, 0.0, math.pi), elastic_safety=safety))
        return w, 600
    if case == "two_balls":
        w = wsim.World(fps=30, gravity=(0.0, 0.0, 0.0), device=device)
        for name, x, v in (("left", -0.3, 1.0), ("right", 0.3, -1.0)):
            w.add(EolBody(trimesh.creation.icosphere(subdivisions=2, radius=0.25), SOFT, resolution=8, name=name,
                          position=(x, 0.05 * (x > 0), 0.0), velocity=(v, 0.0, 0.0), elastic_safety=safety))
        return w, 60
    w = wsim.World(fps=60 if case == "pbd_ball_on_block" else 30, device=device)
    w.add_collider(wsim.GroundPlane(friction=0.5))
    if case == "ball_rest":
        w.add(EolBody(trimesh.creation.icosphere(subdivisions=2, radius=0.5), SOFT, resolution=8,
                      position=(0.0, 0.7, 0.0), elastic_safety=safety))
        return w, 120
    _block(w, safety, name="block")
    if case == "stack":
        w.add(EolBody(trimesh.creation.box((0.15, 0.15, 0.15)).subdivide().subdivide(), FIRM, resolution=6, name="top",
                      position=(0.02, 0.2265, 0.0), friction=0.5, elastic_safety=safety))
    elif case == "pbd_ball_on_block":
        w.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=2, radius=0.06), FIRM, tets="auto", name="ball",
                           position=(0.02, 0.241, 0.0), friction=0.5))
        return w, 180
    return w, 120


def energy(w: wsim.World) -> float:
    g = G if w.gravity[1] else 0.0
    e = 0.0
    for b in w.bodies:
        if isinstance(b, EolBody):
            e += b.kinetic_energy() + b.elastic_energy + g * float(b.node_masses() @ b.node_world_positions()[:, 1])
        else:
            e += b.kinetic_energy() + g * float(b.masses.sum()) * b.center_of_mass()[1]
    return e


def run(case: str, safety: float, device: str) -> dict:
    t0 = time.perf_counter()
    w, frames = build(case, safety, device)
    eol = [b for b in w.bodies if isinstance(b, EolBody)]
    e0, dE, vE = energy(w), [], []
    for _ in range(frames):
        w.step()
        dE.append(energy(w) - e0)
        vE.append(max(float(np.linalg.norm(b.eulerian_velocity(), axis=1).max()) for b in eol))
    tenth = max(frames // 10, 1)
    return dict(case=case, safety=safety, device=device, frames=frames, E0=e0, dE_max=max(dE), dE_end=dE[-1],
                vE_max=max(vE), vE_last_tenth=max(vE[-tenth:]), steps=sum(b.state.steps for b in eol),
                wall_s=round(time.perf_counter() - t0, 1), code=os.environ.get("WSIM_CODE", "even steps"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--safety", default="0.25,0.5", help="elastic caps, comma separated")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    wp.config.quiet = True
    for case in args.cases.split(","):
        if case not in CASES:
            raise SystemExit(f"unknown case {case!r}; known: {', '.join(CASES)}")
        for s in args.safety.split(","):
            print(json.dumps(run(case, float(s), args.device)), flush=True)


if __name__ == "__main__":
    main()
