"""PbdBody: an XPBD soft body (surface-only or tetrahedral) that a World steps and exports.

Per substep of length h (Macklin et al., "Small Steps in Physics Simulation", 2019: many
substeps with few iterations beat few substeps with many iterations at equal cost):

1. predict x from gravity and velocity, write kinematic handle targets;
2. ``iterations`` times: project every constraint family colour by colour, the global volume
   constraint, then contacts with the World's colliders (with friction), accumulating the
   corrections in dx apart from the prediction (float32 momentum, ``wsim.kernels.pbd``);
3. v = v_pred + dx / h, x = x_pred + dx; then (free bodies, ``conserve_angular_momentum``) give
   back the angular momentum the implicit solve took from the rotation.

On CUDA the launches of a whole frame are captured once into a CUDA graph and replayed, so a
frame costs one launch from Python; per-frame inputs (handle targets, collider poses) are copied
into fixed device buffers before each replay. On the CPU (single-threaded Warp kernels) each
family is one launch over all its colour-sorted constraints, which performs exactly the same
updates in the same order as one launch per colour.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Sequence

import numpy as np
import warp as wp

from wsim import mesh as wmesh
from wsim.body import Body, checked_vertex_impulses
from wsim.cache import OperatorCache
from wsim.colliders import Surfaces
from wsim.contact import collider_friction
from wsim.errors import InvalidParameter, SimulationDiverged
from wsim.handles import Handle, as_indices
from wsim.validate import as_rotation, as_vec3, finite_number, positive_int
from wsim.kernels import pbd_contact as kc
from wsim.kernels import pbd as kp
from wsim.materials import ElasticMaterial, body_material
from wsim.pbd.model import MODEL_FORMAT_VERSION, ConstraintFamily, PbdModel, build_model, hinge_edge_layout

_KERNELS = {"distance": kp.solve_distance, "bending": kp.solve_bending, "tet_volume": kp.solve_tet_volume}
SOLVERS = ("gauss_seidel", "jacobi")
_VEC = {2: wp.vec2i, 4: wp.vec4i}


@dataclass
class PbdState:
    """What changes when a PBD body steps: particle positions x [m] and velocities v [m/s]
    (float32, on the body's device). Everything else a substep touches (x_prev, x_pred, dx, the
    multipliers) is rebuilt from these at its start."""

    x: wp.array
    v: wp.array
    # momentum an EoL body pushed the surface particles with, to be taken at the next step's start
    # (``add_vertex_impulses``) [N s] (V, 3), and all it has handed so far [N s] (3,)
    push: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    coupling_impulse: np.ndarray = field(default_factory=lambda: np.zeros(3))
    # (n, 4) the push this body handed each yielding moving surface over the last interval, rows
    # (key, J) per vertex: the partner takes it over the next one, and yields to its change only
    # (``set_moving_surfaces``)
    partner_push: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    # (n, 2) rows (key, the contacts of the last iteration on it): how each particle's projection
    # shares the partner's give in the next interval's first iteration (``shared_give``)
    partner_contacts: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))

    _ragged: ClassVar[tuple[str, ...]] = ("partner_push", "partner_contacts")


@dataclass
class _DeviceFamily:
    kind: str
    offsets: np.ndarray
    indices: wp.array
    rest: wp.array
    compliance: wp.array
    lam: wp.array
    count: wp.array  # (P,) float32: how many of the family's constraints touch each particle (Jacobi)
    # hinges: each one's edge (index into ``edge_family``'s arrays, -1: none), projected with it
    # (``kernels.pbd.solve_hinge_edge``; ``PbdBody._fused_layout``)
    edge: wp.array | None = None
    edge_family: _DeviceFamily | None = None


@dataclass
class _DeviceMeshCollider:
    index: int  # in the World's Surfaces
    friction: float
    mesh: wp.Mesh
    transforms: wp.array  # (S + 1,) mat44 on device
    inverses: wp.array
    host_transforms: np.ndarray  # (S + 1, 4, 4) float32 staging
    host_inverses: np.ndarray
    max_dist: float
    closed: int  # 0: an open sheet, one-sided (kernels/mesh.py query_inside)


@dataclass
class _OwnSurface:
    """A body's own surface for the moving surfaces' vertices (``PbdBody._build_own_surface``):
    its particles' current positions, the triangles, their Warp mesh, how far a query looks and
    the inside test."""

    points: wp.array
    indices: wp.array
    mesh: wp.Mesh
    reach: float
    closed: int


@dataclass
class _MovingSurface:
    """Another body's surface that moves on its own over the frame (explicit two-way coupling):
    its vertices at the frame's start and end, where they are at the current substep's start and
    end, its mesh (on ``cur``, refit each substep) and the momentum the particles gave it."""

    key: int
    p0: wp.array
    p1: wp.array
    prev: wp.array
    cur: wp.array
    indices: wp.array
    mesh: wp.Mesh
    friction: float
    reach: float
    impulse: wp.array
    closed: int  # the surface's inside test (``wsim.mesh.inside_test``)
    keep_out: bool  # its vertices are also kept out of this body's surface (``moving_points_contact``)
    inv_mass_v: wp.array | None  # then: its vertices' inverse lumped masses [1/kg]
    give: wp.array  # how it yields (one ``kernels.pbd_contact.Give``; inv_mass 0: kinematic)
    total: wp.array  # an iteration's push on it (momentum)
    count: wp.array  # contacts of the last iteration, of this one (``moving_surface_contact``)
    area: wp.array  # its lumped vertex areas [m^2] (zero while it is kinematic)
    u: wp.array | None = None  # ... its vertices' yield velocity this interval [m/s]
    y: wp.array | None = None  # ... how far they have yielded [m]
    seen: wp.array | None = None  # ... the impulse its last yield counted
    received_v: wp.array | None = None  # ... the last interval's push per vertex [N s]
    yielding: bool = False


class PbdBody(Body):
    """A soft body simulated with XPBD.

    Args:
        mesh: closed surface of one piece, a ``trimesh.Trimesh`` or a (vertices, faces) pair [m]
            (open only with ``mass`` and no global ``volume``; several pieces only with ``allow_pieces``).
        material: elastic material (default: E = 1e5 Pa, nu = 0.3, rho = 1000 kg/m^3), or a dict of
            its arguments (``dict(E=1e5, nu=0.3, rho=1000.0)``), checked naming the body.
        name: USD prim name.
        position: translation applied to the mesh (and to ``interior_points``) [m].
        rotation: (3, 3) rotation applied to the particles about their centre of mass (default
            identity; like ``EolBody`` and ``BemBody``). The model (and its cache entry) is the
            unrotated one: rest lengths, angles and volumes do not change with a rotation.
        velocity, angular_velocity: initial motion about the centre of mass [m/s], [rad/s].
        tets: None (surface-only body), "auto" (tetrahedralize the surface), or (T, 4) indices into
            the mesh vertices followed by ``interior_points``.
        interior_points: (Q, 3) extra particles used by ``tets`` [m].
        substeps: substeps per frame; or give ``dt`` [s], and the substep is the largest h <= dt
            that divides the frame.
        iterations: constraint iterations per substep.
        solver: how an iteration projects a constraint family: "gauss_seidel" (default: one launch
            per colour of the family, each constraint seeing the corrections of the colours before
            it) or "jacobi" (one launch per family, every constraint seeing the positions before
            the sweep, its multiplier increment scaled by ``omega`` over the largest number of the
            family's constraints on any of its particles; momentum-conserving like Gauss-Seidel).
            Jacobi takes a few launches where Gauss-Seidel takes tens, and needs more iterations
            for the same accuracy (``tools/bench_pbd_peer.py`` measures the trade).
        omega: the Jacobi relaxation (> 0, <= 2; 1 is the safe averaging).
        stretch, bending, volume, tet_volume: constraint families (defaults: bending and global
            volume for surface-only bodies; tet edges and tet volumes for tet bodies).
        thickness: membrane/plate thickness of a surface-only body [m] (see ``wsim.pbd.model``).
        inflation: target volume / rest volume of the global volume constraint.
        stretch_compliance, bend_compliance, volume_compliance, tet_compliance: override the
            material-derived XPBD compliances.
        springs, spring_compliance: extra distance constraints (S, 2) and their compliance [m/N].
        damping: stiffness-proportional Rayleigh damping beta [s] of the edge, bending and tet
            constraints ([XPBD] Eq. 26; not the global volume constraint): a mode of angular
            frequency omega gets the damping ratio beta omega / 2. It damps deformation only.
        drag: air drag [1/s] on absolute velocities (does not conserve momentum; default 0).
        mass: total mass [kg] overriding rho * volume.
        pinned: particle indices held at their initial position.
        handles: kinematic ``Handle`` s.
        contact_margin: distance kept from colliders [m] (default 0). With a margin, place the body at
            least that far from colliders: overlap at the start is removed from the contacting
            particles without velocity, but the rest of the body still feels it as a push.
        friction: Coulomb coefficient against other bodies (the larger of the two bodies' values;
            None: ``wsim.contact.DEFAULT_FRICTION``, 0.5) and against colliders (the larger of it
            and the collider's, ``wsim.contact.collider_friction``; None: the collider's alone),
            as for BEM and EoL bodies. Give it here: a contact records it when the bodies come into
            reach (and a CUDA graph of their frame bakes it in).
        cache: store/load the built model through ``wsim.cache`` (True, False or an ``OperatorCache``).
        use_graph: replay each frame as a CUDA graph on CUDA devices.
        conserve_angular_momentum: after each substep, add to the free particles the rigid rotation
            increment that restores the angular momentum about the centre of mass the substep
            should have (the one it started with plus the angular impulse of contacts). XPBD's
            projection of the straight-line prediction is implicit Euler, which loses about
            (omega h)^2 of a body's spin per substep (10 rad/s at 300 substeps/s: 22 % per second);
            internal forces cannot change angular momentum, so this restores only what the
            integrator took. None (default): on for a body without pinned or driven particles
            (whose angular momentum is not conserved), off otherwise. Costs 3 launches per
            substep (two float64 block reductions and the update).
        velocities: (P, 3) initial particle velocities [m/s] (interior particles included; see
            ``particles()``), added to ``velocity`` and ``angular_velocity``; or use
            ``set_velocities`` once the body is in a World.
        merge_vertices: merge the mesh's vertices at the same position first (a file whose faces
            each have their own corners); particle indices (``pinned``, handles, ``tets``) and
            ``faces`` then refer to the merged vertices (the first of each coincident set, in order).
        allow_pieces: accept a mesh of several separate pieces and simulate them as one body (one
            particle system: they share the global volume constraint and the centre of mass).
            Otherwise such a mesh is refused: make one body per piece.
    """

    #: its particles share each correction with the BEM body they push (its give in translation
    #: and elastically: the World hands ``set_moving_surfaces`` its mass, centre of mass, inertia
    #: and impedance, ``kernels.pbd_contact.Give``)
    yielding_partners = True

    def __init__(
        self,
        mesh,
        material: ElasticMaterial | dict[str, Any] | None = None,
        *,
        name: str = "pbd_body",
        position: Sequence[float] = (0.0, 0.0, 0.0),
        rotation: Any = None,
        velocity: Sequence[float] = (0.0, 0.0, 0.0),
        angular_velocity: Sequence[float] = (0.0, 0.0, 0.0),
        tets: np.ndarray | str | None = None,
        interior_points: np.ndarray | None = None,
        substeps: int | None = None,
        dt: float | None = None,
        iterations: int = 2,
        solver: str = "gauss_seidel",
        omega: float = 1.0,
        stretch: bool = True,
        bending: bool | None = None,
        volume: bool | None = None,
        tet_volume: bool = True,
        thickness: float | None = None,
        inflation: float = 1.0,
        stretch_compliance: float | None = None,
        bend_compliance: float | None = None,
        volume_compliance: float | None = None,
        tet_compliance: float | None = None,
        springs: np.ndarray | None = None,
        spring_compliance: float = 0.0,
        damping: float = 1.0e-3,
        drag: float = 0.0,
        mass: float | None = None,
        pinned: Sequence[int] | np.ndarray | None = None,
        handles: Sequence[Handle] = (),
        contact_margin: float = 0.0,
        friction: float | None = None,
        cache: bool | OperatorCache = True,
        use_graph: bool = True,
        conserve_angular_momentum: bool | None = None,
        velocities: np.ndarray | None = None,
        merge_vertices: bool = False,
        allow_pieces: bool = False,
    ) -> None:
        super().__init__(name, velocity, angular_velocity)
        # a dict of ElasticMaterial's arguments is checked naming the body
        self.material = body_material(material, name, default=ElasticMaterial(E=1.0e5, nu=0.3, rho=1000.0))
        vertices, faces = wmesh.surface_arrays(mesh, name=f"body '{name}'", merge_vertices=merge_vertices)
        self.face_uv = wmesh.face_uvs(mesh)  # carried to the USD output (faces keep their order)
        self.face_color = wmesh.face_colors(mesh)
        # A closed surface must be valid as one (watertight, consistently outward). An open surface
        # (or bare particles) is allowed only when nothing needs an enclosed volume: mass given,
        # no global volume constraint. Several pieces only when asked for (allow_pieces).
        closed = len(faces) > 0 and not wmesh.has_boundary(faces)
        fixes = ("merge_vertices", "allow_pieces")
        if not closed and (mass is None or volume):
            wmesh.check_surface(vertices, faces, name=f"body '{name}'", closed=True, fixes=fixes)  # raises, naming the defect
        wmesh.check_surface(vertices, faces, name=f"body '{name}'", closed=closed, one_piece=not allow_pieces,
                            fixes=fixes)

        if substeps is not None and dt is not None:
            raise InvalidParameter(f"body '{name}': give substeps or dt, not both")
        if dt is not None:
            dt = float(dt)
            if not math.isfinite(dt) or dt <= 0.0:
                raise InvalidParameter(f"body '{name}': dt = {dt} s must be > 0")
        self.dt = dt
        self.substeps = positive_int(substeps, f"body '{name}': substeps") if substeps is not None else None
        if dt is None and substeps is None:
            self.substeps = 10
        self.iterations = positive_int(iterations, f"body '{name}': iterations")
        if solver not in SOLVERS:
            raise InvalidParameter(f"body '{name}': solver = {solver!r} must be one of {', '.join(SOLVERS)}")
        self.solver = solver
        self.omega = finite_number(omega, f"body '{name}': omega")
        if not 0.0 < self.omega <= 2.0:
            raise InvalidParameter(f"body '{name}': omega = {omega} must lie in (0, 2]")
        self.damping = finite_number(damping, f"body '{name}': damping [s]")
        self.drag = finite_number(drag, f"body '{name}': drag [1/s]")
        for what, val in (("damping", self.damping), ("drag", self.drag)):
            if val < 0.0:
                raise InvalidParameter(f"body '{name}': {what} = {val} must be >= 0")
        thickness = None if thickness is None else finite_number(thickness, f"body '{name}': thickness [m]")
        mass = None if mass is None else finite_number(mass, f"body '{name}': mass [kg]")
        inflation = finite_number(inflation, f"body '{name}': inflation")
        spring_compliance = finite_number(spring_compliance, f"body '{name}': spring_compliance [m/N]")

        offset = as_vec3(position, f"body '{name}': position")
        R0 = as_rotation(rotation, f"body '{name}': rotation")
        points = vertices
        if interior_points is not None:
            q = np.asarray(interior_points, dtype=np.float64).reshape(-1, 3)
            if not np.all(np.isfinite(q)):
                raise InvalidParameter(f"body '{name}': interior_points must be finite")
            points = np.concatenate([vertices, q])
        auto_tets = isinstance(tets, str)
        if auto_tets:
            if tets != "auto":
                raise InvalidParameter(f"body '{name}': tets must be None, 'auto' or a (T, 4) array")
            if interior_points is not None:
                raise InvalidParameter(f"body '{name}': tets='auto' makes its own interior points")
        tets_arr = None
        if tets is not None and not auto_tets:
            tets_arr = np.asarray(tets)
            if tets_arr.ndim != 2 or tets_arr.shape[1] != 4 or not np.issubdtype(tets_arr.dtype, np.integer):
                raise InvalidParameter(f"body '{name}': tets must be 'auto' or a (T, 4) array of particle indices")
            tets_arr = tets_arr.astype(np.int32)
        has_tets = auto_tets or (tets_arr is not None and len(tets_arr) > 0)
        options = dict(
            stretch=bool(stretch),
            bending=(not has_tets) if bending is None else bool(bending),
            volume=(closed and not has_tets) if volume is None else bool(volume),
            tet_volume=bool(tet_volume),
            thickness=thickness,
            inflation=float(inflation),
            stretch_compliance=stretch_compliance,
            bend_compliance=bend_compliance,
            volume_compliance=volume_compliance,
            tet_compliance=tet_compliance,
            spring_compliance=float(spring_compliance),
            mass=mass,
            closed=closed,
        )
        springs_arr = None
        if springs is not None:
            springs_arr = np.asarray(springs)
            if springs_arr.ndim != 2 or springs_arr.shape[1] != 2 or not np.issubdtype(springs_arr.dtype, np.integer):
                raise InvalidParameter(f"body '{name}': springs must be an (S, 2) array of particle indices")
            springs_arr = springs_arr.astype(np.int32)

        def build() -> dict[str, np.ndarray]:
            # tetrahedralization is the expensive part, so it happens inside the cached build
            pts, tt = wmesh.tetrahedralize(vertices, faces, name=f"body '{name}'") if auto_tets else (points, tets_arr)
            return build_model(
                pts, faces, len(vertices), self.material, tets=tt, springs=springs_arr, name=name, **options
            ).to_arrays()

        if cache is False:
            arrays = build()
        else:
            store = cache if isinstance(cache, OperatorCache) else OperatorCache()
            inputs = {"points": points, "faces": faces}
            if tets_arr is not None:
                inputs["tets"] = tets_arr
            if springs_arr is not None:
                inputs["springs"] = springs_arr
            arrays = store.get_or_build(
                "pbd_model",
                arrays=inputs,
                # n_surface: the same particles split differently into surface and interior differ
                params={"material": self.material.as_key(), "auto_tets": auto_tets, "n_surface": len(vertices), **options},
                version=MODEL_FORMAT_VERSION,
                build=build,
            )
        self.model: PbdModel = PbdModel.from_arrays(arrays)
        rest = self.model.rest_points
        if rotation is not None:
            com = self.model.mass @ rest / self.model.mass.sum()
            rest = (rest - com) @ R0.T + com
        self._rest = rest + offset
        n = self.model.n_particles

        kinematic = np.zeros(n, dtype=bool)
        self.pinned = np.zeros(0, dtype=np.int64)
        if pinned is not None:
            self.pinned = np.unique(as_indices(pinned, f"body '{name}': pinned"))
            if self.pinned.size and (self.pinned.min() < 0 or self.pinned.max() >= n):
                raise InvalidParameter(f"body '{name}': pinned indices must lie in [0, {n - 1}]")
            kinematic[self.pinned] = True
        self.handles = tuple(handles)
        for hdl in self.handles:
            if not isinstance(hdl, Handle):
                raise InvalidParameter(f"body '{name}': handles must be wsim.Handle objects")
            if hdl.vertices.min() < 0 or hdl.vertices.max() >= n:
                raise InvalidParameter(f"body '{name}': handle '{hdl.name}' indices must lie in [0, {n - 1}]")
            if np.any(kinematic[hdl.vertices]):
                raise InvalidParameter(f"body '{name}': handle '{hdl.name}' overlaps pinned vertices or another handle")
            kinematic[hdl.vertices] = True
        # how errors name each handle's motion: its name (unless the default) and its place in handles=
        self._handle_labels = [
            f"body '{name}': " + (f"handle '{h.name}' (handles[{i}])" if h.name != "handle" else f"handles[{i}]") + " motion"
            for i, h in enumerate(self.handles)
        ]
        self._kinematic_mask = kinematic
        self._handle_idx = (
            np.concatenate([h.vertices for h in self.handles]) if self.handles else np.zeros(0, dtype=np.int64)
        )
        if np.all(kinematic):
            raise InvalidParameter(f"body '{name}': every particle is pinned or driven; nothing to simulate")

        self.contact_margin = finite_number(contact_margin, f"body '{name}': contact_margin [m]")
        self.friction = None if friction is None else finite_number(friction, f"body '{name}': friction")
        if self.friction is not None and self.friction < 0.0:
            raise InvalidParameter(f"body '{name}': friction = {friction} must be >= 0")
        if self.contact_margin < 0.0:
            raise InvalidParameter(f"body '{name}': contact_margin = {contact_margin} m must be >= 0")
        self.use_graph = bool(use_graph)
        self.conserve_angular_momentum = (not np.any(kinematic)) if conserve_angular_momentum is None else bool(conserve_angular_momentum)
        self._initial_velocities = None
        if velocities is not None:
            vel = np.asarray(velocities, dtype=np.float64)
            if vel.shape != (n, 3) or not np.all(np.isfinite(vel)):
                raise InvalidParameter(f"body '{name}': velocities must be a finite ({n}, 3) array (one per particle)")
            self._initial_velocities = vel
        # CPU dispatch: one serial launch per family instead of one per colour (same result, fewer launches)
        self._cpu_serial_sweep = True
        # a frame with handles substep by substep (``_advance_pipelined``); False (the whole frame's
        # motions first) is kept for the tests that compare the two
        self._substep_pipeline = True
        # threads per block of the per-colour launches: measured on an H200 (posed 15k model), 32 gave
        # 3.61 ms/frame, 64: 3.77, 128: 3.88, 256: 4.17 (small latency-bound kernels spread wider)
        self._block_dim = 32
        # Gauss-Seidel: each hinge projects its own edge in its thread (``_fused_layout``); False
        # launches the edges as their own family (kept for the tests that compare the two)
        self._fuse_edges = True
        self._device: wp.Device | None = None

    # ---------------------------------------------------------------- public read-outs
    @property
    def faces(self) -> np.ndarray:
        return self.model.faces

    @property
    def masses(self) -> np.ndarray:
        """(P,) particle masses [kg] (pinned and driven particles included)."""
        return self.model.mass

    @property
    def rest_points(self) -> np.ndarray:
        """(P, 3) rest positions in world space (mesh plus ``position``) [m]."""
        return self._rest

    @property
    def x(self) -> wp.array:
        """(P,) device positions (``state.x``)."""
        return self.state.x

    @property
    def v(self) -> wp.array:
        """(P,) device velocities (``state.v``)."""
        return self.state.v

    def points(self) -> np.ndarray:
        self._require_bound()
        return self.x.numpy()[: self.model.n_surface].astype(np.float64)

    def particles(self) -> np.ndarray:
        """(P, 3) positions of every particle, interior ones included [m]."""
        self._require_bound()
        return self.x.numpy().astype(np.float64)

    def velocities(self) -> np.ndarray:
        """(P, 3) particle velocities [m/s]."""
        self._require_bound()
        return self.v.numpy().astype(np.float64)

    def set_velocities(self, velocities: np.ndarray) -> None:
        """Set every particle's velocity [m/s], (P, 3) in the order of ``particles()``; pinned and
        driven particles are set to 0 (they follow their pin or handle)."""
        self._require_bound()
        n = self.model.n_particles
        vel = np.asarray(velocities, dtype=np.float64)
        if vel.shape != (n, 3) or not np.all(np.isfinite(vel)):
            raise InvalidParameter(f"body '{self.name}': velocities must be a finite ({n}, 3) array (one per particle)")
        vel = vel.copy()
        vel[self._kinematic_mask] = 0.0
        self.state.v.assign(vel.astype(np.float32))

    def _free_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        free = ~self._kinematic_mask
        return self.masses[free], self.particles()[free], self.velocities()[free]

    def linear_momentum(self) -> np.ndarray:
        """Total linear momentum sum m v [kg m/s] (world) of the free particles (pinned and driven
        particles, whose motion is prescribed, are left out); float64 sums of the float32 state."""
        m, _, v = self._free_state()
        return (m[:, None] * v).sum(0)

    def center_of_mass(self) -> np.ndarray:
        """Centre of mass of the free particles [m] (world)."""
        m, x, _ = self._free_state()
        return (m[:, None] * x).sum(0) / m.sum()

    def angular_momentum(self, about: Sequence[float] | None = None) -> np.ndarray:
        """Total angular momentum sum m (x - p) x v [kg m^2/s] (world) of the free particles about
        the point p = ``about`` [m] (world), by default their current centre of mass."""
        m, x, v = self._free_state()
        p = (m[:, None] * x).sum(0) / m.sum() if about is None else as_vec3(about, f"body '{self.name}': about")
        return (m[:, None] * np.cross(x - p, v)).sum(0)

    def kinetic_energy(self) -> float:
        """Total kinetic energy 1/2 sum m |v|^2 [J] of the free particles."""
        m, _, v = self._free_state()
        return 0.5 * float((m * (v * v).sum(1)).sum())

    # ---------------------------------------------------------------- pushed by EoL bodies
    @property
    def mass(self) -> float:
        """Mass of the free particles [kg] (what a push moves)."""
        self._require_bound()
        return float(self.masses[~self._kinematic_mask].sum())

    def world_inertia(self) -> np.ndarray:
        """(3, 3) inertia tensor of the free particles about their centre of mass [kg m^2] (world)."""
        m, x, _ = self._free_state()
        r = x - (m[:, None] * x).sum(0) / m.sum()
        return (m * (r * r).sum(1)).sum() * np.eye(3) - (m[:, None] * r).T @ r

    def add_vertex_impulses(self, impulses: Any, duration: float) -> None:
        """Deliver momentum ``impulses`` [N s] (V, 3) per surface vertex (world axes): the World
        hands a PBD body what an EoL body pushed it with over the last coupling interval (the EoL
        QP takes the PBD body's rigid give, ``EolBody.set_moving_surfaces``). It is taken at the
        start of the body's next step, each surface particle's velocity changing by J / m at once
        (pinned and driven particles take none), so that the velocities read between steps are
        those the step ended with (taken at once, a box resting on an EoL box read g h = 9.8 mm/s
        upward at 1 ms intervals). ``duration`` [s] is that interval (checked, as for the other
        methods)."""
        self._require_bound()
        n = self.model.n_surface
        J = checked_vertex_impulses(self.name, impulses, n, duration)
        J = np.where(~self._kinematic_mask[:n, None], J, 0.0)
        self.state.push = self.state.push + J
        self.state.coupling_impulse = self.state.coupling_impulse + J.sum(axis=0)

    def _take_push(self) -> None:
        """Add the pending push (``add_vertex_impulses``) to the surface particles' velocities."""
        st = self.state
        if st is None or not np.any(st.push):
            return
        n = self.model.n_surface
        v = st.v.numpy()
        v[:n] += (st.push / self.masses[:n, None]).astype(np.float32)
        st.v.assign(v)
        st.push = np.zeros_like(st.push)

    @property
    def coupling_impulse(self) -> np.ndarray:
        """Momentum handed to the body by ``add_vertex_impulses`` so far [N s] (world)."""
        return np.zeros(3) if self.state is None else self.state.coupling_impulse.copy()

    # ---------------------------------------------------------------- set-up
    def signature(self) -> dict:
        return {**super().signature(), "particles": self.model.n_particles, "substeps": self.substeps, "dt": self.dt,
                "iterations": self.iterations, "material": self.material.as_key()}

    def substeps_for(self, frame_dt: float) -> int:
        """Substeps this body takes to cover ``frame_dt`` seconds: a frame, or a World coupling
        interval (``World(coupling_dt=...)``), which gets its share of the frame's substeps."""
        if self.dt is not None:
            return max(1, math.ceil(frame_dt / self.dt - 1e-9))
        full = getattr(self, "frame_dt", None)
        if full and frame_dt < full * (1.0 - 1e-9):
            return max(1, int(round(self.substeps * frame_dt / full)))
        return int(self.substeps)  # type: ignore[arg-type]

    def bind(self, device: wp.Device, gravity: np.ndarray, up: np.ndarray) -> None:
        if self._device is not None:
            raise InvalidParameter(f"body '{self.name}' already belongs to a World")
        self._device = device
        self._up = np.asarray(up, dtype=np.float64)
        self._gravity = wp.vec3(*np.asarray(gravity, dtype=np.float32))
        m = self.model
        n = m.n_particles
        mass = m.mass
        inv_mass = np.where(self._kinematic_mask, 0.0, 1.0 / mass)

        # initial state: rigid motion about the centre of mass of the free particles
        free = ~self._kinematic_mask
        com = (mass[free, None] * self._rest[free]).sum(0) / mass[free].sum()
        v0 = self.initial_velocity + np.cross(self.initial_angular_velocity, self._rest - com)
        if self._initial_velocities is not None:
            v0 = v0 + self._initial_velocities
        v0[self._kinematic_mask] = 0.0

        with wp.ScopedDevice(device):
            # in place on restore (set_state), so a recorded CUDA graph keeps pointing at them
            self.state = PbdState(x=wp.array(self._rest.astype(np.float32), dtype=wp.vec3),
                                  v=wp.array(v0.astype(np.float32), dtype=wp.vec3),
                                  push=np.zeros((m.n_surface, 3)), coupling_impulse=np.zeros(3))
            self.x_prev = wp.zeros(n, dtype=wp.vec3)
            self.x_pred = wp.zeros(n, dtype=wp.vec3)
            self.dx = wp.zeros(n, dtype=wp.vec3)  # corrections of the current substep (x = x_pred + dx)
            self.dxc = wp.zeros(n, dtype=wp.vec3)  # contact part of dx (its angular impulse is kept)
            # the Jacobi sweep's corrections (the Gauss-Seidel kernels get dx in its place, unused)
            self._acc = wp.zeros(n, dtype=wp.vec3) if self.solver == "jacobi" else self.dx
            self._moments = wp.zeros(2 * kp.MOMENT_SUMS, dtype=wp.float64)
            # the moments kernels sum per body ("segment"): one segment here (a ``PbdBatch`` has many)
            self._seg = wp.zeros(n, dtype=int)
            self._seg_first = wp.zeros(1, dtype=int)
            self._seg_count = wp.array([n], dtype=int)
            self._seg_stride = 0
            self._seg_restore = wp.ones(1, dtype=int)
            self.inv_mass = wp.array(inv_mass.astype(np.float32), dtype=float)
            self.flags = wp.zeros(2, dtype=int)
            # one multiplier array for every family: a single memset per substep resets them all
            # the constraints a projection can move (``ConstraintFamily.active``); the batch reads them too
            self._active_families = [a for a in (f.active(self._kinematic_mask) for f in m.families) if a.count]
            launched, edge = self._fused_layout(self._active_families)
            self._lam = wp.zeros(max(sum(f.count for f in launched), 1), dtype=float)
            self._families = []
            start = 0
            for f in launched:
                self._families.append(self._upload_family(f, self._lam[start : start + f.count]))
                start += f.count
            if edge is not None:  # each hinge projects its edge: the bending launches carry them
                hinge = next(f for f in self._families if f.kind == "bending")
                hinge.edge = wp.array(edge, dtype=wp.int32)
                hinge.edge_family = next(f for f in self._families if f.kind == "distance")
            if m.volume is not None:
                vol = m.volume
                self._vf_start = wp.array(vol.vertex_face_start, dtype=int)
                self._vf_pairs = wp.array(vol.face_pairs(m.faces), dtype=wp.vec2i)
                self._vol_grad = wp.zeros(m.n_surface, dtype=wp.vec3)
                # per iteration k: sums [V, sum w|grad V|^2] in slot k, multiplier before it in lam[k]
                # (two views of one buffer, so one memset per substep clears both)
                self._vol_buf = wp.zeros(3 * self.iterations + 1, dtype=wp.float64)
                self._vol_sums = self._vol_buf[: 2 * self.iterations]
                self._vol_lam = self._vol_buf[2 * self.iterations :]
            slots = np.full(n, -1, dtype=np.int32)  # particle -> its row among one substep's handle targets
            slots[self._handle_idx] = np.arange(len(self._handle_idx), dtype=np.int32)
            self._handle_slot = wp.array(slots, dtype=int)
            self._handle_targets_d = wp.zeros(1, dtype=wp.vec3)  # replaced by the frame layout when handles exist
        self._planes: list[tuple[np.ndarray, float, float]] = []  # (normal, height, friction)
        self._surfaces: Surfaces | None = None
        self._mesh_surfaces: list[int] = []
        self._mesh_colliders: list[_DeviceMeshCollider] = []
        self._layout: tuple[int, float] | None = None
        self._graph = None
        self._contact_mesh: wp.Mesh | None = None  # its surface, for contact with other bodies (wsim.pbd.contact)
        self._moving: list[_MovingSurface] = []  # other methods' bodies in reach this frame
        self._own_surface: _OwnSurface | None = None  # this body's surface, while there are moving ones
        self._surface_closed: bool | None = None  # whether it can keep other bodies' vertices out
        self._batch = None  # the PbdBatch that steps this body with others (``wsim.pbd.batch``), if any

    def attach_colliders(self, surfaces: Surfaces) -> None:
        self._surfaces = surfaces
        self._planes = []
        self._mesh_surfaces = []
        for i, c in enumerate(surfaces):
            plane = surfaces.plane(i)
            if plane is not None:
                self._planes.append((plane[0], plane[1], collider_friction(c.friction, self.friction)))
            else:
                self._mesh_surfaces.append(i)
        self._layout = None  # rebuild the per-frame buffers and the CUDA graph

    def _fused_layout(self, families: list[ConstraintFamily]) -> tuple[list[ConstraintFamily], np.ndarray | None]:
        """Gauss-Seidel with stretch and bending: each hinge projects its own edge's distance
        constraint just before itself, in the same thread (``kernels.pbd.solve_hinge_edge``). An
        edge's particles are two of its hinge's, so the hinge colouring holds both, and the edges
        that hinges take need no launches of their own: the posed 15k model launches 16 colours an
        iteration instead of 7 + 16. Returns the families to launch and each hinge's edge
        (``wsim.pbd.model.hinge_edge_layout``); the families unchanged and None without both
        kinds, for a tet body, with Jacobi, or with ``_fuse_edges`` off. The order of projection
        changes (an edge right before its hinge instead of all edges first), not what is
        projected."""
        kinds = {f.kind: f for f in families}
        # surface bodies only: a tet body's edges are mostly interior (and it may step in a batch)
        if not (self._fuse_edges and self.solver == "gauss_seidel" and "distance" in kinds and "bending" in kinds
                and "tet_volume" not in kinds):
            return families, None
        fused, edge = hinge_edge_layout(kinds["distance"], kinds["bending"], self.model.n_particles)
        return [fused if f is kinds["distance"] else f for f in families], edge

    def _upload_family(self, f: ConstraintFamily, lam: wp.array) -> _DeviceFamily:
        # Jacobi's scale counts every constraint of the model's family on a particle (the dropped
        # ones included, so that dropping them changes nothing)
        count = np.zeros(1)
        if self.solver == "jacobi":
            full = next(g for g in self.model.families if g.kind == f.kind)
            count = np.bincount(np.asarray(full.indices).ravel(), minlength=self.model.n_particles)
        return _DeviceFamily(
            kind=f.kind,
            offsets=f.offsets,
            indices=wp.array(f.indices, dtype=_VEC[f.indices.shape[1]]),
            rest=wp.array(f.rest.astype(np.float32), dtype=float),
            compliance=wp.array(f.compliance.astype(np.float32), dtype=float),
            lam=lam,
            count=wp.array(count.astype(np.float32), dtype=float),
        )

    def _prepare_layout(self, substeps: int, h: float) -> None:
        """(Re)allocate the per-frame input buffers for ``substeps`` substeps of ``h`` seconds."""
        device = self._device
        self._layout = (substeps, h)
        self._graph = None
        with wp.ScopedDevice(device):
            if self.handles:
                k = len(self._handle_idx)
                self._handle_targets_d = wp.zeros(substeps * k, dtype=wp.vec3)
                self._handle_targets_h = None  # made on the first frame whose motions are not all matrices
                # rigid motions (4x4 matrices) are applied on the device: only the matrices travel
                H = len(self.handles)
                self._handle_mats_d = wp.zeros(substeps * H, dtype=wp.mat44d)
                self._handle_mats_h = wp.zeros(substeps * H, dtype=wp.mat44d, device="cpu", pinned=device.is_cuda)
                self._staged = wp.Event(device) if device.is_cuda else None  # the staging copies' end
                self._handle_rest_d = wp.array(self._rest[self._handle_idx], dtype=wp.vec3d)
                self._handle_of_slot_d = wp.array(
                    np.repeat(np.arange(H), [len(hd.vertices) for hd in self.handles]).astype(np.int32), dtype=wp.int32)
            self._mesh_colliders = []
            for i in self._mesh_surfaces:
                c = self._surfaces[i]
                self._mesh_colliders.append(
                    _DeviceMeshCollider(
                        index=i,
                        friction=collider_friction(c.friction, self.friction),
                        mesh=c.device_mesh(device),
                        transforms=wp.zeros(substeps + 1, dtype=wp.mat44),
                        inverses=wp.zeros(substeps + 1, dtype=wp.mat44),
                        host_transforms=np.zeros((substeps + 1, 4, 4), dtype=np.float32),
                        host_inverses=np.zeros((substeps + 1, 4, 4), dtype=np.float32),
                        max_dist=2.0 * c.extent + 10.0 * self.contact_margin + 1.0,
                        closed=c.inside_test,
                    )
                )

    # ---------------------------------------------------------------- stepping
    @staticmethod
    def advance_together(bodies: Sequence[PbdBody], t0: float, t1: float, graphs: dict | None = None) -> None:
        """Advance PBD bodies of one World that may touch each other (``wsim.pbd.contact``);
        ``graphs``: the caller's store for what is kept between frames (the recorded lockstep
        frame, the broad phase's layout)."""
        from wsim.pbd.contact import advance_together

        advance_together(bodies, t0, t1, graphs)

    @staticmethod
    def step_sets(bodies: Sequence[PbdBody]) -> list:
        """The bodies of ``bodies`` that can step in one launch set, as batches
        (``wsim.pbd.batch``); bodies of no batch are not listed."""
        from wsim.pbd.batch import batches

        return batches(bodies)

    def advance(self, t0: float, t1: float) -> None:
        self._take_push()
        self._advance_frame(t0, t1)

    def _advance_frame(self, t0: float, t1: float) -> None:
        """The frame's substeps (a ``PbdBatch`` steps its members with it too)."""
        # (f + 1)/fps - f/fps differs from frame to frame in its last bits; round it so the
        # per-frame buffers and the CUDA graph (which bakes h in) are built once, not every frame
        frame_dt = round(t1 - t0, 12)
        substeps = self.substeps_for(frame_dt)
        h = frame_dt / substeps
        if self._layout != (substeps, h):
            self._prepare_layout(substeps, h)
        device = self._device
        # every launch goes to the body's device (Warp's default device may be another one)
        with wp.ScopedDevice(device):
            if self._substep_pipeline and self.handles:  # on every device: motions evaluated at one point
                self._advance_pipelined(t0, substeps, h)
                return
            self._upload_frame_inputs(t0, substeps, h)
            if device.is_cuda and self.use_graph:
                if self._graph is None:
                    self._load_modules()
                    # record the frame once
                    with wp.ScopedCapture(device=device) as capture:
                        self._launch_frame(substeps, h)
                    self._graph = capture.graph
                wp.capture_launch(self._graph)
            else:
                self._launch_frame(substeps, h)

    def _load_modules(self) -> None:
        """Compile and load the kernels' modules outside a CUDA-graph capture."""
        wp.load_module(kp, device=self._device)
        wp.load_module(kc, device=self._device)

    def _advance_pipelined(self, t0: float, substeps: int, h: float) -> None:
        """A frame of a body with handles, substep by substep: each substep's handle motions
        (Python callbacks, ~30 us each for the posed model's head) are evaluated just before the
        substep, on a GPU while it runs the substeps before it, and there each substep is a
        recorded CUDA graph. With the whole frame one graph the motions of all substeps ran
        first, with the GPU idle. A motion that reads the body sees the state after the substep
        before its own, on every device. A motion that fails leaves the body as the frame found
        it (positions and velocities restored) and raises, naming the frame."""
        device = self._device
        graphs = device.is_cuda and self.use_graph  # elsewhere (tests on the CPU) the same launches
        if not isinstance(self._graph, list):  # one graph a substep (reset with the frame's graph)
            if graphs:
                self._load_modules()
            self._graph = [None] * substeps
            self._frame_start = (wp.empty_like(self.state.x), wp.empty_like(self.state.v))
        self._upload_collider_poses(t0, substeps, h)
        wp.copy(self._frame_start[0], self.state.x)
        wp.copy(self._frame_start[1], self.state.v)
        try:
            for s in range(1, substeps + 1):
                self._upload_handle_targets(t0, substeps, h, s - 1, s)
                if not graphs:
                    self._substep(s, h)
                    continue
                if self._graph[s - 1] is None:
                    with wp.ScopedCapture(device=device) as capture:
                        self._substep(s, h)
                    self._graph[s - 1] = capture.graph
                wp.capture_launch(self._graph[s - 1])
        except BaseException:
            wp.copy(self.state.x, self._frame_start[0])  # after the substeps already launched
            wp.copy(self.state.v, self._frame_start[1])
            raise

    def _upload_frame_inputs(self, t0: float, substeps: int, h: float) -> None:
        """Copy this frame's handle targets and collider poses into the fixed device buffers."""
        if self.handles:
            self._upload_handle_targets(t0, substeps, h, 0, substeps)
        self._upload_collider_poses(t0, substeps, h)

    def _upload_handle_targets(self, t0: float, substeps: int, h: float, first: int, last: int) -> None:
        """The handle targets of substeps first .. last - 1 (0-based) of the frame from t0 into
        their slots of the device buffer (asynchronous on a GPU: the page-locked staging buffers
        are written again only once the last interval's copies out of them have run, which
        several intervals a frame (``World(coupling_dt=...)``) would otherwise overtake)."""
        rest = self._rest
        k = len(self._handle_idx)
        H = len(self.handles)
        if first == 0 and self._staged is not None:
            wp.synchronize_event(self._staged)
        poses = []
        for s in range(first, last):
            t = t0 + (s + 1) * h
            frame = self._frame_of(t)
            poses.append([hd.pose(t, (len(hd.vertices), 3), what, frame)
                          for hd, what in zip(self.handles, self._handle_labels)])
        if all(a.shape == (4, 4) for row in poses for a in row):
            # rigid motions: the matrices go to the device, which poses the rest positions
            mats = self._handle_mats_h.numpy()
            mats[first * H : last * H] = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
            wp.copy(self._handle_mats_d, self._handle_mats_h, dest_offset=first * H, src_offset=first * H,
                    count=(last - first) * H)
            wp.launch(kp.handle_targets, dim=(last - first) * k,
                      inputs=[self._handle_rest_d, self._handle_of_slot_d, self._handle_mats_d, H, first,
                              self._handle_targets_d])
        else:
            if self._handle_targets_h is None:
                self._handle_targets_h = wp.zeros(substeps * k, dtype=wp.vec3, device="cpu",
                                                  pinned=self._device.is_cuda)
            host = self._handle_targets_h.numpy()
            for s, row in zip(range(first, last), poses):
                host[s * k : (s + 1) * k] = np.concatenate(
                    [Handle.place(a, rest[hd.vertices]) for hd, a in zip(self.handles, row)])
            wp.copy(self._handle_targets_d, self._handle_targets_h, dest_offset=first * k, src_offset=first * k,
                    count=(last - first) * k)
        if last == substeps and self._staged is not None:
            wp.record_event(self._staged)

    def _upload_collider_poses(self, t0: float, substeps: int, h: float) -> None:
        """The mesh colliders' poses at the frame's substep boundaries into their device buffers."""
        for dc in self._mesh_colliders:
            for s in range(substeps + 1):
                M = self._surfaces.matrix(dc.index, t0 + s * h)
                dc.host_transforms[s] = M
                dc.host_inverses[s] = np.linalg.inv(M)
            dc.transforms.assign(dc.host_transforms)
            dc.inverses.assign(dc.host_inverses)

    def _launch_family(self, fam: _DeviceFamily, h: float) -> None:
        if fam.edge is not None:
            self._launch_hinge_edges(fam, h)
            return
        kernel = _KERNELS[fam.kind]
        args = [self.x_pred, self.dx, self.x_prev, self.inv_mass, fam.indices, fam.rest, fam.compliance, fam.lam]
        if self.solver == "jacobi":  # the whole family in one launch, then its corrections at once
            wp.launch(kernel, dim=int(fam.offsets[-1]),
                      inputs=[*args, 0, self.damping, h, self._acc, fam.count, self.omega])
            wp.launch(kp.apply_jacobi, dim=self.model.n_particles, inputs=[self.dx, self._acc])
            return
        tail = [self.damping, h, self._acc, fam.count, 0.0]
        if self._device.is_cpu and self._cpu_serial_sweep:
            # serial sweep over the colour-sorted array: same updates, same order, one launch
            if fam.offsets[-1] > 0:
                wp.launch(kernel, dim=int(fam.offsets[-1]), inputs=[*args, 0, *tail])
            return
        for c in range(len(fam.offsets) - 1):
            start, stop = int(fam.offsets[c]), int(fam.offsets[c + 1])
            wp.launch(kernel, dim=stop - start, inputs=[*args, start, *tail], block_dim=self._block_dim)

    def _launch_hinge_edges(self, fam: _DeviceFamily, h: float) -> None:
        """The hinges, each with its edge (``kernels.pbd.solve_hinge_edge``): one launch a colour,
        or one serial launch on the CPU (the same updates in the same order)."""
        e = fam.edge_family
        args = [self.x_pred, self.dx, self.x_prev, self.inv_mass, fam.indices, fam.rest, fam.compliance, fam.lam]
        tail = [self.damping, h, fam.edge, e.rest, e.compliance, e.lam]
        if self._device.is_cpu and self._cpu_serial_sweep:
            wp.launch(kp.solve_hinge_edge, dim=int(fam.offsets[-1]), inputs=[*args, 0, *tail])
            return
        for c in range(len(fam.offsets) - 1):
            start, stop = int(fam.offsets[c]), int(fam.offsets[c + 1])
            wp.launch(kp.solve_hinge_edge, dim=stop - start, inputs=[*args, start, *tail], block_dim=self._block_dim)

    def _launch_moments(self, base: int, n_blocks: int) -> None:
        args = [self.x, self.v, self.dxc, self.inv_mass, self._moments, base]
        if self._device.is_cpu:  # the CPU runs kernels serially anyway: one thread a body
            wp.launch(kp.moments_serial, dim=len(self._seg_first), inputs=[*args, self._seg_first, self._seg_count, self._seg_stride])
        else:
            wp.launch(kp.moments, dim=n_blocks, inputs=[*args, self._seg, self._seg_first, self._seg_stride],
                      block_dim=kp.MOMENT_BLOCK)

    def _launch_frame(self, substeps: int, h: float) -> None:
        for s in range(1, substeps + 1):
            self._substep(s, h)

    def _substep(self, s: int, h: float) -> None:
        """Substep s (1-based) of length h: prediction, the iterations, the velocity update."""
        self._substep_begin(s, h)
        for it in range(self.iterations):
            self._substep_iteration(s, it, h)
        self._substep_end(h)

    def _substep_begin(self, s: int, h: float) -> None:
        """Substep s (1-based) of length h: predict positions, reset the multipliers."""
        m = self.model
        n = m.n_particles
        k = len(self._handle_idx)
        wp.launch(
            kp.predict_positions,
            dim=n,
            inputs=[self.x, self.v, self.x_prev, self.x_pred, self.dx, self.inv_mass, self._handle_slot,
                    self._handle_targets_d, (s - 1) * k, self._gravity, self.drag, h],
        )
        if self._planes or self._mesh_colliders or self._contact_mesh is not None or self._moving:
            self.dxc.zero_()  # contact corrections of this substep (colliders and other bodies)
        S = self._layout[0]
        for ms in self._moving:
            if ms.yielding:
                wp.launch(kc.yielding_substep, dim=ms.cur.shape[0],
                          inputs=[ms.p0, ms.p1, float(s - 1) / S, float(s) / S, ms.give, ms.received_v, ms.area,
                                  1.0 / S, S * h, h, ms.u, ms.y, ms.prev, ms.cur])
            else:
                wp.launch(kc.lerp_points, dim=ms.cur.shape[0], inputs=[ms.p0, ms.p1, float(s - 1) / S, ms.prev])
                wp.launch(kc.lerp_points, dim=ms.cur.shape[0], inputs=[ms.p0, ms.p1, float(s) / S, ms.cur])
            ms.mesh.refit()
        if self.conserve_angular_momentum:
            self._moments.zero_()
            self._launch_moments(0, self._moment_blocks())
        self._lam.zero_()
        if m.volume is not None:
            self._vol_buf.zero_()

    def _moment_blocks(self) -> int:
        return -(-self.model.n_particles // kp.MOMENT_BLOCK) * kp.MOMENT_BLOCK

    def _substep_iteration(self, s: int, it: int, h: float) -> None:
        """Iteration ``it`` of substep s: the constraint families, the volume, the colliders."""
        m = self.model
        n = m.n_particles
        for fam in self._families:
            self._launch_family(fam, h)
        if m.volume is not None:
            vol = m.volume
            wp.launch(
                kp.volume_gradient,
                dim=-(-m.n_surface // kp.VOLUME_BLOCK) * kp.VOLUME_BLOCK,
                inputs=[self.x_pred, self.dx, self.inv_mass, self._vf_start, self._vf_pairs, self._vol_grad, self._vol_sums, it],
                block_dim=kp.VOLUME_BLOCK,
            )
            wp.launch(
                kp.volume_apply,
                dim=m.n_surface,
                inputs=[
                    self.dx,
                    self.inv_mass,
                    self._vol_grad,
                    self._vol_sums,
                    self._vol_lam,
                    it,
                    wp.float64(vol.target_volume),
                    wp.float64(vol.compliance),
                    wp.float64(h),
                ],
            )
        for normal, height, friction in self._planes:
            wp.launch(
                kc.ground_contact,
                dim=n,
                inputs=[self.dx, self.dxc, self.x_prev, self.x_pred, self.inv_mass, wp.vec3(*normal.astype(np.float32)), height, self.contact_margin, friction],
            )
        for dc in self._mesh_colliders:
            wp.launch(
                kc.mesh_contact,
                dim=n,
                inputs=[self.dx, self.dxc, self.x_prev, self.x_pred, self.inv_mass, dc.mesh.id, dc.transforms, dc.inverses, s, self.contact_margin, dc.max_dist, dc.friction, dc.closed],
            )
        for ms in self._moving:
            wp.launch(
                kc.moving_surface_contact,
                dim=m.n_surface,
                inputs=[self.x_pred, self.dx, self.dxc, self.x_prev, self.inv_mass, ms.mesh.id, ms.prev,
                        self.contact_margin, ms.reach, ms.friction, 1.0 / h, ms.impulse, ms.closed, ms.give,
                        ms.area, self._layout[0] * h, ms.count, ms.total],
            )
        if self._own_surface is not None:  # and their vertices out of this body's surface (``keep_out``)
            own = self._own_surface
            wp.launch(kc.surface_positions, dim=m.n_surface, inputs=[self.x_pred, self.dx, own.points])
            own.mesh.refit()
            for ms in (ms for ms in self._moving if ms.keep_out):
                wp.launch(
                    kc.moving_points_contact,
                    dim=ms.cur.shape[0],
                    inputs=[ms.cur, ms.prev, own.mesh.id, self.x_prev, self.dx, self.dxc, self.inv_mass,
                            ms.inv_mass_v, self.contact_margin, own.reach, ms.friction, 1.0 / h, ms.impulse,
                            own.closed, ms.give, ms.area, self._layout[0] * h, ms.count, ms.total],
                )
        for ms in self._moving:
            if ms.yielding:  # the partner yields to this iteration's push (``yielding_iteration``)
                wp.launch(kc.yielding_iteration, dim=ms.cur.shape[0],
                          inputs=[ms.impulse, ms.seen, ms.total, ms.give, ms.area, self._layout[0] * h, h, ms.count,
                                  ms.u, ms.y, ms.cur])
                ms.total.zero_()
                ms.mesh.refit()

    def set_moving_surfaces(self, surfaces: Sequence[tuple]) -> None:
        """Surfaces of other bodies that move on their own over the coming frame and may touch this
        one: (key, vertices at the frame start (V, 3), at its end (V, 3), faces (M, 3), friction[,
        vertex masses (V,) or None[, (mass, centre of mass (3,), inertia (3, 3) about it, world[,
        rho c_p of its material[, c_p, where the push engages the half-sphere its P wave reaches]])
        or None]]). Over the frame they move linearly between the two;
        this body's surface particles are kept out of them like out of a moving collider, and where
        the vertices' lumped masses are given (a BEM body's), those vertices out of this body's
        surface, if it is closed (a corner between particles;
        ``kernels.pbd_contact.moving_points_contact``). With the last part the surface yields to
        the change of this body's push, as a rigid body and elastically
        (``kernels.pbd_contact.moving_surface_contact``, ``yielding_iteration``); without it it is
        kinematic over the interval. The momentum that takes is collected per vertex
        (``moving_surface_impulses``) for the World to hand to their bodies. Called by the World
        before each ``advance``; an empty list ends the coupling."""
        self._require_bound()
        d = self._device
        masses = [s[5] if len(s) > 5 else None for s in surfaces]
        rigids = [s[6] if len(s) > 6 else None for s in surfaces]
        if self._surface_closed is None:  # the model's surface is fixed: asked once
            self._surface_closed = len(self.model.faces) > 0 and not wmesh.has_boundary(self.model.faces)
        layout = [(k, len(p0), len(f), self._surface_closed and m is not None, r is not None)
                  for (k, p0, _, f, *_), m, r in zip(surfaces, masses, rigids)]
        if layout != [(ms.key, ms.p0.shape[0], ms.indices.shape[0] // 3, ms.keep_out, ms.yielding)
                      for ms in self._moving]:
            self._graph = None  # the frame's launches change
            self._moving = []
            self._own_surface = self._build_own_surface() if any(lay[3] for lay in layout) else None
            for (key, p0, _, faces, mu, *_), lay, m in zip(surfaces, layout, masses):
                f32 = np.ascontiguousarray(faces, dtype=np.int32)
                test = wmesh.inside_test(f32)  # ray parity for one watertight piece (a third of the cost)
                cur = wp.array(np.asarray(p0, dtype=np.float32), dtype=wp.vec3, device=d)
                indices = wp.array(f32.ravel(), dtype=wp.int32, device=d)
                V = len(p0)
                yielding = lay[4]
                self._moving.append(_MovingSurface(
                    key=key, p0=wp.zeros(V, dtype=wp.vec3, device=d), p1=wp.zeros(V, dtype=wp.vec3, device=d),
                    prev=wp.zeros(V, dtype=wp.vec3, device=d), cur=cur,
                    indices=indices,
                    mesh=wp.Mesh(points=cur, indices=indices, support_winding_number=test == 1), friction=float(mu),
                    reach=0.0, impulse=wp.zeros(V, dtype=wp.vec3d, device=d), closed=test, keep_out=lay[3],
                    inv_mass_v=wp.array((1.0 / np.asarray(m, dtype=np.float64)).astype(np.float32), dtype=float,
                                        device=d) if lay[3] else None,
                    give=wp.zeros(1, dtype=kc.Give, device=d), total=wp.zeros(1, dtype=wp.vec3d, device=d),
                    count=wp.zeros(2, dtype=wp.int32, device=d), area=wp.zeros(V, dtype=wp.float64, device=d),
                    yielding=yielding))
                if yielding:
                    ms = self._moving[-1]
                    ms.u, ms.seen, ms.received_v = (wp.zeros(V, dtype=wp.vec3d, device=d) for _ in range(3))
                    ms.y = wp.zeros(V, dtype=wp.vec3, device=d)
                # how far from the surface a query looks (a particle deep inside is still found);
                # fixed with the launches, which a CUDA graph records
                self._moving[-1].reach = 2.0 * float(np.linalg.norm(np.ptp(p0, axis=0))) + self.contact_margin
        for ms, (_, p0, p1, faces, *_), rigid in zip(self._moving, surfaces, rigids):
            ms.p0.assign(np.asarray(p0, dtype=np.float32))
            ms.p1.assign(np.asarray(p1, dtype=np.float32))
            if ms.yielding:
                last = self.last_push(ms.key, len(p0))  # the last interval's push: it takes it over this one
                contacts = self.state.partner_contacts
                contacts = contacts[contacts[:, 0] == ms.key, 1]
                ms.count.assign(np.array([contacts[0] if len(contacts) else 0, 0], dtype=np.int32))
                self._set_give(ms, np.asarray(p1, dtype=np.float64), faces, rigid, last)
            ms.impulse.zero_()

    def _set_give(self, ms: _MovingSurface, p1: np.ndarray, faces: np.ndarray, rigid: tuple,
                  last: np.ndarray | None) -> None:
        """A yielding surface's give for the coming interval (``kernels.pbd_contact.Give``): its
        mass, impedance and P-wave speed (``kernels.pbd_contact.elastic_give``), and the push
        ``last`` of the interval before, which it takes over this one (``yielding_substep``); its
        yield starts at zero."""
        M, _, _, *more = rigid
        impedance = float(more[0]) if more else 0.0
        wave_speed = float(more[1]) if len(more) > 1 else 0.0
        R = np.zeros((len(p1), 3)) if last is None else np.asarray(last, dtype=np.float64)
        g = kc.Give()
        g.inv_mass = 1.0 / float(M)
        g.impedance = impedance if np.isfinite(impedance) else 0.0
        g.wave_speed = wave_speed if np.isfinite(wave_speed) and g.impedance > 0.0 else 0.0
        g.received = wp.vec3d(*R.sum(axis=0))
        ms.give.assign([g])
        ms.received_v.assign(R)
        ms.area.assign(wmesh.vertex_areas(p1, faces))
        ms.u.zero_()
        ms.y.zero_()
        ms.seen.zero_()

    def _surface_buffers(self) -> tuple[wp.array, wp.array, int]:
        """The surface's point buffer (refit from the particles before each use), its triangles and
        its inside test (ray parity for one watertight piece: a third of the winding number's
        cost), made once: the meshes of contact with other PBD bodies (``wsim.pbd.contact``) and
        of other bodies' vertices (``_build_own_surface``) are built on them."""
        if getattr(self, "_surface_arrays", None) is None:
            faces = np.ascontiguousarray(self.model.faces, dtype=np.int32)
            self._surface_arrays = (wp.zeros(self.model.n_surface, dtype=wp.vec3, device=self._device),
                                    wp.array(faces.ravel(), dtype=wp.int32, device=self._device),
                                    wmesh.inside_test(faces))
        return self._surface_arrays

    def _build_own_surface(self) -> _OwnSurface:
        """This body's surface as a Warp mesh (refit to the particles' current positions before
        each use), which the moving surfaces' vertices are kept out of (``moving_points_contact``)."""
        points, indices, test = self._surface_buffers()
        wp.copy(points, self.state.x, count=self.model.n_surface)
        # a vertex inside is at most the body's smallest width from its surface: a query looks that
        # far (1.5x for the body's deformation), and a vertex farther out costs no inside test
        reach = 1.5 * float(np.ptp(points.numpy(), axis=0).min()) + self.contact_margin
        mesh = wp.Mesh(points=points, indices=indices, support_winding_number=test == 1)
        return _OwnSurface(points=points, indices=indices, mesh=mesh, reach=reach, closed=test)

    def moving_surface_impulses(self) -> dict[int, np.ndarray]:
        """Momentum [N s] (V, 3) per vertex that each moving surface received from this body over
        the last frame (world axes), by key."""
        out = {ms.key: ms.impulse.numpy().copy() for ms in self._moving}  # (a view on the CPU)
        # what yielding partners take over the next interval (``set_moving_surfaces``)
        yielding = [ms for ms in self._moving if ms.yielding]
        self._keep_pushes({ms.key: out[ms.key] for ms in yielding})
        self.state.partner_contacts = np.array([(ms.key, int(ms.count.numpy()[0])) for ms in yielding],
                                               dtype=np.int64).reshape(-1, 2)
        return out

    def _substep_end(self, h: float) -> None:
        """Velocities from the positions; the angular momentum restored net of contact."""
        n = self.model.n_particles
        wp.launch(kp.update_velocities, dim=n, inputs=[self.x, self.x_pred, self.dx, self.v, 1.0 / h])
        if self.conserve_angular_momentum:
            self._launch_moments(kp.MOMENT_SUMS, self._moment_blocks())
            wp.launch(kp.restore_angular_momentum, dim=n,
                      inputs=[self.x, self.v, self.inv_mass, self._moments, wp.float64(1.0 / h), self._seg,
                              self._seg_first, self._seg_stride, self._seg_restore])

    def check_finite(self, frame: int, time: float) -> None:
        if self._batch is not None and self._batch.all_finite(self, frame, time):  # one check for the whole batch
            return
        self.flags.zero_()  # the array's own device
        wp.launch(kp.check_finite, dim=self.model.n_particles, inputs=[self.x, self.v, self.flags], device=self._device)
        bad = self.flags.numpy()
        if bad[0] or bad[1]:
            quantity = "positions" if bad[0] else "velocities"
            raise SimulationDiverged(self.name, frame, quantity, time)
