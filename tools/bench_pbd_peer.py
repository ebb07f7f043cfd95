"""wsim's PBD against Newton's XPBD on the same workload, in one run (issue 21, item 6).

    python tools/bench_pbd_peer.py --device cuda:0                       # Newton's soft grid, 16,359 particles
    python tools/bench_pbd_peer.py --device cpu --dims 6,3,3 --frames 12 \\
        --sweep 4x1,8x1,8x2 --reference 16x8                               # a CPU-sized check

The workload is Newton's own soft grid (``ModelBuilder.add_soft_grid``: (x+1)(y+1)(z+1) particles,
5 tets a cell, taken from Newton when it is installed, else laid out the same way here; default 40 x 18 x 20 = 16,359 particles and 72,000 tets, 5 cm cells, Lame
parameters 1e5 Pa, 1000 kg/m^3) dropped from 1 m onto a ground plane at 60 fps, Z up. Both solvers
get the same particles and tets: Newton's model is built once and wsim's ``PbdBody`` takes its
tets (the boundary faces as the surface, the rest as interior particles) with the same material
(E, nu from the Lame parameters) and friction. Newton runs as its examples do - each frame's
substeps captured in a CUDA graph on CUDA, each frame starting and ending in the same state
buffer - with particle self-contact off (its default particle
radius makes the grid's own particles collide and blow it apart). wsim runs as a user runs it
(``World.step``; ``use_graph`` on).

For each solver and each ``substeps x iterations`` of ``--sweep`` (and the ``--reference``, the
converged run), a JSON line (``--wsim-solver gauss_seidel,jacobi`` runs both of wsim's modes,
"wsim" and "wsim-jacobi"): milliseconds per frame (after the first frame: compilation, capture),
the error - the largest particle distance at the last frame from the same solver's reference
run, over the grid's bounding-box diagonal - and a physical check (finite, the extent at most 3x
the initial one, nothing below the ground by more than a cell): a run that fails it has no
error and is never "fastest". Then, per error level in ``--levels``, each solver's
fastest setting reaching it and the speed ratio, and a last line with the worst ratio over every
level between the first and the last of ``--levels`` (where both solvers reach it). Without Newton (the optional ``bench`` extra:
``pip install "wsim[bench]"``) the wsim half runs and the Newton half says it was skipped.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np


def emit(**fields: Any) -> None:
    print(json.dumps(fields), flush=True)


def parse_settings(text: str) -> list[tuple[int, int]]:
    out = []
    for item in text.split(","):
        s, _, i = item.strip().partition("x")
        out.append((int(s), int(i)))
    return out


def wsim_solvers(text: str) -> list[str]:
    return [s for s in text.split(",") if s]


def grid_model(newton, wp, dims: tuple[int, int, int], cell: float, k_mu: float, k_lambda: float, density: float,
               device):
    """Newton's soft grid on a ground plane (Z up), particle self-contact off."""
    builder = newton.ModelBuilder()
    builder.add_ground_plane()
    builder.add_soft_grid(pos=wp.vec3(0.0, 0.0, 1.0), rot=wp.quat_identity(), vel=wp.vec3(0.0, 0.0, 0.0),
                          dim_x=dims[0], dim_y=dims[1], dim_z=dims[2], cell_x=cell, cell_y=cell, cell_z=cell,
                          density=density, k_mu=k_mu, k_lambda=k_lambda, k_damp=0.0)
    model = builder.finalize(device=device)
    # no particle-particle contact (see the module docstring): XPBD builds its hash grid only with one
    # and solves the contacts only where the largest particle radius is > 0; ground contacts use
    # the per-particle radii, which stay
    model.particle_grid = None
    model.particle_max_radius = 0.0
    return model


def soft_grid(dims: tuple[int, int, int], cell: float) -> tuple[np.ndarray, np.ndarray]:
    """The grid's particles (Z up, bottom at z = 1) and 5-tet cells, without Newton (the same
    layout as ``add_soft_grid``'s: x fastest; the 5-tet split alternating by cell parity)."""
    nx, ny, nz = dims
    i, j, k = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij")
    points = np.stack([i, j, k], axis=-1).transpose(2, 1, 0, 3).reshape(-1, 3) * cell + np.array([0.0, 0.0, 1.0])

    def idx(x: int, y: int, z: int) -> int:
        return (z * (ny + 1) + y) * (nx + 1) + x

    tets = []
    for z in range(nz):
        for y in range(ny):
            for x in range(nx):
                v = [idx(x, y, z), idx(x + 1, y, z), idx(x + 1, y, z + 1), idx(x, y, z + 1),
                     idx(x, y + 1, z), idx(x + 1, y + 1, z), idx(x + 1, y + 1, z + 1), idx(x, y + 1, z + 1)]
                if (x & 1) ^ (y & 1) ^ (z & 1):
                    tets += [[v[0], v[1], v[4], v[3]], [v[2], v[3], v[6], v[1]], [v[5], v[4], v[1], v[6]],
                             [v[7], v[6], v[3], v[4]], [v[4], v[1], v[6], v[3]]]
                else:
                    tets += [[v[1], v[2], v[5], v[0]], [v[3], v[0], v[7], v[2]], [v[4], v[7], v[0], v[5]],
                             [v[6], v[5], v[2], v[7]], [v[5], v[2], v[7], v[0]]]
    return points, np.asarray(tets, dtype=np.int64)


def boundary_surface(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(order, faces, tets, n_surface): particles reordered surface first (``order``: new -> old),
    the boundary faces oriented outward and the tets in the new numbering."""
    faces = np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]])
    opposite = np.concatenate([tets[:, 3], tets[:, 2], tets[:, 1], tets[:, 0]])
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = counts[inverse.ravel()] == 1
    faces, opposite = faces[once], opposite[once]
    a, b, c = (points[faces[:, i]] for i in range(3))
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), points[opposite] - a) > 0.0
    faces[inward] = faces[inward][:, [0, 2, 1]]
    surface = np.unique(faces)
    interior = np.setdiff1d(np.arange(len(points)), surface)
    order = np.concatenate([surface, interior])
    new = np.empty(len(points), dtype=np.int64)
    new[order] = np.arange(len(points))
    return order, new[faces], new[tets], len(surface)


def physical(q: np.ndarray, q0: np.ndarray, cell: float) -> str | None:
    """None if the state is plausible, else why not."""
    if not np.all(np.isfinite(q)):
        return "non-finite positions"
    extent, extent0 = np.ptp(q, axis=0).max(), np.ptp(q0, axis=0).max()
    if extent > 3.0 * extent0:
        return f"extent {extent:.3g} m > 3x the initial {extent0:.3g} m"
    if q[:, 2].min() < -cell:
        return f"{-q[:, 2].min():.3g} m below the ground"
    return None


def run_newton(newton, wp, args, substeps: int, iterations: int) -> tuple[np.ndarray, float]:
    device = wp.get_device(args.device)
    model = grid_model(newton, wp, args.dims, args.cell, args.k_mu, args.k_lambda, args.density, device)
    solver = newton.solvers.SolverXPBD(model, iterations=iterations)
    A, B = model.state(), model.state()
    control = model.control()
    pipeline = newton.CollisionPipeline(model)
    contacts = pipeline.contacts()
    dt = 1.0 / args.fps / substeps

    def frame() -> None:
        """One frame; it starts from A and ends in A (a graph replays fixed buffers)."""
        src, dst = A, B
        for _ in range(substeps):
            src.clear_forces()
            pipeline.collide(src, contacts)
            solver.step(src, dst, control, contacts, dt)
            src, dst = dst, src
        if substeps % 2:  # an odd count ends in B
            wp.copy(A.particle_q, B.particle_q)
            wp.copy(A.particle_qd, B.particle_qd)

    advance = frame
    if device.is_cuda:
        with wp.ScopedCapture(device=device) as capture:
            frame()
        graph = capture.graph

        def advance() -> None:
            wp.capture_launch(graph)

    advance()  # the first frame: compilation (and, on CUDA, the first replay)
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(args.frames - 1):
        advance()
    wp.synchronize_device(device)
    return A.particle_q.numpy().astype(np.float64), (time.perf_counter() - t0) / max(args.frames - 1, 1)


def run_wsim(args, grid, substeps: int, iterations: int, solver: str = "gauss_seidel") -> tuple[np.ndarray, float]:
    import warp as wp

    import wsim

    points, order, faces, tets, n_surface, material = grid
    p = points[order]
    world = wsim.World(fps=args.fps, device=args.device, up_axis="Z")
    world.add_collider(wsim.GroundPlane(0.0, friction=args.friction))
    body = world.add(wsim.PbdBody((p[:n_surface], faces), material, name="grid", tets=tets,
                                  interior_points=p[n_surface:], substeps=substeps, iterations=iterations,
                                  solver=solver, cache=False))
    world.step()  # the first frame: compilation, graph capture
    wp.synchronize_device(world.device)
    t0 = time.perf_counter()
    for _ in range(args.frames - 1):
        world.step()
    wp.synchronize_device(world.device)
    q = np.empty_like(p)
    q[order] = body.particles()  # back to Newton's particle order
    return q, (time.perf_counter() - t0) / max(args.frames - 1, 1)


def fastest(rows: list[dict], level: float) -> dict | None:
    ok = [r for r in rows if r.get("error") is not None and r["error"] <= level]
    return min(ok, key=lambda r: r["ms_per_frame"]) if ok else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--dims", default="40,18,20")
    ap.add_argument("--cell", type=float, default=0.05)
    ap.add_argument("--k-mu", type=float, default=1.0e5)
    ap.add_argument("--k-lambda", type=float, default=1.0e5)
    ap.add_argument("--density", type=float, default=1.0e3)
    ap.add_argument("--friction", type=float, default=0.5)
    ap.add_argument("--fps", type=float, default=60.0)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--sweep", default="5x1,10x1,20x1,25x1,30x1,40x1,50x1,60x1,80x1,10x2,15x2,20x2,40x2,60x2,80x2,20x5")
    ap.add_argument("--reference", default="80x40")
    ap.add_argument("--levels", default="0.005,0.01,0.025,0.05")
    ap.add_argument("--solvers", default="wsim,newton")
    ap.add_argument("--wsim-solver", default="gauss_seidel",
                    help="PbdBody solver(s) for the wsim half: gauss_seidel, jacobi or both (comma separated)")
    args = ap.parse_args()
    args.dims = tuple(int(d) for d in args.dims.split(","))

    import warp as wp

    import wsim
    from wsim.device import quiet_warp, resolve_device

    quiet_warp()
    args.device = resolve_device(args.device).alias
    try:
        import newton
    except ImportError:
        newton = None
    mu, lam = args.k_mu, args.k_lambda
    if newton is not None:  # Newton's own particles and tets, for both solvers
        model = grid_model(newton, wp, args.dims, args.cell, mu, lam, args.density, "cpu")
        points = model.particle_q.numpy().astype(np.float64)
        tets = model.tet_indices.numpy().astype(np.int64)
        del model
    else:
        points, tets = soft_grid(args.dims, args.cell)
    order, faces, tets_new, n_surface = boundary_surface(points, tets)
    nu = lam / (2.0 * (lam + mu))
    material = wsim.ElasticMaterial(E=2.0 * mu * (1.0 + nu), nu=nu, rho=args.density)
    grid = (points, order, faces, tets_new, n_surface, material)
    diag = float(np.linalg.norm(np.ptp(points, axis=0)))
    emit(workload="soft grid", dims=list(args.dims), particles=len(points), tets=len(tets), cell_m=args.cell,
         E=material.E, nu=nu, fps=args.fps, frames=args.frames, device=args.device,
         gpu=wp.get_device(args.device).name if wp.get_device(args.device).is_cuda else None)

    solvers = []
    for s in (s for s in args.solvers.split(",") if s):
        solvers += [f"wsim-{w}" if w != "gauss_seidel" else "wsim" for w in wsim_solvers(args.wsim_solver)] \
            if s == "wsim" else [s]
    rows: dict[str, list[dict]] = {}
    for name in solvers:
        if name == "newton" and newton is None:
            emit(solver="newton", skipped="newton is not installed (pip install 'wsim[bench]')")
            continue
        if name == "newton":
            def run(s: int, i: int) -> tuple[np.ndarray, float]:
                return run_newton(newton, wp, args, s, i)
            version = newton.__version__
        else:
            mode = name.partition("-")[2] or "gauss_seidel"

            def run(s: int, i: int, mode: str = mode) -> tuple[np.ndarray, float]:
                return run_wsim(args, grid, s, i, mode)
            version = wsim.__version__ if hasattr(wsim, "__version__") else None
        ref_s, ref_i = parse_settings(args.reference)[0]
        q_ref, ms_ref = run(ref_s, ref_i)
        bad = physical(q_ref, points, args.cell)
        emit(solver=name, version=version, substeps=ref_s, iterations=ref_i, reference=True,
             ms_per_frame=1e3 * ms_ref, physical=bad is None, why=bad)
        rows[name] = []
        if bad is not None:
            continue
        for s, i in parse_settings(args.sweep):
            q, sec = run(s, i)
            bad = physical(q, points, args.cell)
            err = None if bad else float(np.linalg.norm(q - q_ref, axis=1).max() / diag)
            row = dict(solver=name, substeps=s, iterations=i, ms_per_frame=1e3 * sec, error=err,
                       physical=bad is None, why=bad)
            rows[name].append(row)
            emit(**row)
    summary = []
    for level in (float(x) for x in args.levels.split(",")):
        best = {n: fastest(r, level) for n, r in rows.items()}
        entry = {"error_level": level}
        for n, b in best.items():
            entry[n] = None if b is None else {k: b[k] for k in ("substeps", "iterations", "ms_per_frame", "error")}
        if best.get("wsim") and best.get("newton"):
            entry["newton_over_wsim_time"] = best["newton"]["ms_per_frame"] / best["wsim"]["ms_per_frame"]
        summary.append(entry)
    emit(summary=summary)
    if rows.get("wsim") and rows.get("newton"):
        # every level between the first and last of --levels: each solver's fastest setting changes
        # only at an error some run reached, so those errors (and the range's start) are all the
        # levels there are to check
        levels = [float(x) for x in args.levels.split(",")]
        lo, hi = min(levels), max(levels)
        seen = {r["error"] for rs in rows.values() for r in rs if r.get("error") is not None and lo <= r["error"] <= hi}
        worst = None
        for level in sorted(seen | {lo}):
            w, n = fastest(rows["wsim"], level), fastest(rows["newton"], level)
            if w and n and (worst is None or n["ms_per_frame"] / w["ms_per_frame"] < worst[0]):
                worst = (n["ms_per_frame"] / w["ms_per_frame"], level, w, n)
        if worst is not None:
            ratio, level, w, n = worst
            emit(range=[lo, hi], worst_newton_over_wsim_time=ratio, from_error_level=level,
                 wsim={k: w[k] for k in ("substeps", "iterations", "ms_per_frame", "error")},
                 newton={k: n[k] for k in ("substeps", "iterations", "ms_per_frame", "error")})


if __name__ == "__main__":
    main()
