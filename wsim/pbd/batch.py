"""PbdBatch: PBD bodies of a World stepped in one launch set (issue 21 item 5).

On a GPU a PBD frame is latency bound: one launch per constraint colour, iteration and substep,
a few microseconds each whatever the particle count (README, PBD costs). K bodies stepped one
after the other pay K times the launches. A batch concatenates the bodies' particles into one set
of arrays (each body's positions and velocities become views of its range, so its read-outs,
checks and checkpoints see the same memory) and merges their constraint families colour by
colour: colour c of the batch holds colour c of every body. Bodies share no particle, so a merged
colour is still a set of independent constraints and each projection does exactly the
arithmetic it did alone; the frame costs the launches of the body with the most colours. The
momentum restoration sums per body (``kernels.pbd.moments`` by segment): each body's range is
padded to whole reduction blocks with massless particles that nothing touches.

The launch sequence is ``PbdBody``'s own (its methods run over the batch's arrays). A batch
forms from bodies that agree on what those launches bake in: device, Gauss-Seidel solver,
substeps, iterations, damping, drag, contact margin, friction (a collider's is the larger of
its and the body's), graph use; bodies with handles or a
surface volume constraint step alone. In a frame where a member touches another body or another
method's surface (``wsim.pbd.contact``), every member steps on its own.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import TYPE_CHECKING, Sequence

import numpy as np
import warp as wp

from wsim.kernels import pbd as kp
from wsim.launch import Launcher
from wsim.pbd.model import FAMILY_KINDS

if TYPE_CHECKING:
    from wsim.pbd.body import PbdBody


def batch_key(body: PbdBody) -> tuple | None:
    """What a batch's launches bake in, equal for its members; None: the body steps alone."""
    if body.handles or body.model.volume is not None or body.solver != "gauss_seidel":
        return None
    if any(f.edge is not None for f in body._families):  # hinges with their edges: launched alone
        return None
    return (body._device.alias, body.substeps, body.dt, body.iterations, body.damping, body.drag,
            body.contact_margin, body.friction, body.use_graph, body._cpu_serial_sweep, body._block_dim)


class PbdBatch:
    """K >= 2 bound PBD bodies of one ``batch_key``: their particles side by side, their families
    merged by colour (see the module docstring)."""

    from wsim.pbd.body import PbdBody as _Body

    # the frame's launches are the bodies' own, over the batch's arrays
    _launch_frame = _Body._launch_frame
    _substep = _Body._substep
    _load_modules = _Body._load_modules
    _upload_collider_poses = _Body._upload_collider_poses
    _substep_begin = _Body._substep_begin
    _substep_iteration = _Body._substep_iteration
    _substep_end = _Body._substep_end
    _launch_family = _Body._launch_family
    _launch_moments = _Body._launch_moments
    _moment_blocks = _Body._moment_blocks
    _prepare_layout = _Body._prepare_layout
    _upload_frame_inputs = _Body._upload_frame_inputs
    _frame = _Body._advance_frame  # layout, inputs and the recorded CUDA graph, as for one body
    del _Body

    def __init__(self, bodies: Sequence[PbdBody]) -> None:
        b0 = bodies[0]
        self.bodies = list(bodies)
        self._device = device = b0._device
        for name in ("iterations", "damping", "drag", "contact_margin", "use_graph", "solver", "omega",
                     "_cpu_serial_sweep", "_block_dim", "_gravity", "friction", "_planes", "_surfaces", "_mesh_surfaces"):
            setattr(self, name, getattr(b0, name))
        self.handles = ()
        self._substep_pipeline = False  # no handles: whole-frame graphs
        self.conserve_angular_momentum = any(b.conserve_angular_momentum for b in bodies)
        block = int(kp.MOMENT_BLOCK)
        counts = np.array([b.model.n_particles for b in bodies])
        first = np.concatenate([[0], np.cumsum(-(-counts // block) * block)])  # whole blocks a body
        n = int(first[-1])
        self.model = SimpleNamespace(n_particles=n, volume=None, n_surface=0)
        seg = np.repeat(np.arange(len(bodies)), np.diff(first))
        inv_mass = np.zeros(n, dtype=np.float32)
        for b, f, c in zip(bodies, first, counts):
            inv_mass[f : f + c] = b.inv_mass.numpy()
        with wp.ScopedDevice(device):
            self.x, self.v = wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=wp.vec3)
            self.x_prev, self.x_pred = wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=wp.vec3)
            self.dx, self.dxc = wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=wp.vec3)
            self._acc = self.dx  # Gauss-Seidel: unused
            self.inv_mass = wp.array(inv_mass, dtype=float)
            self._handle_slot = wp.full(n, -1, dtype=int)
            self._handle_targets_d = wp.zeros(1, dtype=wp.vec3)
            self._seg = wp.array(seg.astype(np.int32), dtype=int)
            self._seg_first = wp.array(first[:-1].astype(np.int32), dtype=int)
            self._seg_count = wp.array(counts.astype(np.int32), dtype=int)
            self._seg_stride = 2 * int(kp.MOMENT_SUMS)
            self._seg_restore = wp.array(np.array([b.conserve_angular_momentum for b in bodies], dtype=np.int32), dtype=int)
            self._moments = wp.zeros(len(bodies) * self._seg_stride, dtype=wp.float64)
            self._families = self._merge_families(first)
        self._handle_idx = np.zeros(0, dtype=np.int64)
        self._mesh_colliders: list = []
        self._contact_mesh = None
        self._moving: list = []
        self._own_surface = None
        self._layout: tuple[int, float] | None = None
        self._graph = None
        self.flags = wp.zeros(2, dtype=int, device=device)
        self._checked: tuple | None = None  # (frame, time) of the last check (``all_finite``)
        self._finite = True
        for k, (b, f, c) in enumerate(zip(bodies, first, counts)):  # each body's state becomes a view of its range
            x, v = self.x[int(f) : int(f + c)], self.v[int(f) : int(f + c)]
            wp.copy(x, b.state.x)
            wp.copy(v, b.state.v)
            b.state.x, b.state.v = x, v
            b._graph = None  # its own recorded frame pointed at the old arrays
            b._batch = self
            b._batch_first = int(f)  # its first particle in the batch's arrays
            b._batch_index = k  # its row of ``member_bounds``

    def _merge_families(self, first: np.ndarray) -> list:
        """The bodies' families of each kind as one (the constraints they project,
        ``PbdBody._active_families``), colour c of the batch = colour c of every body, particle
        indices shifted to the body's range; one multiplier array for them all."""
        from wsim.pbd.body import _DeviceFamily

        # every body projects its families in the model's fixed kind order: the batch keeps it (an
        # order by first appearance would reorder a body's sweep by which bodies came before it)
        present = {f.kind for b in self.bodies for f in b._active_families}
        kinds = [k for k in FAMILY_KINDS if k in present]
        merged = []
        for kind in kinds:
            parts = [(b, f, int(base)) for b, base in zip(self.bodies, first) for f in b._active_families
                     if f.kind == kind]
            colours = max(len(f.offsets) - 1 for _, f, _ in parts)
            idx, rest, comp, offsets = [], [], [], [0]
            for c in range(colours):
                for _, f, base in parts:
                    if c < len(f.offsets) - 1:
                        lo, hi = int(f.offsets[c]), int(f.offsets[c + 1])
                        idx.append(np.asarray(f.indices[lo:hi]) + base)
                        rest.append(f.rest[lo:hi])
                        comp.append(f.compliance[lo:hi])
                offsets.append(sum(len(a) for a in idx))
            indices = np.concatenate(idx).astype(np.int32)
            merged.append(dict(kind=kind, offsets=np.array(offsets), indices=indices,
                               rest=np.concatenate(rest), compliance=np.concatenate(comp)))
        self._lam = wp.zeros(max(sum(len(m["indices"]) for m in merged), 1), dtype=float)
        out, start = [], 0
        for m in merged:
            k = len(m["indices"])
            out.append(_DeviceFamily(kind=m["kind"], offsets=m["offsets"],
                                     indices=wp.array(m["indices"], dtype=wp.vec2i if m["indices"].shape[1] == 2 else wp.vec4i),
                                     rest=wp.array(m["rest"].astype(np.float32), dtype=float),
                                     compliance=wp.array(m["compliance"].astype(np.float32), dtype=float),
                                     lam=self._lam[start : start + k], count=wp.zeros(1, dtype=float)))
            start += k
        return out

    def all_finite(self, body: PbdBody, frame: int, time: float) -> bool:
        """Whether every member's positions and velocities are finite: one launch and one
        read-back for all members, made when the first member is checked and reused by the others
        checked for the same frame and time (the World checks every body in order after each
        frame; checked per member, one launch and a synchronization each, 100 bodies spent about
        as long on the checks as on their frame). When it is False each member checks itself, to
        name the body."""
        if body is self.bodies[0] or self._checked != (frame, time):
            self.flags.zero_()
            wp.launch(kp.check_finite, dim=self.model.n_particles, inputs=[self.x, self.v, self.flags], device=self._device)
            self._finite = not bool(self.flags.numpy().any())
            self._checked = (frame, time)
        return self._finite

    def member_bounds(self) -> np.ndarray:
        """(members, 7) each member's surface box (min, max) and largest |v| component, reduced on
        the device (``kernels.pbd.member_bounds``, one block a member): the broad phase reads 7
        numbers a member, not the batch's positions and velocities (100 members of 1.6k
        particles: 3.8 MB a frame, which made a batch with body contact 3.4x one body's frame
        instead of 2.2x). One replayed launch and one read-back: the GPU waits for this."""
        if getattr(self, "_bounds", None) is None:
            with wp.ScopedDevice(self._device):
                self._bounds = wp.empty((len(self.bodies), 7), dtype=float)
                self._n_surface = wp.array(np.array([b.model.n_surface for b in self.bodies], dtype=np.int32), dtype=int)
            self._bounds_launch = Launcher(self._device)
        self._bounds_launch(kp.member_bounds, len(self.bodies),
                            [self.x, self.v, self._seg_first, self._seg_count, self._n_surface, self._bounds],
                            block_dim=kp.MEMBER_BLOCK)
        return self._bounds.numpy()

    def steps_together(self) -> bool:
        """Whether the members can take this frame as a batch (none touches another body or
        another method's surface)."""
        return all(not b._moving and b._contact_mesh is None for b in self.bodies)

    def advance(self, t0: float, t1: float) -> None:
        """Every member from t0 to t1: the batch's frame (recorded as one CUDA graph on a GPU), or
        each member on its own in a frame where one touches something (``steps_together``)."""
        for b in self.bodies:  # what EoL bodies pushed them with (``PbdBody.add_vertex_impulses``)
            b._take_push()
        if not self.steps_together():
            for b in self.bodies:
                b.advance(t0, t1)
            return
        self._frame(t0, t1)

    def substeps_for(self, frame_dt: float) -> int:
        """The members' substeps for ``frame_dt`` (equal: they share ``batch_key``)."""
        return self.bodies[0].substeps_for(frame_dt)


def batches(bodies: Sequence[PbdBody]) -> list[PbdBatch]:
    """``PbdBatch``es of the bound bodies that share a ``batch_key``, two or more to a batch."""
    by_key: dict[tuple, list[PbdBody]] = {}
    for b in bodies:
        key = batch_key(b)
        if key is not None:
            by_key.setdefault(key, []).append(b)
    return [PbdBatch(group) for group in by_key.values() if len(group) > 1]
