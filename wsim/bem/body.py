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
(``wsim.bem.stepper``); 2, 4 and 5 are O(N) host work in float64, except on a free step with the
Warp backend (``device_step``), where 4 and 5 run on the device too (``wsim.bem.device_step``).
"""

from __future__ import annotations

import functools
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import ClassVar
from typing import Any, Callable, Sequence

import numpy as np
import warp as wp

from wsim import mesh as wmesh
from wsim import constraints as wc
from wsim.contact import centroid_faces, collider_friction, nearest_faces, points_inside, query_device
from wsim.bem import stepper
from wsim.bem.device_step import LOG_ROWS, ResidentStep, set_frame
from wsim.bem.constraints import (PointResponse, add_point_displacement, frame_terms, point_displacement,
                                  point_torques, response_matrix)
from wsim.rigid import RigidFrame, cross_matrix, rotation_vector
from wsim.bem.mass import mass_properties
from wsim.bem.operators import PRECISIONS, BemOperators, build_operators
from wsim.bem.surface import prepare_surface
from wsim.body import Body, VertexImpulses
from wsim.cache import OperatorCache
from wsim.colliders import Surfaces
from wsim.errors import InvalidParameter, SimulationDiverged
from wsim.materials import ElasticMaterial, body_material
from wsim.validate import as_rotation, as_vec3, call_user, callback_array, finite_number, positive_int

TractionFn = Callable[[float], Any]
STAGES = ("history", "loads", "solve", "collision", "constraints", "correction", "frame", "device")


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
        contact_impulse, fixed_impulse, joint_impulse: (3,) world impulses of the contact, of the
            fixed and driven points and of the joints so far [N s].
        point_nodes, point_kinds, point_forces: the nodes, constraint kinds and world forces [N] of
            the last constraint solve (its warm start, matched by node and kind).
        material_velocity, material_omega: (3,) world velocity of the centre of mass and angular
            velocity of the material over the last step [m/s], [rad/s] (the read-outs'). Equal to
            the frame's, except on a constrained step, where the pose transfer moves the frame.
        frame_is_material: the last step left the frame's velocities as the material's.
    """

    _ragged: ClassVar[tuple[str, ...]] = ("point_nodes", "point_kinds", "point_forces", "coupling_force")

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
    contact_impulse: np.ndarray = field(default_factory=lambda: np.zeros(3))
    fixed_impulse: np.ndarray = field(default_factory=lambda: np.zeros(3))
    joint_impulse: np.ndarray = field(default_factory=lambda: np.zeros(3))
    point_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    point_kinds: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    point_forces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    coupling_force: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    coupling_until: float = -1.0
    coupling_impulse: np.ndarray = field(default_factory=lambda: np.zeros(3))
    material_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    material_omega: np.ndarray = field(default_factory=lambda: np.zeros(3))
    frame_is_material: bool = True


class BemBody(VertexImpulses, Body):
    """An elastic body simulated by convolution-quadrature BEM in a rigid moving frame.

    Args:
        mesh: closed, outward-oriented triangle mesh (``trimesh.Trimesh`` or (vertices, faces)) [m].
        material: linear-elastic material (``ElasticMaterial(..., incompressible=True)`` for nu = 0.5),
            or a dict of its arguments (``dict(mu=1e5, nu=0.45, rho=1000.0)``), checked naming the body.
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
        method: CQ method "bdf1" (paper) or "bdf2". BDF2 was unstable on the bodies tested unless dt
            was long for the mesh (README, BEM limits): its displacement grows after a load is
            released; a warning says so.
        double_nodes: crease angle [deg] for double nodes at sharp edges, or None.
        n_max: history length override.
        operators: a prebuilt :class:`~wsim.bem.BemOperators` for this mesh (skips the build).
        matvec: "auto" (Warp on CUDA, BLAS on CPU), "warp" or "blas" (CPU only).
        compression: keep 1 / CR of the Haar coefficients of H_k, G_k (k >= 1), H_0^-1 and
            H_0^-1 G' (the paper's compression ratio CR >= 1; ``wsim.bem.compression``).
        compression_error: instead, per matrix the fewest coefficients whose relative matvec error
            stays below this on tuning fields of the kinds a step multiplies: smooth, one-sided and
            local loads (``compression.tuning_fields``, ``compression.choose_keep``). It bounds
            each product, not the history sum: right after a load is released, when that sum
            cancels, the displacement can be far off relative to its small size (README,
            Compression).
        divergence_limit: |u| [m] beyond which the step stops with ``SimulationDiverged``
            (default: the surface diameter; linear elasticity is meaningless past it).
        growth_check: stop with ``SimulationDiverged`` when the displacement of an unloaded body
            keeps growing: a passive elastic body cannot gain energy, so |u| rising by more than
            20 % per history window (n_max steps) for 5 windows in a row, with no traction
            applied, is a numerical instability caught early (see ``_check_growth``).
        cache: operator cache (True, False or an ``OperatorCache``).
        progress: progress bar while the operators are built (None: when stderr is a terminal;
            ``WSIM_PROGRESS=0``, set by ``wsim run --no-progress``, hides it; ``wsim.progress``).
        profile: synchronize the device after each stage so ``timings`` splits GPU time by stage
            (such steps take the host path below).
        device_step: keep a free step on the device (``wsim.bem.device_step``): with dense Warp
            operators, ``frame_update`` and ``error_correction`` on, no held point and no collider
            or other body within reach (``device_window``), the error correction and frame
            update run as one kernel after the passes, on CUDA each step is
            replayed as a CUDA graph, and the host reads the state back once per ``advance`` (a
            World frame or coupling interval; reading ``frame`` or ``points()`` in a load reads it
            back then). False: every step's correction and frame update run on the host in numpy.
        constraint_tol: the constraint solve stops when a Gauss-Seidel sweep moves no point by more
            than this [m] (default 1e-5 of the body's largest radius ``r_max``).
        constraint_iterations: the most sweeps per step; a step that ends above the tolerance is
            recorded in ``constraint_history`` and counted in ``unconverged_steps``, and the first
            one warns.
        contact_margin: points whose predicted end-of-step position (the step without contact forces)
            is closer than this to a collider [m] join the contact solve (default 0.1 % of
            ``r_max``); the rest are free this step. The prediction already carries the step's motion.
        friction: the body's Coulomb coefficient; a contact uses the larger of it and the collider's
            (the BEM authors' "maximum" rule). None: the collider's.
        merge_vertices: merge the mesh's vertices at the same position first (a file whose faces
            each have their own corners, e.g. the BEM authors' ``*_discontinuous.obj``); vertex ids
            (``fix``, joints) and ``faces`` then refer to the merged vertices. The mesh must be one
            closed piece: make one body per piece.
        **quadrature: quadrature knobs of ``build_operators``.
    """

    def __init__(
        self,
        mesh: Any,
        material: ElasticMaterial | dict[str, Any],
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
        compression: float | None = None,
        compression_error: float | None = None,
        divergence_limit: float | None = None,
        growth_check: bool = True,
        cache: bool | OperatorCache = True,
        progress: bool | None = None,
        profile: bool = False,
        device_step: bool = True,
        constraint_tol: float | None = None,
        constraint_iterations: int = 200,
        contact_margin: float | None = None,
        friction: float | None = None,
        merge_vertices: bool = False,
        **quadrature: Any,
    ) -> None:
        super().__init__(name, velocity, angular_velocity)
        material = body_material(material, name)  # a dict of ElasticMaterial's arguments is checked naming the body
        dt = finite_number(dt, f"body '{name}': dt [s]")
        if dt <= 0.0:
            raise InvalidParameter(f"body '{name}': dt = {dt} s must be > 0")
        if operators is not None and precision is None:
            precision = operators.precision
        precision = "float32" if precision is None else precision
        if precision not in PRECISIONS:
            raise InvalidParameter(f"body '{name}': precision = {precision!r} must be one of {', '.join(PRECISIONS)}")
        self._compression: tuple[str, float] | None = None
        if compression is not None and compression_error is not None:
            raise InvalidParameter(f"body '{name}': give compression (a ratio) or compression_error, not both")
        if compression is not None:
            cr = finite_number(compression, f"body '{name}': compression ratio")
            if cr < 1.0:
                raise InvalidParameter(f"body '{name}': compression ratio {cr} must be >= 1 (1: lossless)")
            self._compression = ("ratio", cr)
        elif compression_error is not None:
            eps = finite_number(compression_error, f"body '{name}': compression_error")
            if not 0.0 < eps < 1.0:
                raise InvalidParameter(f"body '{name}': compression_error {eps} must lie in (0, 1)")
            self._compression = ("error", eps)
        if matvec not in stepper.BACKENDS:
            raise InvalidParameter(f"body '{name}': matvec = {matvec!r} must be one of {', '.join(stepper.BACKENDS)}")
        vertices, faces = wmesh.surface_arrays(mesh, f"body '{name}'", merge_vertices=merge_vertices)
        self.face_uv = wmesh.face_uvs(mesh)  # carried to the USD output (faces keep their order)
        self.face_color = wmesh.face_colors(mesh)
        # validates (closed, one piece, oriented, non-degenerate) before anything is built
        surface = prepare_surface(vertices, faces, double_nodes=double_nodes, name=f"body '{name}'",
                                  fixes=("merge_vertices",))
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
        self.device_step = bool(device_step)
        self._build_args = dict(method=method, precision=precision, double_nodes=double_nodes, n_max=n_max,
                                cache=cache, progress=progress, **quadrature)
        if (operators.method if operators is not None else method) == "bdf2":
            warnings.warn(f"body '{name}': method='bdf2' grew without bound on the spheres tested unless dt was "
                          "long for the mesh (42 nodes: at dt = 0.5-4 ms, c2 dt / edge up to 0.4; bounded at 8 ms; "
                          "162 nodes: at 1 ms), where bdf1 rang down; use 'bdf1' (README, BEM limits)",
                          RuntimeWarning, stacklevel=2)
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
        self.constraint_tol = None if constraint_tol is None else finite_number(constraint_tol, f"body '{name}': constraint_tol [m]")
        self.contact_margin = None if contact_margin is None else finite_number(contact_margin, f"body '{name}': contact_margin [m]")
        for what, v in (("constraint_tol", self.constraint_tol), ("contact_margin", self.contact_margin)):
            if v is not None and v <= 0.0:
                raise InvalidParameter(f"body '{name}': {what} = {v} m must be > 0")
        self.friction = None if friction is None else finite_number(friction, f"body '{name}': friction")
        if self.friction is not None and self.friction < 0.0:
            raise InvalidParameter(f"body '{name}': friction = {friction} must be >= 0")
        self.constraint_iterations = positive_int(constraint_iterations, f"body '{name}': constraint_iterations")
        # handle -> (vertex ids, their nodes, target, each node's row in the targets)
        self._fixed: dict[int, tuple[np.ndarray, np.ndarray, Any, np.ndarray]] = {}
        self._next_handle = 0
        self._surfaces: Surfaces | None = None
        self._response: PointResponse | None = None
        self._coupling_load = False  # whether add_vertex_impulses' load is registered
        self._balance: np.ndarray | None = None  # (6,) the coming step's load balance X p (``_frame_loads``)
        self._torque = np.zeros(3)  # the step's alpha beyond C p: pushes' and point forces' own moments (``_point_alphas``)
        self.constraint_history: list[wc.SolveRecord] = []  # diagnostics of every constrained step (not state)
        self.unconverged_steps = 0

    @functools.cached_property
    def _inside_test(self) -> int:
        """Contact's inside test of the node faces (ray parity for one watertight piece; double
        nodes leave cracks in the node faces, which the winding number does not mind); made on
        the first contact query."""
        return wmesh.inside_test(self._surface.faces)

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
        self._sync()
        return self.state.frame

    def displacement(self) -> np.ndarray:
        """(N_nodes, 3) current displacement in frame coordinates [m]."""
        self._require_bound()
        self._sync()
        return self.state.u.reshape(-1, 3).copy()

    def vertex_displacement(self) -> np.ndarray:
        """(V, 3) current displacement per mesh vertex (double-node copies averaged), frame coordinates."""
        self._sync()
        u = self.state.u.reshape(-1, 3)
        out = np.zeros((len(self._node_count), 3))
        np.add.at(out, self._surface.vertex, u)
        return out / self._node_count[:, None]

    def points(self) -> np.ndarray:
        self._require_bound()
        self._sync()
        f = self.state.frame
        return (self.rest_vertices + self.vertex_displacement()) @ f.R.T + f.T

    def volume(self) -> float:
        """Enclosed volume of the deformed surface [m^3] (divergence theorem)."""
        self._sync()
        return wmesh.signed_volume(self._surface.nodes + self.state.u.reshape(-1, 3), self._surface.faces)

    def linear_momentum(self) -> np.ndarray:
        """m v [kg m/s] with v the material's centre-of-mass velocity over the last step: the frame
        carries the body's momentum (the error correction of Sec. 3.2.1 keeps the displacement u
        free of rigid motion, so it adds none). On a free body v is the frame's velocity T_dot; on a
        constrained step it is the frame's motion after the pose transfer (``BemState``), which
        the frame's own velocity is not (README, BEM constraints)."""
        self._require_bound()
        self._sync()
        return self.mass * self.state.material_velocity

    def center_of_mass(self) -> np.ndarray:
        """The frame's origin T [m] (world): the centre of mass of the body, which the frame
        carries (the error correction keeps the displacement u free of rigid motion)."""
        self._require_bound()
        self._sync()
        return self.state.frame.T.copy()

    def world_inertia(self) -> np.ndarray:
        """(3, 3) the inertia tensor about the centre of mass [kg m^2], world axes: the rest
        inertia turned by the frame, R I R^T."""
        self._require_bound()
        self._sync()
        R = self.state.frame.R
        return R @ self._inertia @ R.T

    def angular_momentum(self, about: Sequence[float] | None = None) -> np.ndarray:
        """L = I_world omega [kg m^2/s] (world) about the centre of mass, or about the world point
        ``about`` (L + (T - p) x m v), from the material's motion like ``linear_momentum``. On a
        free body with ``gyroscopic`` this is the frame's integrated L."""
        self._require_bound()
        self._sync()
        st, f = self.state, self.state.frame
        L = f.L.copy() if st.frame_is_material else f.R @ self._inertia @ f.R.T @ st.material_omega
        if about is not None:
            L += np.cross(f.T - as_vec3(about, f"body '{self.name}': about"), self.linear_momentum())
        return L

    def kinetic_energy(self) -> float:
        """Kinetic energy of the rigid motion, 1/2 m |v|^2 + 1/2 omega . L [J] (v, omega as in
        ``linear_momentum``). The deformation's own kinetic energy is not included: a surface-only
        method has no interior velocities to integrate it from."""
        self._require_bound()
        self._sync()
        st = self.state
        v, w = st.material_velocity, st.material_omega
        return 0.5 * self.mass * float(v @ v) + 0.5 * float(w @ self.angular_momentum())

    # -- loads ------------------------------------------------------------------------------
    def add_traction(self, fn: TractionFn) -> None:
        """Add a load: ``fn(t)`` returns tractions [Pa] in frame coordinates, (V, 3) per mesh vertex
        (or (N_nodes, 3) per node); loads add up. Evaluated once per step at the step's end time."""
        if not callable(fn):
            raise InvalidParameter(f"body '{self.name}': add_traction takes a callable fn(t) -> (V, 3) tractions")
        self._loads.append(fn)

    def _coupling_vertices(self) -> int:
        return len(self._node_count)

    def _coupling_time(self) -> float:
        return self.steps * self.dt

    def _register_coupling(self) -> None:
        """The load of ``add_vertex_impulses`` (the World's push from bodies of other methods, issue 18):
        one more traction, only for bodies that are pushed."""
        if not self._coupling_load:
            V = len(self._node_count)
            self._vertex_area = np.bincount(self._surface.vertex, weights=self._surface.node_areas(), minlength=V)
            self._loads.append(self._coupling_tractions)
            self._coupling_load = True

    def _coupling_tractions(self, t: float) -> np.ndarray:
        """The forces of ``add_vertex_impulses`` as tractions in frame axes, per vertex."""
        st = self.state
        if t > st.coupling_until + 1e-9 * self.dt or not len(st.coupling_force):
            return np.zeros((len(self._node_count), 3))
        self._sync()  # the frame's rotation, during a batch of device steps
        return (st.coupling_force @ st.frame.R) / self._vertex_area[:, None]

    def _tractions(self, t: float) -> np.ndarray:
        """The loads' tractions at a step's end time t, per node (frame axes); each load's value is
        checked on the host (shape, finite), naming the body, the load, the time and the frame."""
        n = self._surface.n_nodes
        p = np.zeros((n, 3))
        n_vertices = len(self._node_count)
        shapes = ((n_vertices, 3),) if n == n_vertices else ((n_vertices, 3), (n, 3))
        k = 0  # index of the user's loads, in add_traction order
        for fn in self._loads:
            if fn == self._coupling_tractions:
                what = f"body '{self.name}': the push of other bodies (add_vertex_impulses) as tractions [Pa]"
            else:
                what = f"body '{self.name}': traction load {k} (add_traction fn(t), tractions [Pa])"
                k += 1
            value = callback_array(call_user(fn, t, what, self._frame_of(t)), shapes, what, t, self._frame_of(t))
            p += value[self._surface.vertex] if value.shape == (n_vertices, 3) else value
        return p.reshape(-1)

    # -- World interface --------------------------------------------------------------------
    def bind(self, device: wp.Device, gravity: np.ndarray, up: np.ndarray) -> None:
        if self._ops is None:
            self._ops = build_operators(self._mesh, self.material, self.dt, device=device, **self._build_args)
        ops = self._ops
        self._device = device
        backend = stepper.resolve_backend(self.matvec, device)
        if self._compression is not None and backend == "warp" and ops.precision != "float32":
            raise InvalidParameter(f"body '{self.name}': compressed operators on the Warp backend need "
                                   f"precision='float32' (got {ops.precision!r})")
        self._so = so = stepper.step_operators(ops, device, backend, self._compression,
                                               self._build_args["cache"])
        self._scratch = stepper.CompressedScratch(so) if so.packed is not None else None
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
        self._predicted: tuple | None = None  # (step, u, a_ext, alpha_ext) from the body's ``Instances`` set
        self._set = None  # that set (``wsim.bem.instances``), once the World forms it
        # host staging (page-locked on CUDA, so the per-step copies are direct DMA)
        pinned = device.is_cuda
        self._u_out = wp.zeros(so.pitch, dtype=so.dtype, device="cpu", pinned=pinned)
        self._u_in = wp.zeros(so.pitch, dtype=so.dtype, device="cpu", pinned=pinned)
        self._p_in = wp.zeros(so.pitch, dtype=so.dtype, device="cpu", pinned=pinned)
        self._b_in = wp.zeros(6, dtype=so.dtype, device="cpu", pinned=pinned)
        self._bf_in = wp.zeros(6, dtype=wp.float32, device="cpu", pinned=pinned) if self._scratch is not None else None
        if not self.frame_update:
            self._seed_rigid_history()
        self.state.material_velocity = self.state.frame.velocity.copy()
        self.state.material_omega = self.state.frame.omega.copy()
        self._failure: tuple[str, str, str] | None = None  # quantity, detail, reason
        self._resident: ResidentStep | None = None  # device-step scratch, made on the first such step
        self._dirty = False  # the device holds newer u and frame than the host (a batch in flight)
        self._window_length = max(ops.n_max, 20)  # steps per window of the growth check

    def get_state(self) -> dict[str, np.ndarray]:
        self._sync()  # a load reading it during a batch of device steps gets that step's state
        return super().get_state()

    def _state_loaded(self) -> None:
        if self._scratch is not None:  # the wavelet-domain rings follow the restored ones
            self._scratch.stale = True
        if self.state.coupling_until >= 0.0:  # a restored push still to deliver
            self._register_coupling()
        # the traction buffer is scratch: cleared, so an unloaded next step needs nothing from it
        self._p.zero_()
        self._p_live = False
        self._predicted = None
        self._failure = None
        self._dirty = False  # the restored host state is the truth

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

    def attach_colliders(self, surfaces: Surfaces) -> None:
        self._surfaces = surfaces if len(surfaces) else None

    # -- constraints -----------------------------------------------------------------------------
    @property
    def contact_impulse(self) -> np.ndarray:
        """World impulse the colliders have applied so far [N s] (normal and friction)."""
        self._require_bound()
        return self.state.contact_impulse.copy()

    @property
    def fixed_impulse(self) -> np.ndarray:
        """World impulse the fixed and driven points have applied so far [N s]."""
        self._require_bound()
        return self.state.fixed_impulse.copy()

    @property
    def joint_impulse(self) -> np.ndarray:
        """World impulse the joints have applied to this body so far [N s]."""
        self._require_bound()
        return self.state.joint_impulse.copy()

    def fix(self, vertex_ids: Any, target: Any = None) -> int:
        """Hold mesh vertices at world positions from the next step on; returns a handle for ``release``.

        Args:
            vertex_ids: indices of mesh vertices (every double-node copy of a vertex is held).
            target: None (where the vertices are now), a (k, 3) array of world positions [m], or a
                callable ``fn(t) -> (k, 3)`` evaluated at each step's end time (driven points).
        """
        p = f"body '{self.name}'"
        if self.state is None:
            raise InvalidParameter(f"{p}: fix() needs the body in a World (world.add(body) first): its targets are "
                                   "world positions at the World's time")
        n_vertices = len(self._node_count)
        ids = np.asarray(vertex_ids)
        if ids.ndim != 1 or ids.size == 0 or not np.issubdtype(ids.dtype, np.integer):
            raise InvalidParameter(f"{p}: fix() takes a non-empty 1-D list of integer vertex ids, got shape {ids.shape} "
                                   f"of {ids.dtype}")
        bad = ids[(ids < 0) | (ids >= n_vertices)]
        if bad.size:
            raise InvalidParameter(f"{p}: vertex id {int(bad[0])} is out of range [0, {n_vertices - 1}]")
        if len(np.unique(ids)) != len(ids):
            raise InvalidParameter(f"{p}: fix() got a vertex id twice")
        held = np.intersect1d(ids, np.concatenate([c[0] for c in self._fixed.values()]) if self._fixed else [])
        if held.size:
            raise InvalidParameter(f"{p}: vertex {int(held[0])} is already held by another fix(); release() it first")
        if target is None:
            target = self.points()[ids]
        elif not callable(target):
            target = self._check_targets(target, len(ids), self.time)
        slot = np.full(n_vertices, -1)
        slot[ids] = np.arange(len(ids))
        nodes = np.flatnonzero(slot[self._surface.vertex] >= 0)
        handle = self._next_handle
        self._next_handle += 1
        self._fixed[handle] = (ids, nodes, target, slot[self._surface.vertex[nodes]])
        return handle

    def joint_points(self, vertex_ids: np.ndarray) -> wc.PointRefs:
        """The node a joint holds at each mesh vertex: its first double-node copy (the other copies of
        a vertex on a crease are not held)."""
        first = np.full(len(self._node_count), -1)
        first[self._surface.vertex[::-1]] = np.arange(self._surface.n_nodes)[::-1]
        return wc.PointRefs.nodes(first[np.asarray(vertex_ids)])

    def release(self, handle: int) -> None:
        """Stop holding the vertices of a ``fix`` handle."""
        if handle not in self._fixed:
            raise InvalidParameter(f"body '{self.name}': no fixed points with handle {handle!r}")
        del self._fixed[handle]

    def _node_tractions(self, points: wc.PointRefs, forces: np.ndarray, R1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(nodes, tractions (k, 3) in frame axes of the step start) of world point forces [N]."""
        nodes, f_nodes = points.spread(forces)
        return nodes, (f_nodes @ R1) / self._response.area[nodes][:, None]

    def _point_alphas(self, points: wc.PointRefs) -> np.ndarray:
        """(m, 3, 3) T_j: the frame's angular acceleration (frame axes) per unit force (frame axes)
        at each of ``points`` in the step ``constraint_begin`` opened. With the frame update the
        force's own moment, I^-1 [l_j]x with l_j the point's lever at the step's start in the
        start's axes (the ones the frame update turns alpha by): the moment of its traction, C p,
        acts at the hat functions' centroids, and the two sides of a contact would exert a net
        torque on the pair (a glancing blow between 26-node cubes lost 20 % of its angular
        momentum, 7 % at 98 nodes); the BEM's own frame terms keep C p (``_torque``). The lever
        where the step starts, not where it is predicted to end: the force's direction of action is
        then known before the step, as in SHAKE, and a held cube's swing keeps its height (0.13 mm
        lost a half swing against 4.5 mm with the end's lever, which damped at first order in dt
        like an implicit Euler step of the rotation).
        Without it the BEM's frame terms', which Eq. (9) removes (``point_torques``)."""
        if self.frame_update:
            return self._inertia_inv @ cross_matrix(points.positions(self._cs["lever_body"]))
        return point_torques(self._response, points)

    def _forces_alpha(self, points: wc.PointRefs, forces: np.ndarray, R1: np.ndarray) -> np.ndarray:
        """The frame's angular acceleration (frame axes) of world point forces [N] (``_point_alphas``)."""
        if not len(points):
            return np.zeros(3)
        return np.einsum("mab,mb->a", self._point_alphas(points), np.reshape(forces, (-1, 3)) @ R1)

    def _with_point_forces(self, points: wc.PointRefs, forces: np.ndarray, u: np.ndarray, a_ext: np.ndarray,
                           alpha_ext: np.ndarray, R1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """u, a_ext, alpha_ext with world point forces [N] at ``points`` added as tractions (frame
        axes of the step start, R1), and the (3N,) tractions themselves. The frame's alpha takes
        the forces' own moment (``_point_alphas``); what it adds to C p goes to ``_torque``."""
        so = self._so
        ops = so.operators
        nodes, p_nodes = self._node_tractions(points, forces, R1)
        u = add_point_displacement(so, nodes, p_nodes, u)
        p_c = np.zeros((ops.n_nodes, 3))
        np.add.at(p_c, nodes, p_nodes)
        p_c = p_c.reshape(-1)
        alpha = ops.C @ p_c
        if self.frame_update:
            exact = self._forces_alpha(points, forces, R1)
            self._torque = self._torque + (exact - alpha)
            alpha = exact
        return u, a_ext + ops.A @ p_c, alpha_ext + alpha, p_c

    def _check_targets(self, value: Any, k: int, t: float, handle: int | None = None) -> np.ndarray:
        """Targets given to ``fix`` (``handle`` None) or returned by a driven target ``fn(t)`` at a
        step's end time t, checked on the host value (names the body, the handle and the frame)."""
        what = f"body '{self.name}': fixed-point targets (world positions)" if handle is None else \
            f"body '{self.name}': fix() handle {handle} target fn(t) (world positions)"
        return callback_array(value, ((k, 3),), what, t, None if handle is None else self._frame_of(t))

    def _constraint_points(self, V: np.ndarray, X_prev: np.ndarray, t: float) -> tuple[wc.PointRefs, wc.PointSet]:
        """The points and constraints of this step: fixed and driven nodes, nodes in contact, then
        collider corners pressing on faces."""
        points = wc.PointSet()
        nodes = []
        held = np.zeros(len(V), dtype=bool)
        for handle, (ids, nd, target, row) in self._fixed.items():
            tgt = (self._check_targets(call_user(target, t, f"body '{self.name}': fix() handle {handle} target fn(t)",
                                                 self._frame_of(t)), len(ids), t, handle)
                   if callable(target) else target)
            points.add(wc.FIXED, np.zeros((len(nd), 3)), np.zeros(len(nd)), tgt[row], 0.0)
            nodes.append(nd)
            held[nd] = True
        surfaces = self._surfaces
        if surfaces is not None:
            margin = self.contact_distance
            for ci, col in enumerate(surfaces):
                plane = surfaces.plane(ci)
                if plane is not None:
                    n, h = plane
                    sel = np.flatnonzero((V @ n - h < margin) & ~held)
                    normal, height, target = np.broadcast_to(n, (len(sel), 3)), np.full(len(sel), h), X_prev[sel]
                else:
                    sel, normal, height = self._mesh_points(ci, V, t, margin, held)
                    G, g = surfaces.velocity(ci, t - self.dt, max(1e-6, 1e-3 * self.dt))
                    target = X_prev[sel] + self.dt * (X_prev[sel] @ G.T + g)  # carried by the collider
                mu = collider_friction(col.friction, self.friction)
                if len(sel):
                    points.add(wc.CONTACT, normal, height, target, mu)
                    nodes.append(sel)
        refs = wc.PointRefs.nodes(np.concatenate(nodes) if nodes else np.zeros(0, dtype=np.int64))
        faces = centroid_faces(self._surface.faces)
        if surfaces is not None and len(faces):
            # a coarse surface presses on mesh colliders with its faces' centroids too (as on other
            # BEM bodies, ``wsim.contact.centroid_faces``): an 8-node box set corner over corner on
            # a box collider slid down its edges to the ground, and 2 cm off centre tipped over
            C, C_prev, held_c = V[faces].mean(axis=1), X_prev[faces].mean(axis=1), held[faces].any(axis=1)
            for ci, col in enumerate(surfaces):
                if surfaces.plane(ci) is None:
                    sel, normal, height = self._mesh_points(ci, C, t, self.contact_distance, held_c)
                    if len(sel):
                        G, g = surfaces.velocity(ci, t - self.dt, max(1e-6, 1e-3 * self.dt))
                        mu = collider_friction(col.friction, self.friction)
                        points.add(wc.CONTACT, normal, height, C_prev[sel] + self.dt * (C_prev[sel] @ G.T + g), mu)
                        refs = refs.concat(wc.PointRefs(faces[sel].astype(np.int64), np.full((len(sel), 3), 1.0 / 3.0)))
        if surfaces is not None:
            for ci, col in enumerate(surfaces):
                if surfaces.plane(ci) is None:
                    corners = self._corner_points(ci, V, X_prev, t)
                    if corners is not None:
                        mu = collider_friction(col.friction, self.friction)
                        face_refs, normal, height, target = corners
                        points.add(wc.CONTACT, normal, height, target, mu)
                        refs = refs.concat(face_refs)
        return refs, points

    def _corner_points(self, ci: int, V: np.ndarray, X_prev: np.ndarray, t: float):
        """Vertices of collider mesh ci inside the body's predicted surface: each presses on the
        nearest point of a face, which must retreat behind the vertex along the face's inward normal
        (n . x >= n . c with n = -n_face). None when no vertex is inside."""
        col = self._surfaces[ci]
        M = self._surfaces.matrix(ci, t)
        c = col.vertices @ M[:3, :3].T + M[:3, 3]
        lo, hi = V.min(axis=0), V.max(axis=0)
        near = np.flatnonzero(np.all((c >= lo) & (c <= hi), axis=1))  # inside the body's box
        if not len(near):
            return None
        faces = self._surface.faces
        inside, f, bary, nrm = points_inside(c[near], V, faces, 0.0, self._device, self._inside_test)
        if not len(inside):
            return None
        refs = wc.PointRefs(faces[f].astype(np.int64), bary)
        n = -nrm
        corner = c[near[inside]]
        G, g = self._surfaces.velocity(ci, t - self.dt, max(1e-6, 1e-3 * self.dt))
        prev = refs.positions(X_prev)
        return refs, n, np.einsum("ij,ij->i", n, corner), prev + self.dt * (prev @ G.T + g)

    def _mesh_points(self, ci: int, V: np.ndarray, t: float, margin: float,
                     held: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nodes inside collider mesh ci or within ``margin`` of it, with the tangent plane
        n . x >= height of the nearest collider point (outward normal, world axes)."""
        col = self._surfaces[ci]
        M = self._surfaces.matrix(ci, t)
        local = (V - M[:3, 3]) @ np.linalg.inv(M[:3, :3]).T
        near = ~held
        if col.closed:  # only nodes in a closed collider's box (grown by the margin) can be inside it or that near
            lo, hi = col.local_box
            near &= np.all((local >= lo - margin) & (local <= hi + margin), axis=1)
        # (an open sheet is one-sided: everything behind it, as far as the query reaches, is inside)
        near = np.flatnonzero(near)
        where = query_device(self._device, len(near))
        hit, face, bary, nrm = nearest_faces(col.device_mesh(where), local[near], col.extent, margin, where,
                                             closed=col.inside_test)
        hit = near[hit]
        closest = np.einsum("mk,mkd->md", bary, col.vertices[col.faces[face]]) @ M[:3, :3].T + M[:3, 3]
        normal = nrm @ M[:3, :3].T  # a rigid pose: normals turn like the mesh
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        return hit, normal, np.einsum("ij,ij->i", normal, closest)

    # -- the constraint seam (``wsim.constraints.Participant``) --------------------------------------
    def constraint_begin(self) -> tuple[wc.PointRefs, wc.PointSet, np.ndarray]:
        """Predict the coming step (history, loads, Eq. 12 and the frame update without point forces);
        returns this body's held and contacting points, their constraints and every node's predicted
        world position (see ``wsim.constraints``)."""
        u, a_ext, alpha_ext = self.unconstrained_solve()
        st, so = self.state, self._so
        ops = so.operators
        t0 = time.perf_counter()
        t = (st.steps + 1) * self.dt
        f = st.frame
        pred = f.copy()
        if self.frame_update:
            pred.update(self.dt, self._gravity, a_ext, alpha_ext, self._inertia, self._inertia_inv, self.gyroscopic)
        x = ops.surface.nodes - ops.com
        u_pos = u  # the displacement the step ends with, before the point forces
        if not self.frame_update:  # Eq. (9) with a = alpha = 0 (as _finish_step applies it)
            u_pos = u + so.E @ np.concatenate([-(a_ext + f.R.T @ self._gravity), -alpha_ext])
        lever = (x + u_pos.reshape(-1, 3)) @ pred.R.T
        V = lever + pred.T
        X_prev = (x + st.u.reshape(-1, 3)) @ f.R.T + f.T
        if self._response is None:
            self._response = PointResponse.build(so)
        refs, points = self._constraint_points(V, X_prev, t)
        self._cs = dict(u=u, a_ext=a_ext, alpha_ext=alpha_ext, lever=lever, x=x, pred_R=pred.R, t=t, V=V,
                        X_prev=X_prev, lever_body=x + st.u.reshape(-1, 3))  # frame axes, step start
        self._tick("collision", t0)
        return refs, points, V

    def contact_surface(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float | None, int]:
        """(predicted node positions, faces into the nodes, node positions at the step start,
        friction, the faces' inside test) of the step ``constraint_begin`` opened (``wsim.contact``)."""
        cs = self._cs
        return cs["V"], self._surface.faces, cs["X_prev"], self.friction, self._inside_test

    def constraint_response(self, points: wc.PointRefs) -> tuple[wp.array, wp.array]:
        """K (3m, 3m) of Eq. (14) for ``points`` and its transpose (``wsim.bem.constraints``)."""
        t0 = time.perf_counter()
        cs, f = self._cs, self.state.frame
        lin_a, lin_c = frame_terms(self._so, points, points.positions(cs["lever"]), f.R, self.dt, self.frame_update)
        K = response_matrix(self._so, self._response, points, cs["pred_R"], f.R, lin_a, lin_c, self._point_alphas(points))
        self._tick("constraints", t0)
        return K

    def constraint_positions(self, points: wc.PointRefs, forces: np.ndarray) -> np.ndarray:
        """World positions ``points`` end the step at with the forces applied there."""
        cs, f = self._cs, self.state.frame
        so, ops = self._so, self._so.operators
        nodes, p_nodes = self._node_tractions(points, forces, f.R)
        touched = np.unique(points.ids)
        u_t = cs["u"].reshape(-1, 3)[touched] + point_displacement(so, touched, nodes, p_nodes)
        p_c = np.zeros((ops.n_nodes, 3))
        p_c[nodes] = p_nodes
        a_c = cs["a_ext"] + ops.A @ p_c.reshape(-1)
        alpha_c = cs["alpha_ext"] + (self._forces_alpha(points, forces, f.R) if self.frame_update else ops.C @ p_c.reshape(-1))
        end = f.copy()
        if self.frame_update:
            end.update(self.dt, self._gravity, a_c, alpha_c, self._inertia, self._inertia_inv, self.gyroscopic)
        else:
            E = so.E.reshape(-1, 3, 6)[touched]
            u_t = u_t + E @ np.concatenate([-(a_c + f.R.T @ self._gravity), -alpha_c])
        V = np.zeros((ops.n_nodes, 3))
        V[touched] = (cs["x"][touched] + u_t) @ end.R.T + end.T
        return points.positions(V)

    def constraint_nonlinearity(self, points: wc.PointRefs, forces: np.ndarray) -> float:
        """Eq. (14) drops the second-order terms of the rotation increment dw = dt R C p: the true
        rotation exp(dt (w + dw)) differs from (I + dt [dw]x) exp(dt w) by at most
        dt^2 |dw| (|w| + |dw| / 2) (BCH), times the lever arm (< 2 r_max); the rest is linear."""
        if not self.frame_update or not len(points):
            return 0.0
        f = self.state.frame
        ops = self._so.operators
        dw = self.dt * float(np.linalg.norm(self._forces_alpha(points, forces, f.R)))
        omega = float(np.linalg.norm(f.omega))
        return 2.0 * ops.r_max * self.dt**2 * dw * (omega + 0.5 * dw)

    def constraint_warm(self, points: wc.PointRefs, kind: np.ndarray) -> np.ndarray:
        """Last step's forces of the nodes among ``points`` in constraints of the same kind (a node
        may be held, in contact and joined at once); points on faces start from zero."""
        st = self.state
        out = np.zeros((len(points), 3))
        if len(st.point_nodes):
            last = {(int(n), int(k)): i for i, (n, k) in enumerate(zip(st.point_nodes, st.point_kinds))}
            for i in np.flatnonzero(points.is_node):
                j = last.get((int(points.ids[i, 0]), int(kind[i])))
                if j is not None:
                    out[i] = st.point_forces[j]
        return out

    def constraint_end(self, points: wc.PointRefs, forces: np.ndarray, kind: np.ndarray,
                       record: wc.SolveRecord | None) -> None:
        """Apply the point forces as tractions and finish the step (``_finish_step``)."""
        u, a_ext, alpha_ext = self._close_constraints(points, forces, kind, record)
        # a step nothing held or touched is a free step: the paper's correction, as without colliders
        self._finish_step(u, a_ext, alpha_ext, time.perf_counter(), correct=not len(points))

    @staticmethod
    def constraint_end_free(bodies: Sequence[BemBody], points: Sequence[wc.PointRefs]) -> None:
        """``constraint_end`` of bodies nothing held or touched this step (``points``: their empty
        point lists): members of one instance set finish together (``Instances.finish_free``)."""
        by_set: dict[int, tuple[Any, list, list]] = {}
        for b, pts in zip(bodies, points):
            got = b._close_constraints(pts, np.zeros((0, 3)), np.zeros(0, dtype=np.int32), None)
            if b._set is not None and b.frame_update and b.error_correction:
                entry = by_set.setdefault(id(b._set), (b._set, [], []))
                entry[1].append(b)
                entry[2].append(got)
            else:
                b._finish_step(*got, time.perf_counter())
        for members_set, members, got in by_set.values():
            members_set.finish_free(members, got)

    def _close_constraints(self, points: wc.PointRefs, forces: np.ndarray, kind: np.ndarray,
                           record: wc.SolveRecord | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The point forces as tractions and the solve's records: (u, a_ext, alpha_ext) for
        ``_finish_step``."""
        t0 = time.perf_counter()
        st, so, cs = self.state, self._so, self._cs
        u, a_ext, alpha_ext = cs["u"], cs["a_ext"], cs["alpha_ext"]
        if len(points):
            u, a_ext, alpha_ext, p_c = self._with_point_forces(points, forces, u, a_ext, alpha_ext, st.frame.R)
            n3 = so.size
            self._p_in.numpy()[:n3] = p_c if self._p_loads is None else self._p_loads + p_c
            wp.copy(self._p, self._p_in, count=n3)
            if self._loads:  # the next step's loads rewrite the (pinned) staging buffer: let this copy finish
                wp.synchronize_device(self._device)
            self._p_live = True
            self._loaded_now = True
            for k, attr in ((wc.CONTACT, "contact_impulse"), (wc.FIXED, "fixed_impulse"), (wc.JOINT, "joint_impulse")):
                setattr(st, attr, getattr(st, attr) + self.dt * forces[kind == k].sum(axis=0))
        node = points.is_node
        st.point_nodes = points.ids[node, 0].astype(np.int64)
        st.point_kinds = np.asarray(kind, dtype=np.int64)[node]
        st.point_forces = np.asarray(forces, dtype=np.float64).reshape(-1, 3)[node]
        if record is not None:
            self.constraint_history.append(record)
            if not record.converged:
                self.unconverged_steps += 1
                if self.unconverged_steps == 1:
                    warnings.warn(f"body '{self.name}': the constraint solve at step {record.step} (t = {cs['t']:.6g} s) "
                                  f"stopped after {record.sweeps} sweeps at residual {record.residual:.3g} m "
                                  f"> tol {self.constraint_tolerance:.3g} m (see body.constraint_history)", RuntimeWarning, stacklevel=4)
        self._cs = None
        self._tick("constraints", t0)
        return u, a_ext, alpha_ext

    @property
    def constraint_tolerance(self) -> float:
        """The constraint solve's tolerance [m] in use (``constraint_tol`` or its default)."""
        return self.constraint_tol if self.constraint_tol is not None else 1e-5 * self._so.operators.r_max

    @property
    def contact_distance(self) -> float:
        """The contact margin [m] in use (``contact_margin`` or its default)."""
        return self.contact_margin if self.contact_margin is not None else 1e-3 * self._so.operators.r_max

    @property
    def failed(self) -> bool:
        """Whether the body has stopped (``check_finite`` raises the reason)."""
        return self._failure is not None

    @property
    def constrained(self) -> bool:
        """Whether the body's steps go through the constraint solve (held points or colliders)."""
        return bool(self._fixed) or self._surfaces is not None

    def advance(self, t0: float, t1: float) -> None:
        """Take steps of dt until the body's time is the nearest multiple of dt to t1."""
        self._require_bound()
        if self._failure is not None:
            return
        target = int(math.floor(t1 / self.dt + 0.5))
        while self.state.steps < target:
            if not BemBody.steps_on_device([self], target):
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
        if BemBody.steps_on_device([self], self.steps + 1):
            return
        if self.constrained:
            # On a constrained step the error correction moves u's rigid drift into the frame's pose
            # (``Correction.drift``), not its acceleration: the paper's da, dalpha moved the points
            # after the solve (a resting cube slid ~10 um per step) and held 2.5 % of its weight with
            # a force no collider applied. So the constraints have the last word on the positions.
            wc.solve_group([self], [], self._device, self.constraint_tolerance, self.constraint_iterations, self.steps + 1)
            return
        u, a_ext, alpha_ext = self.unconstrained_solve()
        self._finish_step(u, a_ext, alpha_ext, time.perf_counter())

    def _on_device(self) -> bool:
        """Whether this body's free steps can run on the device (``device_step``; ``wsim.bem.device_step``)."""
        so = self._so
        return (self.device_step and not self.profile and so.backend == "warp" and so.packed is None
                and so.compressed is None and self.error_correction and not self._fixed
                and (self._set is None or self._set.steps_apart)
                and self._predicted is None)

    @staticmethod
    def steps_on_device(bodies: Sequence[BemBody], target: int) -> bool:
        """Take the steps towards ``target`` that ``device_window`` allows ``bodies`` (stepping
        together) on the device, each body its own; False when it allows none."""
        k = BemBody.device_window(bodies, target)
        # a batch ends where the growth check could first stop a body, so that a body it stops
        # is left at the step it names (the checks run on the batch's log after the batch)
        k = max(min([k] + [b._growth_horizon() - b.steps for b in bodies if b.growth_check]), 0)
        for b in bodies:
            if k:
                b._device_steps(b.steps + k)
        return k > 0

    def _growth_horizon(self) -> int:
        """The first step at which the growth check (``_check_growth``) could stop this body: the
        (5 - g)-th window boundary from now, g the windows already counted growing (it counts at
        most one a boundary and stops at five)."""
        L = self._window_length
        # at least the next boundary (a restored checkpoint may hold a count of 5 or more)
        return (self.state.steps // L + max(5 - self.state.window_growing, 1)) * L

    @staticmethod
    def device_window(bodies: Sequence[BemBody], target: int) -> int:
        """How many of the steps up to ``target`` ``bodies`` (stepping together) can take on the
        device: steps on which, by a bound on their motion, no node of any of them can come
        within the contact margin of a collider or of another of them, so the constrained step
        would find no point and end as a free one (``constraint_end_free``). 0: step on the host.

        The bound: every node moves by at most s(tau) = (|v| + |omega| rho) tau + |g| tau^2 / 2 in
        tau seconds (rho the largest lever about the centre of mass), with a factor 2 of safety;
        the gaps (each node's height above a ground plane, the distance between bounding balls
        for a static mesh collider or another body) keep a slack of the contact margin, twice
        the recent peak |u| (elastic vibration) and 5 % of r_max. A kinematic mesh collider, held
        points, a user's traction load or a push of other bodies still in force (their size is
        not known ahead) keep a body near anything on the host path."""
        todo = target - bodies[0].state.steps
        if todo <= 0 or not all(b._on_device() for b in bodies):
            return 0
        reach = [b._reach() for b in bodies]
        gaps: list[tuple[float, float, float]] = []  # (distance, speed bound, acceleration bound)
        for b, (T, rho, slack, a, acc, lever) in zip(bodies, reach):
            found = b._collider_gaps(T, rho, lever)
            if found is None:
                return 0
            gaps += [(d - slack, a, acc) for d in found]
        for i in range(len(bodies)):
            for j in range(i + 1, len(bodies)):
                (Ti, ri, si, ai, bi, _), (Tj, rj, sj, aj, bj, _) = reach[i], reach[j]
                gaps.append((float(np.linalg.norm(Ti - Tj)) - ri - rj - si - sj, ai + aj, bi + bj))
        if not gaps:
            return todo
        if any(b._unknown_loads() for b in bodies):
            return 0
        dt = bodies[0].dt
        for d, a, acc in gaps:
            if d <= 0.0:
                return 0
            # 2 (a tau + acc tau^2 / 2) <= d
            tau = d / (2.0 * a) if acc <= 0.0 else (-a + math.sqrt(a * a + 2.0 * acc * d)) / (2.0 * acc)
            todo = min(todo, int(tau / dt))
        return max(todo, 0)

    def _reach(self) -> tuple[np.ndarray, float, float, float, float, np.ndarray]:
        """(centre T, radius rho, slack, speed bound, acceleration bound, the nodes' lever arms
        about T (N, 3), world axes) of ``device_window``."""
        st, ops = self.state, self._so.operators
        f = st.frame
        lever = (ops.surface.nodes - ops.com + st.u.reshape(-1, 3)) @ f.R.T
        rho = float(np.sqrt((lever * lever).sum(axis=1).max()))
        peak = max(st.window_peak, st.window_previous, float(np.abs(st.u).max(initial=0.0)))
        slack = self.contact_distance + 2.0 * peak + 0.05 * ops.r_max
        speed = float(np.linalg.norm(f.velocity)) + float(np.linalg.norm(f.omega)) * rho
        return f.T.copy(), rho, slack, speed, 0.5 * float(np.linalg.norm(self._gravity)), lever

    def _collider_gaps(self, T: np.ndarray, rho: float, lever: np.ndarray) -> list[float] | None:
        """The body's distance to each collider (see ``device_window``); None with a kinematic mesh."""
        surfaces = self._surfaces
        if surfaces is None:
            return []
        out = []
        for ci, col in enumerate(surfaces):
            plane = surfaces.plane(ci)
            if plane is not None:
                n, h = plane
                out.append(float((lever @ n).min() + T @ n - h))
            elif col.kinematic:
                return None
            else:
                c, r = col.ball(0.0)
                out.append(float(np.linalg.norm(T - c)) - rho - r)
        return out

    def _unknown_loads(self) -> bool:
        """A user's traction load, or a push of other bodies still in force after this step."""
        st = self.state
        if any(fn != self._coupling_tractions for fn in self._loads):
            return True
        return bool(len(st.coupling_force)) and st.coupling_until >= (st.steps + 1) * self.dt - 1e-9 * self.dt

    def _device_steps(self, target: int) -> None:
        """Free steps up to step ``target`` (at most ``LOG_ROWS`` of them) on the device: the host
        evaluates each step's loads and launches; the state comes back once at the end, where each
        step's checks (``_check_step``) run on the device's log. A failing step (non-finite,
        diverging) stops the device there: the body's state and step count are that step's."""
        t0 = time.perf_counter()
        st = self.state
        rs = self._resident
        settings = (self.gyroscopic, float(self.divergence_limit))
        if rs is None or rs.U is not st.U or rs.p is not self._p or rs.settings != settings:
            # first use, rings moved (a set, a restore) or settings the graphs bake in changed
            rs = self._resident = ResidentStep(self._so, (st.U, st.P, st.B, self._U_k, self._P_k),
                                               (self._p, self._h, self._u_dev, self._p_k, self._h_k),
                                               self._inertia, self._gravity, self.dt, *settings)
        first, ring = st.steps, st.ring
        rs.begin(st.frame)
        loaded: list[bool] = []
        try:
            while st.steps < target and len(loaded) < LOG_ROWS:
                p = self._tractions((st.steps + 1) * self.dt) if self._loads else None
                has_p = p is not None and bool(np.any(p))
                if has_p:
                    rs.load(p, self._frame_loads(p, (st.steps + 1) * self.dt))
                    self._p_live = True  # the traction buffer holds this load (the host path zeroes it)
                rs.step(st.ring, has_p)
                if st.steps % 100 == 99:
                    rs.reorthonormalize()
                self._dirty = True
                st.ring += 1
                st.steps += 1
                loaded.append(has_p)
        except Exception:
            self._end_device_steps(rs, first, ring, loaded, t0)
            if self._failure is not None:
                return  # the body failed at an earlier step, before the host path would have called the load
            raise
        self._end_device_steps(rs, first, ring, loaded, t0)

    def _end_device_steps(self, rs: ResidentStep, first: int, ring: int, loaded: list[bool], t0: float) -> None:
        """Read the batch's state back and run each step's checks on the log."""
        st = self.state
        self._sync()
        self._p_loads = None
        self._loaded_now = bool(loaded) and loaded[-1]
        st.point_nodes, st.point_kinds = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)  # no point
        st.point_forces = np.zeros((0, 3))  # held or touched (the constraint solve's warm start)
        for k, ((peak, flags), has_p) in enumerate(zip(rs.read_log(), loaded)):
            self._check_step(first + k + 1, float(peak), int(flags), has_p)
            if self._failure is not None:
                if self._failure[2] != "growing":  # the device stopped at this step (``correct_step``'s halt)
                    st.steps, st.ring = first + k + 1, ring + k + 1
                # (a growing body's batch ended at the first step its check could fail on,
                # ``steps_on_device``: the state is that step's)
                break
        self._tick("device", t0)

    def _sync(self) -> None:
        """The device's u and frame onto the host after steps launched by ``_device_steps``."""
        if not self._dirty:
            return
        u, frame = self._resident.read()
        st = self.state
        st.u = u
        set_frame(st.frame, frame)
        st.material_velocity, st.material_omega = st.frame.velocity.copy(), st.frame.omega.copy()
        st.frame_is_material = True
        self._dirty = False

    def unconstrained_solve(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The paper's UNCNST stage of the coming step: history, loads and Eq. (12), without
        changing the body's state (it uses up a prediction its ``Instances`` set made for this
        step, if any). Returns (u_n float64, a_ext, alpha_ext)."""
        predicted, self._predicted = self._predicted, None
        if predicted is not None and predicted[0] == self.steps:  # computed with its set (``wsim.bem.instances``)
            return predicted[1], predicted[2], predicted[3]
        so = self._so
        n3 = so.size
        t0 = time.perf_counter()
        # the history needs only past steps: launch it first, so the host evaluates the loads
        # while the device streams the matrices
        stepper.history(so, self._U_k, self._P_k, self.state.B, self.state.ring, self._h, self._scratch)
        t0 = self._tick("history", t0)
        a_ext, alpha_ext = self._step_loads()
        t0 = self._tick("loads", t0)
        stepper.solve(so, self._p_k if self._p_loads is not None else None, self._h_k, self._u_dev, self._scratch)
        wp.copy(self._u_out, self._u_dev, count=n3)
        wp.synchronize_device(self._device)
        u = self._balanced(self._u_out.numpy()[:n3].astype(np.float64))
        self._tick("solve", t0)
        return u, a_ext, alpha_ext

    def _balanced(self, u: np.ndarray) -> np.ndarray:
        """u of the coming step with the loads' balance X p (``correction.load_balance``) in the
        BEM's frame terms: u + H_0^-1 [D_0 Q_0] X p."""
        return u if self._balance is None else u + self._so.E @ self._balance

    def _step_loads(self) -> tuple[np.ndarray, np.ndarray]:
        """The coming step's tractions p_n into the device vector (zeroed when there are none) and
        (a_ext, alpha_ext) = (A p_n, C p_n) (Eq. 10)."""
        so = self._so
        n3 = so.size
        self._loaded_now = False
        t = (self.steps + 1) * self.dt
        p = self._tractions(t) if self._loads else None
        has_p = p is not None and bool(np.any(p))
        self._p_loads = p if has_p else None
        self._balance, self._torque = None, np.zeros(3)
        if has_p:
            self._loaded_now = True
            self._p_in.numpy()[:n3] = p
            wp.copy(self._p, self._p_in, count=n3)
            self._p_live = True
            ext = self._frame_loads(p, t)
            return ext[0:3], ext[3:6]
        if self._p_live:
            self._p.zero_()
            self._p_live = False
        return np.zeros(3), np.zeros(3)

    def _frame_loads(self, p: np.ndarray, t: float) -> np.ndarray:
        """(15,) [a_ext, alpha_ext, X p, fix] of the tractions p (3N,) at step end time t: the frame's
        accelerations (A p and C p + fix, Eq. 10), the loads' balance for the BEM's own frame terms
        (``correction.load_balance``; zero without the error correction) and the push's torque fix
        (``_push_torque``: the frame's alpha has it, the BEM's terms not; with ``frame_update``).
        Sets ``_balance`` (X p) and ``_torque`` (fix) for the step."""
        so = self._so
        ops = so.operators
        out = np.zeros(15)
        out[0:3], out[3:6] = ops.A @ p, ops.C @ p
        if self.frame_update:  # the balance serves the error correction; the fix, the frame alone
            if self.error_correction:
                out[6:12] = so.load_balance @ p
            fix = self._push_torque(t)
            if fix is not None:
                out[3:6] += fix
                out[12:15] = fix
            self._balance, self._torque = out[6:12].copy(), out[12:15].copy()
        return out

    def _push_torque(self, t: float) -> np.ndarray | None:
        """alpha [rad/s^2] (frame axes) the push of ``add_vertex_impulses`` lacks at step end time t:
        its point forces' moment about the centre of mass at the vertices, I^-1 sum_v l_v x f_v,
        less C p of their tractions (whose moment acts at each hat function's centroid); None
        without a push."""
        st = self.state
        if not self._coupling_load or t > st.coupling_until + 1e-9 * self.dt or not len(st.coupling_force):
            return None
        f = st.coupling_force @ st.frame.R
        lever = self.rest_vertices + self.vertex_displacement()
        p = (f / self._vertex_area[:, None])[self._surface.vertex]
        return self._inertia_inv @ np.cross(lever, f).sum(axis=0) - self._so.operators.C @ p.reshape(-1)

    def _adopt_rings(self, U: wp.array, P: wp.array, B: wp.array, p: wp.array, h: wp.array, u: wp.array) -> None:
        """Move the rings and step vectors into the given arrays (rows of an ``Instances`` set's
        stacked ones), contents kept; every view is rebuilt on them."""
        st = self.state
        for new, old in ((U, st.U), (P, st.P), (B, st.B), (p, self._p), (h, self._h), (u, self._u_dev)):
            wp.copy(new, old)
        st.U, st.P, st.B, self._p, self._h, self._u_dev = U, P, B, p, h, u
        view = stepper.vec4_view if self._so.backend == "warp" else (lambda a: a)
        self._U_k, self._P_k, self._p_k, self._h_k = view(st.U), view(st.P), view(self._p), view(self._h)

    @staticmethod
    def step_sets(bodies: Sequence[BemBody]) -> list:
        """Bodies of ``bodies`` on one operator set, as sets that step their passes together
        (``wsim.bem.instances``); bodies of no set are not listed."""
        from wsim.bem.instances import instance_sets

        return instance_sets(bodies)

    def _finish_step(self, u: np.ndarray, a_ext: np.ndarray, alpha_ext: np.ndarray, t0: float,
                     correct: bool = True, corrected: tuple | None = None, write_rings: bool = True) -> np.ndarray:
        """Error correction, ring update and frame update of the step (the paper's ERRCR). With
        ``correct`` False (a constrained step) the drift moves to the frame's pose instead of its
        acceleration (``Correction.drift``). ``corrected``: (da, dalpha, u) of ``Correction.apply``
        already computed (an ``Instances`` set corrects its bodies together); ``write_rings``
        False leaves the ring rows of this step to the caller (the set writes them together).
        The frame takes [a_ext + da, alpha_ext + dalpha]; the BEM's own terms (the B ring) that
        plus the loads' balance, less the push's torque fix (``_frame_loads``). Returns the B ring's
        row of the step."""
        st = self.state
        so, f = self._so, st.frame
        n3 = so.size
        g_body = f.R.T @ self._gravity  # g' (Eq. 11a)
        finite = bool(np.all(np.isfinite(u)))  # else no correction (its SVD fails): _check_state reports it
        transfer = None
        if self.frame_update:
            da = dalpha = np.zeros(3)
            if corrected is not None:
                da, dalpha, u = corrected
            elif self.error_correction and correct and finite:
                da, dalpha, u = so.correction.apply(u)
            elif self.error_correction and finite:  # a constrained step: the drift goes to the pose (see ``step``)
                *transfer, u = so.correction.drift(u)
            b = np.concatenate([a_ext + da, alpha_ext + dalpha])  # [a - g', alpha]: the frame's
            b_ring = b - np.concatenate([np.zeros(3), self._torque])
            if self._balance is not None:
                b_ring = b_ring + self._balance
        else:
            # a = alpha = 0 in Eq. (9): H_0 u = G_0 p - D_0 g' + h
            b = b_ring = np.concatenate([-g_body, np.zeros(3)])
            u = u + so.E @ np.concatenate([-(a_ext + g_body), -alpha_ext])
        t0 = self._tick("correction", t0)
        if write_rings:
            slot = st.ring % so.n_max
            self._u_in.numpy()[:n3] = u
            self._b_in.numpy()[:] = b_ring
            wp.copy(st.U, self._u_in, dest_offset=slot * so.pitch, count=n3)
            wp.copy(st.P, self._p, dest_offset=slot * so.pitch, count=n3)
            wp.copy(st.B, self._b_in, dest_offset=slot * 6, count=6)
            if self._scratch is not None:  # the frame terms that go with the stored G'_k (``compression.folded_G``):
                # they fold A p, C p; alpha_ext has the push's torque fix on top, which the ring has not
                self._bf_in.numpy()[:] = b_ring - np.concatenate([a_ext, alpha_ext - self._torque])
            stepper.ring_written(so, self._U_k, self._P_k, slot, self._scratch, self._bf_in)
        if self.frame_update:
            T_old, R_old = f.T.copy(), f.R.copy()
            f.update(self.dt, self._gravity, b[:3], b[3:], self._inertia, self._inertia_inv, self.gyroscopic)
            if transfer is not None:  # x + u = R_e (x + u'' - c0) + c0 + t: every point stays put
                drift, R_e = transfer
                c0 = so.correction.c0
                # Only the pose. Handing the drift's rate to the velocity as well made the drift a
                # support force (23 % of a resting 26-node cube's weight, 7 % at 98 nodes) and
                # the clamped cantilever scene unstable; the paper's da before the solve held 2.5 %
                # of the cube's weight and let the cantilever droop further every second. The cost:
                # on a held or resting body the frame's velocity is not the material's (README).
                f.T = f.T + f.R @ (c0 + drift - R_e @ c0)
                f.R = f.R @ R_e
                st.material_velocity = (f.T - T_old) / self.dt
                st.material_omega = rotation_vector(f.R @ R_old.T) / self.dt
                st.frame_is_material = False
            else:
                st.material_velocity, st.material_omega = f.velocity.copy(), f.omega.copy()
                st.frame_is_material = True
            if st.steps % 100 == 99:
                f.reorthonormalize()
        st.u = u
        st.ring += 1
        st.steps += 1
        self._tick("frame", t0)
        self._check_state()
        return b_ring

    def _check_growth(self, peak: float, steps: int) -> None:
        """Windows of n_max steps: five in a row, all unloaded, each with a peak |u| 20 % above the
        last and above round-off (1e-9 of the body size), mean a growing mode of the discrete
        system - the physical body, passive and unloaded, can only ring down (BDF1 damps it)."""
        st = self.state
        length, current, previous, growing = self._window_length, st.window_peak, st.window_previous, st.window_growing
        current = max(current, peak)
        if steps % length == 0:
            unloaded = steps - st.last_loaded >= 2 * length  # this window and the one before
            if unloaded and previous > 1e-9 * self._so.operators.r_max and current > 1.2 * previous:
                growing += 1
            else:
                growing = 0
            if growing >= 5:
                self._failure = ("displacement", f"|u| grew {current / previous:.2f}x per {length}-step window for "
                                 f"{growing} windows with no load, to {current:.3g} m at step {steps} "
                                 f"(t = {steps * self.dt:.6g} s): the discretization is unstable at this dt and mesh "
                                 "(try a larger dt or a finer mesh)", "growing")
            previous, current = current, 0.0
        st.window_peak, st.window_previous, st.window_growing = current, previous, growing

    # the quantities a step checks for non-finite values, with their bits in the device log
    _CHECKED = ((1, "displacement"), (2, "frame position"), (4, "frame velocity"), (8, "angular velocity"))

    def _check_state(self) -> None:
        f, u = self.state.frame, self.state.u
        flags = 0
        for (bit, _), value in zip(self._CHECKED, (u, f.T, f.velocity, f.omega)):
            if not np.all(np.isfinite(value)):
                flags |= bit
        peak = float(np.max(np.abs(u))) if u.size and not flags else 0.0
        self._check_step(self.steps, peak, flags, self._loaded_now)

    def _check_step(self, steps: int, peak: float, flags: int, loaded: bool) -> None:
        """The checks after step ``steps``: non-finite state (``flags``: bits of ``_CHECKED``),
        the growth check and the divergence limit on ``peak`` = max |u|."""
        when = f"step {steps} (t = {steps * self.dt:.6g} s)"
        for bit, quantity in self._CHECKED:
            if flags & bit:
                self._failure = (quantity, when, "non-finite")
                return
        if loaded:
            self.state.last_loaded = steps
        if self.growth_check:
            self._check_growth(peak, steps)
        if peak > self.divergence_limit:
            self._failure = ("displacement", f"|u| = {peak:.3g} m exceeds divergence_limit = "
                             f"{self.divergence_limit:.3g} m at {when}", "diverging")
