"""EoL fidelity study (issue 16, items 1, 5, 6): one JSON line per case, at the issue's full settings (CPU).

    python tools/study_eol_fidelity.py --cases slide,rest,spin,box,bunny,cylinder --tag before

Cases:
* ``slide``: sphere R = 0.2 m (E = 1e5, nu = 0.3, rho = 1000), resolution 8, damping 200, released
  2 mm above a frictionless GroundPlane, 3 s: drift of the centre of mass along the plane [cm],
  horizontal momentum [kg m/s], horizontal / vertical contact impulse, max penetration [% R].
* ``rest``: the same ball at damping 1000 for 6 s: drift, time to rest (max nodal speed below
  5 mm/s from then on), max and final penetration [% R], the smallest dt and its mean in contact.
* ``spin``: a free sphere spinning at 2 rad/s (no gravity), resolution 8 / 12 / 16: node-mass
  angular momentum and kinetic energy against the continuum rigid values 2/5 M R^2 omega.
* ``box`` / ``box_edge`` / ``box_corner`` / ``bem_cube`` / ``bunny``: ``scenes/eol_spinning_sphere.py``
  with its ``--mesh`` set to a trimesh box (axis-aligned; turned 45 deg about z so an edge leads;
  turned again so a corner leads), the BEM authors' 770-vertex cube or their bunny: frames done
  within a wall-clock budget, s/frame, the lowest point [mm], the grid's growth, failure message.
* ``cylinder``: ``scenes/eol_plastic_cylinder.py``: the lowest point at the end [mm].
* ``fish``: a procedural fish (0.6 m, tail fin 14 mm thick, 20 cells across, E = 50 kPa, damping
  20) spinning at pi rad/s lands at 4 m/s on a frictionless plane, 1 s, at 24, 30, 40, 50 and 60
  fps x hourglass 0.1 and 0 (a thin part crossing the ground): completed, the largest energy rise
  above its running minimum (of the start), the deepest vertex [cells], the largest per-frame
  momentum change not matched by gravity and contact [kg m/s], the contact impulse over the run.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import trimesh

import wsim

ROOT = Path(__file__).resolve().parents[1]
BEM = Path("/work/shared/meshes/bem-paper")
SOFT = dict(E=1e5, nu=0.3, rho=1000.0)


def _ground_ball(damping: float, resolution: int = 8, gap: float = 0.002, radius: float = 0.2, **kw):
    world = wsim.World(fps=30, gravity=(0.0, -9.81, 0.0), device="cpu")
    world.add_collider(wsim.GroundPlane(0.0, friction=0.0))
    m = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    m.apply_translation((0.0, radius + gap, 0.0))
    body = world.add(wsim.EolBody(m, wsim.ElasticMaterial(**SOFT), resolution=resolution, damping=damping, **kw))
    return world, body


def ground_drop(name: str, damping: float, seconds: float, radius: float = 0.2) -> dict:
    world, b = _ground_ball(damping, radius=radius)
    t0 = time.perf_counter()
    x0 = b.points().mean(axis=0)
    max_pen = 0.0
    speeds, times = [], []
    frames = int(round(seconds * world.fps))
    for _ in range(frames):
        world.step()
        p = b.points()
        max_pen = max(max_pen, -float(p[:, 1].min()))
        speeds.append(float(np.linalg.norm(b.node_world_velocities(), axis=1)[b.node_masses() > 0].max()))
        times.append(world.time)
    x1 = b.points().mean(axis=0)
    P = b.linear_momentum()
    J = b.contact_impulse
    moving = [t for t, s in zip(times, speeds) if s >= 5e-3]
    contact_dt = [r.dt for r in b.history if r.rows > 0]
    return dict(case=name, damping=damping, seconds=seconds, resolution=b.resolution, h=b.grid.h,
                drift_cm=100.0 * float(np.hypot(x1[0] - x0[0], x1[2] - x0[2])),
                horizontal_momentum=float(np.hypot(P[0], P[2])), vertical_momentum=float(P[1]),
                contact_impulse=J.tolist(),
                horizontal_over_vertical_impulse=float(np.hypot(J[0], J[2]) / max(abs(J[1]), 1e-300)),
                max_penetration_pct_R=100.0 * max_pen / radius,
                final_penetration_pct_R=100.0 * max(-float(b.points()[:, 1].min()), 0.0) / radius,
                final_penetration_cells=max(-float(b.points()[:, 1].min()), 0.0) / b.grid.h,
                time_to_rest_s=(times[0] if not moving else (None if moving[-1] >= times[-1] - 1e-9 else
                                                             moving[-1] + 1.0 / world.fps)),
                final_max_speed=speeds[-1], steps=b.steps,
                dt_contact_min=min(contact_dt, default=None),
                dt_contact_mean=(float(np.mean(contact_dt)) if contact_dt else None),
                dt_cap=b.dt_elastic, wall_s=time.perf_counter() - t0)


def spin(resolutions=(8, 12, 16), omega=2.0, radius=0.2) -> list[dict]:
    out = []
    for res in resolutions:
        world = wsim.World(fps=30, gravity=(0.0, 0.0, 0.0), device="cpu")
        m = trimesh.creation.icosphere(subdivisions=4, radius=radius)
        b = world.add(wsim.EolBody(m, wsim.ElasticMaterial(**SOFT), resolution=res,
                                   angular_velocity=(0.0, 0.0, omega)))
        world.step()
        M = SOFT["rho"] * 4.0 / 3.0 * np.pi * radius**3
        L_cont = 0.4 * M * radius**2 * omega
        w = b.node_world_velocities()
        mass = b.node_masses()
        x = b.grid.node_positions() @ b.frame[0].T + b.frame[1]
        com = mass @ x / mass.sum()
        L_nodes = float((mass[:, None] * np.cross(x - com, w)).sum(axis=0)[2])
        try:
            L_api = float(b.angular_momentum()[2])
        except Exception:  # noqa: BLE001 - not provided before the fix
            L_api = None
        out.append(dict(case="spin", resolution=res, h=b.grid.h, L_continuum=L_cont, L_nodes=L_nodes,
                        L_api=L_api, L_nodes_rel_err=L_nodes / L_cont - 1.0,
                        L_api_rel_err=None if L_api is None else L_api / L_cont - 1.0,
                        node_mass_rel_err=float(mass.sum()) / M - 1.0, body_mass_rel_err=b.mass / M - 1.0,
                        KE_rel_err=b.kinetic_energy() / (0.5 * 0.4 * M * radius**2 * omega**2) - 1.0))
    return out


def fish_landing(fps: int, hourglass: float, seconds: float = 1.0, resolution: int = 20) -> dict:
    g = 9.81
    world = wsim.World(fps=fps, gravity=(0.0, -g, 0.0), device="cpu")
    world.add_collider(wsim.GroundPlane(0.0, friction=0.0))
    mesh = wsim.mesh.shapes.fish(0.6, 3)
    mesh.apply_translation((0.0, 0.75, 0.0))
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    body = world.add(wsim.EolBody(mesh, wsim.ElasticMaterial(E=5e4, nu=0.3, rho=500.0), resolution=resolution,
                                  damping=20.0, velocity=(0.4, -3.0, 0.0), angular_velocity=tuple(np.pi * axis),
                                  hourglass=hourglass, name="fish"))
    h = body.grid.h

    def energy() -> float:
        m, x = body.node_masses(), body.node_world_positions()
        return float(body.kinetic_energy() + body.elastic_energy + g * np.sum(m * x[:, 1]))

    E = [energy()]
    depth, budget, fail = [], [], None
    P, impulse = body.linear_momentum(), np.zeros(3)
    t0 = time.perf_counter()
    for f in range(int(round(fps * seconds))):
        try:
            world.step()
        except Exception as e:  # noqa: BLE001 - the outcome is what we record
            fail = f"frame {f + 1}: {type(e).__name__}: {e}"
            break
        P1, impulse1 = body.linear_momentum(), body.gravity_impulse + body.contact_impulse + body.load_impulse
        budget.append(float(np.linalg.norm((P1 - P) - (impulse1 - impulse))))
        P, impulse = P1, impulse1
        E.append(energy())
        depth.append(float(-body.points()[:, 1].min() / h))
    E = np.array(E)
    return dict(case="fish", fps=fps, hourglass=hourglass, resolution=resolution, seconds=seconds, outcome=fail or "ok",
                steps=body.steps, wall_s=time.perf_counter() - t0,
                max_energy_rise_rel=float(np.max(E - np.minimum.accumulate(E)) / abs(E[0])),
                deepest_cells=max(depth, default=None), frames_deeper_than_2_cells=sum(d > 2.0 for d in depth),
                max_frame_momentum_mismatch=max(budget, default=None), contact_impulse=body.contact_impulse.tolist())


def _load_scene(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scenes" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def scene_run(case: str, scene: str, mesh: str | None, budget: float, frames: int | None = None) -> dict:
    mod = _load_scene(scene)
    world = mod.build(mesh=mesh, device="cpu")
    body = world.bodies[0] if hasattr(world, "bodies") else None
    n = frames or mod.FRAMES
    t0 = time.perf_counter()
    done, fail, lowest, frame_times, warns = 0, None, [], [], []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for f in range(n):
            tf = time.perf_counter()
            try:
                world.step()
            except Exception as e:  # noqa: BLE001 - the outcome is what we record
                fail = f"{type(e).__name__}: {e}"
                break
            frame_times.append(time.perf_counter() - tf)
            done += 1
            lowest.append(1000.0 * float(body.points()[:, 1].min()))
            if time.perf_counter() - t0 > budget:
                fail = f"wall-clock budget {budget:.0f} s reached"
                break
        warns = sorted({f"{w.category.__name__}: {w.message} ({Path(w.filename).name})" for w in caught})
    return dict(case=case, scene=scene, mesh=mesh, frames_requested=n, frames_done=done, outcome=fail or "ok",
                s_per_frame_mean=float(np.mean(frame_times)) if frame_times else None,
                s_per_frame_max=float(np.max(frame_times)) if frame_times else None,
                lowest_mm_min=min(lowest, default=None), lowest_mm_final=lowest[-1] if lowest else None,
                steps=body.steps, h_mm=1000.0 * body.grid.h, grid_cells=list(body.grid.cells),
                warnings=warns, wall_s=time.perf_counter() - t0)


def main(argv=None) -> None:
    from wsim.device import quiet_warp

    quiet_warp()
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", default="slide,rest,spin,box,box_edge,box_corner,bem_cube,bunny,cylinder")
    ap.add_argument("--tag", default="")
    ap.add_argument("--budget", type=float, default=300.0, help="wall-clock seconds per scene case")
    ap.add_argument("--out", default=None, help="append the JSON lines to this file too")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp())
    boxes = {}
    for name, turns in (("box", ()), ("box_edge", ((np.pi / 4, [0, 0, 1]),)),
                        ("box_corner", ((np.pi / 4, [0, 0, 1]), (np.arctan(1.0 / np.sqrt(2.0)), [1, 0, 0])))):
        m = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
        for angle, axis in turns:
            m.apply_transform(trimesh.transformations.rotation_matrix(angle, axis))
        boxes[name] = tmp / f"{name}.obj"
        m.export(boxes[name])
    rows: list[dict] = []
    for case in args.cases.split(","):
        start = len(rows)
        if case == "slide":
            rows.append(ground_drop("slide", 200.0, 3.0))
        elif case == "rest":
            rows.append(ground_drop("rest", 1000.0, 6.0))
        elif case == "spin":
            rows.extend(spin())
        elif case in boxes:
            rows.append(scene_run(case, "eol_spinning_sphere", str(boxes[case]), args.budget))
        elif case == "bem_cube":
            rows.append(scene_run("bem_cube", "eol_spinning_sphere", str(BEM / "cube_reordered.obj"), args.budget))
        elif case == "bunny":
            rows.append(scene_run("bunny", "eol_spinning_sphere", str(BEM / "bunny_reordered.obj"), args.budget))
        elif case == "cylinder":
            rows.append(scene_run("cylinder", "eol_plastic_cylinder", None, args.budget))
        elif case == "fish":
            rows.extend(fish_landing(fps, hg) for fps in (24, 30, 40, 50, 60) for hg in (0.1, 0.0))
        else:
            raise SystemExit(f"unknown case {case!r}")
        for row in rows[start:]:
            row["tag"] = args.tag
            line = json.dumps(row)
            print(line, flush=True)
            if args.out:
                with open(args.out, "a") as fh:
                    fh.write(line + "\n")


if __name__ == "__main__":
    main()
