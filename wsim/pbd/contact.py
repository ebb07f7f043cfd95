"""Contact between PBD bodies of one World (issue 18: same-method contact).

Bodies that may touch step their substeps in lockstep (the largest substep count of the group, so
the shortest h): each substep predicts every body, then each constraint iteration runs every
body's own constraints and colliders and, for every pair of bodies whose frame-swept boxes
overlap, projects the surface particles of each body out of the other's current surface
(``wsim.kernels.pbd_contact.body_contact``: point-triangle constraints with both bodies' inverse
masses, so the impulses are equal and opposite, and Coulomb friction). A body's surface is a Warp
mesh built from its positions once per frame and refit before each use. Contact corrections go
to ``dxc`` like collider contact, so ``conserve_angular_momentum`` keeps them as external.

On CUDA a lockstep frame is recorded once as a CUDA graph and replayed while the same pairs are
in reach with the same substeps (the bodies' meshes are then kept and only refit, so their BVH
topology is the one of the frame it was built in); bodies with no partner in reach this frame
advance on their own, with their own graph.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np
import warp as wp

from wsim.contact import pair_friction
from wsim.kernels import pbd_contact as kc

if TYPE_CHECKING:
    from wsim.pbd.body import PbdBody


def _layout_key(bodies: Sequence[PbdBody]) -> tuple:
    return tuple((id(b), id(b._batch), b.contact_margin) for b in bodies)


class _BroadPhase:
    """What the broad phase of a fixed list of bodies needs besides their current boxes: each
    body's |g| and contact margin, and which bodies read their boxes from one batch reduction
    (built once: per-body Python for 100 bodies each frame was time the GPU waited)."""

    def __init__(self, bodies: Sequence[PbdBody]) -> None:
        self.key = _layout_key(bodies)
        self.g = np.array([np.linalg.norm(np.array(b._gravity, dtype=np.float64)) for b in bodies])
        self.margin = np.array([b.contact_margin for b in bodies])
        by_batch: dict[int, tuple] = {}  # batch id -> (batch, positions in ``bodies``, rows of its reduction)
        self.alone: list[int] = []
        for k, b in enumerate(bodies):
            if b._batch is not None:
                entry = by_batch.setdefault(id(b._batch), (b._batch, [], []))
                entry[1].append(k)
                entry[2].append(b._batch_index)
            else:
                self.alone.append(k)
        self.batches = [(batch, np.array(at), np.array(rows)) for batch, at, rows in by_batch.values()]

    def bounds(self, bodies: Sequence[PbdBody]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each body's surface box (lo, hi: (n, 3)) and largest |v| component (n,) on the host: a
        batch's members from one reduction on the device (``PbdBatch.member_bounds``), not copies
        of their arrays."""
        rows = np.empty((len(bodies), 7))
        for batch, at, index in self.batches:
            rows[at] = batch.member_bounds()[index]
        for k in self.alone:
            b = bodies[k]
            x, v = b.x.numpy()[: b.model.n_surface], b.v.numpy()
            rows[k, 0:3], rows[k, 3:6], rows[k, 6] = x.min(axis=0), x.max(axis=0), np.abs(v).max(initial=0.0)
        return rows[:, 0:3], rows[:, 3:6], rows[:, 6]


def candidate_pairs(bodies: Sequence[PbdBody], frame_dt: float, cache: dict | None = None) -> list[tuple[PbdBody, PbdBody]]:
    """Pairs whose swept boxes overlap this frame (the broad phase, on the host once per frame):
    each body's surface box grown by how far it can move this frame (its fastest velocity
    component and gravity) and by its contact margin. Array operations over all bodies at once,
    the layout kept in ``cache`` between calls: the host's time here is time the GPU waits (the
    boxes were just read back)."""
    if len(bodies) < 2:
        return []
    layout = cache.get("broad_phase") if cache is not None else None
    if layout is None or layout.key != _layout_key(bodies):
        layout = _BroadPhase(bodies)
        if cache is not None:
            cache["broad_phase"] = layout
    lo, hi, v_max = layout.bounds(bodies)
    grow = (v_max * frame_dt + 0.5 * layout.g * frame_dt**2 + layout.margin)[:, None]
    lo, hi = lo - grow, hi + grow
    # sweep along x: sorted by lo_x, body k's x-overlaps are the next ones whose lo_x <= hi_x[k]
    order = np.argsort(lo[:, 0], kind="stable")
    n = len(bodies)
    count = np.maximum(np.searchsorted(lo[order, 0], hi[order, 0], side="right") - np.arange(n) - 1, 0)
    if not count.any():  # the common case of bodies apart: no pair arrays at all
        return []
    first = np.repeat(np.arange(n), count)
    second = first + 1 + np.arange(len(first)) - np.repeat(np.cumsum(count) - count, count)
    a, b = order[first], order[second]
    a, b = np.minimum(a, b), np.maximum(a, b)
    keep = np.all((hi[a, 1:] >= lo[b, 1:]) & (hi[b, 1:] >= lo[a, 1:]), axis=1)
    a, b = a[keep], b[keep]
    at = np.lexsort((b, a))  # the bodies' order, as the projections run in it
    return [(bodies[i], bodies[j]) for i, j in zip(a[at].tolist(), b[at].tolist())]


def _build_mesh(body: PbdBody) -> None:
    """The body's surface as a Warp mesh on its current positions (BVH built now, refit later)."""
    n = body.model.n_surface
    body._contact_points, body._contact_indices, body._contact_test = body._surface_buffers()
    wp.copy(body._contact_points, body.x, count=n)
    body._contact_mesh = wp.Mesh(points=body._contact_points, indices=body._contact_indices,
                                 support_winding_number=body._contact_test == 1)
    x = body.x.numpy()[:n]
    # how far from its surface a query may look: a particle deep inside is still found
    body._contact_reach = float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))


def _refit(body: PbdBody) -> None:
    wp.launch(kc.surface_positions, dim=body.model.n_surface, device=body._device,
              inputs=[body.x_pred, body.dx, body._contact_points])
    body._contact_mesh.refit()


def _project(a: PbdBody, b: PbdBody, mu: float) -> None:
    """a's surface particles out of b's surface (b's mesh refit to its current positions)."""
    _refit(b)
    reach = b._contact_reach + max(a.contact_margin, b.contact_margin)
    wp.launch(kc.body_contact, dim=a.model.n_surface, device=a._device,
              inputs=[a.x_pred, a.dx, a.dxc, a.x_prev, a.inv_mass, b._contact_mesh.id, b.dx, b.dxc,
                      b.x_prev, b.inv_mass, max(a.contact_margin, b.contact_margin), reach, mu, b._contact_test])


def _lockstep_frame(group: Sequence[PbdBody], pairs: Sequence[tuple[PbdBody, PbdBody]], mus: Sequence[float],
                    substeps: int, h: float) -> None:
    iterations = max(b.iterations for b in group)
    for s in range(1, substeps + 1):
        for b in group:
            b._substep_begin(s, h)
        for it in range(iterations):
            for b in group:
                if it < b.iterations:
                    b._substep_iteration(s, it, h)
            for (a, b), mu in zip(pairs, mus):
                _project(a, b, mu)
                _project(b, a, mu)
        for b in group:
            b._substep_end(h)


def advance_together(bodies: Sequence[PbdBody], t0: float, t1: float, graphs: dict | None = None) -> None:
    """Advance PBD bodies that may touch from t0 to t1 (see the module docstring). ``graphs`` is
    where the caller keeps the recorded lockstep frame and the broad phase's layout between calls
    (None: nothing kept, no frame recorded)."""
    for b in bodies:  # what EoL bodies pushed them with (``PbdBody.add_vertex_impulses``)
        b._take_push()
    frame_dt = round(t1 - t0, 12)
    pairs = candidate_pairs(bodies, frame_dt, graphs)
    touching = {id(b) for pair in pairs for b in pair}
    for b in bodies:
        if id(b) not in touching and b._contact_mesh is not None:  # back on its own: no contact corrections left over
            b._contact_mesh = None
            b.dxc.zero_()
    done: set[int] = set()
    given = {id(b) for b in bodies}
    for b in bodies:
        if id(b) in touching or id(b) in done:
            continue
        batch = b._batch  # a batch all of whose members are free this frame steps as one (wsim.pbd.batch)
        if batch is not None and all(id(m) in given and id(m) not in touching for m in batch.bodies):
            batch.advance(t0, t1)
            done.update(id(m) for m in batch.bodies)
        else:
            b.advance(t0, t1)
    group = [b for b in bodies if id(b) in touching]
    if not group:
        return
    substeps = max(b.substeps_for(frame_dt) for b in group)
    h = frame_dt / substeps
    device = group[0]._device
    mus = [pair_friction(getattr(a, "friction", None), getattr(b, "friction", None)) for a, b in pairs]
    key = (tuple(id(b) for b in group), tuple((id(a), id(b)) for a, b in pairs), substeps, h,
           tuple((ms.key, ms.mesh.id) for b in group for ms in b._moving))  # other methods' surfaces too
    use_graph = graphs is not None and device.is_cuda and all(b.use_graph for b in group)
    with wp.ScopedDevice(device):
        for b in group:
            if b._layout != (substeps, h):
                b._prepare_layout(substeps, h)
            b._upload_frame_inputs(t0, substeps, h)
        recorded = graphs.get("frame") if use_graph else None
        if recorded is not None and recorded[0] == key:
            for b, mesh in zip(group, recorded[2]):
                b._contact_mesh = mesh  # the meshes the graph queries (their ids are baked in)
            wp.capture_launch(recorded[1])
            return
        for b in group:
            _build_mesh(b)
        if not use_graph:
            _lockstep_frame(group, pairs, mus, substeps, h)
            return
        from wsim.kernels import pbd as kp

        wp.load_module(kp, device=device)
        wp.load_module(kc, device=device)
        with wp.ScopedCapture(device=device) as capture:
            _lockstep_frame(group, pairs, mus, substeps, h)
        graphs["frame"] = (key, capture.graph, [b._contact_mesh for b in group])  # keeps the meshes alive
        wp.capture_launch(capture.graph)
