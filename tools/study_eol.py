"""EoL speed/accuracy knobs and stability at the extremes: one JSON line per case (CPU by default).

    python tools/study_eol.py                                    # both parts, CPU (~15 min on 2 cores)
    python tools/study_eol.py --part knobs --out tools/results/study_eol_cpu.jsonl
    python tools/study_eol.py --part stability --cases nu_0.49,stiff_x1000
    python tools/study_eol.py --device cuda:0 --ref-resolution 32   # on a GPU machine
    python tools/study_eol.py --quick                            # smoke test, < 60 s with warm kernels

Every case runs in a fresh (spawned) process, so ``peak_rss_mb`` (the process's ru_maxrss) is
that case's own peak, a frame that never ends (dt collapsing but not yet below the body's
failure threshold) can be killed (``status = "timeout"``), and one case's crash does not end the study.

**Part A, knobs** (``--part knobs``). The reference scene: an elastic icosphere (subdivisions 2,
radius 0.5 m, E = 1e5 Pa, nu = 0.3, rho = 1000 kg/m^3, damping 1000 Pa s as in
tests/test_eol_body.py's ``drop``) with its centre at y = 0.7 m, moving sideways at 0.5 m/s and
spinning at 2 rad/s about z, dropped on a ground plane (World at 30 fps, g = 9.81 m/s^2), for 15
frames (0.5 s: the fall, the impact at ~0.2 s and the rebound/settling). One knob of EolBody is
varied at a time from the default (resolution 8, semi-Lagrangian advection, cfl 0.5,
collision_block 1, dt_max None); ``lagrangian = "eulerian"`` (no Lagrangian frame, with padding 4 so
the body stays on its grid) is a baseline for context. The errors compare the final state with a
reference run (``--ref-resolution``, default 16, BFECC, cfl 0.2, dt_max 1.5e-4 s):

* ``err_max_rel``, ``err_rms_rel``: max and RMS over the surface vertices of |x_i - x_i^ref| over
  the sphere's diameter (the mesh lives in material space, so vertex i is the same material point
  in every run, whatever the grid);
* ``shape_err_max_rel``: the same after removing the centre-of-mass offset (orientation and shape);
* ``rot_err_deg``: the angle of the rotation that best aligns the centred surfaces (Kabsch), and
  ``deform_err_max_rel``: the max error left after that alignment (deformation alone);
* ``com_err`` [m]: distance between the centres of mass, the centroid of the volume enclosed by the
  tracked surface (uniform density; independent of how each grid samples the mass);
* ``freefall_com_err`` [m]: the centre of mass at t = 0.2 s (frame 6, the last before contact)
  against the exact ballistic path: an error with an exact answer (the pose is integrated
  v-then-x, so it is g t dt / 2 to first order);
* ``cfl_limited_frac``: the fraction of steps whose dt fell below the caps' (each frame split
  into equal steps within them, ``StepRecord.cap``), i.e. where Eq. (33)'s CFL root bound
  (where ``cfl`` can matter at all);
* ``wall_per_sim_s``: wall seconds per simulated second, timed from the end of frame 1 (frame 1
  compiles or loads the kernels; its time is ``first_frame_s``);
* ``steps``, ``dt_mean`` [s] (sim_time / steps), ``dt_min``, ``dt_cap`` (the elastic/viscous cap);
* ``peak_rss_mb``: host max RSS of the case's process, ``rss_delta_mb`` that less the RSS after
  importing Warp (before the body is built), ``state_mb``: bytes of the body's Warp arrays;
  ``device_mem_high_mb``: the CUDA mempool high-water mark (CUDA only);
* ``lowest_min`` [m]: the lowest surface vertex over the run (penetration into the ground < 0),
  ``rows_mean``: contact rows per step in contact, ``qp_fallbacks``: steps where the QP fell back to NNLS.

``ref_check`` runs the reference settings one grid coarser (``--ref-resolution`` - 4): its error
against the reference estimates the reference's own error, which should be well below the
knob cases' errors for them to mean anything. ``err_vs`` names what the errors are against. With
damping 1000 Pa s the viscous cap sets dt and cfl never binds, so the ``cfl@damping=20`` group
repeats the cfl sweep at tools/bench_eol.py's damping (20 Pa s), its errors against its own
cfl = 0.1 run.

**Part B, stability** (``--part stability``). Each case steps one body (radius 0.5 m) for a
long-ish time, catching ``wsim.SimulationDiverged``, and reports ``max_vE`` (largest |Eulerian
velocity| at a node [m/s]), ``vE_first_half``/``vE_last_tenth`` (the same over the first half and
the last tenth of the frames), ``max_vE_heavy`` etc. (the same over nodes holding at least a
quarter cell of material: the largest |vE| is nearly always at a sliver node at the mass floor),
``vol_ratio_{min,max,final}`` (volume of the tracked surface over its initial volume),
``dev_max_rel``/``dev_final_rel`` (max vertex distance from the rigidly moved rest shape
rest @ F.T + T, over the diameter), ``steps``, ``dt_mean``, ``dt_last_tenth`` (mean dt
over the last tenth of the steps: has dt recovered to ``dt_cap``?), ``lowest_min``/``lowest_final``
(lowest vertex [m], with a ground), ``omega_drift`` (|omega| change, relative), ``L_drift``
(angular momentum about the frame origin, relative), ``energy_drift`` ((KE + elastic) change
over the initial, for free flight only), ``wall_s``. ``status``:

* ``bounded``: ran to its end (or its cap) with vE_last_tenth <= 1.2 vE_first_half + 1e-6 m/s
  and the final volume within 10 % of the initial;
* ``growing``: vE_last_tenth above that; ``volume``: the volume off by more than 10 %;
* ``diverged``: SimulationDiverged (``message`` says which quantity); ``timeout``: a frame ran past
  the hard limit and the process was killed; ``error``: any other exception.

``bulk_status`` is the same verdict from the |vE| of the nodes with at least a quarter cell of
material (a short run from rest rings up its sliver nodes, which the all-node test calls growing).

``truncated`` is true where the wall-clock or step cap stopped the run before ``sim_time_target``.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import queue
import resource
import subprocess
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np

RADIUS = 0.5  # [m]; the errors are relative to the diameter
DIAMETER = 2.0 * RADIUS
BASE_MATERIAL = {"E": 1e5, "nu": 0.3, "rho": 1000.0}

# the drop scene of Part A (and of the material cases of Part B); tests/test_eol_body.py's drop plus
# a sideways velocity and a spin so that rotation, translation and contact all carry error
DROP = {"centre": (0.0, 0.7, 0.0), "velocity": (0.5, 0.0, 0.0), "angular_velocity": (0.0, 0.0, 2.0),
        "gravity": True, "ground": True, "damping": 1000.0, "fps": 30.0}
DEFAULT = {"resolution": 8, "advection": "semi-lagrangian", "cfl": 0.5, "collision_block": 1, "dt_max": None}
KNOBS: dict[str, list[Any]] = {
    "resolution": [6, 8, 10, 12],
    "advection": ["semi-lagrangian", "bfecc"],
    "cfl": [0.2, 0.5, 0.8],
    "collision_block": [1, 2, 4],
    "dt_max": [None, 1e-3, 3e-4],
}


def reference_settings(resolution: int) -> dict[str, Any]:
    # the damping cap rho h^2 / (12 eta) is 3.3e-4 s at 16 cells: dt_max below it halves the step
    # everywhere, cfl 0.2 shortens the steps in contact, BFECC is second order in smooth regions
    return {"resolution": resolution, "advection": "bfecc", "cfl": 0.2, "collision_block": 1,
            "dt_max": 1.5e-4 * (16.0 / resolution) ** 2}


# Part B: name -> (scene overrides, body overrides, target sim time [s], step cap, wall cap [s], note)
STABILITY: dict[str, tuple[dict, dict, float, int, float, str]] = {
    "base": ({}, {}, 2.0, 20_000, 60.0, "the Part A drop scene at 8 cells, 2 s"),
    "nu_0.45": ({"material": {"nu": 0.45}}, {}, 2.0, 20_000, 90.0, "drop scene, 2 s"),
    "nu_0.49": ({"material": {"nu": 0.49}}, {}, 2.0, 20_000, 90.0, "drop scene, 2 s"),
    "nu_0.499": ({"material": {"nu": 0.499}}, {}, 2.0, 12_000, 90.0,
                 "drop scene; c1 = 129 m/s caps dt at 4.8e-4 s (8 cells); capped at 12000 steps / 90 s"),
    "stiff_x1000": ({"material": {"E": 1e8}}, {}, 1.0, 12_000, 90.0,
                    "drop scene, E = 1e8: c1 = 367 m/s, dt 1.7e-4 s; 1 s"),
    "soft_div1000": ({"material": {"E": 1e2}}, {}, 2.0, 20_000, 90.0,
                     "drop scene, E = 1e2 with the base damping 1000 Pa s (eta/E = 10 s: a viscous "
                     "fluid); rho g r / E = 49 and the bulk modulus (83 Pa) is far below rho g h: "
                     "it is crushed (volume loss expected), not a bounded elastic solid"),
    "soft_div1000_free": ({"gravity": False, "ground": False, "velocity": (0.0, 0.0, 0.0),
                           "angular_velocity": (0.0, 0.3, 0.0), "material": {"E": 1e2}, "damping": 0.0},
                          {}, 4.0, 20_000, 60.0,
                          "E = 1e2 free flight at 0.3 rad/s, no damping: centrifugal strain ~0.2"),
    "fast_spin_10rev": ({"gravity": False, "ground": False, "velocity": (0.0, 0.0, 0.0),
                         "angular_velocity": (0.0, 2.0 * math.pi * 10.0, 0.0)}, {}, 1.0, 20_000, 90.0,
                        "free flight at 62.8 rad/s (damping 1000): rho w^2 r^2 / E = 9.9, far past "
                        "what E = 1e5 can hold, so it is expected to fly apart; 1 s"),
    "fast_spin_10rev_stiff": ({"gravity": False, "ground": False, "velocity": (0.0, 0.0, 0.0),
                               "angular_velocity": (0.0, 2.0 * math.pi * 10.0, 0.0),
                               "material": {"E": 1e7}}, {}, 1.0, 20_000, 90.0,
                              "the same spin with E = 1e7 (centrifugal strain ~0.1), 1 s"),
    "tiny_dt_1e-5": ({"fps": 300.0}, {"dt_max": 1e-5, "resolution": 6}, 0.05, 10_000, 60.0,
                     "drop scene at 6 cells with dt_max = 1e-5 s, 0.05 s (free fall only) at 300 fps"),
    "long_spin_20s": ({"gravity": False, "ground": False, "velocity": (0.0, 0.0, 0.0),
                       "angular_velocity": (0.0, 0.0, math.pi), "damping": 0.0},
                      {"resolution": 6}, 20.0, 40_000, 120.0,
                      "free flight at pi rad/s, fictitious loads on, no damping (energy is conserved "
                      "by the equations; only advection dissipates), 6 cells, 20 s"),
    "rest_on_ground_5s": ({"velocity": (0.0, 0.0, 0.0), "angular_velocity": (0.0, 0.0, 0.0)}, {}, 5.0, 20_000,
                          120.0, "dropped from y = 0.7 with no spin, then resting on the ground, 8 cells, 5 s"),
}
QUICK_STABILITY = {"base": 0.2, "long_spin_20s": 0.5}  # name -> sim time [s] in --quick


# ------------------------------------------------------------------------------------------------
# the worker (runs in a spawned process)
# ------------------------------------------------------------------------------------------------
def build(scene: dict[str, Any], body_kw: dict[str, Any], device: str):
    """The world and the body of one case (the way tools/bench_eol.py builds them)."""
    import trimesh

    import wsim

    mat = {**BASE_MATERIAL, **scene.get("material", {})}
    world = wsim.World(fps=scene["fps"], gravity=(0.0, -9.81, 0.0) if scene["gravity"] else (0.0, 0.0, 0.0),
                       device=device)
    if scene["ground"]:
        world.add_collider(wsim.GroundPlane(0.0))
    ball = trimesh.creation.icosphere(subdivisions=2, radius=RADIUS)
    ball.apply_translation(scene["centre"])
    body = world.add(wsim.EolBody(ball, wsim.ElasticMaterial(**mat), damping=scene["damping"],
                                  velocity=scene["velocity"], angular_velocity=scene["angular_velocity"], **body_kw))
    return world, body


def _state_bytes(body: Any) -> int:
    """Bytes of the Warp arrays the body holds (its grid fields, samples, contact slots)."""
    import warp as wp

    total = 0
    for v in vars(body).values():
        for a in (v if isinstance(v, tuple) else (v,)):
            if isinstance(a, wp.array):
                total += int(a.capacity)
    surf = getattr(body, "_surface", None)  # the contact struct's own arrays (samples)
    if surf is not None:
        for k in ("sample_face", "sample_bary", "sample_share"):
            a = getattr(surf, k, None)
            if isinstance(a, wp.array):
                total += int(a.capacity)
    return total


def _centroid(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Centroid of the volume enclosed by a closed, outward surface (the centre of mass at uniform density)."""
    a, b, c = points[faces[:, 0]], points[faces[:, 1]], points[faces[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0  # signed tetrahedra from the origin
    return (vol[:, None] * (a + b + c) / 4.0).sum(axis=0) / vol.sum()


def _angular_momentum(body: Any) -> np.ndarray:
    """sum_s m_s (x_s - T) x x_dot_s over the nodes (world, about the frame origin)."""
    F, T = body.frame  # x = F y + T for every Lagrangian kind (F = I for "eulerian")
    x = body.grid.node_positions() @ F.T + T
    return np.cross(x - T, body.node_world_velocities()).T @ body.node_masses()


def worker(spec: dict[str, Any], out: Any) -> None:
    """Run one case: build, step frame by frame, send ("progress", ...) after each frame and
    ("done", result) at the end (or ("error", ...))."""
    try:
        out.put(("done", _simulate(spec, out)))
    except BaseException as exc:  # report anything; the parent decides
        out.put(("error", {"status": "error", "message": f"{type(exc).__name__}: {exc}",
                           "traceback": traceback.format_exc()[-2000:]}))


def _simulate(spec: dict[str, Any], out: Any) -> dict[str, Any]:
    import warp as wp

    import wsim
    from wsim.device import quiet_warp

    quiet_warp()
    wp.init()
    device = spec["device"]
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    t0 = time.perf_counter()
    world, body = build(spec["scene"], spec["body"], device)
    setup_s = time.perf_counter() - t0
    track = spec["track"]  # per-frame stability read-outs (Part B)
    res: dict[str, Any] = {"status": "ok", "message": "", "setup_s": setup_s, "dt_cap": float(body.dt_elastic),
                           "h": float(body.grid.h), "grid_nodes": int(body.grid.n_nodes),
                           "material_points": int(len(body._volumes)), "mass": float(body.mass)}
    vol0 = body.volume()
    e0 = body.kinetic_energy() + body.elastic_energy
    w0 = np.linalg.norm(body.angular_velocity)
    L0 = _angular_momentum(body) if track else None
    frames_target = int(round(spec["sim_time"] * spec["scene"]["fps"]))
    vE: list[float] = []
    vE_heavy: list[float] = []
    full_cell = body.material.rho * body.grid.h**3  # [kg] the mass of a node whose cells are full
    vols: list[float] = []
    devs: list[float] = []
    lows: list[float] = []
    t_first = t_start = time.perf_counter()
    t_after_first = None
    sim_after_first = 0.0
    truncated = False
    for f in range(frames_target):
        try:
            world.step()
        except wsim.SimulationDiverged as err:
            res.update(status="diverged", message=str(err))
            break
        now = time.perf_counter()
        if f == 0:  # frame 1 compiles/loads the kernels: time the rest
            res["first_frame_s"] = now - t_first
            t_after_first, sim_after_first = now, world.time
        pts = body.points()
        lows.append(float(pts[:, 1].min()))
        if f + 1 == spec.get("probe_frame"):  # the last frame before contact: against the ballistic path
            res["probe_time"], res["probe_com"] = world.time, _centroid(pts, body.faces).tolist()
        if track:
            speed = np.linalg.norm(body.eulerian_velocity(), axis=1)
            vE.append(float(speed.max()))
            # the largest |vE| is nearly always at a node holding a sliver of material (at the
            # mass floor); the nodes with at least a quarter cell of material show the bulk
            heavy = body.node_masses() > 0.25 * full_cell
            vE_heavy.append(float(speed[heavy].max()) if heavy.any() else 0.0)
            vols.append(body.volume() / vol0)
            F, T = body.frame
            devs.append(float(np.linalg.norm(pts - (body.rest_vertices @ F.T + T), axis=1).max()) / DIAMETER)
        out.put(("progress", {"sim_time": world.time, "steps": body.steps, "wall_s": now - t_start,
                              "dt_last": body.history[-1].dt if body.history else None}))
        if f + 1 < frames_target and (now - t_start > spec["wall_cap"] or body.steps >= spec["step_cap"]):
            truncated = True
            break
    t_end = time.perf_counter()
    wall = t_end - t_start
    hist = body.history
    dts = np.array([r.dt for r in hist]) if hist else np.zeros(1)
    sim_time = float(sum(r.dt for r in hist))
    res.update(steps=body.steps, sim_time=sim_time, frames=world.frame, wall_s=wall, truncated=truncated,
               dt_mean=sim_time / max(body.steps, 1), dt_min=float(dts.min()), dt_max_seen=float(dts.max()),
               lowest_min=min(lows) if lows else None, lowest_final=lows[-1] if lows else None)
    if t_after_first is not None and world.time > sim_after_first:
        res["wall_per_sim_s"] = (t_end - t_after_first) / (world.time - sim_after_first)
    else:
        res["wall_per_sim_s"] = wall / max(sim_time, 1e-12)
    # steps whose dt fell below the caps' (elastic/viscous, dt_max: each advance split evenly
    # within them, ``StepRecord.cap``): there the CFL root of Eq. (33) bound (or the contact QP's
    # guess), so cfl mattered
    cfl_bound = [r for r in hist if r.dt < 0.999 * r.cap]
    res["cfl_limited_frac"] = len(cfl_bound) / max(len(hist), 1)
    contact = [r for r in hist if r.rows > 0]
    res.update(contact_steps=len(contact), rows_mean=float(np.mean([r.rows for r in contact])) if contact else 0.0,
               qp_fallbacks=int(sum(r.qp_iterations > 50 for r in contact)))
    finite = res["status"] == "ok"
    if finite:
        pts = body.points()
        res["points"] = pts.tolist()
        res["com"] = _centroid(pts, body.faces).tolist()
    if track:
        n = len(vE)
        if n:
            half, tenth = vE[: max(n // 2, 1)], vE[n - max(n // 10, 1):]
            res.update(max_vE=max(vE), vE_first_half=max(half), vE_last_tenth=max(tenth), vE_final=vE[-1],
                       max_vE_heavy=max(vE_heavy), vE_heavy_first_half=max(vE_heavy[: max(n // 2, 1)]),
                       vE_heavy_last_tenth=max(vE_heavy[n - max(n // 10, 1):]),
                       vol_ratio_min=min(vols), vol_ratio_max=max(vols), vol_ratio_final=vols[-1],
                       dev_max_rel=max(devs), dev_final_rel=devs[-1])
        k = max(len(hist) // 10, 1)
        res["dt_last_tenth"] = float(np.mean(dts[-k:]))
        if finite:
            e1 = body.kinetic_energy() + body.elastic_energy
            res.update(energy_initial=e0, energy_final=e1, energy_drift=(e1 - e0) / e0 if e0 > 0 else None,
                       omega_initial=float(w0), omega_final=float(np.linalg.norm(body.angular_velocity)),
                       omega_drift=float(np.linalg.norm(body.angular_velocity) / w0 - 1.0) if w0 > 0 else None)
            L1 = _angular_momentum(body)
            nL = np.linalg.norm(L0)
            res["L_drift"] = float(np.linalg.norm(L1 - L0) / nL) if nL > 0 else None
    res["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    res["rss_delta_mb"] = res["peak_rss_mb"] - rss0
    res["state_mb"] = _state_bytes(body) / 2**20
    dev = wp.get_device(device)
    res["device"] = str(dev)
    if dev.is_cuda:
        try:
            res["device_mem_high_mb"] = wp.get_mempool_used_mem_high(dev) / 2**20
        except Exception:  # older Warp, or the mempool is off
            res["device_mem_high_mb"] = None
    return res


# ------------------------------------------------------------------------------------------------
# the parent
# ------------------------------------------------------------------------------------------------
def run_isolated(spec: dict[str, Any], hard_limit: float) -> dict[str, Any]:
    """Run ``worker`` in a spawned process; kill it if it runs past ``hard_limit`` seconds."""
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=worker, args=(spec, q), daemon=True)
    t0 = time.perf_counter()
    p.start()
    last: dict[str, Any] = {}
    result: dict[str, Any] | None = None
    while result is None:
        try:
            kind, payload = q.get(timeout=1.0)
        except queue.Empty:
            if not p.is_alive():
                result = {"status": "error", "message": f"worker exited with code {p.exitcode}", **last}
            elif time.perf_counter() - t0 > hard_limit:
                p.terminate()  # the process this function started; a frame that does not end
                result = {"status": "timeout", "message": f"killed after {hard_limit:.0f} s inside a frame",
                          "truncated": True, **last}
            continue
        if kind == "progress":
            last = payload
        else:
            result = payload
    p.join(timeout=10.0)
    result["process_s"] = time.perf_counter() - t0
    return result


def _errors(res: dict[str, Any], ref: dict[str, Any] | None) -> dict[str, Any]:
    if ref is None or "points" not in ref or "points" not in res:
        return {"err_max_rel": None, "err_rms_rel": None, "shape_err_max_rel": None, "rot_err_deg": None,
                "deform_err_max_rel": None, "com_err": None}
    p, q = np.asarray(res["points"]), np.asarray(ref["points"])
    c, cr = np.asarray(res["com"]), np.asarray(ref["com"])
    d = np.linalg.norm(p - q, axis=1)
    a, b = p - c, q - cr
    ds = np.linalg.norm(a - b, axis=1)
    # Kabsch: the rotation R minimising |R a - b|; what is left is deformation, not rigid motion
    U, _, Vt = np.linalg.svd(b.T @ a)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    dd = np.linalg.norm(a @ R.T - b, axis=1)
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(R) - 1.0) / 2.0))))
    return {"err_max_rel": float(d.max() / DIAMETER), "err_rms_rel": float(np.sqrt(np.mean(d**2)) / DIAMETER),
            "shape_err_max_rel": float(ds.max() / DIAMETER), "rot_err_deg": angle,
            "deform_err_max_rel": float(dd.max() / DIAMETER), "com_err": float(np.linalg.norm(c - cr))}


KEEP = ("status", "message", "device", "resolution", "steps", "sim_time", "frames", "wall_s", "wall_per_sim_s",
        "first_frame_s", "setup_s", "dt_mean", "dt_min", "dt_max_seen", "dt_cap", "h", "grid_nodes", "material_points",
        "err_max_rel", "err_rms_rel", "shape_err_max_rel", "rot_err_deg", "deform_err_max_rel", "com_err", "com",
        "freefall_com_err", "cfl_limited_frac", "lowest_min", "lowest_final",
        "contact_steps", "rows_mean", "qp_fallbacks", "peak_rss_mb", "rss_delta_mb", "state_mb",
        "device_mem_high_mb", "truncated", "process_s")


def _row(part: str, case: str, knob: str | None, value: Any, body: dict[str, Any], res: dict[str, Any],
         extra: dict[str, Any]) -> dict[str, Any]:
    row: dict[str, Any] = {"part": part, "case": case, "knob": knob, "value": value}
    row.update({k: body.get(k) for k in ("resolution", "advection", "cfl", "collision_block", "dt_max", "lagrangian",
                                         "padding") if k in body})
    row.update({k: res[k] for k in KEEP if k in res and k != "resolution"})
    row.update(extra)
    return row


def part_knobs(args: argparse.Namespace, emit) -> None:
    frames = 3 if args.quick else args.frames
    sim_time = frames / DROP["fps"]
    # frame 6 (t = 0.2 s) is the last before the ground contact (the lowest vertex is still ~5 mm up):
    # there the centre of mass has an exact answer, the ballistic path
    base = {"scene": DROP, "device": args.device, "sim_time": sim_time, "track": False,
            "wall_cap": 1e9, "step_cap": 10**9, "probe_frame": min(6, frames)}
    ref_res = 8 if args.quick else args.ref_resolution
    ref_body = {**reference_settings(ref_res), "lagrangian": "rigid"}
    log(f"knobs: reference {ref_body}")
    ref = run_isolated({**base, "body": ref_body}, args.hard_limit)
    emit(_row("knobs", "reference", None, None, ref_body, ref,
              {"err_max_rel": 0.0, "freefall_com_err": _freefall(ref, DROP), "sim_time_target": sim_time}))
    if "points" not in ref:
        log("the reference run failed: no errors below")
        ref = None

    def one(case: str, knob: str | None, value: Any, body: dict[str, Any], cache: dict,
            scene: dict[str, Any] = DROP, against: dict[str, Any] | None = None, err_vs: str = "reference") -> dict:
        key = json.dumps([body, scene], sort_keys=True)
        shared = key in cache  # the default appears once per knob: run it once
        if not shared:
            log(f"knobs: {case} {body}")
            cache[key] = run_isolated({**base, "scene": scene, "body": body}, args.hard_limit)
        res = cache[key]
        emit(_row("knobs", case, knob, value, body, res,
                  {**_errors(res, ref if against is None else against), "err_vs": err_vs,
                   "freefall_com_err": _freefall(res, scene), "damping": scene["damping"], "shared_run": shared,
                   "sim_time_target": sim_time}))
        return res

    cache: dict[str, dict] = {}
    knobs = {"resolution": [6], "advection": ["bfecc"]} if args.quick else KNOBS
    default = {**DEFAULT, "lagrangian": "rigid"}
    if args.quick:
        default["resolution"] = 6
    one("default", None, None, default, cache)
    for knob, values in knobs.items():
        for v in values:
            one(f"{knob}={v}", knob, v, {**default, knob: v}, cache)
    if args.quick:
        return
    # the purely Eulerian baseline (Fig. 7): the grid does not move, so it needs room to fall and slide in
    eul = {**default, "lagrangian": "eulerian", "padding": 4}
    one("eulerian", "lagrangian", "eulerian", eul, cache)
    # the reference's own error: its settings one grid coarser
    if ref_res - 4 >= 6:
        chk = {**reference_settings(ref_res - 4), "lagrangian": "rigid"}
        one("ref_check", "reference", ref_res - 4, chk, cache)
    # with damping 1000 Pa s the viscous cap rho h^2 / (12 eta) sets dt and cfl never binds; at the
    # damping of tools/bench_eol.py (20 Pa s) it does: errors here are against this group's cfl = 0.1
    low = {**DROP, "damping": 20.0}
    tight = one("cfl=0.1,damping=20", "cfl@damping=20", 0.1, {**default, "cfl": 0.1}, cache, low, {}, "none")
    for v in (0.2, 0.5, 0.8):
        one(f"cfl={v},damping=20", "cfl@damping=20", v, {**default, "cfl": v}, cache, low, tight,
            "cfl=0.1,damping=20")


def _freefall(res: dict[str, Any], scene: dict[str, Any]) -> float | None:
    """Distance [m] of the centre of mass at the probe frame from the ballistic path."""
    if "probe_com" not in res:
        return None
    t = res["probe_time"]
    g = np.array([0.0, -9.81, 0.0]) if scene["gravity"] else np.zeros(3)
    exact = np.asarray(scene["centre"]) + t * np.asarray(scene["velocity"]) + 0.5 * t * t * g
    return float(np.linalg.norm(np.asarray(res["probe_com"]) - exact))


def _verdict(last_tenth: float, first_half: float, vol_ratio: float) -> str:
    if last_tenth > 1.2 * first_half + 1e-6:
        return "growing"
    if abs(vol_ratio - 1.0) > 0.1:
        return "volume"
    return "bounded"


def part_stability(args: argparse.Namespace, emit) -> None:
    names = list(QUICK_STABILITY) if args.quick else args.cases.split(",")
    for name in names:
        if name not in STABILITY:
            raise SystemExit(f"unknown case {name!r}; known: {', '.join(STABILITY)}")
        scene_kw, body_kw, sim_time, step_cap, wall_cap, note = STABILITY[name]
        if args.quick:
            sim_time, wall_cap = QUICK_STABILITY[name], 15.0
        scene = {**DROP, **scene_kw}
        body = {**DEFAULT, "lagrangian": "rigid", **body_kw}
        spec = {"scene": scene, "body": body, "device": args.device, "sim_time": sim_time, "track": True,
                "wall_cap": wall_cap * args.wall_scale, "step_cap": step_cap}
        log(f"stability: {name}")
        res = run_isolated(spec, max(args.hard_limit, 2.0 * wall_cap * args.wall_scale))
        status = bulk = res["status"]
        if status == "ok":
            # the same test twice: on every node, and on the nodes holding at least a quarter cell
            # (a short run from rest still rings up its sliver nodes, which "growing" would flag)
            status, bulk = (_verdict(res.get(f"vE{k}_last_tenth", 0.0), res.get(f"vE{k}_first_half", 0.0),
                                     res.get("vol_ratio_final", 1.0)) for k in ("", "_heavy"))
        mat = {**BASE_MATERIAL, **scene.get("material", {})}
        extra = {k: res.get(k) for k in ("max_vE", "vE_first_half", "vE_last_tenth", "vE_final", "vol_ratio_min",
                                        "vol_ratio_max", "vol_ratio_final", "dev_max_rel", "dev_final_rel",
                                        "max_vE_heavy", "vE_heavy_first_half", "vE_heavy_last_tenth",
                                        "dt_last_tenth", "omega_initial", "omega_final", "omega_drift", "L_drift",
                                        "energy_initial", "energy_final", "energy_drift") if k in res}
        if scene["gravity"] or scene["ground"]:  # gravity does work, contact dissipates: no energy balance
            for k in ("energy_initial", "energy_final", "energy_drift"):
                extra.pop(k, None)
        extra.update(status=status, bulk_status=bulk, sim_time_target=sim_time, step_cap=step_cap,
                     wall_cap=wall_cap * args.wall_scale,
                     E=mat["E"], nu=mat["nu"], rho=mat["rho"], damping=scene["damping"], gravity=scene["gravity"],
                     ground=scene["ground"], angular_velocity=list(scene["angular_velocity"]), fps=scene["fps"],
                     note=note, quick=bool(args.quick))
        emit(_row("stability", name, None, None, body, res, extra))


def log(msg: str) -> None:
    print(f"[study_eol {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _git_rev() -> str | None:
    try:
        root = Path(__file__).resolve().parent.parent
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True).stdout
        dirty = subprocess.run(["git", "status", "--porcelain", "wsim", "kernels"], cwd=root, capture_output=True,
                               text=True).stdout  # others may be editing the solver while this runs
        return rev.strip() + ("+dirty" if dirty.strip() else "")
    except OSError:
        return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", choices=("knobs", "stability", "all"), default="all")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--frames", type=int, default=15, help="Part A frames at 30 fps (15: 0.5 s)")
    ap.add_argument("--ref-resolution", type=int, default=16, help="Part A reference grid (cells across)")
    ap.add_argument("--cases", default=",".join(STABILITY), help="Part B cases, comma separated")
    ap.add_argument("--wall-scale", type=float, default=1.0, help="scales Part B's wall-clock caps")
    ap.add_argument("--hard-limit", type=float, default=600.0, help="kill a case's process after this many seconds")
    ap.add_argument("--quick", action="store_true", help="a tiny subset (smoke test, < 60 s with warm kernels)")
    ap.add_argument("--out", default=None, help="also write the JSON lines to this file")
    args = ap.parse_args()
    sink = open(args.out, "w") if args.out else None
    t0 = time.perf_counter()

    def emit(row: dict[str, Any]) -> None:
        row["git"] = _git_rev()  # per row: the solver's files may change during a long study
        line = json.dumps(row)
        print(line, flush=True)
        if sink:
            sink.write(line + "\n")
            sink.flush()

    if args.part in ("knobs", "all"):
        part_knobs(args, emit)
    if args.part in ("stability", "all"):
        part_stability(args, emit)
    log(f"total {time.perf_counter() - t0:.1f} s")
    if sink:
        sink.close()


if __name__ == "__main__":
    main()
