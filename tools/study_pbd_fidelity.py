"""PBD fidelity at the settings of issue 16 (items 2, 3, 4): one JSON object on stdout.

Cases (all ``tets="auto"``, trimesh icospheres of subdivision 3, material rho = 1000 kg/m^3):

- ``momentum``: R = 0.5 m, E = 1e5, nu = 0.3, zero gravity, damping 0, 400 fps x 10 substeps x
  2 iterations, 0.4 s; initial breathing field v0 = 0.1 m/s * (x - c) / R (zero net momentum),
  set through ``get_state``/``set_state``. Figures: momentum gained max_t |P(t) - P(0)| as % of
  sum m |v0|; centre-of-mass drift [mm]. With ``--cause`` also the numpy reference
  (``wsim.pbd.reference``) of the same frames in float64 and with float32 position storage.
- ``spin``: ellipsoid 0.15/0.10/0.06 m, E = 1e6, nu = 0.3, omega0 = 2 pi rad/s about x (the axis
  of least inertia), zero gravity, default damping, 30 fps x 10 substeps, 3 s. Figures: |L| and
  kinetic energy kept [%], orientation error [deg] against the rigid body of the same particle
  inertia (torque-free Euler equations, integrated with 100 steps per PBD substep).
- ``sag``: R = 0.2 m, E = 1e5, nu = 0.3 on a ground plane (friction 0.5), gravity 9.81, default
  substeps, damping 0.01 s (to come to rest), 4 s. Sag = drop of the centre of mass from its
  height at placement (lowest vertex on the ground), mean over the last second; Hertz estimate
  (9 F^2 / (16 R E*^2))^(1/3) with F = m g, E* = E / (1 - nu^2).

    python tools/study_pbd_fidelity.py [--cases momentum,spin,sag] [--cause] [--substeps-sag 10,40]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import trimesh

import wsim


def _com(m, x):
    return (m[:, None] * x).sum(0) / m.sum()


def _readout(body):
    m = body.masses
    x, v = body.particles(), body.velocities()
    c = _com(m, x)
    P = (m[:, None] * v).sum(0)
    L = (m[:, None] * np.cross(x - c, v)).sum(0)
    K = 0.5 * float((m * (v * v).sum(1)).sum())
    return c, P, L, K


def case_momentum(device: str, cause: bool) -> dict:
    R = 0.5
    fps, substeps, iterations, seconds = 400, 10, 2, 0.4
    world = wsim.World(fps=fps, gravity=(0.0, 0.0, 0.0), device=device)
    body = world.add(wsim.PbdBody(trimesh.creation.icosphere(radius=R), wsim.ElasticMaterial(E=1e5, nu=0.3, rho=1000.0),
                                  name="ball", tets="auto", substeps=substeps, iterations=iterations, damping=0.0))
    m = body.masses
    st = body.get_state()
    x0 = st["x"].astype(np.float64)
    c0 = _com(m, x0)
    v0 = 0.1 * (x0 - c0) / R
    v0 -= (m[:, None] * v0).sum(0) / m.sum()  # exactly zero net momentum in float64
    st["v"] = v0.astype(np.float32)
    body.set_state(st)
    scale = float((m * np.linalg.norm(body.velocities(), axis=1)).sum())
    _, P0, _, _ = _readout(body)
    gained = 0.0
    t = time.perf_counter()
    for _ in range(int(round(fps * seconds))):
        world.step()
        _, P, _, _ = _readout(body)
        gained = max(gained, float(np.linalg.norm(P - P0)))
    secs = time.perf_counter() - t
    c1 = _com(m, body.particles())
    out = {"particles": body.model.n_particles, "sum_m_abs_v0": scale,
           "momentum_gained_pct": 100.0 * gained / scale,
           "com_drift_mm": 1e3 * float(np.linalg.norm(c1 - c0 - P0 / m.sum() * seconds)),
           "seconds": secs}
    if cause:
        from wsim.pbd import reference

        frames = 40  # 0.1 s: the reference is slow
        inv_mass = 1.0 / m
        for label, dtype in (("reference_float64", np.float64), ("reference_float32_storage", np.float32)):
            x = x0.astype(dtype).copy()
            v = v0.astype(dtype).copy()
            p_start = (m[:, None] * v.astype(np.float64)).sum(0)
            worst = 0.0
            for _ in range(frames):
                reference.run_frame(body.model, x, v, inv_mass, np.zeros(3), 1.0 / fps, substeps, iterations, 0.0,
                                    hinge_edges=any(f.edge is not None for f in body._families))
                worst = max(worst, float(np.linalg.norm((m[:, None] * v.astype(np.float64)).sum(0) - p_start)))
            out[label + "_momentum_gained_pct_0.1s"] = 100.0 * worst / scale
    return out


def rigid_orientation(I_body: np.ndarray, L: np.ndarray, seconds: float, steps: int) -> np.ndarray:
    """Torque-free rigid body from R = I: world angular momentum L constant, omega = R I^-1 R^T L,
    dR/dt = [omega]x R (RK4 on R with re-orthonormalization)."""
    Iinv = np.linalg.inv(I_body)
    Rm = np.eye(3)
    dt = seconds / steps

    def f(Rk):
        w = Rk @ Iinv @ Rk.T @ L
        W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        return W @ Rk

    for _ in range(steps):
        k1 = f(Rm)
        k2 = f(Rm + 0.5 * dt * k1)
        k3 = f(Rm + 0.5 * dt * k2)
        k4 = f(Rm + dt * k3)
        Rm = Rm + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        u, _, vt = np.linalg.svd(Rm)
        Rm = u @ vt
    return Rm


def kabsch(rest: np.ndarray, now: np.ndarray, m: np.ndarray) -> np.ndarray:
    a = rest - _com(m, rest)
    b = now - _com(m, now)
    H = (m[:, None] * a).T @ b
    u, _, vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def case_spin(device: str, substeps: int = 10, seconds: float = 3.0, subdivisions: int = 3) -> dict:
    shape = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    shape.vertices = shape.vertices * np.array([0.15, 0.10, 0.06])
    world = wsim.World(fps=30, gravity=(0.0, 0.0, 0.0), device=device)
    omega0 = 2.0 * np.pi
    body = world.add(wsim.PbdBody(shape, wsim.ElasticMaterial(E=1e6, nu=0.3, rho=1000.0), name="ellipsoid",
                                  tets="auto", substeps=substeps, angular_velocity=(omega0, 0.0, 0.0)))
    m = body.masses
    rest = body.particles()
    r = rest - _com(m, rest)
    I_body = (m[:, None, None] * ((r * r).sum(1)[:, None, None] * np.eye(3) - r[:, :, None] * r[:, None, :])).sum(0)
    _, _, L0, K0 = _readout(body)
    t = time.perf_counter()
    frames = int(round(30 * seconds))
    for _ in range(frames):
        world.step()
    secs = time.perf_counter() - t
    _, _, L1, K1 = _readout(body)
    R_pbd = kabsch(rest, body.particles(), m)
    R_rigid = rigid_orientation(I_body, L0, seconds, frames * substeps * 10)
    dR = R_pbd @ R_rigid.T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0))))
    return {"particles": body.model.n_particles, "substeps": substeps,
            "angular_momentum_kept_pct": 100.0 * float(np.linalg.norm(L1) / np.linalg.norm(L0)),
            "energy_kept_pct": 100.0 * K1 / K0, "orientation_error_deg": angle, "seconds": secs}


def case_sag(device: str, substeps: int = 10, seconds: float = 4.0, subdivisions: int = 3) -> dict:
    R, E, nu, rho, g = 0.2, 1e5, 0.3, 1000.0, 9.81
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=R)
    world = wsim.World(fps=30, device=device)
    world.add_collider(wsim.GroundPlane(friction=0.5))
    lift = -float(mesh.vertices[:, 1].min())
    body = world.add(wsim.PbdBody(mesh, wsim.ElasticMaterial(E=E, nu=nu, rho=rho), name="ball", tets="auto",
                                  substeps=substeps, damping=0.01, position=(0.0, lift, 0.0)))
    m = body.masses
    c0 = _com(m, body.particles())[1]
    heights = []
    t = time.perf_counter()
    frames = int(round(30 * seconds))
    for f in range(frames):
        world.step()
        if f >= frames - 30:
            heights.append(_com(m, body.particles())[1])
    secs = time.perf_counter() - t
    F = m.sum() * g
    Estar = E / (1.0 - nu**2)
    hertz = (9.0 * F**2 / (16.0 * R * Estar**2)) ** (1.0 / 3.0)
    return {"particles": body.model.n_particles, "substeps": substeps, "sag_mm": 1e3 * float(c0 - np.mean(heights)),
            "sag_spread_mm": 1e3 * float(np.ptp(heights)), "hertz_mm": 1e3 * hertz, "seconds": secs}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--cases", default="momentum,spin,sag")
    ap.add_argument("--cause", action="store_true", help="also run the numpy reference in float64 and float32")
    ap.add_argument("--substeps-sag", default="10,40")
    ap.add_argument("--label", default="")
    args = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    device = args.device or str(wp.get_preferred_device())
    cases = args.cases.split(",")
    out: dict = {"label": args.label, "device": device, "settings": {
        "momentum": "icosphere R=0.5 sub3, E=1e5 nu=0.3 rho=1000, g=0, damping=0, 400 fps x 10 x 2, 0.4 s, v0=0.1*(x-c)/R",
        "spin": "ellipsoid 0.15/0.10/0.06 sub3, E=1e6 nu=0.3, omega0=2pi about x, g=0, 30 fps x 10, 3 s, default damping",
        "sag": "icosphere R=0.2 sub3, E=1e5 nu=0.3 rho=1000, ground mu=0.5, 30 fps, damping 0.01, 4 s"}}
    t = time.perf_counter()
    if "momentum" in cases:
        out["momentum"] = case_momentum(device, args.cause)
    if "spin" in cases:
        out["spin"] = case_spin(device)
    if "sag" in cases:
        out["sag"] = [case_sag(device, int(s)) for s in args.substeps_sag.split(",")]
    out["seconds"] = time.perf_counter() - t
    print(json.dumps(out))


if __name__ == "__main__":
    main()
