"""The interface every body (PBD, BEM, EoL) implements so that one World can step and export it.

A body owns its operators (immutable, possibly shared) and its state, and advances itself from
one frame time to the next with whatever internal step it needs: PBD with fixed substeps, BEM
with the dt baked into its operators, EoL with an adaptive dt. The World only asks it to
``advance``, to report non-finite state, and for world-space surface points for export.

What a new method implements (the README's "Architecture" section says the same):

- ``__init__``: validate input, build or load the immutable operators (nothing on a device yet);
- ``bind(device, gravity, up)``: allocate ``self.state`` (one dataclass of everything that
  changes when the body steps, see ``wsim.state``) and scratch on the World's device;
- ``attach_colliders(surfaces)``: prepare contact with the World's ``wsim.colliders.Surfaces``
  (query poses through it, never the colliders' own functions);
- ``advance(t0, t1)``, ``points()``, ``faces``, ``check_finite(frame, t)``;
- optionally ``_state_loaded()`` (recompute what derives from the state after a restore) and
  ``signature()`` (settings a checkpoint must match besides the state's shapes).
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import warp as wp

from wsim import mesh as wmesh
from wsim.errors import InvalidParameter
from wsim.state import load_state_arrays, state_arrays
from wsim.validate import as_vec3

if TYPE_CHECKING:
    from wsim.colliders import Surfaces


class Body(ABC):
    """Base class of simulated bodies.

    ``face_uv``: (M, 3, 2) texture coordinates at the corners of ``faces`` (from the input mesh,
    ``wsim.mesh.face_uvs``), written to the USD output as ``primvars:st``; ``face_color``: (M, 3, 3)
    the input's vertex colours per corner (``wsim.mesh.face_colors``), written as a faceVarying
    ``primvars:displayColor`` in place of the body's single colour; None without them.

    Args:
        name: the body's name (its USD prim is /World/<name>); unique within a World.
        velocity: initial linear velocity of the centre of mass [m/s].
        angular_velocity: initial angular velocity about the centre of mass [rad/s].
    """

    face_uv: np.ndarray | None = None
    face_color: np.ndarray | None = None

    def __init__(
        self,
        name: str,
        velocity: Sequence[float] = (0.0, 0.0, 0.0),
        angular_velocity: Sequence[float] = (0.0, 0.0, 0.0),
    ) -> None:
        if not isinstance(name, str) or not name:
            raise InvalidParameter(f"a body name must be a non-empty string, got {name!r}")
        self.name = name
        self.initial_velocity = as_vec3(velocity, f"body '{name}': velocity")
        self.initial_angular_velocity = as_vec3(angular_velocity, f"body '{name}': angular_velocity")
        self.state: Any = None  # the method's state dataclass, allocated by bind
        self.timings: dict[str, float] = {}  # seconds per stage of the method's step (``_tick``)
        self.profile = False  # synchronize the device at each ``_tick`` so GPU time lands in its stage
        self._device: wp.Device | None = None  # set by bind
        self.frame_dt: float | None = None  # the World's frame length [s], set at its first step
        #: the body's display colour in the USD output (RGB in [0, 1]); None: one of a palette, by
        #: the body's place in the World
        self.display_color: tuple[float, float, float] | None = None

    @property
    def bound(self) -> bool:
        """True once the body belongs to a World (its state is allocated)."""
        return self._device is not None

    def _frame_of(self, t: float, start: bool = False) -> int | None:
        """The World frame being computed when a user's function is evaluated at time t [s], for
        error messages; numbered like ``SimulationDiverged.step`` (the frame at whose end the state
        lands: t in (37/fps - 1/fps, 37/fps] is frame 37). ``start``: t is a step's start time (the
        step lies after it), else its end time. None before the body's first World step."""
        if not self.frame_dt:
            return None
        q = t / self.frame_dt
        return math.floor(q + 1e-9) + 1 if start else max(math.ceil(q - 1e-9), 0)

    def _require_bound(self) -> None:
        if self._device is None:
            raise InvalidParameter(f"body '{self.name}': add it to a World (world.add) before reading or setting its state")

    # -- conservation read-outs ----------------------------------------------------------------
    # Every body type gives these with the same meaning, so users and tests can watch what the
    # physics conserves. Totals over the whole body (rigid and deformation motion), world axes.
    def linear_momentum(self) -> np.ndarray:
        """Total linear momentum sum m v [kg m/s] (world)."""
        raise NotImplementedError(f"{type(self).__name__} does not report linear momentum")

    def angular_momentum(self, about: Sequence[float] | None = None) -> np.ndarray:
        """Total angular momentum sum m (x - p) x v [kg m^2/s] (world) about the point p = ``about``
        [m] (world), by default the body's current centre of mass."""
        raise NotImplementedError(f"{type(self).__name__} does not report angular momentum")

    def kinetic_energy(self) -> float:
        """Total kinetic energy 1/2 sum m |v|^2 [J]."""
        raise NotImplementedError(f"{type(self).__name__} does not report kinetic energy")

    def center_of_mass(self) -> np.ndarray:
        """The body's centre of mass [m] (world): the point ``angular_momentum()`` is taken about."""
        raise NotImplementedError(f"{type(self).__name__} does not report its centre of mass")

    # -- state --------------------------------------------------------------------------------
    def get_state(self) -> dict[str, np.ndarray]:
        """A copy of the body's state as named host arrays (what a checkpoint stores)."""
        self._require_bound()
        return state_arrays(self.state)

    def set_state(self, arrays: dict[str, np.ndarray]) -> None:
        """Load state saved by ``get_state`` of a body built the same way; checked whole before
        anything changes (``wsim.state.StateMismatch`` otherwise)."""
        self._require_bound()
        load_state_arrays(self.state, arrays, f"body '{self.name}'")
        self._state_loaded()

    def _state_loaded(self) -> None:
        """Hook after ``set_state``: recompute quantities derived from the state (none by default)."""

    def signature(self) -> dict[str, Any]:
        """What a checkpoint of this body must match besides the state's shapes: its class, its
        surface and the settings that change the meaning of the state. Extended by subclasses."""
        import hashlib

        return {"class": type(self).__name__,
                "faces": hashlib.sha256(np.ascontiguousarray(self.faces, dtype=np.int32).tobytes()).hexdigest()[:16]}

    @property
    @abstractmethod
    def faces(self) -> np.ndarray:
        """(M, 3) int32 surface triangles, fixed for the body's life."""

    @abstractmethod
    def bind(self, device: wp.Device, gravity: np.ndarray, up: np.ndarray) -> None:
        """Allocate state on ``device``; called once by ``World.add``, so state can be read at once.

        ``gravity`` [m/s^2] and the unit ``up`` vector are the World's.
        """

    @abstractmethod
    def attach_colliders(self, surfaces: Surfaces) -> None:
        """Prepare contact with the World's colliders (``surfaces``: poses, velocities and device
        meshes through one interface); called once before the first step."""

    @abstractmethod
    def advance(self, t0: float, t1: float) -> None:
        """Advance the state from time t0 to t1 [s] (one frame)."""

    def last_push(self, key: int, n: int) -> np.ndarray | None:
        """(n, 3) what this body pushed the moving surface ``key`` (of n vertices) with over the
        last interval, as its state's ``partner_push`` keeps it (a pushing EoL or PBD body), or
        None: the surface takes it over the coming interval, and the pusher yields to its change."""
        pushed = self.state.partner_push
        last = pushed[pushed[:, 0] == key, 1:]
        return last.copy() if len(last) == n else None

    def _keep_pushes(self, pushes: dict[int, np.ndarray]) -> None:
        """Keep ``pushes`` (per surface key, (V, 3) [N s]) as the state's ``partner_push``."""
        self.state.partner_push = np.concatenate(
            [np.zeros((0, 4))] + [np.column_stack([np.full(len(J), float(k)), np.asarray(J, dtype=np.float64)])
                                  for k, J in pushes.items()])

    def expect_push(self, key: int, impulses: np.ndarray) -> None:
        """Take ``impulses`` (V, 3) [N s] as what the moving surface ``key`` receives over the
        coming interval (``last_push``, which this body yields to the change from; by default
        what it pushed it with over the last one): the World's implicit coupling sets its guess
        this way (``World(coupling=...)``)."""
        pushed = self.state.partner_push
        keys = [int(k) for k in dict.fromkeys(pushed[:, 0]) if int(k) != key]
        self._keep_pushes({**{k: pushed[pushed[:, 0] == k, 1:] for k in keys}, key: impulses})

    def check_frames(self, last: int, fps: float) -> None:
        """Raise before a run if this body cannot be stepped up to World frame ``last`` (at ``fps``);
        most bodies can step forever (a reconstruction covers its recording's frames only)."""

    @abstractmethod
    def points(self) -> np.ndarray:
        """(N, 3) world-space surface vertex positions [m] at the current time, as numpy float64."""

    @abstractmethod
    def check_finite(self, frame: int, time: float) -> None:
        """Raise ``SimulationDiverged`` naming this body, the frame and the quantity if state is NaN/Inf."""

    def _tick(self, stage: str, t0: float) -> float:
        """Add the seconds since t0 to ``self.timings[stage]`` and return now. With ``self.profile``
        the device is synchronized first, so GPU time lands in its own stage."""
        if self.profile and self._device is not None and not self._device.is_cpu:
            wp.synchronize_device(self._device)
        t1 = time.perf_counter()
        self.timings[stage] = self.timings.get(stage, 0.0) + t1 - t0
        return t1


def checked_vertex_impulses(name: str, impulses: Any, vertices: int, duration: float) -> np.ndarray:
    """``add_vertex_impulses``' arguments checked, naming the body: finite (vertices, 3) impulses
    (float64) and a positive duration."""
    J = np.asarray(impulses, dtype=np.float64)
    if J.shape != (vertices, 3) or not np.all(np.isfinite(J)):
        raise InvalidParameter(f"body '{name}': vertex impulses must be finite, shape ({vertices}, 3); got {J.shape}")
    if not (duration > 0.0):
        raise InvalidParameter(f"body '{name}': impulse duration must be > 0 s, got {duration}")
    return J


class VertexImpulses:
    """What a body needs to be pushed by bodies of another method (BEM and EoL; issue 18):
    ``add_vertex_impulses`` keeps the push in the state (``coupling_force`` (V, 3) [N],
    ``coupling_until`` [s], ``coupling_impulse`` [N s]: a checkpoint carries them) and registers the
    body's load for it once. The body defines ``_coupling_vertices`` (V), ``_coupling_time`` (its
    time now) and ``_register_coupling``.

    A PBD body that pushes such a body also keeps its surface vertices out of its own surface,
    the correction shared with each vertex's lumped mass (``vertex_masses``;
    ``wsim.kernels.pbd_contact.moving_points_contact``): a cube's corners sank 35-44 mm (BEM)
    and 40 mm (EoL) between the particles of a coarse PBD box."""

    vertices_kept_out = True

    def vertex_masses(self) -> np.ndarray:
        """(V,) the body's mass lumped onto its surface vertices by their areas [kg], on the
        surface where it first is asked (areas do not change with a rigid motion)."""
        if getattr(self, "_vertex_masses", None) is None:
            areas = wmesh.vertex_areas(self.points(), self.faces)
            self._vertex_masses = self.mass * areas / areas.sum()
        return self._vertex_masses

    def add_vertex_impulses(self, impulses: Any, duration: float, keep_pending: bool = False) -> None:
        """Deliver momentum ``impulses`` [N s] (V, 3) per mesh vertex (world axes) as constant point
        forces impulses / duration over the next ``duration`` seconds, replacing what is left of an
        earlier call (``keep_pending``: adding what is left of it, ``pending_vertex_impulses``, to
        them). The World hands a body this way what bodies of other methods pushed it with
        over the last coupling interval (explicit two-way coupling), or its guess of what they
        push it with over the coming one (implicit coupling, ``World(coupling=...)``)."""
        self._require_bound()
        J = checked_vertex_impulses(self.name, impulses, self._coupling_vertices(), duration)
        st = self.state
        total = J + self.pending_vertex_impulses() if keep_pending else J
        st.coupling_force = total / duration
        st.coupling_until = self._coupling_time() + duration
        st.coupling_impulse = st.coupling_impulse + J.sum(axis=0)
        self._register_coupling()

    def pending_vertex_impulses(self) -> np.ndarray:
        """(V, 3) the momentum [N s] an earlier ``add_vertex_impulses`` has still to deliver."""
        self._require_bound()
        st = self.state
        left = st.coupling_until - self._coupling_time()
        n = self._coupling_vertices()
        if left <= 1e-12 or st.coupling_force.shape != (n, 3):
            return np.zeros((n, 3))
        return st.coupling_force * left

    @property
    def coupling_impulse(self) -> np.ndarray:
        """Momentum handed to the body by ``add_vertex_impulses`` so far [N s] (world)."""
        return np.zeros(3) if self.state is None else self.state.coupling_impulse
