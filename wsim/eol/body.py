"""``EolBody``: an Eulerian-on-Lagrangian solid in a World (Fan, Litven, Levin, Pai; Algorithm 1).

State (``EolState``, ``self.state``; see ``wsim.eol.state``). An Eulerian grid in the
intermediate domain y stores the reference map z(y) (material coordinates, advected) and the
Eulerian velocity v at its nodes; Lagrangian coordinates carry the
grid through space: ``rigid`` x = R y + T (6 DOF, Eq. 1), ``affine`` x = A y + b (12 DOF, the
linear-modal case of Eq. 7 with the affine modes), or ``eulerian`` (frame fixed: the purely
Eulerian baseline of Fig. 7). The surface mesh and the material quadrature points live in the
material domain z; each step Algorithm 2 finds them in y.

One step (Table II's stages):

1. **forces**: Neo-Hookean forces and lumped masses from the material points (``sample_forces``),
   gravity, centrifugal and Coriolis loads (``node_velocities``): w_hat = w + dt a (Eq. 16).
2. **collision**: surface triangles inside a collider (Eq. 27, one-point quadrature).
3. **assembly** and **QP**: rows of Eq. (28) binned by a spatial collision grid; the QP of
   Eq. (29) by a primal-dual active set; its solution split as w_0 + dt w_1 (Eq. 31).
4. **LS**: the least-squares momentum split (Eqs. 23-25, 32) of w_0 and w_1 into Lagrangian
   velocities and Eulerian residuals v*_0, v*_1; dt from Eq. (33), capped by the frame and the
   explicit elastic limit.
5. **advect**: v* advected by itself (v^{t+1}), the reference map advected by v^{t+1}
   (Algorithm 1 steps 2-4, written for z = y - u), the Lagrangian pose integrated.
6. **track**: Algorithm 2 for the material points and the surface; **plasticity** (Eqs. 34-37).

Precision: float64 everywhere on the grid (strain is a difference of nearby absolute coordinates;
the paper's J-bar and LS sums are ill-conditioned in float32). Contact with colliders is the
paper's volume constraint, plus Coulomb friction at the grid nodes its rows push (the paper's is
frictionless). Other methods' bodies' surfaces (``set_moving_surfaces``, issue 18) get the same
rows and friction. EoL bodies that
may touch step together with one dt and one QP across them (``advance_group``, the paper's Eq. 29
across objects; the rows between them in ``wsim.eol.pairs``).
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Callable, Iterator, Sequence

import numpy as np
import trimesh
import warp as wp

from wsim import mesh as wmesh
from wsim.body import Body, VertexImpulses
from wsim.colliders import Surfaces
from wsim.contact import collider_friction
from wsim.eol import pairs
from wsim.eol.advection import advect_arrays, check_scheme, extend_reference_map
from wsim.eol.contact import (ContactRows, ContactSolution, ContactSystem, block_nodes, rows_from_blocks, solve_contact,
                              surface_samples)
from wsim.eol.elastic import I3, hourglass_forces, inverse_mat33, mat33, sample_forces, viscous_forces
from wsim.eol.grid import EolGrid, make_grid, material_samples
from wsim.eol.split import split_on_device, unpack_fields
from wsim.eol.state import EolState
from wsim.eol.timestep import adaptive_dt, elastic_dt_limit
from wsim.eol.tracking import track_points
from wsim.errors import InvalidParameter, SimulationDiverged
from wsim.kernels import eol_contact as kc
from wsim.kernels import eol_loads as kl
from wsim.kernels import eol_plastic as kp
from wsim.kernels import eol_step as ks
from wsim.kernels import mesh as km
from wsim.kernels.eol_grid import grid_struct
from wsim.launch import Launcher
from wsim.materials import ElasticMaterial, body_material
from wsim.rigid import advance_pose, cross_matrix, point_inertia, rigid_fit
from wsim.validate import as_rotation, as_vec3, call_user, callback_array, finite_number, positive_int

if TYPE_CHECKING:
    from wsim.colliders import Collider

LAGRANGIAN = ("rigid", "affine", "eulerian")
# layers of empty nodes around the material into which z is continued each step: advection samples
# at most cfl (< 1) cells upstream and the surface lies within a cell of the material points, so
# two would do; the third keeps a node that loses its material consistent for one more step
EXTEND_LAYERS = 3
READ_LOAD = 8 + ks.FIELDS  # where the loads' delivered force sits in a step's read-back (``_readout``)
STAGES = ("forces", "collision", "assembly", "qp", "ls", "advect", "track", "plasticity")


@dataclass(eq=False)
class _MovingSurface:
    """Another body's surface this body may touch during one ``advance`` (``set_moving_surfaces``):
    its vertices at the start and end (world, float64), where they are now (float32, the Warp
    mesh's points), their velocity, and the impulse this body gives them (per vertex, world)."""

    key: int
    p0: wp.array
    p1: wp.array
    cur: wp.array
    mesh: wp.Mesh
    n_faces: int
    impulse: wp.array  # the normal part, summed on the device
    step_impulse: wp.array
    step_weight: wp.array
    velocity: wp.array
    mu: float = 0.0
    reach: float = 0.0
    closed: int = 1  # the inside test of ``kernels.mesh.query_inside`` (``wsim.mesh.inside_test``)
    hits: Any = None  # ``kernels.eol_contact.SurfaceHits`` of this body's contact samples
    vhits: Any = None  # ``kernels.eol_contact.VertexHits`` of its vertices inside this body's surface
    varea: wp.array | None = None  # its vertices' lumped areas [m^2] (``vertex_rows``)
    box: tuple | None = None  # (min, max) of its vertices over the advance (world)
    vactive: bool = False  # whether this step's ``vertex_rows`` ran for it (its ``vhits`` are current)
    rigid: tuple | None = None  # (1 / M, I^-1 (world), com at the end, mean shift over the advance): it yields
    wrench: wp.array | None = None  # per row, what a unit multiplier does to it (``partner_wrenches``)
    push: wp.array | None = None  # a step's reaction as momentum and angular momentum (``partner_push``)
    p0_host: np.ndarray | None = None
    p1_host: np.ndarray | None = None
    G: np.ndarray | None = None  # the rigid fit of its motion, v = G x + g (world), for friction
    g: np.ndarray | None = None
    friction: np.ndarray | None = None  # friction impulse this body took from it this step (world)
    friction_moment: np.ndarray | None = None  # its moment about the world origin
    friction_impulse: np.ndarray | None = None  # (V, 3) the friction part handed to it over the advance
    received: tuple = (np.zeros(3), np.zeros(3))  # that push as momentum and angular momentum (its ``rigid`` com)
    received_v: wp.array | None = None  # that push per vertex, on the device (the elastic give's)
    impedance: float | None = None  # rho c_p of its material [kg / (m^2 s)]: its elastic give (``partner_compliance``)
    pre_share: float = 0.0  # the share of ``received`` taken off its velocity before this step (``_expect_partners``)


@dataclass(frozen=True)
class Plasticity:
    """Plastic flow of Eqs. (34-37).

    Args:
        yield_stress: ||dev tau|| [Pa] (Frobenius norm of the deviatoric Kirchhoff stress) below
            which the material is elastic.
        flow_rate: [1/s]; the fraction gamma of Eq. (37) removed per step is
            min(1, flow_rate dt (1 - yield/||dev tau||)).
    """

    yield_stress: float
    flow_rate: float = 100.0

    def __post_init__(self) -> None:
        y = finite_number(self.yield_stress, "Plasticity: yield_stress [Pa]")
        f = finite_number(self.flow_rate, "Plasticity: flow_rate [1/s]")
        if y < 0.0:
            raise InvalidParameter(f"Plasticity: yield_stress = {y} Pa must be >= 0")
        if f <= 0.0:
            raise InvalidParameter(f"Plasticity: flow_rate = {f} 1/s must be > 0")


@dataclass
class StepRecord:
    """One EoL step: its start time and dt [s], contact rows and active rows, LS residual max |v*| [m/s],
    the overlap volume with the colliders at its start [m^3], the QP's active-set iterations (51:
    the active set cycled and the NNLS fallback solved it), and the step the caps allowed there
    [s] (the advance's equal split within the elastic limit and ``dt_max``: dt below it is Eq.
    33's, or the QP's guess)."""

    time: float
    dt: float
    rows: int
    active: int
    v_star: float
    overlap: float = 0.0
    qp_iterations: int = 0
    cap: float = math.inf


class EolBody(VertexImpulses, Body):
    """An Eulerian-on-Lagrangian solid.

    Args:
        mesh: closed, outward-oriented surface of one piece (trimesh or (vertices, faces)) in world
            coordinates [m]; make one body per piece.
        material: compressible ``ElasticMaterial`` (elastic forces are explicit), or a dict of its
            arguments (``dict(E=5e4, nu=0.3, rho=500.0)``), checked naming the body.
        resolution: grid cells along the longest side of the body's bounding box (>= 4).
        lagrangian: "rigid" (6 DOF), "affine" (12 DOF) or "eulerian" (no Lagrangian motion).
        advection: "semi-lagrangian" (first order, the paper's) or "bfecc" (second order on smooth
            fields, 3x cost; limited so it adds no extrema: unlimited, it overshoots at contacts).
        cfl: alpha of Eq. (30), in (0, 1): the Eulerian velocity moves at most this many cells per step.
        plasticity: a :class:`Plasticity`, or None for a purely elastic body.
        padding: empty cells around the body at the start (room for Eulerian deformation). Where
            material comes within a cell of the grid's boundary (a soft body squashed on impact
            bulges sideways by more than the padding), the grid grows on that side by
            ``max(2, padding)`` cells, up to 3x its first size per axis (``grid``, and the state's
            ``grid_grown``); node values are copied exactly, so growing changes nothing else.
        dt_max: cap on the step [s] besides the frame and the elastic limit (None: none).
        elastic_safety: the elastic cap is this fraction of h / c1 (P-wave cell crossing time).
            0.5 (default). Each advance (a frame, or a coupling interval) is split into equal
            steps no longer than the caps (``advance_group``). Taken to the cap with the
            remainder last, the steps repeated a pattern every advance, and an explicit step
            under a periodically varying dt pumps a mode that it holds at a fixed one: a free,
            undamped box (0.3 x 0.2 x 0.15 m, E = 1e5, 8 cells) given a small random velocity
            field gained 35x its energy in 4 s at 0.5, and a PBD ball on an EoL block drove the
            block's sliver nodes to 4 m/s. With equal steps the box decays at 0.5 and at 0.7;
            at 1.0 it grows (``tools/results/study_eol_even_steps.jsonl``).
        quadrature: material points per cell axis (Gauss-Legendre).
        collision_block: edge of a collision cell, in cells of the body's grid (an integer >= 1): one
            contact row per collider and collision cell. Larger blocks: fewer rows and a cheaper QP
            (O(m^3) in the rows m), coarser resolution of the overlap along the surface
            (``tools/bench_eol.py`` measures both). None (default): ``resolution // 16`` (at least
            1), a collision cell of about 1/16 of the body, which the paper leaves unspecified. Two
            32-cell spheres squashing (``scenes/eol_two_spheres.py``) had ~100 active rows per step
            at 1 and ~40 at 2, with the same deepest interpenetration (6.2 and 6.5 mm, h = 16 mm)
            and momentum error (``tools/results/profile_eol_collision_block_h100.jsonl``).
        contact_spacing: the largest spacing of the surface's contact samples, in cells h: a triangle
            wider than this is subdivided (one sample per sub-triangle), so a coarse mesh cannot
            slip through a collider between its triangle centroids.
        contact_relaxation: time [s] over which overlap already present is pushed out (b -= vol / tau).
        track_tol: Algorithm 2 tolerance, as a fraction of h.
        fictitious: include the centrifugal and Coriolis loads on the Eulerian velocities.
        damping: Kelvin-Voigt viscosity eta [Pa s] of the deformation (0: none; the paper states
            none, and then only advection dissipates). Explicit: it adds the cap rho h^2 / (12 eta),
            which holds for nodes of full cells; next to nodes holding a sliver of material (at the
            ``mass_floor``) the viscosity is cut until their explicit step is as stable as a full
            node's (kernel ``viscous_forces``; momentum stays exact).
        mass_floor: every node with material has at least mass_floor rho h^3 (a small phantom mass).
            A node whose support holds a sliver of material (a quadrature point in the far corner
            of its cell) is otherwise flung by stress gradients and by contact impulses, which
            the QP finds cheapest to apply there: huge Eulerian velocity, collapsing dt. The floor
            is used consistently (forces, split, QP, momentum), so momentum stays exact; the
            phantom mass is reported by ``node_masses`` (0.02: about 0.5 % at 8 cells across a sphere).
        split: norm of the least-squares momentum split (Eq. 23): "uniform" (the paper's 2-norm
            over nodes, smallest max-type Eulerian velocity) or "mass" (the mass-weighted norm:
            the Eulerian velocities then carry no net linear or angular momentum, so advection
            error cannot change the body's momentum to first order; the default).
        profile: synchronize the device after each stage so ``timings`` splits GPU time by stage.
        position: translation applied to the mesh [m] (like PbdBody and BemBody; ``rotation`` turns
            the mesh about its centre of mass).
        velocity_field: ``fn(x)`` -> (n, 3) initial world velocities [m/s] at the (n, 3) world rest
            positions x of the grid nodes that hold material, added to ``velocity`` and
            ``angular_velocity``; the body's least-squares split puts its rigid (affine) part into
            the frame and leaves the rest as Eulerian velocity (a rigid field: v = 0 exactly).
        coriolis: "midpoint" (default: the Coriolis term -2 L v at the step's midpoint velocity,
            ``eol_step.coriolis_matrix``) or "explicit" (forward Euler, the earlier scheme).
        hourglass: hourglass control of cells the material points under-integrate (a thin part's
            cells hold one or two of them), as a fraction of the shear modulus (0: off; see
            ``eol_elastic.hourglass_forces``). Fully integrated cells get none. It keeps the
            nodes that hold a sliver of material from ringing: a ball resting on the ground 5 s
            has them at 0.04 m/s with it and 1.9 m/s without (``tools/study_eol.py``). Since the
            contact rows push thin parts out from both faces (``pushed_area``) the landings do
            not need it (a bunny, a fish at 24-60 fps, boxes complete without). It doubles the
            amplitude decay of a breathing sphere (0.49/s against 0.26/s at 12 cells; README
            "EoL solids").
        friction: Coulomb coefficient against other bodies (the larger of the two bodies' values,
            ``wsim.contact.pair_friction``; None counts as ``wsim.contact.DEFAULT_FRICTION``) and
            colliders (the larger of it and the collider's, ``wsim.contact.collider_friction``;
            None: the collider's). Friction acts at the grid
            nodes the contact rows push (``kernels.eol_contact.node_friction``), relative to the
            collider's or surface's motion; the paper's contact is frictionless (a frictionless
            collider, ``friction=0``, gives it).
        merge_vertices: merge the mesh's vertices at the same position first (a file whose faces
            each have their own corners); ``faces`` and vertex indices then refer to the merged ones.

    Loads: ``add_traction`` (surface tractions [Pa], world axes), ``add_body_force`` (accelerations
    [m/s^2]); ``load_impulse`` is the momentum they delivered. A body that starts more than half a
    cell inside a collider is refused at its first step (``InvalidParameter``); one whose material
    needs a grid larger than 3x its first size on an axis (it flies apart) stops the run
    (``SimulationDiverged``, "material left the grid").
    """

    #: its rows against another method's body share each correction with that body's rigid give
    #: (the World hands ``set_moving_surfaces`` its mass, centre of mass and inertia)
    yielding_partners = True

    def __init__(
        self,
        mesh: Any,
        material: ElasticMaterial | dict[str, Any],
        *,
        resolution: int = 32,
        lagrangian: str = "rigid",
        advection: str = "semi-lagrangian",
        cfl: float = 0.5,
        plasticity: Plasticity | None = None,
        name: str = "eol_body",
        rotation: Any = None,
        velocity: Sequence[float] = (0.0, 0.0, 0.0),
        angular_velocity: Sequence[float] = (0.0, 0.0, 0.0),
        padding: int = 2,
        dt_max: float | None = None,
        elastic_safety: float = 0.5,
        quadrature: int = 2,
        collision_block: int | None = None,
        contact_spacing: float = 1.0,
        contact_relaxation: float = 0.05,
        track_tol: float = 1e-9,
        fictitious: bool = True,
        damping: float = 0.0,
        mass_floor: float = 0.02,
        split: str = "mass",
        profile: bool = False,
        position: Sequence[float] = (0.0, 0.0, 0.0),
        velocity_field: Callable[[np.ndarray], Any] | None = None,
        coriolis: str = "midpoint",
        friction: float | None = None,
        hourglass: float = 0.1,
        merge_vertices: bool = False,
    ) -> None:
        super().__init__(name, velocity, angular_velocity)
        p = f"body '{name}'"
        self.friction = None if friction is None else finite_number(friction, f"{p}: friction")
        if self.friction is not None and self.friction < 0.0:
            raise InvalidParameter(f"{p}: friction = {friction} must be >= 0")
        self._offset = as_vec3(position, f"{p}: position [m]")
        if velocity_field is not None and not callable(velocity_field):
            raise InvalidParameter(f"{p}: velocity_field must be a callable fn(x) -> (n, 3) velocities [m/s], "
                                   f"got {type(velocity_field).__name__}")
        self._velocity_field = velocity_field
        if coriolis not in ("midpoint", "explicit"):
            raise InvalidParameter(f"{p}: coriolis = {coriolis!r} must be 'midpoint' or 'explicit'")
        self.coriolis = coriolis
        self._tractions: list[Callable[[float], Any]] = []
        self._point_forces: list[Callable[[float, np.ndarray], Any]] = []
        self._accelerations: list[Callable[[float], Any]] = []
        material = body_material(material, name)  # a dict of ElasticMaterial's arguments is checked naming the body
        if material.incompressible:
            raise InvalidParameter(f"{p}: material '{material.name}' is incompressible; EoL elasticity is explicit and "
                                   "needs a compressible material (nu < 0.5)")
        if lagrangian not in LAGRANGIAN:
            raise InvalidParameter(f"{p}: lagrangian = {lagrangian!r} must be one of {', '.join(LAGRANGIAN)}")
        check_scheme(advection, f"{p}: advection")
        cfl_f = finite_number(cfl, f"{p}: cfl")
        if not 0.0 < cfl_f < 1.0:
            raise InvalidParameter(f"{p}: cfl = {cfl_f} must be in (0, 1) (Eq. 30 of first-order advection)")
        if split not in ("mass", "uniform"):
            raise InvalidParameter(f"{p}: split = {split!r} must be 'mass' or 'uniform'")
        self.split = split
        if plasticity is not None and not isinstance(plasticity, Plasticity):
            raise InvalidParameter(f"{p}: plasticity must be a wsim.eol.Plasticity or None")
        padding = positive_int(padding, f"{p}: padding")
        quadrature = positive_int(quadrature, f"{p}: quadrature")
        if collision_block is None:
            collision_block = max(1, positive_int(resolution, f"{p}: resolution") // 16)
        collision_block = positive_int(collision_block, f"{p}: collision_block")
        if dt_max is not None:
            dt_max = finite_number(dt_max, f"{p}: dt_max [s]")
            if dt_max <= 0.0:
                raise InvalidParameter(f"{p}: dt_max = {dt_max} s must be > 0")
        elastic_safety = finite_number(elastic_safety, f"{p}: elastic_safety")
        if elastic_safety <= 0.0:
            raise InvalidParameter(f"{p}: elastic_safety = {elastic_safety} must be > 0")
        self._positive = {k: finite_number(v, f"{p}: {k}") for k, v in
                          (("contact_relaxation", contact_relaxation), ("track_tol", track_tol),
                           ("contact_spacing", contact_spacing))}
        for k, v in self._positive.items():
            if v <= 0.0:
                raise InvalidParameter(f"{p}: {k} = {v} must be > 0")
        self.damping = finite_number(damping, f"{p}: damping [Pa s]")
        self.hourglass = finite_number(hourglass, f"{p}: hourglass")
        if self.hourglass < 0.0:
            raise InvalidParameter(f"{p}: hourglass = {hourglass} must be >= 0")
        floor = finite_number(mass_floor, f"{p}: mass_floor")
        if self.damping < 0.0 or not 0.0 <= floor <= 1.0:
            raise InvalidParameter(f"{p}: damping must be >= 0 and mass_floor in [0, 1]")
        vertices, faces = wmesh.surface_arrays(mesh, p, merge_vertices=merge_vertices)
        self.face_uv = wmesh.face_uvs(mesh)  # carried to the USD output (faces keep their order)
        self.face_color = wmesh.face_colors(mesh)
        wmesh.check_surface(vertices, faces, name=p, closed=True, one_piece=True, fixes=("merge_vertices",))
        self.grid = make_grid(vertices, resolution, padding)  # validates the resolution; grows with the body (_regrid)
        self.resolution = int(resolution)
        self.padding = padding
        self.quadrature = quadrature
        self.material = material
        self.lagrangian = lagrangian
        self.advection = advection
        self.cfl = cfl_f
        self.plasticity = plasticity
        self.dt_max = dt_max
        self.fictitious = bool(fictitious)
        self.profile = bool(profile)
        self.collision_block = int(collision_block)
        self._R0 = as_rotation(rotation, f"{p}: rotation")
        self._faces = faces.astype(np.int32)
        # The tracked surface: the mesh with every edge longer than contact_spacing h split
        # (trimesh keeps the given vertices first). Contact samples and their velocities are then
        # tracked material points at the grid's resolution; on a coarse mesh (a box of 8 vertices)
        # samples interpolated across a big triangle moved with its corners, not with the
        # material under them, and the corners sank 2.5 cells into the ground (issue 16).
        spacing = self._positive["contact_spacing"] * self.grid.h
        tracked, self._tracked_faces = vertices, self._faces
        if len(faces) and np.linalg.norm(vertices[faces[:, [1, 2, 0]]] - vertices[faces], axis=2).max() > spacing:
            tracked, tf = trimesh.remesh.subdivide_to_size(vertices, faces, spacing)
            self._tracked_faces = np.asarray(tf, dtype=np.int32)
        self._n_surface = len(vertices)
        samples = material_samples(self.grid, vertices, faces, per_axis=quadrature)
        if len(samples.weights) == 0:
            raise InvalidParameter(f"{p}: no material point inside the mesh at resolution {resolution}")
        # the intermediate domain is centred on the centre of mass: rigid rotations turn about it
        self.com = samples.points.mean(axis=0)
        self.grid = self._grid0 = replace(self.grid, origin=self.grid.origin - self.com)
        self._z_points = samples.points - self.com
        self._volumes = samples.weights
        self._z_vertices = np.asarray(tracked, dtype=np.float64) - self.com  # the given vertices first
        self.mass = material.rho * float(samples.weights.sum())
        self.elastic_safety = float(elastic_safety)
        self.dt_elastic = elastic_dt_limit(self.grid.h, material, self.elastic_safety)
        if self.damping > 0.0:  # explicit viscosity: diffusion number eta dt / (rho h^2) <= 1/12
            self.dt_elastic = min(self.dt_elastic, material.rho * self.grid.h**2 / (12.0 * self.damping))
        self._mass_floor = floor * material.rho * self.grid.h**3
        self._coupling_load = False  # whether add_vertex_impulses' load is registered
        self.timings = {k: 0.0 for k in STAGES}
        self.history: list[StepRecord] = []  # diagnostics of every step (not state)
        self.state: EolState | None = None

    # -- read-outs -------------------------------------------------------------------------
    @property
    def faces(self) -> np.ndarray:
        return self._faces

    @property
    def rest_vertices(self) -> np.ndarray:
        """(V, 3) material-space vertex positions (centred on the centre of mass) [m]."""
        return self._z_vertices[: self._n_surface]

    @property
    def frame(self) -> tuple[np.ndarray, np.ndarray]:
        """(F_L, T): the Lagrangian map x = F_L y + T (F_L = R rigid, A affine, I Eulerian)."""
        self._require_bound()
        return self.state.F.copy(), self.state.T.copy()

    @property
    def time(self) -> float:
        """The body's time [s] (0 before ``bind``)."""
        return 0.0 if self.state is None else self.state.time

    @property
    def steps(self) -> int:
        """Steps taken so far."""
        return 0 if self.state is None else self.state.steps

    @property
    def contact_impulse(self) -> np.ndarray:
        """Momentum delivered by contact so far [kg m/s] (world): the colliders' push and friction,
        and this body's own rows against other bodies (other EoL bodies; PBD and BEM surfaces it
        pushes, ``set_moving_surfaces``). What a pusher of another method hands this body one
        interval later is in ``coupling_impulse``."""
        return np.zeros(3) if self.state is None else self.state.contact_impulse

    @property
    def gravity_impulse(self) -> np.ndarray:
        """Momentum delivered by gravity so far [kg m/s] (world)."""
        return np.zeros(3) if self.state is None else self.state.gravity_impulse

    @property
    def _failure(self) -> tuple[str, str, str] | None:
        return None if self.state is None else self.state.get_failure()

    @_failure.setter
    def _failure(self, value: tuple[str, str, str] | None) -> None:
        self.state.set_failure(value)

    def signature(self) -> dict[str, Any]:
        """The base signature plus the settings that change the meaning of the state."""
        sig = super().signature()
        sig.update(resolution=self.resolution, padding=self.padding, quadrature=self.quadrature,
                   grid_cells=[int(c) for c in self._grid0.cells], lagrangian=self.lagrangian, advection=self.advection,
                   plastic=self.plasticity is not None, split=self.split, collision_block=self.collision_block,
                   material=self.material.as_key())
        if self.plasticity is not None:
            sig.update(yield_stress=self.plasticity.yield_stress, flow_rate=self.plasticity.flow_rate)
        return sig

    def set_state(self, arrays: dict[str, np.ndarray]) -> None:
        """``Body.set_state`` on a grid grown as the saved state's was (``grid_grown``); a state
        that does not fit leaves the body as it was."""
        self._require_bound()
        grown = np.asarray(arrays.get("grid_grown", self.state.grid_grown), dtype=np.int64).reshape(-1)
        before = self.state.grid_grown.copy()
        if grown.shape != before.shape or np.array_equal(grown, before):
            super().set_state(arrays)
            return
        kept = self.get_state()
        self._regrid(grown)
        try:
            super().set_state(arrays)
        except Exception:
            self._regrid(before)
            super().set_state(kept)
            raise

    def _state_loaded(self) -> None:
        """Forces, lumped masses and elastic energy of the loaded state (what the last step's force pass left)."""
        if self.state.coupling_until >= 0.0:  # a restored push still to deliver
            self._register_coupling()
        self._views.clear()  # the state may hold new arrays
        self._forget_finish()
        self._force_pass()

    def intermediate_vertices(self) -> np.ndarray:
        """(V, 3) surface vertices in the intermediate domain y (Algorithm 2) [m]."""
        self._require_bound()
        return self.state.y_vertices.numpy()[: self._n_surface]

    def points(self) -> np.ndarray:
        return self.intermediate_vertices() @ self.state.F.T + self.state.T

    def eulerian_velocity(self) -> np.ndarray:
        """(n_nodes, 3) Eulerian velocities v [m/s] (zero on nodes without mass)."""
        self._require_bound()
        return self.state.v.numpy() * (self._mass.numpy() > 0.0)[:, None]

    def reference_map(self) -> np.ndarray:
        """(n_nodes, 3) material coordinates z at the grid nodes [m]."""
        self._require_bound()
        return self.state.z.numpy()

    def node_masses(self) -> np.ndarray:
        """(n_nodes,) lumped masses of the last step's force pass [kg], with the ``mass_floor``."""
        self._require_bound()
        return self._mass.numpy()

    @property
    def angular_velocity(self) -> np.ndarray:
        """World angular velocity of the Lagrangian frame [rad/s] (rigid: R omega; affine: of A's rotation)."""
        if self.lagrangian == "rigid":
            return self.state.F @ self.state.omega
        if self.lagrangian == "affine":
            W = self.state.Adot @ np.linalg.inv(self.state.F)
            return 0.5 * np.array([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])
        return np.zeros(3)

    def node_world_velocities(self) -> np.ndarray:
        """(n_nodes, 3) world velocity of the material at each node [m/s]: Eq. (2) / (9)."""
        self._require_bound()
        L, c = self._lagrangian_field()
        y = self.grid.node_positions()
        w = y @ L.T + c + self.eulerian_velocity() @ self._F_L().T
        return w @ self._axes().T

    def max_speed(self) -> float:
        """A cheap upper bound on the speed of the body's material [m/s], for broad phases: the
        Lagrangian field at the grid's farthest corner plus the last step's largest Eulerian
        velocity, |x_dot| <= |axes| (|L| r + |c| + |F_L| |v|) (Eq. 2). The last step's v* bounds the
        advected v up to the step's own change, which the broad phase's margin covers."""
        self._require_bound()
        L, c = self._lagrangian_field()
        g = self.grid
        corners = g.origin + g.h * np.array([[i, j, k] for i in (0, g.cells[0]) for j in (0, g.cells[1])
                                             for k in (0, g.cells[2])])
        r = float(np.linalg.norm(corners, axis=1).max())
        if self.history and self.lagrangian != "eulerian":  # v_star: per-axis maxima of the last step
            v = math.sqrt(3.0) * self.history[-1].v_star
        else:  # before the first step (or all motion on the grid): read the velocities
            v = float(np.linalg.norm(self.state.v.numpy(), axis=1).max(initial=0.0))
        return float(np.linalg.norm(self._axes(), 2) * (np.linalg.norm(L, 2) * r + np.linalg.norm(c)
                                                        + np.linalg.norm(self._F_L(), 2) * v))

    def linear_momentum(self) -> np.ndarray:
        """sum_s m_s x_dot_s over the nodes [kg m/s] (world)."""
        return self.node_masses() @ self.node_world_velocities()

    def node_world_positions(self) -> np.ndarray:
        """(n_nodes, 3) world positions of the grid nodes [m]: x = F_L y + T."""
        self._require_bound()
        return self.grid.node_positions() @ self.state.F.T + self.state.T

    def world_inertia(self) -> np.ndarray:
        """(3, 3) the inertia tensor about the centre of mass [kg m^2], world axes, of the lumped
        node masses that ``angular_momentum`` sums: sum_s m_s (|r_s|^2 I - r_s r_s^T), r_s from
        the centre of mass."""
        m = self.node_masses()
        x = self.node_world_positions()
        return point_inertia(x - (m @ x) / m.sum(), m)

    def angular_momentum(self, about: Sequence[float] | None = None) -> np.ndarray:
        """sum_s m_s (x_s - p) x x_dot_s over the nodes [kg m^2/s] (world), about p = ``about``
        (world) or, by default, the nodes' current centre of mass. The lumped node masses are the
        ones the step conserves momentum with (split, QP, contact impulse); their second moment
        exceeds the continuum's by O(h^2) (mass spread to the corners of a cell, the ``mass_floor``):
        +11.0 % for a sphere at 8 cells across, +3.2 % at 12, +1.3 % at 16
        (``tools/study_eol_fidelity.py``)."""
        m = self.node_masses()
        x = self.node_world_positions()
        p = (m @ x) / m.sum() if about is None else as_vec3(about, f"body '{self.name}': about")
        return (m[:, None] * np.cross(x - p, self.node_world_velocities())).sum(axis=0)

    def center_of_mass(self) -> np.ndarray:
        """sum_s m_s x_s / sum_s m_s over the nodes [m] (world), with the lumped masses that
        ``linear_momentum`` sums: it moves at linear_momentum() / their total."""
        m = self.node_masses()
        return (m @ self.node_world_positions()) / m.sum()

    def kinetic_energy(self) -> float:
        m = self.node_masses()
        return 0.5 * float(m @ np.einsum("ij,ij->i", w := self.node_world_velocities(), w))

    def volume(self) -> float:
        """Enclosed volume of the tracked surface [m^3]."""
        self._require_bound()
        x = self.state.y_vertices.numpy() @ self.state.F.T + self.state.T
        return wmesh.signed_volume(x, self._tracked_faces)

    @property
    def elastic_energy(self) -> float:
        """Elastic energy [J] of the last force pass."""
        return float(self._energy.numpy()[0]) if self.bound else 0.0

    def plastic_strain(self) -> np.ndarray:
        """(P, 3, 3) F_p^-1 at the material points (identity without plasticity)."""
        self._require_bound()
        return self.state.Fp_inv.numpy() if self.plasticity else np.broadcast_to(np.eye(3), (len(self._volumes), 3, 3))

    # -- loads ---------------------------------------------------------------------------------
    def add_traction(self, fn: Callable[[float], Any]) -> None:
        """Add a surface load: ``fn(t)`` returns (V, 3) tractions [Pa] per surface vertex in **world**
        axes (BemBody's are in frame axes: an EoL body's deformation is not small in its frame).

        Each vertex's traction times its lumped area on the deformed surface (a third of its
        triangles' current areas, ``vertex_areas()``) is a point force at the vertex's intermediate
        position y, spread to the nodes of its cell by the trilinear shape functions (over the nodes
        with mass: the total is kept exactly, so momentum changes by exactly its impulse). Evaluated
        at each step's start time (like gravity: forward Euler). Loads add up; they are functions of
        time, not state (a checkpoint does not store them). For a pressure p(t):
        ``body.add_traction(lambda t: -p(t) * body.vertex_normals())``."""
        if not callable(fn):
            raise InvalidParameter(f"body '{self.name}': add_traction takes a callable fn(t) -> (V, 3) tractions [Pa], "
                                   f"got {type(fn).__name__}")
        self._tractions.append(fn)

    def add_body_force(self, fn: Callable[..., Any], *, per_point: bool = False) -> None:
        """Add a body force as an acceleration [m/s^2] (world axes), like gravity.

        ``fn(t)`` returns a (3,) acceleration, uniform over the body (the force density is rho times
        it; it goes exactly into the frame, like gravity). With ``per_point=True``, ``fn(t, x)``
        takes the (P, 3) world positions of the material points and returns their (P, 3)
        accelerations; each point's force rho w_p a_p is spread to the nodes of its cell by the
        trilinear shape functions. Evaluated at each step's start time; loads add up."""
        if not callable(fn):
            raise InvalidParameter(f"body '{self.name}': add_body_force takes a callable fn(t) -> (3,) acceleration "
                                   f"[m/s^2], got {type(fn).__name__}")
        (self._point_forces if per_point else self._accelerations).append(fn)

    def _coupling_vertices(self) -> int:
        return self._n_surface

    def _coupling_time(self) -> float:
        return self.state.time

    def _register_coupling(self) -> None:
        """The load of ``add_vertex_impulses`` (the World's push from other bodies, issue 18): point
        forces at the surface vertices (``_apply_loads``), so the force and its momentum are exact
        (it counts in ``load_impulse``); only bodies that are pushed take it."""
        self._coupling_load = True

    def _coupling_forces(self, t: float) -> np.ndarray | None:
        """The push still being delivered at t [N] per surface vertex (world), or None."""
        st = self.state
        if not self._coupling_load or not len(st.coupling_force) \
                or t >= st.coupling_until - 1e-9 * max(self.dt_elastic, 1e-12):
            return None
        return st.coupling_force

    @property
    def load_impulse(self) -> np.ndarray:
        """Momentum delivered by the tractions and body forces so far [kg m/s] (world)."""
        return np.zeros(3) if self.state is None else self.state.load_impulse

    def vertex_areas(self) -> np.ndarray:
        """(V,) lumped areas of the deformed surface: a third of each incident triangle's area [m^2]."""
        return wmesh.vertex_areas(self.points(), self._faces)

    def vertex_normals(self) -> np.ndarray:
        """(V, 3) outward unit normals of the deformed surface (area-weighted, world axes)."""
        return wmesh.vertex_normals(self.points(), self._faces)

    def _load_value(self, value: Any, shape: tuple[int, ...], what: str, t: float, in_step: bool = True) -> np.ndarray:
        """What a user's function returned at t (a step's start time when ``in_step``), checked on the
        host: shape and finite, else InvalidParameter naming the body, ``what``, t and the frame."""
        return callback_array(value, (shape,), f"body '{self.name}': {what}", t,
                              self._frame_of(t, start=True) if in_step else None)

    def _body_acceleration(self, t: float) -> np.ndarray:
        """The uniform body-force accelerations at t [m/s^2] (world)."""
        acc = np.zeros(3)
        for fn in self._accelerations:
            acc += self._load_value(call_user(fn, t, f"body '{self.name}': a body force", self._frame_of(t, start=True)),
                                    (3,), "a body force (acceleration [m/s^2])", t)
        return acc

    def _apply_loads(self, t: float) -> None:
        """Tractions and per-point body forces at t, spread to the nodes and added to a (a += f / m);
        the total delivered (world) is kept for the load impulse. All loads are evaluated and checked
        before anything is added, so a bad load leaves the state as it was."""
        d = self._device
        A = self._axes()  # velocity axes -> world
        work = []
        if self._tractions:
            V = self._n_surface
            tr = sum(self._load_value(call_user(fn, t, f"body '{self.name}': a traction", self._frame_of(t, start=True)),
                                      (V, 3), "a traction [Pa]", t) for fn in self._tractions)
            work.append((self.state.y_vertices, self.vertex_areas()[:, None] * tr, 1))
        push = self._coupling_forces(t)
        if push is not None:  # forces as they are (no round trip through the vertex areas)
            work.append((self.state.y_vertices, push, 1))
        if self._point_forces:
            st = self.state
            x = st.y_points.numpy() @ st.F.T + st.T
            acc = sum(self._load_value(fn(t, x), x.shape, "a body force (acceleration [m/s^2] per point)", t)
                      for fn in self._point_forces)
            work.append((st.y_points, (self.material.rho * self._volumes)[:, None] * acc, 0))
        self._tmp.zero_()
        applied = self._readout[READ_LOAD:READ_LOAD + 3]  # read back with the step's velocity maxima
        applied.zero_()
        for y, f_world, surface in work:
            self._launch(kl.scatter_point_forces, len(f_world),
                         [y, wp.array(f_world @ A, dtype=wp.vec3d, device=d), self._g3(self._mass),
                          self._grid, surface, self._g3(self._tmp), self._readout, READ_LOAD])
        self._launch(ks.add_acceleration, self.grid.n_nodes, [self._tmp, self._mass, self._a])
        self._loads_applied = True  # the step's read-back sets _load_force

    def _check_initial_overlap(self) -> None:
        """Refuse a body that starts deeper than half a cell inside a collider (it would start
        inside and crawl out at a collapsing dt); shallower overlap is left to contact."""
        x = self.points()
        tol = 0.5 * self.grid.h
        for ci, col in enumerate(self._colliders):
            plane = self._surfaces.plane(ci)
            if plane is not None:
                nrm, height = plane
                depth = float(np.max(height - x @ np.asarray(nrm, dtype=np.float64)))
            else:
                M = self._surfaces.matrix(ci, self.state.time)
                local = (x - M[:3, 3]) @ np.linalg.inv(M[:3, :3]).T
                out = wp.zeros(len(x), dtype=wp.float32, device=self._device)
                self._launch(kl.mesh_depth, len(x),
                          [col.device_mesh(self._device).id,
                                  wp.array(local.astype(np.float32), dtype=wp.vec3, device=self._device),
                                  float(col.extent), col.inside_test, out])
                depth = float(out.numpy().max())
            if depth > tol:
                raise InvalidParameter(
                    f"body '{self.name}': starts {depth:.4g} m inside collider '{col.name}' at t = {self.state.time:.6g} s "
                    f"(deepest surface point; the tolerance is half a cell, {tol:.3g} m): place it outside, "
                    f"e.g. with position=")

    # -- Body interface --------------------------------------------------------------------------
    def bind(self, device: wp.Device, gravity: np.ndarray, up: np.ndarray) -> None:
        self._gravity = np.asarray(gravity, dtype=np.float64)
        self._up = np.asarray(up, dtype=np.float64)
        self.grid = grid = self._grid0
        n = grid.n_nodes
        d = device
        y_nodes = grid.node_positions()
        self._grid = grid_struct(grid)
        vec = dict(dtype=wp.vec3d, device=d)
        # immutable on the device: material points and surface in z, their volumes, the faces
        self._z_pts = wp.array(self._z_points, **vec)
        self._vol = wp.array(self._volumes, dtype=wp.float64, device=d)
        self._z_vert = wp.array(self._z_vertices, **vec)
        self._faces_dev = wp.array(self._tracked_faces, dtype=wp.vec3i, device=d)
        # the state; the initial velocity is a rigid motion about the centre of mass
        v0, w0 = self.initial_velocity, self.initial_angular_velocity
        F = self._R0.copy() if self.lagrangian != "eulerian" else np.eye(3)
        plastic = self.plasticity is not None
        self.state = EolState(
            z=wp.array(y_nodes, **vec),  # at rest y = z
            # purely Eulerian: all motion is on the grid, v = w0 x y + v0
            v=wp.array(np.cross(w0, y_nodes) + v0, **vec) if self.lagrangian == "eulerian" else wp.zeros(n, **vec),
            y_points=wp.array(self._z_points, **vec),
            y_vertices=wp.array(self._z_vertices, **vec),
            # F_p^-1 only for plastic bodies (a 1-element placeholder keeps the kernel signature)
            Fp_inv=wp.array(np.broadcast_to(np.eye(3), (len(self._volumes) if plastic else 1, 3, 3)).copy(),
                            dtype=wp.mat33d, device=d),
            F=F,
            T=self.com + self._offset,  # the mesh as given, moved by position=
            Tdot=v0.copy(),  # world velocity of the frame origin
            omega=F.T @ w0,  # rigid: body axes
            Adot=cross_matrix(w0) @ F,  # affine
            dt_prev=self.dt_elastic,
        )
        self._device = device
        self._launch = Launcher(device)  # the step's launches, replayed (``wsim.launch``)
        self._views: dict[tuple, wp.array] = {}  # ``_g3``
        self._allocate_grid_arrays()
        self._energy = wp.zeros(1, dtype=wp.float64, device=d)
        self._moments = wp.zeros(40, dtype=wp.float64, device=d)
        # the step's dt on the device, copied from a (page-locked) host value: the finish's kernels
        # read it there, so a captured finish replays with each step's dt (``_finish_graph``)
        self._dt_at = wp.zeros(1, dtype=wp.float64, device=d)
        self._dt_host = wp.zeros(1, dtype=wp.float64, device="cpu", pinned=d.is_cuda)
        self._dt_np = self._dt_host.numpy()  # a view: the host writes each step's dt here
        # what a step reads back, in one copy: max |v*_0|, |v*_1| per axis and the material outside
        # the grid's margin (8), the split's fields (``kernels.eol_step.FIELDS``), the loads' force
        self._readout = wp.zeros(READ_LOAD + 3, dtype=wp.float64, device=d)
        self._vmax, self._fields = self._readout[:8], self._readout[8:READ_LOAD]
        self._readout_host = wp.zeros(READ_LOAD + 3, dtype=wp.float64, device="cpu", pinned=d.is_cuda)  # its copy
        self._loads_applied = False
        self._restore_fields = wp.zeros(ks.FIELDS, dtype=wp.float64, device=d)
        self._iters = wp.zeros(max(len(self._volumes), len(self._z_vertices)), dtype=wp.int32, device=d)
        self._flowing = wp.zeros(1, dtype=wp.int32, device=d)
        self._m_total = 0.0
        self._load_force = np.zeros(3)
        self._colliders: list[Collider] = []
        self._collider_mu: list[float] = []  # Coulomb friction against each (``attach_colliders``)
        self._surface = None  # contact samples and rows, made once the body can touch something
        self._row_groups = 0  # row groups (colliders, other methods' surfaces) with accumulators
        self._moving: list[_MovingSurface] = []  # other bodies' surfaces in reach this advance
        self._collider_friction = np.zeros(3)  # the colliders' friction impulse of the last step (``_friction``)
        self._rubbing: list[_MovingSurface | None] = []  # the row groups whose friction awaits its read
        self._span = (0.0, 1.0)
        self._fraction = 0.0  # where in the span the moving surfaces were placed this step
        self._force_pass()
        if self._velocity_field is not None:
            self._set_velocity_field()

    def _allocate_grid_arrays(self) -> None:
        """The node-sized arrays derived from the state (forces, masses) and the scratch, for the current grid."""
        self._forget_finish()
        n, shape, d = self.grid.n_nodes, self.grid.node_shape, self._device
        vec = dict(dtype=wp.vec3d, device=d)
        self._grid = grid_struct(self.grid)
        # derived from the state by the force pass
        self._forces = wp.zeros(n, **vec)
        self._mass = wp.zeros(n, dtype=wp.float64, device=d)
        self._mass_real = wp.zeros(n, dtype=wp.float64, device=d)  # before the mass floor
        # scratch
        self._w = wp.zeros(n, **vec)
        self._a = wp.zeros(n, **vec)
        self._v0 = wp.zeros(n, **vec)
        self._v1 = wp.zeros(n, **vec)
        self._vstar = wp.zeros(n, **vec)
        self._tmp = wp.zeros(n, **vec)
        self._tmp2 = wp.zeros(n, **vec)
        self._w_hat = wp.zeros(n, **vec)  # the unconstrained w, a of a step in contact (QP re-solves)
        self._a_hat = wp.zeros(n, **vec)
        self._advect_scratch = (wp.zeros(shape, **vec), wp.zeros(shape, **vec)) if self.advection == "bfecc" else None
        self._layer = wp.zeros(shape, dtype=wp.int32, device=d)  # the reference-map extension's
        self._G_ext = wp.zeros(shape, dtype=wp.mat33d, device=d)
        # material volume per cell, for the hourglass control (only when it is on)
        self._filled = wp.zeros(self.grid.cells, dtype=wp.float64, device=d) if self.hourglass > 0.0 else None
        # the viscous stiffness' row bounds (only with damping)
        self._bound = wp.zeros(shape, dtype=wp.float64, device=d) if self.damping > 0.0 else None

    def _regrid(self, grown: np.ndarray) -> None:
        """Move to the bind-time grid enlarged by ``grown`` = (cells added below x, y, z; above x, y, z).

        The spacing is kept and the new grid's nodes include every old node, so z and v are copied
        exactly; a new node's reference map continues its nearest old node's as a rest-like
        extension (z = z_near + y - y_near) and its Eulerian velocity is zero (it holds no material).
        Material points, surface and frame are positions in y and do not change. Everything sized
        by the grid (masses, scratch, contact rows) is rebuilt and the force pass redone; the
        contact warm start (row ids of the old layout) is dropped."""
        st = self.state
        grown = np.asarray(grown, dtype=np.int64)
        old, old_grown = self.grid, st.grid_grown
        base = self._grid0
        new = EolGrid(origin=base.origin - base.h * grown[:3], h=base.h,
                      cells=tuple(int(c) for c in np.array(base.cells) + grown[:3] + grown[3:]))
        offset = grown[:3] - old_grown[:3]  # old node (i, j, k) is new node (i, j, k) + offset
        ijk = np.stack(np.meshgrid(*(np.arange(k) for k in new.node_shape), indexing="ij"), axis=-1).reshape(-1, 3)
        src = ijk - offset
        near = np.clip(src, 0, np.array(old.node_shape) - 1)
        inside = np.all(near == src, axis=1)
        idx = old.node_index(near)
        z_old, v_old = st.z.numpy(), st.v.numpy()
        z = z_old[idx] + old.h * (src - near)  # rest-like extension outside the old grid
        v = np.where(inside[:, None], v_old[idx], 0.0)
        self.grid = new
        d = self._device
        st.z = wp.array(z, dtype=wp.vec3d, device=d)
        st.v = wp.array(v, dtype=wp.vec3d, device=d)
        st.grid_grown = grown.copy()
        st.active_rows = np.zeros(0, dtype=np.int64)
        self._launch.clear()  # the recorded launches and the views hold the old grid's arrays
        self._views.clear()
        self._allocate_grid_arrays()
        if self._surface is not None:  # samples and rows laid out on the new grid
            self._ensure_surface()
            self._contact_slots(self._row_groups, regrid=True)
        self._force_pass()

    def _grow_grid(self) -> bool:
        """Grow the grid on every side that material (points or surface) came within one cell of:
        by ``max(2, padding)`` cells, up to 3x the bind-time cells per axis. False if a side that
        needs room has reached that limit (the body flies apart)."""
        st, g = self.state, self.grid
        y = np.concatenate([st.y_points.numpy(), st.y_vertices.numpy()])
        if not np.all(np.isfinite(y)):
            return False
        c = (y - g.origin) / g.h
        slack = 1e-6  # the host test must include every side the device test flagged
        near_lo = c.min(axis=0) < 1.0 + slack
        near_hi = c.max(axis=0) > np.array(g.node_shape) - 2.0 - slack
        need = np.concatenate([near_lo, near_hi])
        if not need.any():
            return False
        step = max(2, self.padding)
        grown = st.grid_grown + step * need
        cells = np.array(self._grid0.cells) + grown[:3] + grown[3:]
        if np.any(cells > 3 * np.array(self._grid0.cells)):
            return False
        self._regrid(grown)
        return True

    def _set_velocity_field(self) -> None:
        """Initial velocity = velocity + angular_velocity x (x - com) + velocity_field(x) at the nodes
        with mass (world rest positions), split by the body's own least-squares split (Eq. 23): the
        Lagrangian part goes to the frame, the residual to the Eulerian velocities (a rigid field
        leaves v = 0)."""
        st = self.state
        mass = self._mass.numpy()
        has = mass > 0.0
        x = self.grid.node_positions() @ st.F.T + st.T
        u = self._load_value(self._velocity_field(x[has]), (int(has.sum()), 3), "velocity_field [m/s]", 0.0, in_step=False)
        u = u + self.initial_velocity + np.cross(self.initial_angular_velocity, x[has] - st.T)
        w = np.zeros((self.grid.n_nodes, 3))
        w[has] = u @ self._axes()  # world -> velocity axes (rigid: body axes)
        self._w.assign(w)
        self._a.zero_()
        if self.lagrangian == "eulerian":
            st.v.assign(w)
            return
        self._split(self._w, self._a)
        self._vmax.zero_()
        self._residual(self._w, self._a)
        wp.copy(st.v, self._v0)
        (L0, c0), _, _ = unpack_fields(self._fields.numpy())
        if self.lagrangian == "rigid":
            st.omega = np.array([L0[2, 1], L0[0, 2], L0[1, 0]])
            st.Tdot = st.F @ c0
        else:
            st.Adot, st.Tdot = np.array(L0), np.array(c0)

    def attach_colliders(self, surfaces: Surfaces) -> None:
        self._surfaces = surfaces
        self._colliders = list(surfaces)
        # Coulomb friction against each collider (``wsim.contact.collider_friction``)
        self._collider_mu = [collider_friction(c.friction, self.friction) for c in self._colliders]
        self._surface = None
        self._row_groups = 0
        self._contact_slots(len(self._colliders))

    def _contact_slots(self, n: int, regrid: bool = False) -> None:
        """Row accumulators for n row groups (colliders, then other methods' surfaces), made only
        once the body can touch something and grown, never shrunk, with n; ``regrid``: laid out
        again on a new grid."""
        if n == 0 or (not regrid and n <= self._row_groups):
            return
        self._ensure_surface()
        d = self._device
        k = self.collision_block
        self._row_groups = n
        n_rows = n * int(np.prod(self._ccells))
        width = 3 * (k + 1) ** 3 + 2
        # slots for every (collider, collision cell), cleared by compact_rows after each use
        self._row_acc = wp.zeros((n_rows, width), dtype=wp.float64, device=d)
        self._row_flag = wp.zeros(n_rows, dtype=wp.int32, device=d)
        self._row_ids = wp.zeros(n_rows, dtype=wp.int32, device=d)
        self._row_packed = wp.zeros((n_rows, width), dtype=wp.float64, device=d)
        self._row_of_slot = wp.full(n_rows, -1, dtype=wp.int32, device=d)
        self._n_rows = wp.zeros(1, dtype=wp.int32, device=d)
        self._n_rows_host = wp.zeros(1, dtype=wp.int32, device="cpu", pinned=d.is_cuda)  # its copy (``_own_rows_all``)
        self._system = wp.empty(0, dtype=wp.float64, device=d)  # S and the row vectors, grown on demand
        self._system_host = wp.empty(0, dtype=wp.float64, device="cpu", pinned=d.is_cuda)  # their copy
        self._friction_acc = wp.zeros(2, dtype=wp.vec3d, device=d)  # ``_friction``'s force and moment

    def set_moving_surfaces(self, surfaces: Sequence[tuple]) -> None:
        """Surfaces of other bodies that move on their own over the coming ``advance`` and may touch
        this one (issue 18): (key, vertices at its start (V, 3), at its end (V, 3), faces (M, 3),
        friction[, vertex masses (V,) or None[, (mass, centre of mass (3,), inertia (3, 3) about
        it, world[, rho c_p of its material]) or None]]); the vertex masses are a PBD pusher's,
        unused here; with the last part the surface yields to this body's push, as a rigid body
        and elastically (``kernels.eol_contact.partner_compliance``), without it it is kinematic.
        They move linearly between the two; this body's contact rows (Eq. 28) keep it out of them
        as out of a moving collider, each at the velocity of its vertices, and the opposite of
        what the rows push with is collected per vertex (``moving_surface_impulses``) for the
        World to hand to their bodies. Called by the World
        before each ``advance``; an empty list ends the coupling. The normal contact is the paper's
        volume constraint against the surface moving with its vertices; Coulomb friction with
        coefficient ``friction`` acts at the grid nodes it pushes, relative to the rigid motion that
        best fits the surface's vertices over the interval (``kernels.eol_contact.node_friction``).
        Other EoL bodies are not moving surfaces: touching EoL bodies share one QP
        (``advance_group``)."""
        self._require_bound()
        d = self._device
        keep = {ms.key: ms for ms in self._moving}
        moving = []
        for key, p0, p1, faces, mu, *rest in surfaces:
            p0 = np.asarray(p0, dtype=np.float64)
            rigid = rest[1] if len(rest) > 1 else None
            ms = keep.get(key)
            if ms is None or ms.p0.shape[0] != len(p0) or ms.n_faces != len(faces):
                cur = wp.array(p0.astype(np.float32), dtype=wp.vec3, device=d)
                ms = _MovingSurface(key=key, p0=wp.zeros(len(p0), dtype=wp.vec3d, device=d),
                                    p1=wp.zeros(len(p0), dtype=wp.vec3d, device=d), cur=cur,
                                    mesh=wp.Mesh(points=cur, indices=wp.array(np.ascontiguousarray(faces, dtype=np.int32).ravel(),
                                                                              dtype=wp.int32, device=d),
                                                 support_winding_number=True),
                                    n_faces=len(faces), impulse=wp.zeros(len(p0), dtype=wp.vec3d, device=d),
                                    velocity=wp.zeros(len(p0), dtype=wp.vec3d, device=d),
                                    step_impulse=wp.zeros(len(p0), dtype=wp.vec3d, device=d),
                                    step_weight=wp.zeros(len(p0), dtype=wp.float64, device=d),
                                    closed=wmesh.inside_test(faces))
            # the push of the last advance, which the partner takes over this one: its motion p0 -> p1
            # already carries it (``_react``)
            last = self.last_push(key, len(p0))
            ms.p0_host, ms.p1_host = p0, np.asarray(p1, dtype=np.float64)
            ms.p0.assign(ms.p0_host)
            ms.p1.assign(ms.p1_host)
            ms.impulse.zero_()
            ms.friction_impulse = np.zeros((len(p0), 3))
            ms.mu = float(mu)
            ms.rigid = None  # a kinematic surface, unless it says how it yields (``partner_compliance``)
            ms.impedance = None
            if rigid is not None:
                M, com, inertia, *more = rigid
                ms.impedance = float(more[0]) if more else None
                ms.rigid = (1.0 / float(M), np.linalg.inv(np.asarray(inertia, dtype=np.float64)),
                            np.asarray(com, dtype=np.float64), (ms.p1_host - ms.p0_host).mean(axis=0))
                start = ms.rigid[2] - ms.rigid[3]  # its centre of mass at the start
                if ms.impedance is None:  # it yields to the whole push (it takes it at once, a PBD body)
                    last = None
                ms.received = ((last.sum(axis=0), np.cross(p0 - start, last).sum(axis=0)) if last is not None
                               else (np.zeros(3), np.zeros(3)))
                if ms.received_v is None:
                    ms.received_v = wp.zeros(len(p0), dtype=wp.vec3d, device=d)
                if last is not None:
                    ms.received_v.assign(last)
                else:
                    ms.received_v.zero_()
            both = np.concatenate([p0, np.asarray(p1)])
            ms.reach = 2.0 * float(np.linalg.norm(np.ptp(both, axis=0))) + self.grid.h
            if ms.vhits is None:  # per partner vertex: its row, coefficient and position (``vertex_rows``)
                ms.vhits = kc.VertexHits()
                ms.vhits.row = wp.full(len(p0), -1, dtype=wp.int32, device=d)
                ms.vhits.c = wp.zeros(len(p0), dtype=wp.vec3d, device=d)
                ms.vhits.point = wp.zeros(len(p0), dtype=wp.vec3d, device=d)
                ms.varea = wp.zeros(len(p0), dtype=wp.float64, device=d)
            ms.varea.assign(wmesh.vertex_areas(p0, faces))
            ms.box = (both.min(axis=0), both.max(axis=0))
            moving.append(ms)
        self._moving = moving
        self._contact_slots(len(self._colliders) + len(moving))
        P = 0 if self._surface is None else self._surface.sample_face.shape[0]
        for ms in moving:
            if ms.hits is None:  # per contact sample: its row, barycentric weights and face on this surface
                ms.hits = kc.SurfaceHits()
                ms.hits.row = wp.full(P, -1, dtype=wp.int32, device=d)
                ms.hits.bary = wp.zeros(P, dtype=wp.vec3d, device=d)
                ms.hits.face = wp.zeros(P, dtype=wp.int32, device=d)

    def moving_surface_impulses(self) -> dict[int, np.ndarray]:
        """Momentum [N s] (V, 3) per vertex that each moving surface received from this body over
        the last ``advance`` (world axes), by key."""
        normal = {ms.key: ms.impulse.numpy().copy() for ms in self._moving}  # (a view on the CPU)
        # the normal part is kept: the partner takes it over the next interval (``set_moving_surfaces``)
        self._keep_pushes(normal)
        return {ms.key: normal[ms.key] + ms.friction_impulse for ms in self._moving}

    def advance(self, t0: float, t1: float) -> None:
        """Adaptive steps (Eq. 33) from the body's time to t1: equal steps within the elastic limit
        and ``dt_max`` (``advance_group``), shorter where Eq. (33) asks."""
        EolBody.advance_group([self], [0], t0, t1)

    @staticmethod
    def advance_group(bodies: Sequence[EolBody], keys: Sequence[int], t0: float, t1: float) -> None:
        """Step EoL bodies that may touch each other from their common time to t1 with one dt per
        step (the smallest any of them asks for, Eq. 33) and one contact QP across them (Eq. 29:
        each body's rows against colliders and other methods' surfaces, and the rows between the
        bodies, ``wsim.eol.pairs``). ``keys``: the bodies' stable keys in the World (the rows
        between bodies keep their warm start under them). A body failing stops the group.

        What is left of the advance is split into the fewest equal steps within the elastic limit
        and ``dt_max``, not run to the limit with the remainder last: that repeated a pattern of
        uneven steps every advance, which pumps a mode the explicit step holds at a fixed dt
        (parametric resonance; ``EolBody``'s elastic_safety). Where Eq. (33) asks for less, the
        step is shorter and the rest is split again."""
        for b in bodies:
            b._require_bound()
            b._begin_advance(t1)
        eps = 1e-9 * max(t1 - t0, 1e-12)
        while all(b._failure is None for b in bodies) and bodies[0].time < t1 - eps:
            left = t1 - bodies[0].time
            limit = min(min(b.dt_elastic, b.dt_max or math.inf) for b in bodies)
            cap = left / max(math.ceil((left - eps) / limit), 1)  # eps: the time's round-off
            _step_together(bodies, keys, cap)
        if all(b._failure is None for b in bodies):
            for b in bodies:
                b.state.time = t1

    def _begin_advance(self, t1: float) -> None:
        """Before the steps to t1: the first step's overlap check, and where the moving surfaces go."""
        if self.state.steps == 0 and self._colliders and not getattr(self, "_overlap_checked", False):
            self._check_initial_overlap()
            self._overlap_checked = True
        self._span = (self.time, t1)  # where the moving surfaces are: linear over this advance
        for ms in self._moving:
            if ms.mu > 0.0:  # friction's reference motion
                ms.G, ms.g = rigid_fit(ms.p0_host, ms.p1_host, t1 - self.time)
            self._launch(kc.surface_velocity, ms.p0.shape[0],
                         [ms.p0, ms.p1, wp.float64(1.0 / max(t1 - self.time, 1e-300)), ms.velocity])

    def check_finite(self, frame: int, time_: float) -> None:
        if self._failure is None:
            for q, arr in (("reference map", self.state.z), ("Eulerian velocity", self.state.v), ("surface", self.state.y_vertices)):
                if not np.all(np.isfinite(arr.numpy())):
                    self._failure = (q, "", "non-finite")
                    break
        if self._failure is not None:
            quantity, detail, reason = self._failure
            raise SimulationDiverged(self.name, frame, quantity, time_, detail, reason)

    # -- the step ------------------------------------------------------------------------------
    def _F_L(self) -> np.ndarray:
        """The Lagrangian deformation gradient in the velocity axes: A (affine), I (rigid, Eulerian)."""
        return self.state.F if self.lagrangian == "affine" else I3

    def _axes(self) -> np.ndarray:
        """Velocity axes -> world: R for rigid (body axes), I otherwise."""
        return self.state.F if self.lagrangian == "rigid" else I3

    def _lagrangian_field(self) -> tuple[np.ndarray, np.ndarray]:
        """(L, c) with J_L(y) q1_dot = L y + c in the velocity axes."""
        if self.lagrangian == "rigid":
            return cross_matrix(self.state.omega), self.state.F.T @ self.state.Tdot
        if self.lagrangian == "affine":
            return self.state.Adot.copy(), self.state.Tdot.copy()
        return np.zeros((3, 3)), np.zeros(3)

    def _g3(self, a: wp.array) -> wp.array:
        """The grid-shaped (3-D) view of a flat nodal array, made once per array: a fresh
        ``reshape`` costs several microseconds of host time, and a step takes about twenty."""
        key = (a.ptr, a.dtype, a.shape)
        view = self._views.get(key)
        if view is None:
            view = self._views[key] = a.reshape(self.grid.node_shape)
        return view

    def _force_pass(self) -> None:
        """Forces, lumped masses (with the floor) and elastic energy of the current state."""
        sample_forces(self._grid, self._g3(self.state.z), self.state.y_points, self._vol, self.state.Fp_inv,
                      self.plasticity is not None, self._F_L(), self.material, self._g3(self._forces),
                      self._g3(self._mass), self._energy, self._device, self._launch)
        if self._filled is not None:
            full = self.grid.h**3 if self.quadrature > 1 else 0.0  # one point per cell integrates no cell fully
            hourglass_forces(self._grid, self._g3(self.state.z), self.state.y_points, self._vol, full,
                             self._F_L(), self.hourglass * self.material.mu, self._filled,
                             self._g3(self._forces), self._energy, self._device, self._launch)
        self._launch.copy(self._mass_real, self._mass)
        if self._mass_floor > 0.0:
            self._launch(ks.floor_mass, self.grid.n_nodes,
                      [self._mass, wp.float64(self._mass_floor)])

    # The step's phases (``_step_together`` runs them for one body or for touching bodies at once):
    # forces, own rows, contact (applied per QP attempt), split and dt (per attempt), finish.
    def _step_forces(self, cap: float, dt_guess: float) -> _StepWork:
        """1. forces: w_hat = w + dt a (Eq. 16) from the state's forces (the force pass of this state
        was done at the end of the last step), loads and damping."""
        d = self._device
        st = self.state
        n = self.grid.n_nodes
        work = _StepWork(t=time.perf_counter(), dt_guess=dt_guess, cap=cap)
        L, c = self._lagrangian_field()
        self._body_acc = self._body_acceleration(st.time) if self._accelerations else np.zeros(3)
        g_axes = self._axes().T @ (self._gravity + self._body_acc)
        gyro = ks.coriolis_matrix(L, dt_guess, self.coriolis == "midpoint")
        self._launch(ks.node_velocities, n,
                  [self.state.v, self._mass, self._forces, self._grid, _mat(L), wp.vec3d(*c),
                          _mat(self._F_L()), wp.vec3d(*g_axes), int(self.fictitious and self.lagrangian == "rigid"),
                          _mat(gyro), self._mass_real, self._w, self._a])
        if self._tractions or self._point_forces or self._coupling_load:
            self._apply_loads(st.time)
        if self.damping > 0.0:
            viscous_forces(self._grid, self._g3(self._w), self.state.y_points, self._vol, self._F_L(), self.damping,
                           self._g3(self._mass), cap, self._g3(self._tmp), self._bound, d, self._launch)
            self._launch(ks.add_acceleration, n,
                      [self._tmp, self._mass, self._a])
        work.t = self._tick("forces", work.t)
        return work

    def _own_rows_launch(self, work: _StepWork) -> bool:
        """2. collision of this body's samples with the colliders and other methods' surfaces,
        binned and compacted into rows on the device, the row count's copy to the host queued
        (``_own_rows_all`` reads it); False when there is nothing to collide with."""
        if not (self._colliders or self._moving):
            return False
        if self._moving:  # the partners where they are at this step, then their yield (which reads them)
            self._place_moving()
            self._expect_partners(work.dt_guess)
        self._collide(placed=True)
        self._compact_launch()
        wp.copy(self._n_rows_host, self._n_rows)
        return True

    def _keep_unconstrained(self) -> None:
        """The unconstrained w, a, kept for a re-solve at a shorter dt."""
        self._launch.copy(self._w_hat, self._w)
        self._launch.copy(self._a_hat, self._a)

    def _step_contact(self, work: _StepWork, attempt: int, dt_guess: float) -> None:
        """The QP's multipliers on w, a (which become w_0, w_1 of Eq. 31 in place): this body's
        own rows (``work.sol``) and the velocity changes of the rows between bodies
        (``work.changes``), then friction against the colliders and other methods' surfaces."""
        if not (work.m or work.changes is not None):
            return
        if attempt:  # back to the unconstrained w, a
            self._launch.copy(self._w, self._w_hat)
            self._launch.copy(self._a, self._a_hat)
        if work.m:
            lam = np.empty((work.m, 2))
            lam[work.order] = np.column_stack([work.sol.lam0, work.sol.lam1])  # back to the device's row order
            self._lam = wp.array(lam, dtype=wp.float64, device=self._device)  # friction and the reaction read it too
            self._launch(kc.apply_impulses, work.m,
                         [self._surface, self._row_packed, self._row_ids, self._mass, self._lam, -1, 1,
                          wp.float64(0.0), self._w, self._a])
        if work.changes is not None:
            nodes, d0, d1 = work.changes
            d = self._device
            self._launch(kc.add_node_changes, len(nodes),
                         [wp.array(nodes.astype(np.int32), dtype=wp.int32, device=d), wp.array(d0, dtype=wp.vec3d, device=d),
                          wp.array(d1, dtype=wp.vec3d, device=d), self._w, self._a])
        if work.m and (self._moving or any(self._collider_mu)):
            self._friction(work.m, dt_guess)
        work.t = self._tick("qp", work.t)

    def _split_launch(self, work: _StepWork, attempt: int) -> None:
        """4. the least-squares split of w_0 and w_1 (Eqs. 23-25, 32) on the device, the velocity
        maxima and fields' copy to the host queued (``_split_read`` reads it)."""
        w0, w1 = self._w, self._a
        self._split(w0, w1)  # the fields stay on the device; read back with vmax below
        if attempt == 0:
            self._vmax.zero_()
            # material within one cell of the grid's boundary (tracked at the end of the last
            # step): the grid grows on that side (``_grow_grid``) and the step starts again on
            # it, unless the grid has reached its limit (the body flies apart). Read back with
            # the velocity maxima; a QP re-solve does not change it.
            for slot, y in ((6, self.state.y_vertices), (7, self.state.y_points)):
                self._launch(kl.outside_margin, y.shape[0],
                          [y, self._grid, wp.float64(1.0), self._vmax, slot])
        else:
            self._vmax[:6].zero_()
        self._residual(w0, w1)
        wp.copy(self._readout_host, self._readout)

    def _split_read(self, work: _StepWork, cap: float) -> float | None:
        """The step size this body allows (Eq. 33) from ``_split_launch``'s read-back (its copy
        complete); None when the step cannot go on (the grid grew: step again; or failed)."""
        st = self.state
        readout = self._readout_host.numpy().copy()
        vmax = readout[:8]
        work.fields = unpack_fields(readout[8:READ_LOAD])
        weight = work.fields[2]
        if self._loads_applied:
            self._load_force = self._axes() @ readout[READ_LOAD:READ_LOAD + 3]
            self._loads_applied = False
        if self.lagrangian != "eulerian" and self.split == "mass":
            self._m_total = weight  # the mass norm's total weight is the body's mass
        if vmax[6] > 0.0 or vmax[7] > 0.0:
            if np.all(np.isfinite(vmax[6:])) and self._grow_grid():
                return None  # nothing advanced: the caller steps again on the larger grid
            what = "surface vertices" if vmax[6] > 0.0 else "material points"
            self._failure = ("material outside the grid",
                             (f"material left the grid: {what} came within a cell of the grid boundary "
                              f"({max(vmax[6], vmax[7]):.3g} cells past that margin) at step {st.steps} "
                              f"(t = {st.time:.6g} s) after the grid had grown to 3x its first size on that "
                              f"axis ({self.grid.cells} cells): the body flies apart"), "diverging")
            return None
        vmax = work.vmax = vmax[:6].copy()
        (L0, c0), (L1, c1), _ = work.fields
        if not np.all(np.isfinite(vmax)) or not np.all(np.isfinite(L0 + L1)):
            self._failure = ("Eulerian velocity", f"non-finite at step {st.steps} (t = {st.time:.6g} s)", "non-finite")
            return None
        dt = adaptive_dt(vmax[:3], vmax[3:], self.grid.h, self.cfl, cap)
        if dt < 1e-9 * cap and dt < 1e-12:
            self._failure = ("time step", f"dt = {dt:.3g} s collapsed at step {st.steps}", "diverging")
            return None
        work.t = self._tick("ls", work.t)
        return dt

    def _step_finish(self, work: _StepWork, dt: float, stream: wp.Stream | None = None) -> None:
        """5-6. advect v* by itself, then z by v^{t+1} (Algorithm 1), move the frame; Algorithm 2 for
        the material points and the surface, plasticity, the new state's forces. The launches
        (``_finish_launches``) replay as one CUDA graph where they can (``_finish_graph``), on
        ``stream`` if given (the bodies of a group side by side, ``_step_together``)."""
        st = self.state
        (L0, c0), (L1, c1), _ = work.fields
        L_new, c_new = L0 + dt * L1, c0 + dt * c1
        if work.sol is not None:  # momentum the QP delivered: sum_s m_s (w_s - w_hat_s) = -J^T lambda
            self._read_friction()
            st.contact_impulse = st.contact_impulse - self._axes() @ ((work.sol.lam0 + dt * work.sol.lam1) @ work.system.jsum)
            if self._moving:
                st.contact_impulse = st.contact_impulse + self._react(work.m, dt)
            st.contact_impulse = st.contact_impulse + self._collider_friction
        if work.changes is not None:  # and the rows between bodies
            st.contact_impulse = st.contact_impulse + work.pair_impulse[0] + dt * work.pair_impulse[1]
        if self._moving:
            self._settle_partners(dt, pushed=work.sol is not None)
        self._integrate_pose(dt, L_new, c_new)  # host only: none of the launches below reads the pose
        self._dt_np[0] = dt
        graph = self._finish_graph()
        if graph is not None:
            if stream is not None:  # after this step's launches so far (the reaction above reads the surface it moves)
                stream.wait_stream(wp.get_stream(self._device))
            wp.capture_launch(graph, stream=stream)
            self._tick("forces", work.t)  # the finish's stages in one: advection, tracking, forces
        else:
            self._finish_launches(work.t, dt)
        st.gravity_impulse = st.gravity_impulse + dt * self._m_total * self._gravity
        if self._accelerations or self._tractions or self._point_forces or self._coupling_load:
            st.load_impulse = st.load_impulse + dt * (self._m_total * self._body_acc + self._load_force)
        vmax = work.vmax
        self.history.append(StepRecord(time=st.time, dt=dt, rows=work.m + work.pair_rows,
                                       active=work.active + work.pair_active,
                                       v_star=float(max(vmax[:3].max(), 0.0) + dt * vmax[3:].max()),
                                       overlap=(0.0 if work.system is None else float(work.system.overlap.sum()))
                                       + work.pair_overlap,
                                       qp_iterations=0 if work.sol is None else work.sol.iterations,
                                       cap=work.cap))
        st.time += dt
        st.steps += 1
        st.dt_prev = dt

    def _finish_launches(self, t: float, dt: float) -> None:
        """The finish's device work, launches only (what ``_finish_graph`` captures): the step's dt
        to the device, v* = v*_0 + dt v*_1, advection, tracking, plasticity, the force pass and the
        momentum restore."""
        wp.copy(self._dt_at, self._dt_host)
        self._launch(ks.combine, self.grid.n_nodes, [self._v0, self._v1, self._dt_at, self._vstar])
        self._advect_fields()
        t = self._tick("advect", t)
        self._track()
        t = self._tick("track", t)
        if self.plasticity is not None:
            self._flowing.zero_()
            self._launch(kp.plastic_flow, len(self._volumes),
                      [self._g3(self.state.z), self._grid, self.state.y_points,
                              _mat(self._F_L()), wp.float64(self.material.mu), wp.float64(self.material.lam),
                              wp.float64(self.plasticity.yield_stress), wp.float64(self.plasticity.flow_rate * dt),
                              self.state.Fp_inv, self._flowing])
            t = self._tick("plasticity", t)
        self._force_pass()
        self._restore_momentum()
        self._tick("forces", t)

    #: capture the finish's launches in a CUDA graph (``_finish_graph``); None: on CUDA devices
    #: (Warp captures on the CPU too, which the tests use to check the graph against the launches)
    capture_finish: bool | None = None

    def _finish_graph(self) -> Any:
        """The finish's launches (``_finish_launches``) as one graph, captured on the second finish
        after the arrays it launches with were made (the first loads the kernels), or None where
        they run one by one: with ``profile`` (stages are timed apart), affine coordinates (F_L, a
        launch argument, changes every step) and plasticity (the flow's dt). A graph replays a
        step's ~30 launches for the host's cost of one: on an H100 a free 32^3 step spent about
        0.3 ms of host time launching them, with the GPU busy about 0.5 ms."""
        use = self.capture_finish if self.capture_finish is not None else self._device.is_cuda
        if not use or self.profile or self.lagrangian == "affine" or self.plasticity is not None:
            return None
        # the settings the captured launches took by value: a change (they are public) recaptures
        key = (self.hourglass, self.material.mu, self.material.lam, self.material.rho, self._mass_floor,
               self._positive["track_tol"], self._filled is not None)
        if self._graph is not None and key != self._graph_key:
            self._forget_finish()
        if self._graph is None:
            if not self._graph_ready:
                self._graph_ready = True
                return None
            timings = dict(self.timings)  # the capture runs the Python once: its ticks are no step's
            with wp.ScopedCapture(device=self._device) as capture:
                self._finish_launches(time.perf_counter(), 0.0)
            self.timings.clear()
            self.timings.update(timings)
            self._graph, self._graph_key = capture.graph, key
        return self._graph

    def _forget_finish(self) -> None:
        """Drop the captured finish: the arrays it launches with are about to change."""
        self._graph = None
        self._graph_key = None
        self._graph_ready = False

    def _split(self, w0: wp.array, w1: wp.array) -> None:
        """The least-squares split of w0 and w1 (Eq. 23) into ``self._fields`` on the device
        (``wsim.eol.split.split_on_device``; zero for Eulerian coordinates); sets the body's mass
        for the gravity impulse where the split's weights do not give it."""
        if self.lagrangian == "eulerian":
            self._fields.zero_()
            self._m_total = float(np.sum(self._mass.numpy()))
            return
        mass_norm = self.split == "mass"
        split_on_device(self._grid, w0, w1, self._mass, mass_norm, self._moments, self.lagrangian,
                        self._fields, self._device, self._launch)
        if not mass_norm:  # the uniform split's weights are 1: the mass needs its own sum
            self._m_total = float(np.sum(self._mass.numpy()))

    def _residual(self, w0: wp.array, w1: wp.array) -> None:
        """v*_0, v*_1 (Eqs. 24, 32) of w0 and w1 without the split's fields, and their maxima per
        axis into ``_vmax`` (``kernels.eol_step.eulerian_residual``)."""
        blocks = ks.reduce_blocks(self.grid.n_nodes, self._device)
        self._launch(ks.eulerian_residual, blocks,
                     [w0, w1, self._mass, self._grid, self._fields, inverse_mat33(self._F_L()), blocks,
                      self._v0, self._v1, self._vmax], block_dim=ks.REDUCE_BLOCK)

    def _restore_momentum(self) -> None:
        """Keep the Eulerian velocity free of momentum after advection (Lagrangian frames, the
        mass-weighted split).

        The mass-weighted split (Eqs. 23-25) leaves the residual v* with no momentum of its own (its
        linear and, rigid, angular momentum, or affine moments, are zero), so the frame carries
        the body's. (The paper's uniform split leaves the residual some momentum of its own, which
        this would remove: that split is left as it was.) Advecting v* semi-Lagrangian and re-lumping the masses from the tracked material
        points break that: at an impact, where v* varies sharply, the residual gains momentum that
        no force gave it, and the next split hands it to the frame. A slab landing edge-first on a
        frictionless plane (a purely vertical contact impulse) gained 0.58 kg m/s sideways in two
        frames and slid off at 0.38 m/s (an independent check; issue 16). The Lagrangian part the
        split finds in the advected v, with the new masses, is that error: it is removed (on the
        device, no read-back; a body without mass gets a zero field)."""
        if self.lagrangian == "eulerian" or self.split != "mass":
            return
        split_on_device(self._grid, self.state.v, self.state.v, self._mass, True, self._moments,
                        self.lagrangian, self._restore_fields, self._device, self._launch)
        self._launch(ks.remove_lagrangian_part, self.grid.n_nodes,
                     [self.state.v, self._mass, self._grid, self._restore_fields])

    def _advect_fields(self) -> None:
        d = self._device
        shape = self.grid.node_shape
        mass3 = self._g3(self._mass)
        # v* extended one layer into empty nodes, then advected by itself: v^{t+1}
        self._launch(ks.extrapolate, shape, [self._g3(self._vstar), mass3, self._g3(self._tmp)])
        self._advect(self._tmp, self._tmp, self.state.v)
        self._launch(ks.extrapolate, shape, [self._g3(self.state.v), mass3, self._g3(self._tmp)])
        self._launch.copy(self.state.v, self._tmp)
        # z = y - u: Dz/Dt = 0, advected by v^{t+1}
        self._launch.copy(self._tmp2, self.state.z)
        self._advect(self._tmp2, self.state.v, self.state.z)
        # ... and continued into the empty nodes around the material (``extend_reference_map``)
        extend_reference_map(self._g3(self.state.z), self._g3(self._mass_real), self.grid.h,
                             EXTEND_LAYERS, self._layer, self._G_ext, d, self._launch)

    def _advect(self, q: wp.array, vel: wp.array, out: wp.array) -> None:
        advect_arrays(self._g3(q), self._g3(vel), self._g3(out), self._grid, self._dt_at,
                      self.advection, self._advect_scratch, self._device, launcher=self._launch)

    def _integrate_pose(self, dt: float, L: np.ndarray, c: np.ndarray) -> None:
        st = self.state
        if self.lagrangian == "rigid":  # omega in body axes; advance_pose takes the world one, F omega
            st.omega = np.array([L[2, 1], L[0, 2], L[1, 0]])
            st.Tdot = st.F @ c  # world velocity of the origin: transported exactly between steps
            st.F, st.T = advance_pose(st.F, st.T, st.Tdot, st.F @ st.omega, dt)
        elif self.lagrangian == "affine":
            st.Adot, st.Tdot = np.array(L), np.array(c)
            st.T = st.T + dt * c
            st.F = st.F + dt * L

    def _track(self) -> None:
        """Algorithm 2 for the material points and the surface vertices, each from its last position."""
        z3 = self._g3(self.state.z)
        tol = self._positive["track_tol"] * self.grid.h
        for zs, ys in ((self._z_pts, self.state.y_points), (self._z_vert, self.state.y_vertices)):
            track_points(self._grid, z3, zs, ys, tol, 20, ys, self._iters, self._device, self._launch)

    # -- contact --------------------------------------------------------------------------------
    def _place_moving(self) -> None:
        """Each moving surface where it is at this step (linear over the advance's span), its mesh
        refit."""
        t0, t1 = self._span
        f = self._fraction = min(max((self.state.time - t0) / max(t1 - t0, 1e-300), 0.0), 1.0)
        for ms in self._moving:
            self._launch(kc.place_surface, ms.p0.shape[0], [ms.p0, ms.p1, wp.float64(f), ms.cur])
            ms.mesh.refit()

    def _collide(self, placed: bool = False) -> None:
        """Collision: the surface samples inside each collider, binned into rows on the device
        (``placed``: the moving surfaces are already where they are at this step)."""
        d = self._device
        surf = self._surface
        self._place_surface()
        for ci, col in enumerate(self._colliders):
            plane = self._surfaces.plane(ci)
            if plane is not None:
                nrm, height = plane
                self._launch(kc.plane_rows, surf.sample_face.shape[0],
                          [surf, wp.vec3d(*nrm), wp.float64(height), ci, self._row_acc, self._row_flag])
            else:
                M = self._surfaces.matrix(ci, self.state.time)
                # world velocity of the collider's material, over a short interval
                G, g = self._surfaces.velocity(ci, self.state.time, max(1e-6, 1e-3 * self.state.dt_prev))
                self._launch(kc.mesh_rows, surf.sample_face.shape[0],
                          [surf, col.device_mesh(d).id, wp.mat44d(*np.linalg.inv(M).ravel()),
                                  _mat(M[:3, :3]), float(col.extent), _mat(G), wp.vec3d(*g), ci, col.inside_test,
                                  self._row_acc, self._row_flag])
        if not placed:
            self._place_moving()
        for k, ms in enumerate(self._moving):  # other bodies' surfaces, where they are at this step
            self._launch(kc.surface_rows, surf.sample_face.shape[0],
                      [surf, ms.mesh.id, ms.closed, ms.velocity, float(ms.reach), len(self._colliders) + k,
                              self._row_acc, self._row_flag, ms.hits])
        # and their vertices inside this body's surface (vertex-face both ways), for the surfaces
        # whose box meets the grid's (the queries and the mesh refit cost a sixth of the showcase's
        # CPU time when run for every surface every step)
        lo, hi = self._grid_box() if self._moving else (None, None)
        placed = False
        for k, ms in enumerate(self._moving):
            ms.vactive = bool(np.all(ms.box[1] >= lo) and np.all(ms.box[0] <= hi))
            if ms.vactive:
                if not placed:
                    self._place_world_mesh()
                    placed = True
                self._launch(kc.vertex_rows, ms.cur.shape[0],
                             [surf, self._world_mesh.id, self._world_closed, ms.cur, ms.velocity, ms.varea,
                              float(ms.reach), len(self._colliders) + k, self._row_acc, self._row_flag, ms.vhits])

    def _grid_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) of the grid's corners in the world (the body and its padding lie inside)."""
        g = self.grid
        corners = g.origin + g.h * np.array([[i, j, k] for i in (0, g.cells[0]) for j in (0, g.cells[1])
                                             for k in (0, g.cells[2])])
        x = corners @ self.state.F.T + self.state.T
        return x.min(axis=0), x.max(axis=0)

    def _place_surface(self) -> None:
        """The contact samples' Lagrangian map and axes at the current state."""
        surf = self._surface
        surf.F, surf.T, surf.to_axes = _mat(self.state.F), wp.vec3d(*self.state.T), _mat(self._axes().T)

    def _ensure_surface(self) -> None:
        """The contact samples (made once) and their collision grid on the current grid: what rows
        against colliders and surfaces and rows between EoL bodies (``_pair_samples``) both need;
        a body that touches only other EoL bodies gets no row accumulators."""
        d = self._device
        k = self.collision_block
        if self._surface is None:
            face, bary, share = surface_samples(self._z_vertices, self._tracked_faces,
                                                self._positive["contact_spacing"] * self.grid.h)
            surf = kc.ContactSurface()  # the constant part; the frame is set each step
            surf.y, surf.faces = self.state.y_vertices, self._faces_dev
            surf.sample_face = wp.array(face, dtype=wp.int32, device=d)
            surf.sample_bary = wp.array(bary, dtype=wp.vec3d, device=d)
            surf.sample_share = wp.array(share, dtype=wp.float64, device=d)
            surf.inv_tau = wp.float64(1.0 / self._positive["contact_relaxation"])
            self._surface = surf
        surf = self._surface
        self._ccells = tuple(-(-c // k) for c in self.grid.cells)
        surf.grid = self._grid
        surf.block, surf.ccells = k, wp.vec3i(*self._ccells)
        surf.mass = self._mass  # the lumped masses (updated in place by each force pass)

    def _place_world_mesh(self) -> None:
        """This body's tracked surface in the world where it is now, as a Warp mesh (made once,
        refit each step) that other EoL bodies' samples are tested against (``_pair_samples``)."""
        n = self.state.y_vertices.shape[0]
        if getattr(self, "_world_mesh", None) is None or self._world_points.shape[0] != n:
            self._world_points = wp.zeros(n, dtype=wp.vec3, device=self._device)
            self._launch(kc.world_surface, n, [self._surface, self._world_points])
            self._world_closed = wmesh.inside_test(self._tracked_faces)
            # the winding number's solid-angle data only where the inside test uses it (its refit
            # took 0.11 ms a body and step at 32 cells; ray parity needs the plain tree)
            self._world_mesh = wp.Mesh(points=self._world_points, support_winding_number=self._world_closed != km.WATERTIGHT,
                                       indices=wp.array(self._tracked_faces.ravel(), dtype=wp.int32, device=self._device))
        else:
            self._launch(kc.world_surface, n, [self._surface, self._world_points])
            self._world_mesh.refit()

    def _pair_samples(self, others: list[tuple[EolBody, int, int, float]]) -> None:
        """Launch the records of this body's samples inside other EoL bodies
        (``kernels.eol_contact.pair_samples``): (other body, whether this body is the pair's A,
        pair index, query reach [m]) each, counted in ``_pair_count``; ``_pair_records`` takes
        the count (read back for every body of a group at once) and relaunches into a larger
        buffer when it overflowed."""
        d = self._device
        P = self._surface.sample_face.shape[0]
        if getattr(self, "_pair_count", None) is None:
            self._pair_count = wp.zeros(1, dtype=wp.int32, device=d)
            self._pair_capacity = 0
        if self._pair_capacity < max(64, P // 8):
            self._pair_capacity = max(64, P // 8)
        if getattr(self, "_pair_rec_i", None) is None or self._pair_rec_i.shape[0] < self._pair_capacity:
            self._pair_rec_i = wp.zeros((self._pair_capacity, 5), dtype=wp.int32, device=d)
            self._pair_rec_f = wp.zeros((self._pair_capacity, kc.PAIR_RECORD), dtype=wp.float64, device=d)
        self._pair_count.zero_()
        self._pair_others = others
        for other, own_is_a, pair, reach in others:
            F = other.state.F
            inverse = F.T if other.lagrangian == "rigid" else np.linalg.inv(F)
            self._launch(kc.pair_samples, P,
                         [self._surface, other._surface, _mat(inverse), other._world_mesh.id, other._world_closed,
                          float(reach),
                          int(own_is_a), int(pair), self._w, self._a, other._w, other._a, self._pair_count,
                          self._pair_rec_i, self._pair_rec_f])

    def _pair_records(self, n: int) -> tuple[wp.array, wp.array, int]:
        """The device arrays (rec_i, rec_f) of ``_pair_samples``' launches and the number of
        records in them, ``n`` (their count as read back); a buffer that overflowed grows and the
        launches run again."""
        while n > self._pair_rec_i.shape[0]:
            self._pair_capacity = 2 * n
            self._pair_samples(self._pair_others)
            n = int(self._pair_count.numpy()[0])
        return self._pair_rec_i, self._pair_rec_f, n

    def _friction(self, m: int, dt: float) -> None:
        """Coulomb friction at the nodes each rubbing row group pushed (the m rows' multipliers
        ``self._lam`` at dt), on w0: against the colliders of nonzero friction, relative to the
        collider's motion (kinematic colliders carry the body), and against the moving surfaces,
        whose impulses are kept for ``_react``; ``_collider_friction`` is what the colliders'
        friction gave this step (world), both read back at the finish (``_read_friction``)."""
        self._collider_friction = np.zeros(3)
        self._rubbing = []
        for ms in self._moving:
            ms.friction = np.zeros(3)
        t, eps = self.state.time, max(1e-6, 1e-3 * self.state.dt_prev)
        rubbing = [(ci, *self._surfaces.velocity(ci, t, eps), mu, None)
                   for ci, mu in enumerate(self._collider_mu) if mu > 0.0]
        n_col = len(self._colliders)
        rubbing += [(n_col + k, ms.G, ms.g, ms.mu, ms) for k, ms in enumerate(self._moving) if ms.mu > 0.0]
        if not rubbing:
            return
        if self._friction_acc.shape[0] < 2 * len(rubbing):
            self._friction_acc = wp.zeros(2 * (n_col + len(self._moving)), dtype=wp.vec3d, device=self._device)
        acc = self._friction_acc
        acc.zero_()
        cells = int(np.prod(self._ccells))
        for j, (group, G, g, mu, _) in enumerate(rubbing):
            # the velocity change this group's rows gave each node: -M^-1 J^T lambda over them
            self._tmp.zero_()
            self._launch(kc.apply_impulses, m,
                         [self._surface, self._row_packed, self._row_ids, self._mass, self._lam,
                          group, cells, wp.float64(dt), self._tmp, self._tmp])
            self._launch(kc.node_friction, self.grid.n_nodes,
                         [self._surface, self._tmp, self._mass, self._w, self._a, wp.float64(dt), _mat(G),
                          wp.vec3d(*g), wp.float64(mu), acc[2 * j:2 * j + 2]])
        self._rubbing = [ms for *_, ms in rubbing]  # read by ``_read_friction`` at the finish

    def _read_friction(self) -> None:
        """The last ``_friction``'s impulses, read back once the step's dt is chosen (the group has
        synchronized by then: no wait of its own, one read per step however many QP attempts):
        ``_collider_friction`` and each rubbing surface's ``friction`` and ``friction_moment``."""
        if not self._rubbing:
            return
        host = self._friction_acc.numpy()
        for j, ms in enumerate(self._rubbing):
            if ms is None:
                self._collider_friction = self._collider_friction + self._axes() @ host[2 * j]
            else:
                ms.friction = self._axes() @ host[2 * j]
                ms.friction_moment = host[2 * j + 1]
        self._rubbing = []

    def _react(self, m: int, dt: float) -> np.ndarray:
        """Hand each moving surface the opposite of the impulse this body took from it this step:
        the normal part per sample (the m rows' multipliers ``self._lam`` at dt), the friction
        spread over the vertices in proportion to their normal part. Returns the total friction
        impulse this body took (world)."""
        total = np.zeros(3)
        for ms in self._moving:
            ms.step_impulse.zero_()
            ms.step_weight.zero_()
            self._launch(kc.surface_reaction, self._surface.sample_face.shape[0],
                         [self._surface, ms.mesh.id, ms.hits, self._row_of_slot, self._lam, wp.float64(dt),
                          ms.step_impulse, ms.step_weight])
            if ms.vactive:
                self._launch(kc.vertex_reaction, ms.p0.shape[0],
                             [ms.vhits, self._row_of_slot, self._lam, wp.float64(dt), ms.step_impulse, ms.step_weight])
            self._launch(kc.accumulate, ms.p0.shape[0], [ms.impulse, ms.step_impulse])
            if ms.rigid is not None:  # the next step's rows see it yield
                if ms.push is None:
                    ms.push = wp.zeros(2, dtype=wp.vec3d, device=self._device)
                ms.push.zero_()
                com = self._partner_com(ms)
                self._launch(kc.partner_push, ms.p0.shape[0], [ms.cur, ms.step_impulse, com, ms.push])
            if ms.friction is not None and np.any(ms.friction):  # friction is spread on the host
                weight = ms.step_weight.numpy()
                if weight.sum() > 0.0:
                    ms.friction_impulse += _opposite_push(ms.friction, ms.friction_moment, weight / weight.sum(),
                                                          ms.p0_host + self._fraction * (ms.p1_host - ms.p0_host))
                    total += ms.friction
        return total

    def _compact_launch(self) -> None:
        """Pack the rows that received samples (their data stay on the device), their number m in
        ``_n_rows``."""
        self._n_rows.zero_()
        self._launch(kc.compact_rows, self._row_flag.shape[0],
                  [self._row_acc, self._row_flag, self._n_rows, self._row_ids, self._row_packed,
                          self._row_of_slot])

    def _compact(self) -> int:
        """``_compact_launch`` and its m, read back."""
        self._compact_launch()
        return int(self._n_rows.numpy()[0])

    def _system_launch(self, m: int) -> None:
        """The dual QP of the m compacted rows, assembled on the device, its copy to the host (m^2 +
        8 m numbers) queued (``_system_read`` reads it)."""
        d = self._device
        size = m * m + 8 * m
        if self._system.shape[0] < size:
            self._system = wp.empty(2 * size, dtype=wp.float64, device=d)
            self._system_host = wp.empty(2 * size, dtype=wp.float64, device="cpu", pinned=d.is_cuda)
        self._system[: m * m].zero_()
        self._launch(kc.row_products, m, [self._surface, self._row_packed, self._row_ids, self._mass,
                                                           self._w, self._a, m, self._system])
        self._launch(kc.schur_complement, (m, 27 * self._row_groups),
                  [self._surface, self._row_packed, self._row_ids, self._row_of_slot, self._mass, m,
                          self._system])
        self._partner_compliance(m)
        wp.copy(self._system_host, self._system, count=size)

    def _read_system(self, m: int) -> tuple[ContactSystem, np.ndarray]:
        """``_system_launch`` and ``_system_read``: the m rows' dual QP, read back."""
        self._system_launch(m)
        wp.synchronize_device(self._device)
        return self._system_read(m)

    def _system_read(self, m: int) -> tuple[ContactSystem, np.ndarray]:
        """The m rows' dual QP of ``_system_launch`` (its copy complete), sorted by row id; and that
        order (sorted row i is the device's row order[i])."""
        host = self._system_host.numpy()[: m * m + 8 * m]
        ids = host[m * m + 7 * m:m * m + 8 * m].astype(np.int64)
        order = np.argsort(ids, kind="stable")
        vec = host[m * m:m * m + 7 * m].reshape(7, m)[:, order]
        system = ContactSystem(S=host[: m * m].reshape(m, m)[np.ix_(order, order)], Jw=vec[0], Ja=vec[1], b=vec[2],
                               ids=ids[order], overlap=vec[3],
                               jsum=vec[4:].T.copy())
        return system, order

    def _partner_com(self, ms: _MovingSurface) -> wp.vec3d:
        """A yielding moving surface's centre of mass where it is at this step (its end point moved
        back with the surface's mean motion)."""
        return wp.vec3d(*(ms.rigid[2] + (self._fraction - 1.0) * ms.rigid[3]))

    def _partner_compliance(self, m: int) -> None:
        """Add each yielding moving surface's give to the m rows' dual matrix on the device, S +=
        S_B (``kernels.eol_contact.partner_compliance``): the QP then shares each correction
        between this body's nodes and the partner by their masses instead of moving this body
        alone."""
        d = self._device
        P = self._surface.sample_face.shape[0]
        for ms in self._moving:
            if ms.rigid is None:
                continue
            if ms.wrench is None or ms.wrench.shape[0] < m:
                ms.wrench = wp.zeros((max(m, 2 * (0 if ms.wrench is None else ms.wrench.shape[0]), 16), 2),
                                     dtype=wp.vec3d, device=d)
            else:
                ms.wrench[:m].zero_()
            inv_M, inv_I, _, _ = ms.rigid
            self._launch(kc.partner_wrenches, P, [self._surface, ms.mesh.id, ms.hits, self._row_of_slot,
                                                  self._partner_com(ms), ms.wrench])
            if ms.vactive:
                self._launch(kc.vertex_wrenches, ms.p0.shape[0], [ms.vhits, self._row_of_slot, self._partner_com(ms),
                                                                   ms.wrench])
            self._launch(kc.partner_compliance, (m, m), [ms.wrench, wp.float64(inv_M), _mat(inv_I),
                                                          wp.float64(self._elastic_give(ms)), m, self._system])

    def _yield_partner(self, ms: _MovingSurface, push: float, share: float) -> None:
        """A yielding moving surface's velocity as the next rows see it (``partner_yield``): + its
        give to this step's reaction times ``push`` (1: ``_react``'s ``ms.push``; 0: none), - its
        give to ``share`` of the last interval's push, which it takes over this advance (its motion
        p0 -> p1 carries that already)."""
        if ms.push is None:
            ms.push = wp.zeros(2, dtype=wp.vec3d, device=self._device)
        inv_M, inv_I, _, _ = ms.rigid
        self._launch(kc.partner_yield, ms.p0.shape[0],
                     [ms.velocity, ms.cur, ms.push, wp.float64(push), wp.vec3d(*(share * ms.received[0])),
                      wp.vec3d(*(share * ms.received[1])), self._partner_com(ms), wp.float64(inv_M), _mat(inv_I),
                      ms.step_impulse, ms.received_v, wp.float64(share), ms.varea, wp.float64(self._elastic_give(ms))])

    def _expect_partners(self, dt_guess: float) -> None:
        """Before a step's rows: each yielding partner takes about dt_guess / T of the last
        interval's push over the step, and this step's push takes its place, so the rows see it
        yield to the difference only. Its velocity loses that share's give now (this step's QP
        adds the give to its own push, S + S_B); ``_settle_partners`` squares it with the dt taken."""
        span = max(self._span[1] - self._span[0], 1e-300)
        for ms in self._moving:
            if ms.rigid is not None and ms.impedance is not None:
                ms.pre_share = dt_guess / span
                self._yield_partner(ms, 0.0, ms.pre_share)

    def _settle_partners(self, dt: float, pushed: bool) -> None:
        """After a step of dt: each yielding partner's velocity gains the give to the step's push
        (``pushed``: ``_react`` summed it) and loses that to the rest of its share of the last
        interval's push, dt / T less what ``_expect_partners`` took off."""
        span = max(self._span[1] - self._span[0], 1e-300)
        for ms in self._moving:
            if ms.rigid is not None and (pushed or ms.impedance is not None):
                share = dt / span - ms.pre_share if ms.impedance is not None else 0.0
                self._yield_partner(ms, 1.0 if pushed else 0.0, share)
                ms.pre_share = 0.0

    def _elastic_give(self, ms: _MovingSurface) -> float:
        """1 / (rho c_p T): the normal velocity a yielding partner's surface takes per unit impulse
        per unit area pushed steadily over this advance's interval T (the plane-wave impedance
        rho c_p of its material: a push engages the column of material its P-wave reaches in T).
        Rigid give alone took a BEM cube carrying an EoL box of its own mass as four times too
        stiff: the push alternated between 50 and 280 mN s each 2 ms interval (the box's weight
        157), the cube shaking at 17 mm/s."""
        span = self._span[1] - self._span[0]
        if ms.impedance is None or not np.isfinite(ms.impedance) or span <= 0.0:
            return 0.0
        return 1.0 / (ms.impedance * span)

    def contact_rows(self) -> ContactRows | None:
        """The contact constraints of Eq. (28) at the current state, read back with J (None: no
        contact). For inspection and tests: a step keeps J on the device."""
        self._require_bound()
        if not self._colliders:
            return None
        self._collide()
        m = self._compact()
        if m == 0:
            return None
        ids = self._row_ids[:m].numpy().astype(np.int64)
        nodes = block_nodes(self.grid.node_shape, self.collision_block, self._ccells, ids)
        return rows_from_blocks(ids, self._row_packed[:m].numpy(), nodes, int(np.prod(self._ccells)))


@dataclass(eq=False)
class _StepWork:
    """One step of a body in progress (``_step_together``): what its phases hand each other.
    ``changes``: (nodes, dw, da) the rows between bodies change w and a by; ``pair_impulse``: the
    momentum they deliver (world), the part independent of dt (with their friction) and the
    part per unit dt (Eq. 31)."""

    t: float
    dt_guess: float = 0.0  # the QP's dt (the step's dt is at most this)
    cap: float = math.inf  # the step the caps allow (``advance_group``'s equal split)
    m: int = 0
    system: ContactSystem | None = None
    order: np.ndarray | None = None
    sol: ContactSolution | None = None
    active: int = 0
    own_at: Any = None  # its own rows at the nodes the rows between bodies touch (``pairs.own_rows_at``)
    changes: tuple | None = None
    pair_impulse: tuple = field(default_factory=lambda: (np.zeros(3), np.zeros(3)))
    pair_rows: int = 0
    pair_active: int = 0
    pair_overlap: float = 0.0
    fields: tuple | None = None
    vmax: np.ndarray | None = None


def _step_together(bodies: Sequence[EolBody], keys: Sequence[int], cap: float) -> None:
    """One step of EoL bodies with one dt (a single body: its own step).

    Each body computes its unconstrained velocities and its own contact rows; the rows between
    bodies come from the samples of each inside another (``_rows_between``). Bodies joined by such
    rows solve one QP (``_solve``), the others their own. The QP is solved at dt_guess and split
    on its final active set as lambda_0 + dt lambda_1 (Eq. 31). Extrapolated to a dt far from
    dt_guess that split is no QP solution: multipliers turn negative (the collider pulls the body
    in) and rows inactive at dt_guess are violated, which on landing flat faces pumped Eulerian
    velocity until dt collapsed (issue 16). So in contact dt never exceeds dt_guess, and when Eq.
    (33) asks for less (the smallest any body asks for) the QP is solved again there."""
    dt_guess = min(cap, 2.0 * min(b.state.dt_prev for b in bodies))  # the QP's guess, and the Coriolis factor's
    # each body's forces on a stream of its own, side by side on the device; the collisions follow
    # on the main stream (colliders' meshes are shared, made on first use) once all are done (the
    # QP's assembly reads w and a)
    d = bodies[0]._device
    streams = _group_streams(bodies) if d.is_cuda and len(bodies) > 1 else None
    works = []
    with _side_by_side(d, streams):
        for k, b in enumerate(bodies):
            with _on(streams, k):
                works.append(b._step_forces(cap, dt_guess))
    _own_rows_all(bodies, works)
    rows = _rows_between(bodies, keys, works) if len(bodies) > 1 else None
    problems = _problems(works, rows)
    for k in sorted({k for ks_, _ in problems for k in ks_}):
        bodies[k]._keep_unconstrained()
    cache: dict[int, Any] = {}
    guesses: dict[int, np.ndarray | None] = {}
    dts: list[float | None] = [None] * len(bodies)
    dt = cap
    for attempt in range(4):
        for p, problem in enumerate(problems):
            guesses[p] = _solve(bodies, works, rows, problem, dt_guess, guesses.get(p), cache, p)
        # no contact: a body's split and dt do not depend on the QP's dt
        todo = [k for k, w in enumerate(works) if not attempt or w.m or w.changes is not None]
        for k in todo:
            bodies[k]._step_contact(works[k], attempt, dt_guess)
            bodies[k]._split_launch(works[k], attempt)
        wp.synchronize_device(bodies[0]._device)  # every body's read-back at once
        for k in todo:
            dts[k] = bodies[k]._split_read(works[k], cap)
            if dts[k] is None:
                return  # the grid grew (step again) or the body failed
        dt = min(dts)
        if not problems:
            break
        if dt >= dt_guess * (1.0 - 1e-9) or attempt == 3:
            dt = min(dt, dt_guess)
            break
        dt_guess = dt
    # the bodies' finishes (one captured graph each, ~0.27 ms of GPU at 32 cells) side by side, each
    # on a stream of its own after the main stream's work so far (``_step_finish``): one after the
    # other they were 4.4 ms of the 32-cell pile's step
    with _side_by_side(d, streams):
        for k, (b, w) in enumerate(zip(bodies, works)):
            b._step_finish(w, dt, None if streams is None else streams[k])


def _group_scratch(bodies: Sequence[EolBody]) -> pairs.PairScratch:
    """The group's scratch (``pairs.PairScratch``), kept by its lead body."""
    lead, d = bodies[0], bodies[0]._device
    if getattr(lead, "_pair_scratch", None) is None or lead._pair_scratch.device != d:
        lead._pair_scratch = pairs.PairScratch(d)
    return lead._pair_scratch


def _group_streams(bodies: Sequence[EolBody]) -> list[wp.Stream]:
    """A CUDA stream per body of a group (kept with the group's scratch)."""
    return _group_scratch(bodies).streams(len(bodies))


@contextlib.contextmanager
def _side_by_side(device: wp.Device, streams: list[wp.Stream] | None) -> Iterator[None]:
    """Work launched inside on ``streams`` (``_on``) runs side by side: each stream first waits for
    the main stream's work so far (one event: a stream that waited on the main stream after
    another's join would wait for that stream too), and the main stream's later work waits for
    all of them, also when the work inside raises (no stream's work is left to run against the
    next step's). None: no streams (the CPU, one body), nothing to order."""
    if streams is None:
        yield
        return
    main = wp.get_stream(device)
    ready = main.record_event()
    for stream in streams:
        stream.wait_event(ready)
    try:
        yield
    finally:
        for stream in streams:
            main.wait_stream(stream)


def _on(streams: list[wp.Stream] | None, k: int) -> contextlib.AbstractContextManager:
    """Launches on ``streams[k]`` (inside ``_side_by_side``; None: on the current stream)."""
    return contextlib.nullcontext() if streams is None else wp.ScopedStream(streams[k], sync_enter=False)


def _overlapping(lo: np.ndarray, hi: np.ndarray) -> list[tuple[int, int]]:
    """The pairs (i < j) of boxes (lo, hi: (n, 3) corners) that overlap, in row-major order (one
    broadcast test: a Python loop over the 120 pairs of a 16-body pile cost ~1 ms a step)."""
    meet = np.all(hi[:, None, :] >= lo[None, :, :], axis=2)
    i, j = np.nonzero(np.triu(meet & meet.T, 1))
    return list(zip(i.tolist(), j.tolist()))


def _own_rows_all(bodies: Sequence[EolBody], works: list[_StepWork]) -> None:
    """2-3. every body's rows against the colliders and other methods' surfaces: collision and
    compaction launched for all bodies, their counts read back together, then the dual QPs
    (S = J M^-1 J^T and the rows' rates, ``work.system`` by row id) assembled for all and read
    back together: two synchronizations a step for a group instead of two per body (the 16
    bodies of a pile waited on the device 32 times a step, each time for one body's work)."""
    launched = [b._own_rows_launch(w) for b, w in zip(bodies, works)]
    if not any(launched):
        return
    wp.synchronize_device(bodies[0]._device)
    for b, w, on in zip(bodies, works, launched):
        if on:
            w.t = b._tick("collision", w.t)
            w.m = int(b._n_rows_host.numpy()[0])
            if w.m:
                b._system_launch(w.m)
    if any(w.m for w in works):
        wp.synchronize_device(bodies[0]._device)
    for b, w, on in zip(bodies, works, launched):
        if w.m:
            w.system, w.order = b._system_read(w.m)
        if on:
            w.t = b._tick("assembly", w.t)


def _rows_between(bodies: Sequence[EolBody], keys: Sequence[int], works: list[_StepWork]) -> pairs.PairRows | None:
    """The contact rows between bodies whose grid boxes overlap: every sample of each inside the
    other's tracked surface, on the device (``kernels.eol_contact.pair_samples``), summed there
    per row and per (body, row, node) (``wsim.eol.pairs.entries_device``); the host keeps each
    body's entries from the sums (``wsim.eol.pairs.rows_from_entries``)."""
    from wsim.contact import pair_friction

    boxes = []
    for b in bodies:
        b._ensure_surface()
        b._place_surface()
        boxes.append(b._grid_box())
    found = [(i, j, pair_friction(bodies[i].friction, bodies[j].friction))
             for i, j in _overlapping(np.array([lo for lo, _ in boxes]), np.array([hi for _, hi in boxes]))]
    if not found:
        return None
    near = sorted({k for i, j, _ in found for k in (i, j)})
    for k in near:
        bodies[k]._place_world_mesh()
    # a sample inside the other's surface lies in both surfaces' bounding boxes: pairs whose grid
    # boxes (padded, so larger) overlap but whose surfaces' boxes do not get no sample launches
    # (in a pile most neighbours' grid boxes overlap; each pair costs two launches and read-backs)
    d = bodies[0]._device
    scratch = _group_scratch(bodies)
    bounds, counts_host = scratch.per_body(len(bodies))
    for k in near:
        pts = bodies[k]._world_points
        wp.launch(kc.surface_bounds, pts.shape[0], [pts, k, bounds], device=d)
    lo_hi = bounds.numpy().astype(np.float64)
    pad = 1e-4 * max(float(np.linalg.norm(b[1] - b[0])) for b in boxes)  # float32 points
    keep = set(_overlapping(lo_hi[:, :3], lo_hi[:, 3:] + pad))
    found = [f for f in found if (f[0], f[1]) in keep]
    if not found:
        return None
    launches: dict[int, list[tuple]] = {}
    for p, (i, j, _) in enumerate(found):
        launches.setdefault(i, []).append((j, 1, p))
        launches.setdefault(j, []).append((i, 0, p))
    # each body's launches on a stream of its own: a launch is one tree walk per sample in the
    # other's material cells (latency, not throughput, sets its time: ~0.5 ms at 32 cells), and the
    # 16 bodies of a pile made ~23 of them a step, one after the other, 12 ms of the GPU's time
    todo_by_body = [(k, [(bodies[o], a, p, float(np.linalg.norm(boxes[o][1] - boxes[o][0]))) for o, a, p in todo])
                    for k, todo in launches.items()]
    streams = scratch.streams(len(bodies))[: len(todo_by_body)] if d.is_cuda and len(todo_by_body) > 1 else None
    with _side_by_side(d, streams):
        for i, (k, others) in enumerate(todo_by_body):
            with _on(streams, i):
                bodies[k]._pair_samples(others)
    # every body's record count in one synchronization (copies into one page-locked buffer), so
    # that the bodies' launches queue up behind each other instead of each waiting for its own
    for k in launches:
        wp.copy(counts_host, bodies[k]._pair_count, dest_offset=k, count=1)
    wp.synchronize_device(d)
    counts = counts_host.numpy().copy()
    buffers = []
    for k in launches:
        ri, rf, n = bodies[k]._pair_records(int(counts[k]))
        if n:
            buffers.append((k, ri, rf, n))
    if not buffers:
        return None
    infos = [pairs.BodyInfo(node_shape=b.grid.node_shape, origin=np.asarray(b.grid.origin, dtype=np.float64), h=b.grid.h,
                            F=b.state.F, T=b.state.T, Q=b._axes(), inv_tau=1.0 / b._positive["contact_relaxation"],
                            key=int(key), ccells=tuple(int(c) for c in b._ccells)) for b, key in zip(bodies, keys)]
    # the records are summed per row and per (body, row, node) on the device: only the sums reach
    # the host (the records of two 32-cell spheres in contact were 2 MB and ~10 ms of numpy a step)
    rows = pairs.rows_from_entries(pairs.entries_device(buffers, found, infos, scratch), found, infos)
    for k, side in rows.sides.items():  # each body's own rows at the nodes the rows between bodies touch
        w, b = works[k], bodies[k]
        if w.m:
            packed = b._row_packed[: w.m].numpy()[w.order]
            nodes = block_nodes(b.grid.node_shape, b.collision_block, b._ccells, w.system.ids)
            w.own_at = pairs.own_rows_at(side, packed, nodes)
    return rows


def _problems(works: list[_StepWork], rows: pairs.PairRows | None) -> list[tuple[list[int], np.ndarray]]:
    """The QPs of a step: bodies joined by rows between them (with those rows' indices) solve one
    together; a body with only its own rows solves its own; a body without rows none."""
    if rows is None:  # no rows between bodies (one body, or none touching): each its own, if any
        return [([k], np.zeros(0, dtype=np.int64)) for k, w in enumerate(works) if w.m]
    n = len(works)
    # the bodies' connected components over the pairs that have rows (a few dozen links at most:
    # union-find in Python, no sparse graph)
    label = list(range(n))

    def root(k: int) -> int:
        while label[k] != k:
            label[k] = label[label[k]]
            k = label[k]
        return k

    for link in np.unique(rows.bodies[:, 0] * n + rows.bodies[:, 1]):
        a, b = root(int(link) // n), root(int(link) % n)
        label[max(a, b)] = min(a, b)
    groups: dict[int, list[int]] = {}
    for k, w in enumerate(works):
        if w.m or k in rows.sides:
            groups.setdefault(root(k), []).append(k)
    out = []
    for members in groups.values():
        member = np.zeros(n, dtype=bool)
        member[members] = True
        out.append((members, np.flatnonzero(member[rows.bodies[:, 0]])))  # the rows whose A is a member
    return out


def _solve(bodies: Sequence[EolBody], works: list[_StepWork], rows: pairs.PairRows | None,
           problem: tuple[list[int], np.ndarray], dt_guess: float, guess: np.ndarray | None,
           cache: dict[int, Any], p: int) -> np.ndarray:
    """Solve one QP of a step at dt_guess (warm-started from ``guess``, the last attempt's active
    set, or else the bodies' rows active last step) and hand each body its part: its own rows'
    multipliers (``work.sol``) and the velocity changes of the rows between bodies with their
    friction (``work.changes``). Returns the active set (the next attempt's guess)."""
    members, idx = problem
    if not len(idx):  # one body, its own rows
        k = members[0]
        w, st = works[k], bodies[k].state
        if guess is None:
            guess = np.isin(w.system.ids, st.active_rows)
            guess = guess if guess.any() else None
        w.sol = solve_contact(w.system, dt_guess, active=guess)
        st.active_rows = w.system.ids[w.sol.active]
        w.active = int(w.sol.active.sum())
        return w.sol.active
    if p not in cache:  # the joint system is the same for every attempt
        sub = rows.take(idx)
        own = [works[k].system for k in members]
        cache[p] = (sub, pairs.joint_system(own, [works[k].own_at for k in members], members, sub))
    sub, system = cache[p]
    if guess is None:
        between = np.zeros(sub.m, dtype=bool)
        for k in members:
            on = sub.owner == k
            between[on] = np.isin(sub.ids[on], bodies[k].state.active_rows)
        guess = np.concatenate([np.isin(works[k].system.ids, bodies[k].state.active_rows) for k in members
                                if works[k].system is not None] + [between])
        guess = guess if guess.any() else None
    sol = solve_contact(system, dt_guess, active=guess)
    at = 0
    own_lam: dict[int, np.ndarray] = {}
    for k in members:
        w = works[k]
        if w.system is None:
            w.sol = None
            continue
        sl = slice(at, at + w.m)
        at += w.m
        w.sol = ContactSolution(lam0=sol.lam0[sl], lam1=sol.lam1[sl], active=sol.active[sl], iterations=sol.iterations)
        w.active = int(w.sol.active.sum())
        own_lam[k] = w.sol.lam0 + dt_guess * w.sol.lam1
    lam0, lam1, active = sol.lam0[at:], sol.lam1[at:], sol.active[at:]
    # the velocity change of the nodes the rows between bodies touch, every body's at once
    # (``PairRows.stacked``: body k's nodes at slices[k]), the dt-independent part and the part
    # per unit dt; the slip those rows see after every normal impulse (its own rows' too), and
    # their friction
    nodes = sub.stacked().slices
    dv = pairs.node_changes(sub, np.stack([lam0, lam1]))
    total = dv[0] + dt_guess * dv[1]
    for k, lam in own_lam.items():
        if k in nodes and works[k].own_at is not None:
            total[nodes[k]] += pairs.own_changes(sub, k, works[k].own_at, lam)
    slip = sub.slip_w + dt_guess * sub.slip_a + pairs.slip_change(sub, total)
    P = pairs.row_friction(sub, lam0 + dt_guess * lam1, slip)
    dv[0] += pairs.friction_changes(sub, P)  # the dt-independent part carries the friction
    dv += pairs.moment_couples(sub, dv)  # each pair's angular momentum kept, for both parts at once
    for k in members:
        st = bodies[k].state
        own_ids = works[k].system.ids[works[k].sol.active] if works[k].sol is not None else np.zeros(0, np.int64)
        st.active_rows = np.concatenate([own_ids, sub.ids[active & (sub.owner == k)]])
        w = works[k]
        side = sub.sides.get(k)
        if side is None:
            w.changes = None
            continue
        w.changes = (side.nodes, dv[0, nodes[k]], dv[1, nodes[k]])
        p0, p1 = (1.0 / side.inv_mass) @ dv[:, nodes[k]]  # the momentum of each part (velocity axes)
        w.pair_impulse = (side.Q @ p0, side.Q @ p1)
        on = (sub.bodies == k).any(axis=1)
        w.pair_rows, w.pair_active = int(on.sum()), int((active & on).sum())
        w.pair_overlap = float(sub.overlap[on].sum())
    return sol.active


def _opposite_push(force: np.ndarray, moment: np.ndarray, weight: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(V, 3) vertex impulses at positions x (world) with total -force and moment -moment about
    the origin: -force spread by ``weight`` (summing to one), plus the least-norm couple
    w_k omega x r_k (r_k about the weighted centroid; zero net force) that makes up the moment."""
    J = -np.outer(weight, force)
    on = weight > 0.0
    c = weight @ x
    r = x[on] - c
    w = weight[on]
    missing = -moment - np.cross(x, J).sum(axis=0)
    A = point_inertia(r, w)
    omega = np.linalg.lstsq(A, missing, rcond=1e-10)[0]
    J[on] += w[:, None] * np.cross(omega, r)
    return J


_mat = mat33
