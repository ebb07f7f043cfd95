"""World: the clock, the bodies, the colliders and the frame loop.

The World owns time. ``step`` advances every body from frame time t_f = f / fps to t_{f+1}; each
body covers that interval with its own internal steps (PBD substeps, BEM's fixed dt, EoL's
adaptive dt). After each frame every body is checked for NaN/Inf, and ``run`` hands the frame to
the USD writer. BEM bodies of one dt that are joined by ``PointJoint`` s or may touch
(``body_contact``) step together: one constraint solve per step covers all of them
(``wsim.constraints.solve_group``, ``wsim.contact``); PBD bodies that may touch step their
substeps in lockstep (``wsim.pbd.contact``); EoL bodies that may touch step together with one dt
and one contact QP (``EolBody.advance_group``, ``wsim.eol.pairs``). Across methods contact is an
explicit exchange at a coupling interval: one body (the pusher: PBD or EoL against BEM; between PBD
and EoL bodies the method ``_eol_pushes_pbd`` picks per group of EoL bodies) keeps
itself out of the other's surface as it moves over the interval and the other is handed the
opposite impulse over the next interval (``_couple_surfaces``).
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from wsim import constraints as wc
from wsim.body import Body
from wsim.validate import as_vec3, finite_number, output_folder, positive_int
from wsim.colliders import Collider, Surfaces
from wsim.device import resolve_device
from wsim.errors import InvalidParameter
from wsim.usd import UsdWriter, check_up_axis

#: longest coupling interval [s] when EoL bodies push BEM bodies (``World(coupling_dt=None)``): the
#: exchange's lag rang an EoL box resting on another when EoL bodies still pushed each other this
#: way (mean speed 142 mm/s at 1/60 s intervals, 9.6 at 1/240 s, 4.6 at 1/960 s; ``tools/study_coupling.py``)
EOL_COUPLING_DT = 1.0e-3

_UP = {"Y": np.array([0.0, 1.0, 0.0]), "Z": np.array([0.0, 0.0, 1.0])}


@dataclass(frozen=True)
class RunSummary:
    """What ``World.run`` did: frames simulated, simulated time [s], wall-clock seconds, output file."""

    frames: int
    sim_time: float
    wall_seconds: float
    out: Path | None
    device: str
    bodies: dict[str, int] = field(default_factory=dict)
    appended: bool = False  # the frames were added to an existing file of this scene (``run(append=True)``)

    @property
    def seconds_per_frame(self) -> float:
        return self.wall_seconds / max(self.frames, 1)

    def __str__(self) -> str:
        where = f" -> {self.out}" if self.out else ""
        parts = ", ".join(f"{k} ({v} vertices)" for k, v in self.bodies.items())
        return (
            f"{self.frames} frames ({self.sim_time:.3f} s simulated) in {self.wall_seconds:.2f} s "
            f"({1000.0 * self.seconds_per_frame:.1f} ms/frame) on {self.device}: {parts}{where}"
        )


class World:
    """A scene: bodies and colliders stepped frame by frame.

    Args:
        fps: frames per second of the output animation [1/s].
        gravity: gravitational acceleration [m/s^2]; None means 9.81 m/s^2 down the up axis.
        device: Warp device ("cpu", "cuda:0", ...); None picks cuda:0 when present, else cpu.
        up_axis: "Y" or "Z", the axis the scene is built in (ground planes default to it).
        coupling_dt: the interval [s] at which bodies exchange contact explicitly (a push reaches
            the other body one interval late): PBD with BEM and EoL bodies, EoL with BEM bodies;
            EoL bodies that may meet within it step together (one QP, no lag). It must divide the
            frame, and every BEM body's dt must divide it. None: automatic - with PBD bodies and
            BEM or EoL bodies in one World, the shortest interval that is a whole number of every
            BEM body's steps and at least one PBD substep; with EoL and BEM bodies (and no PBD)
            the longest interval of whole BEM steps no longer than ``EOL_COUPLING_DT`` (1 ms);
            otherwise the frame. A frame-long interval made a thrown ball rebound 40 % too fast
            off a BEM cube (above the elastic bound: the lag adds energy; ``tools/study_coupling.py``).
        body_contact: bodies touch each other: BEM bodies of one dt (``wsim.contact``, one
            constraint solve per step), PBD bodies (``wsim.pbd.contact``, substeps in lockstep),
            EoL bodies (one QP, ``wsim.eol.pairs``) and every pair across methods (explicit
            coupling, ``coupling_dt``); False lets them pass through each other. BEM bodies of
            different dt cannot touch each other: a frame in which they may raises
            ``InvalidParameter`` (the frames before it are kept).
        coupling: how a PBD or EoL body's push reaches a BEM body. "explicit": one interval late.
            "implicit": within the interval - the interval is stepped again, every body restored,
            until the push the pushers hand over matches the guess the BEM bodies stepped with
            (``coupling_tol``, at most ``coupling_iterations`` passes; what is left over reaches
            them in the next interval, so momentum stays exact; each pass runs the bodies'
            handle motions and loads over the interval again). "auto" (default): implicit for the
            intervals in which a PBD or EoL body at least twice as heavy as a BEM body
            (``IMPLICIT_MASS_RATIO``) may touch it (one interval late, a heavier pusher hands back
            the overshoot of each push: an 8 kg BEM cube on a 48 kg EoL slab shook at 23 mm/s,
            1.0 implicitly; a 24 kg, 98-vertex PBD box rocking on a 4 kg cube gained 0.45 J in
            2 s, 0.08 implicitly), and for the intervals after one in which a PBD body carried
            at least half a BEM body's weight (``SUPPORT_FRACTION``: an 8 kg BEM cube resting on
            an 8 kg PBD slab was kicked at 10 mm/s by each interval's late push, 1 implicitly);
            explicit otherwise.
        coupling_tol: the implicit coupling's tolerance: the change of the push between passes
            relative to the push (root mean square over every pushed vertex).
        coupling_iterations: the implicit coupling's passes per interval at most.
    """

    def __init__(
        self,
        fps: float = 30.0,
        gravity: Sequence[float] | None = None,
        device: str | None = None,
        up_axis: str = "Y",
        body_contact: bool = True,
        coupling_dt: float | None = None,
        coupling: str = "auto",
        coupling_tol: float = 0.05,
        coupling_iterations: int = 6,
    ) -> None:
        fps_f = float(fps)
        if not math.isfinite(fps_f) or fps_f <= 0.0:
            raise InvalidParameter(f"World: fps = {fps} must be > 0")
        self.fps = fps_f
        self.up_axis = check_up_axis(up_axis)
        self.up = _UP[self.up_axis]
        self.gravity = -9.81 * self.up if gravity is None else as_vec3(gravity, "World: gravity")
        self.device = resolve_device(device)
        self.bodies: list[Body] = []
        self.colliders: list[Collider] = []
        self.frame = 0
        self._bound = False
        self.surfaces: Surfaces | None = None  # the colliders as kinematic surfaces, made at the first step
        self.joints: list[wc.PointJoint] = []
        self.body_contact = bool(body_contact)
        self.coupling_steps = 1  # coupling intervals per frame (coupling_dt; automatic: see _bind)
        self._coupling_given = coupling_dt is not None
        if coupling not in ("auto", "explicit", "implicit"):
            raise InvalidParameter(f"World: coupling = {coupling!r} must be 'auto', 'explicit' or 'implicit'")
        self.coupling = coupling
        self.coupling_tol = finite_number(coupling_tol, "World: coupling_tol")
        if not 0.0 < self.coupling_tol < 1.0:
            raise InvalidParameter(f"World: coupling_tol = {coupling_tol} must be in (0, 1)")
        self.coupling_iterations = positive_int(coupling_iterations, "World: coupling_iterations")
        # implicit intervals stepped, their passes, and those that ended at ``coupling_iterations``
        # unconverged (``_advance_implicit``)
        self.coupling_stats = {"implicit_intervals": 0, "passes": 0, "unconverged": 0}
        if coupling_dt is not None:
            c = finite_number(coupling_dt, "World: coupling_dt [s]")
            k = int(round(self.frame_dt / c)) if c > 0.0 else 0
            if k < 1 or abs(k * c - self.frame_dt) > 1e-9 * self.frame_dt:
                raise InvalidParameter(f"World: coupling_dt = {coupling_dt} s must divide the frame ({self.frame_dt:.6g} s) "
                                       f"into whole intervals")
            self.coupling_steps = k
        self._groups: list[tuple[list[Body], list]] = []  # bodies stepped together, their joints as points
        self._group_sets: list[list] = []  # per group, its sets of bodies that step together (``_step_sets``)
        self._sets: list = []  # the sets of the bodies in no group
        self.timings: dict[str, float] = {}  # seconds per stage: each method's stepping, "coupling"
        self.profile = False  # synchronize the device after each stage (``timings`` then splits GPU time)

    @property
    def frame_dt(self) -> float:
        """Length of one frame [s]."""
        return 1.0 / self.fps

    @property
    def time(self) -> float:
        """Current simulation time [s]."""
        return self.frame / self.fps

    def add(self, body: Body) -> Body:
        """Add a body (returned, for chaining); names must be unique."""
        if self._bound:
            raise InvalidParameter(f"World: add body '{getattr(body, 'name', body)}' before the first step")
        if not isinstance(body, Body):
            raise InvalidParameter(f"World.add takes a wsim body (PbdBody, ...), got {type(body).__name__}")
        if any(b.name == body.name for b in self.bodies):
            raise InvalidParameter(f"World: a body named '{body.name}' already exists")
        body.bind(self.device, self.gravity, self.up)
        self.bodies.append(body)
        return body

    def add_collider(self, collider: Collider) -> Collider:
        """Add a ground plane or mesh collider (returned)."""
        if self._bound:
            raise InvalidParameter(f"World: add collider '{collider.name}' before the first step")
        if not isinstance(collider, Collider):
            raise InvalidParameter(f"World.add_collider takes a GroundPlane or MeshCollider, got {type(collider).__name__}")
        if any(c.name == collider.name for c in self.colliders):
            raise InvalidParameter(f"World: a collider named '{collider.name}' already exists")
        self.colliders.append(collider)
        return collider

    def add_joint(self, joint: wc.PointJoint) -> wc.PointJoint:
        """Join vertices of two bodies of this World (returned); the joined bodies then step together."""
        if self._bound:
            raise InvalidParameter(f"World: add joint '{getattr(joint, 'name', joint)}' before the first step")
        if not isinstance(joint, wc.PointJoint):
            raise InvalidParameter(f"World.add_joint takes a wsim.PointJoint, got {type(joint).__name__}")
        for body, ids in ((joint.body_a, joint.vertices_a), (joint.body_b, joint.vertices_b)):
            if not any(body is b for b in self.bodies):
                raise InvalidParameter(f"joint '{joint.name}': body '{getattr(body, 'name', body)}' is not in this World "
                                       "(add both bodies with world.add first)")
            if not hasattr(body, "constraint_begin"):
                raise InvalidParameter(f"joint '{joint.name}': body '{body.name}' is a {type(body).__name__}; "
                                       "joints join BEM bodies")
            n = len(body.rest_vertices)
            bad = ids[(ids < 0) | (ids >= n)]
            if bad.size:
                raise InvalidParameter(f"joint '{joint.name}': vertex id {int(bad[0])} of body '{body.name}' is out of "
                                       f"range [0, {n - 1}]")
        if abs(joint.body_a.dt - joint.body_b.dt) > 1e-12 * joint.body_a.dt:
            raise InvalidParameter(f"joint '{joint.name}': bodies '{joint.body_a.name}' (dt = {joint.body_a.dt} s) and "
                                   f"'{joint.body_b.name}' (dt = {joint.body_b.dt} s) must step with one dt")
        self.joints.append(joint)
        return joint

    def _bind(self) -> None:
        if not self._bound:
            if not self._coupling_given:
                self.coupling_steps = _automatic_coupling_steps(self.bodies, self.frame_dt) if self.body_contact else 1
            interval = self.frame_dt / self.coupling_steps
            for b in self.bodies:
                b.frame_dt = self.frame_dt
                dt = getattr(b, "dt", None) if hasattr(b, "constraint_begin") else None
                if self.coupling_steps > 1 and dt and abs(interval / dt - round(interval / dt)) > 1e-6:
                    raise InvalidParameter(f"World: body '{b.name}' steps with dt = {dt:.6g} s, which does not divide "
                                           f"the coupling interval {interval:.6g} s (coupling_dt)")
            self.surfaces = Surfaces(self.colliders, self.up)
            for body in self.bodies:
                body.attach_colliders(self.surfaces)
            links = []
            # PBD bodies that can touch step in lockstep (wsim.pbd.contact)
            self._pbd = [b for b in self.bodies if hasattr(b, "advance_together")] if self.body_contact else []
            self._lockstep = self._pbd if len(self._pbd) > 1 else []
            self._lockstep_graphs: dict = {}  # the recorded lockstep frame (CUDA)
            # explicit coupling: bodies that are pushed (BEM; between EoL and PBD bodies the method
            # ``_eol_pushes_pbd`` picks per group of EoL bodies that may touch, decided again before
            # each interval, ``_update_roles``) and that push (PBD, EoL). A pusher keeps itself out of
            # its targets' surfaces after they have stepped and hands them the momentum
            # (``_targets``), which reaches them one interval late. EoL bodies do not push each
            # other (touching EoL bodies step together with one QP, ``EolBody.advance_group``), nor
            # PBD bodies each other (lockstep, ``wsim.pbd.contact``).
            self._eol = [b for b in self.bodies if hasattr(b, "advance_group")] if self.body_contact else []
            self._eol_groups: list[list[Body]] | None = None  # this interval's EoL groups (``_update_roles``)
            self._interval_points: dict[int, np.ndarray] = {}  # points read at the interval's start, by id
            first = _eol_pushes_pbd(self._pbd, self._eol)
            self._assign_roles({id(b): first for b in self._eol})
            self._apart: list[tuple[Body, Body]] = []  # BEM bodies that cannot touch (``_check_apart``)
            if self.body_contact:  # bodies that can touch: participants of one dt
                by_dt: dict[float, list[Body]] = {}
                for b in self.bodies:
                    if hasattr(b, "constraint_begin"):
                        by_dt.setdefault(round(float(b.dt), 15), []).append(b)
                links = [(g[0], b) for g in by_dt.values() for b in g[1:]]
                groups = list(by_dt.values())
                self._apart = [(a, b) for i, g in enumerate(groups) for h in groups[i + 1:] for a in g for b in h]
            self._groups = _joint_groups(self.joints, links)
            # bodies that step together (``_step_sets``: BEM bodies on one operator set, PBD bodies
            # in one launch set): sets within each group, and sets of the bodies no group steps
            # (PBD bodies in lockstep are stepped by ``advance_together``, which uses their batch)
            grouped = {id(b) for bodies, _ in self._groups for b in bodies}
            self._group_sets = [_step_sets(bodies) for bodies, _ in self._groups]
            self._sets = _step_sets([b for b in self.bodies if id(b) not in grouped])
            self._index = {id(b): i for i, b in enumerate(self.bodies)}  # a body's key in the exchange
            self._bound = True

    def _assign_roles(self, eol_pushes: dict[int, bool]) -> None:
        """Who pushes whom in the explicit coupling (``_bind``; again when an answer of
        ``_eol_pushes_pbd`` changes, ``_update_roles``): ``eol_pushes`` says per EoL body (by id)
        whether it pushes the PBD bodies (else they push it; one answer per group of EoL bodies
        that may touch); from it the pushed bodies (BEM, EoL, and PBD where an EoL body pushes),
        each pusher's targets, and the pairs whose push the implicit coupling finds."""
        eol = {id(b) for b in self._eol}
        pbd = {id(b) for b in self._pbd}
        self._eol_pushes = dict(eol_pushes)
        any_pushes = any(self._eol_pushes.values())
        self._pushed = [b for b in self.bodies if hasattr(b, "add_vertex_impulses")
                        and (id(b) not in pbd or any_pushes)] if self.body_contact else []
        pushers = [b for b in self.bodies if hasattr(b, "set_moving_surfaces")] if self._pushed else []

        def pushes(p: Body, b: Body) -> bool:
            if b is p or (id(p) in eol and id(b) in eol) or (id(p) in pbd and id(b) in pbd):
                return False
            if id(p) in pbd and id(b) in eol:
                return not self._eol_pushes[id(b)]
            if id(p) in eol and id(b) in pbd:
                return self._eol_pushes[id(p)]
            return True  # a BEM target: every pusher pushes it

        self._targets = {id(p): [b for b in self._pushed if pushes(p, b)] for p in pushers}
        self._pushers = [p for p in pushers if self._targets[id(p)] and id(p) not in eol]  # PBD
        # pushers of BEM bodies whose push the implicit coupling iterates (``_advance_implicit``):
        # automatically PBD and EoL bodies at least ``IMPLICIT_MASS_RATIO`` times as heavy as
        # the BEM body (one interval late, a heavier pusher hands back the overshoot of each push)
        self._implicit = [(p, b) for p in pushers for b in self._targets[id(p)] if hasattr(b, "constraint_begin")
                          and (self.coupling == "implicit"
                               or (self.coupling == "auto" and _mass(p) >= IMPLICIT_MASS_RATIO * _mass(b)))]
        # and, automatically, a lighter PBD pusher in the intervals after it carried a BEM body's
        # weight (``_supports``): each interval's push from a few particles' contacts, handed over
        # late, kicked an 8 kg BEM cube resting on an 8 kg PBD slab at 10 mm/s (0.6-1.1 found within
        # the interval); an EoL body's QP push does not (an 8 kg BEM cube on an 8 kg EoL box
        # rests at 0.1 mm/s handed over late)
        iterated = {(id(p), id(b)) for p, b in self._implicit}
        self._supported = [(p, b) for p in pushers if id(p) in pbd for b in self._targets[id(p)]
                           if hasattr(b, "constraint_begin") and self.coupling == "auto"
                           and (id(p), id(b)) not in iterated]

    def _update_roles(self, interval: float) -> None:
        """Before an interval: the groups of EoL bodies that may touch over it (``_touching``,
        kept for the interval's EoL stages) and, per group, whether its bodies push the PBD bodies
        within its reach over it (``_eol_pushes_pbd``, from where the bodies are: a light PBD
        ball resting on a heavy EoL block pushes it while a heavy EoL ball elsewhere pushes the
        light PBD box it rests on; with one answer for the World the ball on the block, pushed,
        kept bouncing). A group with no PBD body in reach keeps its answer. On a change the roles
        are assigned again and the bodies that push no more let go of the surfaces they kept out
        of (what they pushed is still handed over)."""
        g = float(np.linalg.norm(self.gravity))
        points: dict[int, np.ndarray] = {}
        boxes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._eol_groups = _touching(self._eol, interval, g, points, boxes)
        self._interval_points = points  # read before anything steps: the interval's start (``_step_interval``)
        # without gravity the answer is always that the EoL bodies push: no PBD body is read; with
        # it only PBD bodies lighter than an EoL body can change it (``_eol_pushes_pbd``)
        pbd = [p for p in self._pbd if g > 0.0 and _mass(p) < max(float(e.mass) for e in self._eol)]
        # the rule's reach boxes (each body's contact margin, no cell), made once an interval for
        # every group and part asked (a PBD body's reads its velocities back from the device)
        rule_boxes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        eol_pushes = dict(self._eol_pushes)

        def near(group: list[Body]) -> list[Body]:  # the PBD bodies in the group's reach
            return [p for p in pbd if any(_overlap(_rule_box(p, points, rule_boxes, interval, g), boxes[id(e)])
                                          for e in group)]

        def answer(group: list[Body]) -> bool:
            close = near(group)
            if close or g == 0.0:
                return _eol_pushes_pbd(close, group, self.gravity, interval, points, rule_boxes)
            return eol_pushes[id(group[0])]  # nothing to push: as before (its one answer, or the first's)

        groups = []
        for group in self._eol_groups:
            pushes = answer(group)
            if len(group) > 1 and near(group):
                # a group whose bodies can meet only through the cell the groups are grown by may be
                # split where its parts want different pushers: a 1.2 kg PBD box, 6 cm thick,
                # between a 19 kg EoL block under it and a 3.5 kg EoL ball on it joined the two in one
                # group, both pushed the box from both sides one interval late, and at E = 2e5 Pa
                # the stack blew up at 0.76 s (+99 J; an independent check); apart, the box pushes
                # the block and the ball the box
                parts = _touching(group, interval, g, points, cells=0.0)
                answers = [answer(part) for part in parts]
                if len(set(answers)) > 1:
                    groups += parts
                    eol_pushes.update({id(e): a for part, a in zip(parts, answers) for e in part})
                    continue
            groups.append(group)
            eol_pushes.update({id(e): pushes for e in group})
        self._eol_groups = groups
        if eol_pushes == self._eol_pushes:
            return
        before = {k for k, targets in self._targets.items() if targets}
        self._assign_roles(eol_pushes)
        for b in self._pbd + self._eol:
            if id(b) in before and not self._targets.get(id(b)):
                b.set_moving_surfaces([])

    def checkpoint(self, path: str | Path) -> Path:
        """Save the frame and every body's state to ``path`` (HDF5, written atomically; see
        ``wsim.checkpoint``). Returns the path."""
        from wsim import checkpoint

        return checkpoint.save(self, path)

    def restore(self, path: str | Path) -> int:
        """Load a checkpoint saved by a World built by the same scene script (same bodies, settings
        and colliders) and continue from its frame, which is returned. A file from another scene or
        format version, or one that cannot be read, raises ``CheckpointError`` and changes nothing."""
        from wsim import checkpoint

        return checkpoint.restore(self, path)

    def step(self) -> None:
        """Advance every body by one frame (writes nothing). Raises SimulationDiverged on NaN/Inf."""
        self._advance_frame()
        self._check_frame()

    def _advance_frame(self) -> None:
        self._bind()
        if self._apart:
            self._check_apart()
        self.surfaces.new_frame(self.frame + 1)
        k = self.coupling_steps
        if k > 1:  # bodies that take no part in contact step the whole frame at once
            for body in self.bodies:
                if not _couples(body):
                    self._timed(_stage(body), body.advance, self.frame / self.fps, (self.frame + 1) / self.fps)
        for i in range(k):  # coupling intervals of the frame
            self._advance_interval((self.frame * k + i) / (self.fps * k), (self.frame * k + i + 1) / (self.fps * k))
        self.frame += 1

    def _check_apart(self) -> None:
        """Raise before a frame in which BEM bodies of different dt may touch: contact between BEM
        bodies is a constraint solve per step of bodies that step together, and no exchange between
        BEM bodies of different steps exists, so they would pass through each other unnoticed."""
        g = float(np.linalg.norm(self.gravity))
        for a, b in self._apart:
            if _in_reach(a, b, self.frame_dt, g):
                raise InvalidParameter(
                    f"World: BEM bodies '{a.name}' (dt = {float(a.dt):.6g} s) and '{b.name}' (dt = {float(b.dt):.6g} s) "
                    f"may touch in frame {self.frame + 1} (t = {self.time:.6g} s), but BEM bodies touch only bodies "
                    f"of their own dt (one constraint solve per step): give them one dt, or pass "
                    f"World(body_contact=False) to let bodies pass through each other")

    def _timed(self, stage: str, fn: Callable, *args) -> Any:
        """Run fn(*args) and add its seconds to ``timings[stage]`` (after a device synchronization
        when ``profile`` is on, so GPU time lands in its own stage); returns what fn returns."""
        t = _time.perf_counter()
        out = fn(*args)
        if self.profile and not self.device.is_cpu:
            import warp as wp

            wp.synchronize_device(self.device)
        self.timings[stage] = self.timings.get(stage, 0.0) + _time.perf_counter() - t
        return out

    def _advance_interval(self, t0: float, t1: float) -> None:
        self._interval_points = {}
        if self._pbd and self._eol:
            self._timed("coupling", self._update_roles, t1 - t0)
        if self._implicit or self._supported:
            g = float(np.linalg.norm(self.gravity))
            near = {id(b) for p, b in self._implicit if _in_reach(p, b, t1 - t0, g)}
            near |= {id(b) for p, b in self._supported if _supports(p, self._index[id(b)], b, self.gravity, t1 - t0)}
            if near:
                self._advance_implicit(t0, t1, [b for b in self._pushed if id(b) in near])
                return
        self._step_interval(t0, t1)

    def _advance_implicit(self, t0: float, t1: float, targets: list[Body]) -> None:
        """One coupling interval with the pushes on the BEM bodies ``targets`` found implicitly
        (``coupling``): each pass steps every body, the targets under a guess of what every
        pusher pushes them with over this interval (with what is still pending from the
        interval before), the pushers with each target yielding to the change from that guess
        (``PbdBody.set_moving_surfaces``, ``EolBody.set_moving_surfaces``); if the pushes they
        hand over differ from the guess by more than ``coupling_tol``, every body is restored
        and the interval stepped again from a guess moved towards them (Aitken's relaxation of
        the fixed point, as in partitioned fluid-structure coupling: the first guess is each
        pusher's push of the interval before, less its share of what is still pending,
        ``_pending_shares``). The pushes' difference from the last guess is handed over after the
        interval, as an explicit push (momentum exact)."""
        T = t1 - t0
        keys = [self._index[id(b)] for b in targets]
        pushers = [p for p in self._pushers + [e for e in self._eol if self._targets[id(e)]]
                   if any(b in targets for b in self._targets[id(p)])]
        pairs = [(p, k) for p in pushers for k in keys if self.bodies[k] in self._targets[id(p)]]
        last = [_last_push(p, k, self.bodies[k]) for p, k in pairs]  # per pair (V_k, 3): targets' meshes differ
        pending = {k: self.bodies[k].pending_vertex_impulses() for k in keys}
        grav = float(np.linalg.norm(self.gravity))
        held = _pending_shares(pairs, last, pending, lambda j: _in_reach(pairs[j][0], self.bodies[pairs[j][1]], T, grav))
        # the first guess: each pusher's push of the interval before, less its share of what is
        # still pending (an unconverged interval's leftover), so that the first pass hands the
        # target what the explicit coupling would. The push alone, with the leftover on top,
        # extrapolates: an 8 kg BEM cube resting on a 48 kg PBD slab was flung at 4-6 m/s with
        # ``coupling_iterations`` 2 or 3 (now 40 and 2.4 mm/s; 1.1 at 6, against 1.9 before)
        guess = [lp - h for lp, h in zip(last, held)]
        saved = [b.get_state() for b in self.bodies]
        omega, r_last = _OMEGA_0, None
        stats = self.coupling_stats
        stats["implicit_intervals"] += 1
        implicit = frozenset(id(b) for b in targets)  # their elastic give to PBD pushers (``_wave_speed``)
        for it in range(self.coupling_iterations):
            # every pass from the saved state (the first too: a restored state's derived values
            # may differ from the live ones in their last bits, and each pass should depend on the
            # guess alone)
            for body, st in zip(self.bodies, saved):
                body.set_state(st)
            for k in keys:
                on_k = [g for (_, kk), g in zip(pairs, guess) if kk == k]
                self.bodies[k].add_vertex_impulses(np.sum(on_k, axis=0), T, keep_pending=True)
            for (p, k), g, h in zip(pairs, guess, held):  # what the target takes from this pusher over the interval
                p.expect_push(k, g + h)
            self._step_interval(t0, t1, implicit)
            stats["passes"] += 1
            pushed = {id(p): p.moving_surface_impulses() for p in pushers}
            J = [pushed[id(p)].get(k, np.zeros_like(g)) for (p, k), g in zip(pairs, guess)]
            r = np.concatenate([(j - g).ravel() for j, g in zip(J, guess)])
            # relative to the push or the guess, whichever is larger: once the bodies part the push
            # is zero and the guess (less what is pending) is not, and only its own size can say
            # that the pass has converged
            size = max(np.linalg.norm(np.concatenate([j.ravel() for j in J])),
                       np.linalg.norm(np.concatenate([g.ravel() for g in guess])))
            if np.linalg.norm(r) <= self.coupling_tol * size + 1e-12:
                break
            if it == self.coupling_iterations - 1:
                stats["unconverged"] += 1
                break
            if r_last is not None:  # Aitken: omega from the last two residuals
                dr = r - r_last
                omega = float(np.clip(-omega * np.dot(r_last, dr) / max(np.dot(dr, dr), 1e-300), 0.1, 1.0))
            r_last = r
            guess = [g + omega * (j - g) for j, g in zip(J, guess)]
        # what the guess missed reaches the targets over the next interval; pushes on other bodies
        # are handed over as in the explicit coupling
        impulses: dict[int, np.ndarray] = {}
        for b in self._pushers + [e for e in self._eol if self._targets[id(e)]]:
            for key, Jk in (pushed[id(b)] if id(b) in pushed else b.moving_surface_impulses()).items():
                impulses[key] = impulses.get(key, 0.0) + Jk
        for (p, k), g in zip(pairs, guess):
            impulses[k] = impulses.get(k, 0.0) - g
        for key, Jk in impulses.items():
            self.bodies[key].add_vertex_impulses(Jk, T)

    def _step_interval(self, t0: float, t1: float, implicit: frozenset[int] | None = None) -> None:
        """Step every body over the interval; the pushes are handed over after it (explicit
        coupling), unless this is a pass of ``_advance_implicit`` (``implicit``: the ids of the BEM
        bodies whose push it finds)."""
        grouped = {id(b) for bodies, _ in self._groups for b in bodies} | {id(b) for b in self._lockstep}
        pushers = self._pushers
        late = {id(b) for b in pushers} | {id(b) for b in self._eol}
        coupled = pushers or any(self._targets[id(p)] for p in self._eol)
        start: dict[int, np.ndarray] = {}
        if coupled:  # (an explicit interval reuses what ``_update_roles`` read at its start)
            known = self._interval_points if implicit is None else {}
            self._timed("coupling", lambda: start.update({id(b): known[id(b)] if id(b) in known else b.points()
                                                          for b in self._pushed}))
        g = float(np.linalg.norm(self.gravity))
        # bodies that push nothing go first (their surfaces are then known over the interval) ...
        in_set = {id(b): s for s in self._sets for b in s.bodies}
        for body in self.bodies:
            if id(body) not in grouped and id(body) not in late and (self.coupling_steps == 1 or _couples(body)):
                if id(body) not in in_set:
                    self._timed(_stage(body), body.advance, t0, t1)
                elif body is in_set[id(body)].bodies[0]:  # the set steps its bodies together
                    self._timed(_stage(body), in_set[id(body)].advance, t0, t1)
        for (bodies, joints), sets in zip(self._groups, self._group_sets):
            self._timed("bem", _advance_group, bodies, joints, t1, self.device, self.body_contact, sets)
        end: dict[int, np.ndarray] = {}  # each target's points at the interval's end (read once per interval)
        # ... then the PBD and EoL bodies, the pushed first (``_eol_pushes_pbd``): the groups of EoL
        # bodies that the PBD bodies push, the PBD bodies, the groups that push them
        found = implicit or frozenset()
        groups = self._eol_groups
        if self._eol and groups is None:  # no PBD bodies: no roles asked, the groups found here
            groups = self._timed("coupling", _touching, self._eol, t1 - t0, g, start)
        pushed = [grp for grp in groups or () if not self._eol_pushes[id(grp[0])]]
        self._step_eol(t0, t1, start, end, g, found, pushed)
        self._step_pbd(t0, t1, start, end, g, found)
        self._step_eol(t0, t1, start, end, g, found, [grp for grp in groups or () if self._eol_pushes[id(grp[0])]])
        if coupled and implicit is None:
            self._timed("coupling", self._exchange, t1 - t0)

    def _step_pbd(self, t0: float, t1: float, start: dict, end: dict, g: float, implicit: frozenset[int]) -> None:
        """The PBD bodies that push (with their targets' surfaces) and those in lockstep."""
        pushers = self._pushers
        lockstep = {id(b) for b in self._lockstep}
        for p in pushers:
            self._timed("coupling", _couple_surfaces, p, self._targets[id(p)], self._index, start, end, t1 - t0, g,
                        implicit)
            if id(p) not in lockstep:
                self._timed(_stage(p), p.advance, t0, t1)
        if self._lockstep:
            self._timed("pbd", type(self._lockstep[0]).advance_together, self._lockstep, t0, t1, self._lockstep_graphs)

    def _step_eol(self, t0: float, t1: float, start: dict, end: dict, g: float, implicit: frozenset[int],
                  groups: list[list[Body]]) -> None:
        """The EoL bodies of ``groups`` (bodies that may touch, ``_touching``; one QP each) with
        their targets' surfaces (``implicit`` is the PBD stage's: EoL rows keep the column's
        elastic give)."""
        for group in groups:
            for p in group:
                if self._targets[id(p)]:
                    self._timed("coupling", _couple_surfaces, p, self._targets[id(p)], self._index, start, end,
                                t1 - t0, g)
            if len(group) == 1:
                self._timed("eol", group[0].advance, t0, t1)
            else:
                self._timed("eol", type(group[0]).advance_group, group, [self._index[id(b)] for b in group], t0, t1)

    def _exchange(self, interval: float) -> None:
        """Hand every pushed body what the pushers pushed it with over the interval just stepped
        (keys: the bodies' indices in ``bodies``)."""
        impulses: dict[int, np.ndarray] = {}
        for b in self._pushers + [p for p in self._eol if self._targets[id(p)]]:
            for key, J in b.moving_surface_impulses().items():
                impulses[key] = impulses.get(key, 0.0) + J
        for key, J in impulses.items():
            self.bodies[key].add_vertex_impulses(J, interval)

    def _check_frame(self) -> None:
        for body in self.bodies:
            body.check_finite(self.frame, self.time)

    def run(
        self,
        frames: int,
        out: str | Path | None = None,
        *,
        up_axis: str | None = None,
        progress: bool = True,
        on_frame: Callable[[World], None] | None = None,
        append: bool = False,
        checkpoint: str | Path | None = None,
        checkpoint_every: int = 0,
        start_frame: int = 0,
    ) -> RunSummary:
        """Simulate ``frames`` frames and write them (plus the starting frame) to ``out`` as USD.

        The output path is checked before any simulation. If a step fails (e.g. SimulationDiverged)
        or the run is interrupted, the frames computed so far are written and the error re-raised.
        ``on_frame(world)`` is called after each frame, before it is written (for scripted events).

        ``append``: when ``out`` already holds this scene's prims (the file an earlier run of the same
        scene wrote), keep its frames up to the World's current frame and add the new ones after
        them (a resumed run: one file for the whole animation); otherwise a new file is written.
        ``checkpoint``: a path saved to every ``checkpoint_every`` frames (0: only at the end of the
        run), so a long run can be resumed (``restore``); after a failed step it holds the last
        checkpoint written before the failure.
        ``start_frame``: the USD time code of frame 0 (e.g. 1001), added to every frame written.
        """
        frames = positive_int(frames, "World.run: frames")
        every = positive_int(checkpoint_every, "World.run: checkpoint_every", 0)
        if every and checkpoint is None:
            raise InvalidParameter("World.run: checkpoint_every needs checkpoint= (the file to save to)")
        writer = (UsdWriter(out, self.fps, up_axis or self.up_axis, self.up_axis, start_frame=start_frame)
                  if out is not None else None)
        if checkpoint is not None:
            from wsim import checkpoint as ckpt

            ckpt_path = Path(checkpoint).expanduser()
            output_folder(ckpt_path, "World.run: checkpoint")
        for body in self.bodies:  # before any frame: a run that cannot finish should not start
            body.check_frames(self.frame + frames, self.fps)
        self._bind()
        start = _time.perf_counter()
        done = 0
        try:
            if writer is not None:
                writer.begin(self.bodies, self.surfaces, append_from=self.frame if append else None)
                writer.write_frame(self.frame, self.time)
            from tqdm import tqdm

            from wsim.progress import show_progress

            for _ in tqdm(range(int(frames)), desc="wsim", unit="frame", disable=not show_progress(progress), leave=False):
                self._advance_frame()
                if on_frame is not None:
                    on_frame(self)
                self._check_frame()  # after on_frame: a frame is written only if every body is finite
                done += 1
                if writer is not None:
                    writer.write_frame(self.frame, self.time)
                if checkpoint is not None and every and done % every == 0:
                    ckpt.save(self, ckpt_path)
            if checkpoint is not None and not (every and done % every == 0):
                ckpt.save(self, ckpt_path)
        finally:
            path = writer.close() if writer is not None else None
        return RunSummary(
            frames=done,
            sim_time=done / self.fps,
            wall_seconds=_time.perf_counter() - start,
            out=path,
            device=self.device.alias,
            appended=bool(writer is not None and writer.appended),
            bodies={b.name: int(b.faces.max()) + 1 if len(b.faces) else 0 for b in self.bodies},
        )


def _joint_groups(joints: Sequence[wc.PointJoint], links: Sequence[tuple[Body, Body]] = ()) -> list[tuple[list[Body], list]]:
    """Bodies connected by joints or by ``links`` (bodies that may touch; union-find), each group
    with its joints as body points."""
    parent: dict[int, int] = {}
    bodies: dict[int, Body] = {}

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in [(j.body_a, j.body_b) for j in joints] + list(links):
        for body in (a, b):
            parent.setdefault(id(body), id(body))
            bodies[id(body)] = body
        parent[find(id(a))] = find(id(b))
    groups: dict[int, tuple[list[Body], list]] = {}
    for key, b in bodies.items():
        groups.setdefault(find(key), ([], []))[0].append(b)
    for j in joints:
        groups[find(id(j.body_a))][1].append((j.body_a, j.body_a.joint_points(j.vertices_a),
                                              j.body_b, j.body_b.joint_points(j.vertices_b)))
    return list(groups.values())


def _advance_group(bodies: list[Body], joints: list, t1: float, device, contact: bool, sets: Sequence = ()) -> None:
    """Step joined or touching bodies together to the nearest multiple of their dt to t1, one
    solve per step (with contact between them when ``contact``); ``sets``: members that share an
    operator set (``wsim.bem.instances``), predicted together before each solve."""
    dt = bodies[0].dt
    target = int(math.floor(t1 / dt + 0.5))
    tol = min(b.constraint_tolerance for b in bodies)
    iterations = max(b.constraint_iterations for b in bodies)
    margin = min(b.contact_distance for b in bodies) if contact else None
    on_device = getattr(type(bodies[0]), "steps_on_device", None)
    while bodies[0].steps < target and not any(b.failed for b in bodies):
        # steps on which nothing can touch (and no joint holds) run on the device (``BemBody.device_window``)
        if on_device is not None and not joints and on_device(bodies, target):
            continue
        for s in sets:
            s.predict(s.bodies)
        wc.solve_group(bodies, joints, device, tol, iterations, bodies[0].steps + 1, contact_margin=margin)


def _step_sets(bodies: Sequence[Body]) -> list:
    """Sets of bodies that step together (each with ``bodies`` and ``advance(t0, t1)``), per body
    type that forms them (its ``step_sets``: ``BemBody``'s instance sets, ``PbdBody``'s batches)."""
    by_type: dict[type, list[Body]] = {}
    for b in bodies:
        if hasattr(b, "step_sets"):
            by_type.setdefault(type(b), []).append(b)
    return [s for cls, members in by_type.items() if len(members) > 1 for s in cls.step_sets(members)]


def _couple_surfaces(pusher: Body, targets: Sequence[Body], index: dict[int, int], start: dict[int, np.ndarray],
                     end: dict[int, np.ndarray], interval: float, g: float,
                     implicit: frozenset[int] = frozenset()) -> None:
    """Explicit two-way coupling between bodies (issue 18): a body that takes moving surfaces (EoL,
    PBD) gets the surfaces of its ``targets`` it may reach in this coupling interval (their
    vertices at its start and end: those bodies have already stepped), with the larger of the two
    frictions. What it pushes them with comes back per vertex after its step and is delivered
    over the next interval (``add_vertex_impulses``): one interval late, the momentum exact.
    ``end`` caches the targets' points at the interval's end: every pusher of a target reads
    them after the target's one step of the interval (in a pile of 16 bodies each was read back
    up to 15 times an interval). Targets are keyed by their ``index`` in the World (stable across
    a checkpoint). ``implicit``: the ids of the targets whose push the World finds implicitly this
    interval (``_advance_implicit``; their elastic give to a PBD pusher: ``_wave_speed``)."""
    from wsim.contact import pair_friction

    box = _reach_box(pusher, pusher.points(), interval, g, getattr(pusher, "contact_margin", 0.0))
    surfaces = []
    for b in targets:
        if id(b) not in end:
            end[id(b)] = b.points()
        p0, p1 = start[id(b)], end[id(b)]
        if _overlap(box, (np.minimum(p0.min(axis=0), p1.min(axis=0)), np.maximum(p0.max(axis=0), p1.max(axis=0)))):
            mu = pair_friction(getattr(pusher, "friction", None), getattr(b, "friction", None))
            # a pushed body's vertices are also kept out of a PBD pusher's surface (``VertexImpulses``)
            kept = getattr(b, "vertices_kept_out", False)
            # an EoL pusher's rows share each correction with the pushed body's rigid give
            # (``EolBody.set_moving_surfaces``), a PBD pusher's particles with a BEM body's
            # (``PbdBody.set_moving_surfaces``; a PBD body pushes the EoL bodies of a group whose
            # answer is that they do not push, ``_eol_pushes_pbd``: under gravity, a PBD body rests
            # on one of them ``PBD_PUSHER_MASS_RATIO`` times heavier; it takes them as immovable:
            # with the EoL body's give an 8.6 kg EoL cube on a coarse 6.5 kg PBD box walked 10.6 mm
            # in 0.5 s instead of 6.0)
            rigid = None
            yields = getattr(pusher, "yielding_partners", False) and hasattr(b, "world_inertia")
            if yields and (hasattr(b, "constraint_begin") or not hasattr(pusher, "advance_together")):
                rigid = (b.mass, b.center_of_mass(), b.world_inertia())
                if hasattr(b, "constraint_begin"):  # a BEM body: it yields elastically too (``_impedance``)
                    rigid = rigid + (_impedance(b), _wave_speed(b) if id(b) in implicit else 0.0)
            surfaces.append((index[id(b)], p0, p1, b.faces, mu, b.vertex_masses() if kept else None, rigid))
    pusher.set_moving_surfaces(surfaces)


def _impedance(body: Body) -> float:
    """rho c_p of a BEM body's material [kg / (m^2 s)] (inf: incompressible): how stiffly its
    surface resists a push over a short time (``EolBody._elastic_give``). A BEM body takes a push
    as point forces spread over the next interval, so an EoL pusher also counts only the change of
    its push (``kernels.eol_contact.partner_yield``). Not for PBD bodies, which take a push at
    once: with the change of the push (elastic give or not), an 8 kg PBD box resting on an 8 kg EoL
    box sank 0.36-0.48 mm over 2 s and shook at 2.4-5.1 mm/s (0.001 mm and 1.6-1.7 mm/s without)."""
    material = body.material
    return float(material.rho * material.c1)


def _wave_speed(body: Body) -> float:
    """c_p of a BEM body's material [m/s], handed to a PBD pusher where the World finds the push
    implicitly: the push then engages the half-sphere of material its P wave reaches in the
    interval where that is more than the patch's column (``kernels.pbd_contact.elastic_give``).
    With the column alone, a 24 kg, 98-vertex PBD box rocking 3 cm off centre on a 4 kg BEM cube
    gained 2.1 J by 2 s (the surface's elastic yield did +6.7 J of work on it over 2 s, its
    own motion -4.1 J: an independent check's energy accounts); with the half-sphere its energy
    stays within 0.08 J (74.07-74.14 J over 3 s). Explicitly the column stays: there the give
    also stands in for the lag, and with the half-sphere the 24 kg, 386-vertex box moved 9.9 mm
    at 83 mm/s."""
    return float(body.material.c1)


#: the implicit coupling's first relaxation factor (Aitken's sets the later ones): the 8 kg BEM cube on
#: the 48 kg EoL slab took 3.2 passes an interval from 0.5, 3.9 from 1
_OMEGA_0 = 0.5

#: a PBD body resting on an EoL body at least this many times its mass pushes it (the EoL bodies
#: push otherwise; ``_eol_pushes_pbd``, where the measurements are)
PBD_PUSHER_MASS_RATIO = 5.0


#: ``coupling="auto"``: a PBD or EoL body this many times as heavy as a BEM body it may touch has its
#: push found implicitly. An 8 kg BEM cube on a 48 kg EoL slab shook at 23 mm/s with the push handed
#: over one interval late and 1.0 mm/s implicitly (3.2 passes an interval), a 0.8 kg cube 8.6 and
#: 3.8 mm/s; PBD boxes 3 cm off centre on BEM cubes six times lighter gained energy handed over late
#: (a 98-vertex 24 kg box 0.45 J in 2 s, a 386-vertex 48 kg box 3.0 J in 4 s) and ring down
#: iterated, though a 386-vertex 24 kg box more slowly (23.5 mm/s over its second second against
#: 13.3: the lag damped it). Lighter pushers rest better explicitly: an 8 kg EoL box on the 8 kg
#: cube (0.46 mm/s against 2.6), a coarse 8 kg PBD box (1.2 against 23.5)
IMPLICIT_MASS_RATIO = 2.0


#: ``coupling="auto"``: a lighter PBD pusher of a BEM body has its push found implicitly in the
#: intervals after one in which it pushed the body up with at least this fraction of its weight
SUPPORT_FRACTION = 0.5


def _supports(pusher: Body, key: int, target: Body, gravity: np.ndarray, interval: float) -> bool:
    """Whether ``pusher`` carried at least ``SUPPORT_FRACTION`` of the weight of ``target`` (World
    key ``key``) over the last interval: its push there against gravity, per interval of the
    length coming (no gravity: never)."""
    g = float(np.linalg.norm(gravity))
    if g == 0.0:
        return False
    last = pusher.last_push(key, len(target.rest_vertices))  # (not points(): no device read-back each interval)
    if last is None:
        return False
    return float(-(last.sum(axis=0) @ gravity) / g) >= SUPPORT_FRACTION * _mass(target) * g * interval


def _mass(body: Body) -> float:
    """A body's mass [kg] (an EoL body's: its grid nodes')."""
    return float(body.node_masses().sum()) if hasattr(body, "node_masses") else float(body.mass)


def _in_reach(a: Body, b: Body, interval: float, g: float) -> bool:
    """Whether the surfaces of a and b may meet within the coming interval (``_reach_box``, each
    with its contact margin)."""
    return _overlap(*(_reach_box(body, body.points(), interval, g, getattr(body, "contact_margin", None) or 0.0)
                      for body in (a, b)))


def _pending_shares(pairs: list[tuple[Body, int]], last: list[np.ndarray], pending: dict[int, np.ndarray],
                    near: Callable[[int], bool]) -> list[np.ndarray]:
    """Each (pusher, target key) pair's share (V, 3) of the impulses still pending on the target:
    at each vertex in proportion to the pushers' last pushes there (what was handed over after
    the interval before came from the pushers that pushed there), and equally among the target's
    pushers that pushed it at all where none pushed that vertex (a guess's leftover); where none
    pushed it at all (a bounce), equally among those ``near`` it (within reach over the
    interval), or all. An equal split over all pushers gave a pusher 2 m away a share of the
    leftover of the one that touched, and changed the result; holding none where none pushed
    flung the 8 kg BEM cube off the 48 kg PBD slab at 2 passes an interval (the leftover on top
    of a zero guess)."""
    shares: list[np.ndarray] = [np.zeros(0)] * len(pairs)
    mag = [np.linalg.norm(push, axis=1) for push in last]
    for k in dict.fromkeys(k for _, k in pairs):  # each target once, its pushers together
        same = [j for j, (_, kk) in enumerate(pairs) if kk == k]
        total = np.sum([mag[j] for j in same], axis=0)
        touching = [j for j in same if mag[j].any()] or [j for j in same if near(j)] or same
        for j in same:
            even = (1.0 / len(touching)) if j in touching else 0.0
            weight = np.where(total > 0.0, mag[j] / np.where(total > 0.0, total, 1.0), even)
            shares[j] = pending[k] * weight[:, None]
    return shares


def _last_push(pusher: Body, key: int, target: Body) -> np.ndarray:
    """(V, 3) what ``pusher`` pushed the body ``key`` with over the last interval (zeros if
    nothing): the implicit coupling's first guess."""
    n = len(target.points())
    last = pusher.last_push(key, n)
    return np.zeros((n, 3)) if last is None else last


def _points_of(body: Body, points: dict[int, np.ndarray]) -> np.ndarray:
    """``body.points()``, read once into ``points`` (by id) for the rest of the interval."""
    if id(body) not in points:
        points[id(body)] = body.points()
    return points[id(body)]


def _rule_box(body: Body, points: dict[int, np.ndarray], boxes: dict[int, tuple[np.ndarray, np.ndarray]],
              interval: float, g: float) -> tuple[np.ndarray, np.ndarray]:
    """``body``'s reach box over the interval with its contact margin (``_reach_box``), made once
    into ``boxes`` (by id): the boxes ``_eol_pushes_pbd`` asks whether bodies meet by."""
    if id(body) not in boxes:
        boxes[id(body)] = _reach_box(body, _points_of(body, points), interval, g,
                                     getattr(body, "contact_margin", None) or 0.0)
    return boxes[id(body)]


def _touching(bodies: Sequence[Body], interval: float, g: float, points: dict[int, np.ndarray],
              reach: dict[int, tuple[np.ndarray, np.ndarray]] | None = None, cells: float = 1.0) -> list[list[Body]]:
    """EoL bodies that may touch each other within the coming interval, as groups (connected
    components of their surfaces' overlapping boxes, each grown by how far it can move:
    ``max_speed`` times the interval, the fall under gravity and ``cells`` of its grid's cells);
    a body alone is a group of one. ``points``: the bodies' points where the interval's coupling
    already read them (and those read here); ``reach``: if given, receives each body's box (by
    id)."""
    boxes = [_reach_box(b, _points_of(b, points), interval, g, cells * b.grid.h) for b in bodies]
    if reach is not None:
        reach.update({id(b): box for b, box in zip(bodies, boxes)})
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(bodies)
    links = [(i, j) for i in range(n) for j in range(i + 1, n) if _overlap(boxes[i], boxes[j])]
    i, j = np.array(links, dtype=np.int64).reshape(-1, 2).T
    _, label = connected_components(coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)), directed=False)
    groups: dict[int, list[Body]] = {}
    for k, b in enumerate(bodies):
        groups.setdefault(int(label[k]), []).append(b)
    return list(groups.values())


def _max_speed(body: Body) -> float:
    """A bound on the speed of a body's points [m/s] (its ``max_speed``, its fastest particle, or
    for a BEM body its rigid motion's fastest point, doubled for its deformation)."""
    if hasattr(body, "max_speed"):
        return body.max_speed()
    if hasattr(body, "velocities"):
        return float(np.linalg.norm(body.velocities(), axis=1).max(initial=0.0))
    omega = np.linalg.solve(body.world_inertia(), body.angular_momentum())
    r = float(np.linalg.norm(body.points() - body.center_of_mass(), axis=1).max())
    return 2.0 * (float(np.linalg.norm(body.linear_momentum())) / body.mass + float(np.linalg.norm(omega)) * r)


def _reach_box(body: Body, x: np.ndarray, interval: float, g: float, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The box of the points x of ``body`` grown by how far they can move within the interval
    (``_max_speed`` times it and the fall under gravity) and a margin."""
    grow = _max_speed(body) * interval + g * interval**2 + margin
    return x.min(axis=0) - grow, x.max(axis=0) + grow


def _overlap(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether boxes (lo, hi) a and b overlap."""
    return bool(np.all(a[1] >= b[0]) and np.all(b[1] >= a[0]))


def _eol_pushes_pbd(pbd: Sequence[Body], eol: Sequence[Body], gravity: np.ndarray | None = None,
                    interval: float = 0.0, points: dict[int, np.ndarray] | None = None,
                    boxes: dict[int, tuple[np.ndarray, np.ndarray]] | None = None) -> bool:
    """Whether EoL bodies push PBD bodies over the coming coupling interval (else PBD bodies push
    EoL bodies). The pushed body takes its momentum one interval late, and the pusher keeps
    itself out of the other: the EoL QP's rows take a PBD partner's give, a PBD body's particles
    take an EoL surface as immovable.

    Under gravity EoL bodies push, unless a PBD body rests on an EoL body at least
    ``PBD_PUSHER_MASS_RATIO`` times heavier than itself (within reach of it over the interval,
    its lowest point above the middle of the EoL body's surface along the vertical): a light
    body resting on a much heavier one must keep itself out at once. Up to about that ratio the
    EoL body's push is the better (``tools/study_stacks.py``'s 0.2 m cubes, a PBD top on an 8 kg
    EoL box, 2 cm off centre, mean speeds bottom / top over the third second [mm/s], 2026-11-28,
    ``tools/results/study_stacks_pusher_cpu.jsonl``):

    ======================  ==============  ===============
    PBD top                 EoL pushes      PBD pushes
    ======================  ==============  ===============
    16 kg (0.5x the box)    1.9 / 9.1       80 / 101, +3.7 J
    8 kg (1x)               0.94 / 3.2      43 / 88, +0.79 J
    4 kg (2x lighter)       0.18 / 0.61     27 / 74, +0.23 J
    2.6 kg (3x)             0.37 / 1.0      20 / 37, +0.07 J
    1.6 kg (5x)             0.48 / 1.9      0.39 / 1.9
    1 kg (8x)               0.46 / 2.7      0.12 / 0.86
    0.5 kg (16x)            0.63 / 3.3      0.04 / 0.09
    ======================  ==============  ===============

    With the lighter PBD body pushing (the rule before, strict, on the EoL box's lumped node
    masses: their sum fluctuating about the PBD box's 8 kg switched the pusher between intervals)
    the 8 kg pair moved at 7-8 / 11-12 mm/s, its energy rising 0.14-0.23 J. The masses compared
    are now the EoL body's material mass (``EolBody.mass``, constant) and the PBD particles'.
    The World asks it per group of EoL bodies that may touch (``World._update_roles``), with the
    PBD bodies in the group's reach; one answer serves every pair of the group, so where one of
    its EoL bodies also rests so on a PBD body lighter than itself the EoL bodies push (of the two
    failures the heavy EoL body's is the worse: when one answer served the whole World, a 0.9 kg
    PBD ball resting on an 11.6 kg EoL block let the World's PBD bodies push, and a heavy EoL
    ball elsewhere bounced on a light PBD box at 363 mm/s, 8.6 alone; an independent check). Measured (0.26 x 0.14 x 0.26 m box under a 0.15 m cube 2 cm off centre, E = 1 MPa,
    2 s; an independent check):

    - a 23 kg EoL cube on a 7.6 kg PBD box: pushed by the box, it gained 4 J a second and walked
      off, and an 11 kg one fell off within 2 s; pushing the box, 0.8 / 1.5 mm/s (box / cube) and
      0.02 / 0.8 mm/s, its energy falling;
    - a 23 kg PBD cube on an 8 kg EoL box: pushed by the box, 0.8 / 0.03 mm/s; pushing it, 113 /
      68 mm/s and +6 J;
    - a 2.5 kg PBD cube on an 8 kg EoL box: pushing it, 0.2 / 2.2 mm/s; pushed by the box, 1.2 /
      4.7 mm/s; a 1 kg PBD box on a stiff 32 kg EoL slab pushed by the slab bounced at 0.2 m/s.

    Without gravity (nothing rests) the EoL bodies push. A PBD pusher takes an EoL surface as
    immovable and hands the EoL body its push as tractions over the next interval, on the few
    light nodes of the cells at its surface: an 8 kg EoL cube (8 cells) and a 3.4 kg PBD cube
    thrown at each other at 0.5 m/s each (100 fps) came apart faster than they met (restitution
    1.58, kinetic energy +130 %; the EoL cube's own kinetic energy 1.0 to 22 J within the frame
    of the blow, its fastest node at 48 m/s), and a 0.42 kg PBD cube rebounded at 0.75 with the
    cube's nodes at 17.5 m/s; with the EoL cube pushing, 0.50 and 0.51, kinetic energy -62 %
    and -14 %, nodes at most 0.6 and 1.6 m/s (an independent check; the rule before, the lighter
    method pushing, let the PBD cube push)."""
    g = 0.0 if gravity is None else float(np.linalg.norm(gravity))
    if not pbd or not eol or g == 0.0:
        return True
    up = -np.asarray(gravity, dtype=np.float64) / g
    # each body's points and reach box read once, when needed (``points``, ``boxes``: shared by the caller)
    points = {} if points is None else points
    boxes = {} if boxes is None else boxes

    def at(b: Body) -> np.ndarray:
        return _points_of(b, points)

    def rests(a: Body, b: Body) -> bool:  # a's lowest point above b's middle height, within reach
        h = at(b) @ up
        return (float((at(a) @ up).min()) > 0.5 * float(h.min() + h.max())
                and _overlap(_rule_box(a, points, boxes, interval, g), _rule_box(b, points, boxes, interval, g)))

    masses = {id(p): _mass(p) for p in pbd}
    pbd_rests = False
    for e in eol:
        m_e = float(e.mass)  # its material's, constant: the lumped nodes' sum fluctuates step to step
        for p in (p for p in pbd if masses[id(p)] < m_e):
            if rests(e, p):
                return True  # a heavy EoL body on a light PBD body: the worse failure, first
            if PBD_PUSHER_MASS_RATIO * masses[id(p)] <= m_e:
                pbd_rests = pbd_rests or rests(p, e)
    return not pbd_rests


def _automatic_coupling_steps(bodies: Sequence[Body], frame_dt: float) -> int:
    """Coupling intervals per frame when the World is not told (``coupling_dt=None``): 1 unless
    bodies push others (``World._targets``). With PBD bodies and BEM or EoL bodies: the largest k
    that splits the frame into whole numbers of every BEM body's steps and gives each interval at
    least one substep of every PBD body; with EoL bodies pushing BEM bodies (and no PBD): the
    smallest k whose intervals hold whole BEM steps and are no longer than ``EOL_COUPLING_DT``.
    EoL bodies alone keep the frame: touching EoL bodies share one QP, with no lag."""
    pbd = [b for b in bodies if hasattr(b, "advance_together")]
    eol = [b for b in bodies if hasattr(b, "advance_group")]
    bem = [b for b in bodies if hasattr(b, "constraint_begin")]
    pushed = bem + eol  # what PBD bodies touch across methods (PBD pushes BEM, EoL pushes PBD)
    if not (pbd and pushed) and not (eol and bem):
        return 1  # nothing pushes anything (an EoL body pushes a BEM body, a PBD body both)
    steps = []
    for b in bodies:
        dt = getattr(b, "dt", None) if hasattr(b, "constraint_begin") else None
        if dt:
            n = frame_dt / dt
            if abs(n - round(n)) > 1e-6:
                return 1  # a BEM body whose dt does not divide the frame: couple at the frame
            steps.append(int(round(n)))
    if pbd and pushed:
        limit = min(b.substeps_for(frame_dt) for b in pbd)
        return max(k for k in range(1, limit + 1) if all(n % k == 0 for n in steps))
    # EoL bodies pushing BEM bodies: intervals of at most EOL_COUPLING_DT that hold whole BEM steps
    want = math.ceil(frame_dt / EOL_COUPLING_DT - 1e-9)
    fits = [k for k in range(1, max([want] + steps) + 1) if all(n % k == 0 for n in steps)]
    return min([k for k in fits if k >= want] or [max(fits)])


def _stage(body: Body) -> str:
    """The ``World.timings`` stage of a body's own stepping: its method."""
    return {"BemBody": "bem", "EolBody": "eol", "PbdBody": "pbd"}.get(type(body).__name__, "other")


def _couples(body: Body) -> bool:
    """Whether a body exchanges contact with other bodies (steps by coupling interval)."""
    return any(hasattr(body, a) for a in ("set_moving_surfaces", "add_vertex_impulses", "constraint_begin"))
