"""BemBody: a surface-only elastodynamic BEM body in a moving rigid frame (paper Sec. 3).

Per step n (length dt, fixed by the operators):

1. the history h_n of Eq. (9) from ring buffers of the last n_max u, p and [a - g', alpha]
   (launched first: it needs only past steps, so the host evaluates the loads meanwhile);
2. nodal tractions p_n from the loads (``add_traction``), frame coordinates [Pa];
   a_ext = A p_n, alpha_ext = C p_n (Eq. 10);
3. u_n = H_0^-1 G' p_n + H_0^-1 h_n (Eq. 12); with ``frame_update=False`` the frame stays fixed
   and Eq. (9) is solved with a = 0, alpha = 0 instead (the paper's comparison run, Fig. 5);
4. error correction (Sec. 3.2.1, ``wsim.bem.correction``): rigid drift moves from u_n to a_n, alpha_n;
5. frame update (Eq. 11, ``wsim.rigid``) with a_n = g' + a_ext + da, alpha_n = alpha_ext + dalpha.

World-space surface points are R (x + u) + T. Steps 1 and 3 run on the body's Warp device
(``wsim.bem.stepper``); 2, 4 and 5 are O(N) host work in float64.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import warp as wp

from wsim import mesh as wmesh
from wsim.bem import stepper
from wsim.rigid import RigidFrame
from wsim.bem.mass import mass_properties
from wsim.bem.operators import PRECISIONS, BemOperators, build_operators
from wsim.bem.surface import prepare_surface
from wsim.body import Body
from wsim.cache import OperatorCache
from wsim.colliders import Collider
from wsim.errors import InvalidParameter, SimulationDiverged
from wsim.materials import ElasticMaterial
from wsim.validate import as_rotation, as_vec3, finite_number

TractionFn = Callable[[float], Any]
STAGES = ("history", "loads", "solve", "correction", "frame")


@dataclass
class BemState:
    """What changes when a BEM body steps (its operators never do).

    Attributes:
        U, P: (n_max, pitch) device rings of the last n_max displacements u and tractions p
            (frame coordinates; row m holds step m mod n_max), in the storage precision.
        B: (n_max, 6) device ring of [a - g', alpha] (Eq. 9's D_k, Q_k terms).
        u: (3N,) this step's displacement, float64 on the host.
        frame: the rigid frame (Eq. 11).
        ring: ring index of the next step (offset by n_max so ring - k >= 0).
        steps: steps taken.
        last_loaded: last step with a nonzero traction (for the growth check).
        window_peak, window_previous, window_growing: the growth check's running window.
    """

    U: wp.array
    P: wp.array
    B: wp.array
    u: np.ndarray
    frame: RigidFrame
    ring: int
    steps: int = 0
    last_loaded: int = 0
    window_peak: float = 0.0
    window_previous: float = 0.0
    window_growing: int = 0


class BemBody(Body):
    """An elastic body simulated by convolution-quadrature BEM in a rigid moving frame.

    Args:
        mesh: closed, outward-oriented triangle mesh (``trimesh.Trimesh`` or (vertices, faces)) [m].
        material: linear-elastic material (``ElasticMaterial(..., incompressible=True)`` for nu = 0.5).
        dt: time step [s]; the operators (and n_max) are built for it.
        name: USD prim name.
        position: translation applied to the mesh [m].
        rotation: (3, 3) rotation applied to the mesh about its centre of mass (default identity).
        velocity, angular_velocity: initial velocity of the centre of mass [m/s] and spin [rad/s] (world).
        frame_update: move the frame with the body (Eq. 11). False: the frame is fixed at the start
            pose and all motion is BEM displacement (linear elasticity: large rotations inflate).
        error_correction: apply Sec. 3.2.1 each step (only with ``frame_update``).
        gyroscopic: integrate the frame's angular momentum (torque-free precession) instead of
            Eq. (11e)'s omega, which stays fixed under zero torque about any axis.
        precision: storage of the dense matrices, "float32" (default) or "float64"; with
            ``operators`` given, theirs (a different explicit value is an error).
        method: CQ method "bdf1" (paper) or "bdf2".
        double_nodes: crease angle [deg] for double nodes at sharp edges, or None.
        n_max: history length override.
        operators: a prebuilt :class:`~wsim.bem.BemOperators` for this mesh (skips the build).
        matvec: "auto" (Warp on CUDA, BLAS on CPU), "warp" or "blas" (CPU only).
        divergence_limit: |u| [m] beyond which the step stops with ``SimulationDiverged``
            (default: the surface diameter; linear elasticity is meaningless past it).
        growth_check: stop with ``SimulationDiverged`` when the displacement of an unloaded body
            keeps growing: a passive elastic body cannot gain energy, so |u| rising by more than
            20 % per history window (n_max steps) for 5 windows in a row, with no traction
            applied, is a numerical instability caught early (see ``_check_growth``).
        cache: operator cache (True, False or an ``OperatorCache``).
        progress: progress bar while the operators are built.
        profile: synchronize the device after each stage so ``timings`` splits GPU time by stage.
        **quadrature: quadrature knobs of ``build_operators``.
    """

    def __init__(
        self,
        mesh: Any,
        material: ElasticMaterial,
        dt: float,
        *,
        name: str = "bem_body",
        position: Sequence[float] = (0.0, 0.0, 0.0),
        rotation: Any = None,
        velocity: Sequence[float] = (0.0, 0.0, 0.0),
        angular_velocity: Sequence[float] = (0.0, 0.0, 0.0),
        frame_update: bool = True,
        error_correction: bool = True,
        gyroscopic: bool = True,
        precision: str | None = None,
        method: str = "bdf1",
        double_nodes: float | None = None,
        n_max: int | None = None,
        operators: BemOperators | None = None,
        matvec: str = "auto",
        divergence_limit: float | None = None,
        growth_check: bool = True,
        cache: bool | OperatorCache = True,
        progress: bool = False,
        profile: bool = False,
        **quadrature: Any,
    ) -> None:
        super().__init__(name, velocity, angular_velocity)
        if not isinstance(material, ElasticMaterial):
            raise InvalidParameter(f"body '{name}': material must be a wsim.ElasticMaterial")
        dt = finite_number(dt, f"body '{name}': dt [s]")
        if dt <= 0.0:
            raise InvalidParameter(f"body '{name}': dt = {dt} s must be > 0")
        if operators is not None and precision is None:
            precision = operators.precision
        precision = "float32" if precision is None else precision
        if precision not in PRECISIONS:
            raise InvalidParameter(f"body '{name}': precision = {precision!r} must be one of {', '.join(PRECISIONS)}")
        if matvec not in stepper.BACKENDS:
            raise InvalidParameter(f"body '{name}': matvec = {matvec!r} must be one of {', '.join(stepper.BACKENDS)}")
        vertices, faces = wmesh.surface_arrays(mesh, f"body '{name}'")
        # validates (closed, oriented, non-degenerate) before anything is built
        surface = prepare_surface(vertices, faces, double_nodes=double_nodes, name=f"body '{name}'")
        props = mass_properties(surface.nodes, surface.faces, material.rho)
        R0 = as_rotation(rotation, f"body '{name}': rotation")
        if operators is not None:
            if not isinstance(operators, BemOperators):
                raise InvalidParameter(f"body '{name}': operators must be a wsim.bem.BemOperators")
            if operators.surface.n_nodes != surface.n_nodes or not np.allclose(operators.surface.nodes, surface.nodes):
                raise InvalidParameter(f"body '{name}': the given operators were built for another mesh")
            if operators.precision != precision:
                raise InvalidParameter(f"body '{name}': precision = {precision!r} but the operators store {operators.precision}")
            if abs(operators.dt - dt) > 1e-12 * dt:
                raise InvalidParameter(f"body '{name}': the given operators have dt = {operators.dt}, not {dt}")
        self.material = material
        self.dt = dt
        self.frame_update = bool(frame_update)
        self.error_correction = bool(error_correction) and self.frame_update
        self.gyroscopic = bool(gyroscopic)
        self.precision = precision
        self.matvec = matvec
        self.profile = bool(profile)
        self._build_args = dict(method=method, precision=precision, double_nodes=double_nodes, n_max=n_max,
                                cache=cache, progress=progress, **quadrature)
        self._mesh = (vertices, faces)
        self._faces = faces.astype(np.int32)
        self._surface = surface
        self._props = props
        self._R0 = R0
        self._T0 = props.com + as_vec3(position, f"body '{name}': position")  # rotation is about the com
        self._ops = operators
        self.divergence_limit = divergence_limit
        if divergence_limit is not None:
            self.divergence_limit = finite_number(divergence_limit, f"body '{name}': divergence_limit [m]")
        self._loads: list[TractionFn] = []
        self.growth_check = bool(growth_check)
        # vertex <- mean of its nodes' displacements (double nodes share a vertex)
        self._node_count = np.bincount(surface.vertex, minlength=len(vertices)).astype(np.float64)
        self.timings: dict[str, float] = {k: 0.0 for k in STAGES}

    # -- public read-outs -------------------------------------------------------------------
    @property
    def faces(self) -> np.ndarray:
        return self._faces

    @property
    def operators(self) -> BemOperators:
        self._require_bound()
        return self._ops

    @property
    def rest_vertices(self) -> np.ndarray:
        """(V, 3) rest vertex positions in frame coordinates (origin at the centre of mass) [m]."""
        return self._mesh[0] - self._props.com

    @property
    def rest_normals(self) -> np.ndarray:
        """(V, 3) unit area-weighted vertex normals of the rest mesh (frame coordinates)."""
        return wmesh.vertex_normals(*self._mesh)

    @property
    def mass(self) -> float:
        return self._props.mass

    @property
    def steps(self) -> int:
        """Steps taken (0 before the body is added to a World)."""
        return 0 if self.state is None else self.state.steps

    @property
    def time(self) -> float:
        """Simulated time of the body's state [s]."""
        return self.steps * self.dt

    @property
    def frame(self) -> RigidFrame:
        self._require_bound()
        return self.state.frame

    def displacement(self) -> np.ndarray:
        """(N_nodes, 3) current displacement in frame coordinates [m]."""
        self._require_bound()
        return self.state.u.reshape(-1, 3).copy()

    def vertex_displacement(self) -> np.ndarray:
        """(V, 3) current displacement per mesh vertex (double-node copies averaged), frame coordinates."""
        u = self.state.u.reshape(-1, 3)
        out = np.zeros((len(self._node_count), 3))
        np.add.at(out, self._surface.vertex, u)
        return out / self._node_count[:, None]

    def points(self) -> np.ndarray:
        self._require_bound()
        f = self.state.frame
        return (self.rest_vertices + self.vertex_displacement()) @ f.R.T + f.T

    def volume(self) -> float:
        """Enclosed volume of the deformed surface [m^3] (divergence theorem)."""
        return wmesh.signed_volume(self._surface.nodes + self.state.u.reshape(-1, 3), self._surface.faces)

    def linear_momentum(self) -> np.ndarray:
        """m T_dot [kg m/s]: the frame carries the body's momentum (the error correction of Sec.
        3.2.1 keeps the displacement u free of rigid motion, so it adds none)."""
        return self.mass * self.frame.velocity

    def angular_momentum(self, about: Sequence[float] | None = None) -> np.ndarray:
        """L [kg m^2/s] (world) about the centre of mass, or about the world point ``about``
        (L + (T - p) x m T_dot); carried by the frame, like the linear momentum."""
        f = self.frame
        L = f.L.copy()
        if about is not None:
            L += np.cross(f.T - as_vec3(about, f"body '{self.name}': about"), self.mass * f.velocity)
        return L

    def kinetic_energy(self) -> float:
        """Kinetic energy of the frame's motion, 1/2 m |T_dot|^2 + 1/2 omega . L [J]. The
        deformation's own kinetic energy is not included: a surface-only method has no interior
        velocities to integrate it from."""
        f = self.frame
        return 0.5 * self.mass * float(f.velocity @ f.velocity) + 0.5 * float(f.omega @ f.L)

    # -- loads ------------------------------------------------------------------------------
    def add_traction(self, fn: TractionFn) -> None:
        """Add a load: ``fn(t)`` returns tractions [Pa] in frame coordinates, (V, 3) per mesh vertex
        (or (N_nodes, 3) per node); loads add up. Evaluated once per step at the step's end time."""
        if not callable(fn):
            raise InvalidParameter(f"body '{self.name}': add_traction takes a callable fn(t) -> (V, 3) tractions")
        self._loads.append(fn)

    def _tractions(self, t: float) -> np.ndarray:
        n = self._surface.n_nodes
        p = np.zeros((n, 3))
        n_vertices = len(self._node_count)
        for fn in self._loads:
            value = np.asarray(fn(t), dtype=np.float64)
            if value.shape == (n_vertices, 3):
                p += value[self._surface.vertex]
            elif value.shape == (n, 3):
                p += value
            else:
                expected = f"({n_vertices}, 3)" + ("" if n == n_vertices else f" per vertex or ({n}, 3) per node")
                raise InvalidParameter(
                    f"body '{self.name}': a traction load returned shape {value.shape} at t = {t:g} s; expected {expected}")
            if not np.all(np.isfinite(value)):
                raise InvalidParameter(f"body '{self.name}': a traction load returned non-finite values at t = {t:g} s")
        return p.reshape(-1)

    # -- World interface --------------------------------------------------------------------
    def bind(self, device: wp.Device, gravity: np.ndarray, up: np.ndarray) -> None:
        if self._ops is None:
            self._ops = build_operators(self._mesh, self.material, self.dt, device=device, **self._build_args)
        ops = self._ops
        self._device = device
        self._so = so = stepper.step_operators(ops, device, stepper.resolve_backend(self.matvec, device))
        self._gravity = np.asarray(gravity, dtype=np.float64)
        self._inertia = ops.inertia
        self._inertia_inv = np.linalg.inv(ops.inertia)
        if self.divergence_limit is None:
            self.divergence_limit = ops.r_max
        n_max = ops.n_max
        # device state: rings of the last n_max steps and the step's vectors, rows of length pitch
        # the rings are written in place on restore (set_state), so the vec4 views stay valid
        self.state = BemState(
            U=so.vectors(n_max), P=so.vectors(n_max), B=wp.zeros((n_max, 6), dtype=so.dtype, device=device),
            u=np.zeros(so.size),
            frame=RigidFrame.at_rest(self._R0, self._T0, self.initial_velocity, self.initial_angular_velocity,
                                     ops.inertia),
            ring=n_max)
        self._p, self._h, self._u_dev = so.vectors(), so.vectors(), so.vectors()
        view = stepper.vec4_view if so.backend == "warp" else (lambda a: a)
        self._U_k, self._P_k, self._p_k, self._h_k = (view(self.state.U), view(self.state.P), view(self._p),
                                                      view(self._h))
        self._p_live = False
        # host staging (page-locked on CUDA, so the per-step copies are direct DMA)
        pinned = device.is_cuda
        self._u_out = wp.zeros(so.pitch, dtype=so.dtype, device="cpu", pinned=pinned)
        self._u_in = wp.zeros(so.pitch, dtype=so.dtype, device="cpu", pinned=pinned)
        self._p_in = wp.zeros(so.pitch, dtype=so.dtype, device="cpu", pinned=pinned)
        self._b_in = wp.zeros(6, dtype=so.dtype, device="cpu", pinned=pinned)
        if not self.frame_update:
            self._seed_rigid_history()
        self._failure: tuple[str, str, str] | None = None  # quantity, detail, reason
        self._window_length = max(ops.n_max, 20)  # steps per window of the growth check

    def _state_loaded(self) -> None:
        # the traction buffer is scratch: cleared, so an unloaded next step needs nothing from it
        self._p.zero_()
        self._p_live = False
        self._failure = None

    def signature(self) -> dict:
        return {**super().signature(), "nodes": self._surface.n_nodes, "dt": self.dt, "n_max": self._so.n_max,
                "precision": self.precision, "frame_update": self.frame_update, "material": self.material.as_key()}

    def _seed_rigid_history(self) -> None:
        """Without the frame, an initial velocity lives in u: u_{-k} = -k dt (v + omega x x), p = 0 (a
        rigid motion at constant velocity is traction-free)."""
        f = self.state.frame
        v_b, w_b = f.R.T @ f.velocity, f.R.T @ f.omega
        x = self._so.operators.surface.nodes - self._so.operators.com
        rigid = (v_b + np.cross(w_b, x)).reshape(-1)
        U = np.zeros((self._so.n_max, self._so.pitch))
        for k in range(1, self._so.n_max + 1):
            U[(self.state.ring - k) % self._so.n_max, : self._so.size] = -k * self.dt * rigid
        self.state.U.assign(U.astype(PRECISIONS[self.precision]))
        f.velocity = np.zeros(3)
        f.omega = np.zeros(3)
        f.L = np.zeros(3)

    def attach_colliders(self, colliders: Sequence[Collider]) -> None:
        # Contact for BEM bodies is a later issue: refuse rather than silently ignore colliders.
        if colliders:
            raise InvalidParameter(
                f"body '{self.name}': BEM bodies do not collide yet; remove the World's colliders "
                f"({', '.join(c.name for c in colliders)}) or use another body type")

    def advance(self, t0: float, t1: float) -> None:
        """Take steps of dt until the body's time is the nearest multiple of dt to t1."""
        self._require_bound()
        if self._failure is not None:
            return
        target = int(math.floor(t1 / self.dt + 0.5))
        while self.state.steps < target:
            self.step()
            if self._failure is not None:
                return

    def check_finite(self, frame: int, time: float) -> None:
        if self._failure is not None:
            quantity, detail, reason = self._failure
            raise SimulationDiverged(self.name, frame, quantity, time, detail, reason)

    # -- the step -----------------------------------------------------------------------------
    def step(self) -> None:
        """One step of length dt (Eqs. 9-12, Sec. 3.2.1, Eq. 11)."""
        u, a_ext, alpha_ext = self.unconstrained_solve()
        self._finish_step(u, a_ext, alpha_ext, time.perf_counter())

    def unconstrained_solve(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The paper's UNCNST stage of the coming step: history, loads and Eq. (12), without
        changing any state. Returns (u_n float64, a_ext, alpha_ext)."""
        so = self._so
        n3 = so.size
        self._loaded_now = False
        t = (self.steps + 1) * self.dt
        t0 = time.perf_counter()
        # the history needs only past steps: launch it first, so the host evaluates the loads
        # while the device streams the matrices
        stepper.history(so, self._U_k, self._P_k, self.state.B, self.state.ring, self._h)
        t0 = self._tick("history", t0)
        p = self._tractions(t) if self._loads else None
        has_p = p is not None and bool(np.any(p))
        ops = so.operators
        a_ext, alpha_ext = (ops.A @ p, ops.C @ p) if has_p else (np.zeros(3), np.zeros(3))
        if has_p:
            self._loaded_now = True
            self._p_in.numpy()[:n3] = p
            wp.copy(self._p, self._p_in, count=n3)
            self._p_live = True
        elif self._p_live:
            self._p.zero_()
            self._p_live = False
        t0 = self._tick("loads", t0)
        stepper.solve(so, self._p_k if has_p else None, self._h_k, self._u_dev)
        wp.copy(self._u_out, self._u_dev, count=n3)
        wp.synchronize_device(self._device)
        u = self._u_out.numpy()[:n3].astype(np.float64)
        self._tick("solve", t0)
        return u, a_ext, alpha_ext

    def _finish_step(self, u: np.ndarray, a_ext: np.ndarray, alpha_ext: np.ndarray, t0: float) -> None:
        """Error correction, ring update and frame update of the step (the paper's ERRCR)."""
        st = self.state
        so, f = self._so, st.frame
        n3 = so.size
        g_body = f.R.T @ self._gravity  # g' (Eq. 11a)
        if self.frame_update:
            da = dalpha = np.zeros(3)
            if self.error_correction:
                da, dalpha, u = so.correction.apply(u)
            b = np.concatenate([a_ext + da, alpha_ext + dalpha])  # [a - g', alpha]
        else:
            # a = alpha = 0 in Eq. (9): H_0 u = G_0 p - D_0 g' + h
            b = np.concatenate([-g_body, np.zeros(3)])
            u = u + so.E @ np.concatenate([-(a_ext + g_body), -alpha_ext])
        t0 = self._tick("correction", t0)
        slot = st.ring % so.n_max
        self._u_in.numpy()[:n3] = u
        self._b_in.numpy()[:] = b
        wp.copy(st.U, self._u_in, dest_offset=slot * so.pitch, count=n3)
        wp.copy(st.P, self._p, dest_offset=slot * so.pitch, count=n3)
        wp.copy(st.B, self._b_in, dest_offset=slot * 6, count=6)
        if self.frame_update:
            f.update(self.dt, self._gravity, b[:3], b[3:], self._inertia, self._inertia_inv, self.gyroscopic)
            if st.steps % 100 == 99:
                f.reorthonormalize()
        st.u = u
        st.ring += 1
        st.steps += 1
        self._tick("frame", t0)
        self._check_state()

    def _check_growth(self, peak: float) -> None:
        """Windows of n_max steps: five in a row, all unloaded, each with a peak |u| 20 % above the
        last and above round-off (1e-9 of the body size), mean a growing mode of the discrete
        system - the physical body, passive and unloaded, can only ring down (BDF1 damps it)."""
        st = self.state
        length, current, previous, growing = self._window_length, st.window_peak, st.window_previous, st.window_growing
        current = max(current, peak)
        if self.steps % length == 0:
            unloaded = self.steps - st.last_loaded >= 2 * length  # this window and the one before
            if unloaded and previous > 1e-9 * self._so.operators.r_max and current > 1.2 * previous:
                growing += 1
            else:
                growing = 0
            if growing >= 5:
                self._failure = ("displacement", f"|u| grew {current / previous:.2f}x per {length}-step window for "
                                 f"{growing} windows with no load, to {current:.3g} m at step {self.steps} "
                                 f"(t = {self.time:.6g} s): the discretization is unstable at this dt and mesh "
                                 "(try a larger dt or a finer mesh)", "growing")
            previous, current = current, 0.0
        st.window_peak, st.window_previous, st.window_growing = current, previous, growing

    def _check_state(self) -> None:
        f = self.state.frame
        for quantity, value in (("displacement", self.state.u), ("frame position", f.T), ("frame velocity", f.velocity),
                                ("angular velocity", f.omega)):
            if not np.all(np.isfinite(value)):
                self._failure = (quantity, f"step {self.steps} (t = {self.time:.6g} s)", "non-finite")
                return
        u = self.state.u
        peak = float(np.max(np.abs(u))) if u.size else 0.0
        if self._loaded_now:
            self.state.last_loaded = self.steps
        if self.growth_check:
            self._check_growth(peak)
        if peak > self.divergence_limit:
            self._failure = ("displacement", f"|u| = {peak:.3g} m exceeds divergence_limit = "
                             f"{self.divergence_limit:.3g} m at step {self.steps} (t = {self.time:.6g} s)", "diverging")
