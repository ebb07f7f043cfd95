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


def _swept_box(lo: np.ndarray, hi: np.ndarray, v_max: float, body: PbdBody, frame_dt: float,
               reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The box [lo, hi] of the body's surface now, grown by how far it can move this frame (its
    fastest velocity component ``v_max`` and gravity) and by ``reach``."""
    grow = v_max * frame_dt + 0.5 * float(np.linalg.norm(body._gravity)) * frame_dt**2 + reach
    return lo - grow, hi + grow


def _host_bounds(bodies: Sequence[PbdBody]) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Each body's surface box (min, max) and largest |v| component on the host: a batch's members
    from one reduction on the device (``PbdBatch.member_bounds``), not copies of their arrays."""
    reduced: dict[int, np.ndarray] = {}
    out = []
    for b in bodies:
        if b._batch is not None:
            if id(b._batch) not in reduced:  # (not setdefault: its default would reduce for every member)
                reduced[id(b._batch)] = b._batch.member_bounds().astype(np.float64)
            row = reduced[id(b._batch)][b._batch_index]
            out.append((row[0:3], row[3:6], float(row[6])))
        else:
            x, v = b.x.numpy()[: b.model.n_surface], b.v.numpy()
            out.append((x.min(axis=0), x.max(axis=0), float(np.abs(v).max(initial=0.0))))
    return out


def candidate_pairs(bodies: Sequence[PbdBody], frame_dt: float) -> list[tuple[PbdBody, PbdBody]]:
    """Pairs whose swept boxes overlap this frame (the broad phase, on the host once per frame)."""
    if len(bodies) < 2:
        return []
    boxes = [_swept_box(lo, hi, v_max, b, frame_dt, b.contact_margin)
             for b, (lo, hi, v_max) in zip(bodies, _host_bounds(bodies))]
    lo, hi = np.array([bx[0] for bx in boxes]), np.array([bx[1] for bx in boxes])
    # every pair at once: 100 bodies are 4950 pairs, whose one-by-one tests took milliseconds
    overlap = np.all(hi[:, None, :] >= lo[None, :, :], axis=2) & np.all(hi[None, :, :] >= lo[:, None, :], axis=2)
    i, j = np.nonzero(np.triu(overlap, k=1))
    return [(bodies[a], bodies[b]) for a, b in zip(i.tolist(), j.tolist())]


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
    where the caller keeps the recorded lockstep frame between calls (None: not recorded)."""
    frame_dt = round(t1 - t0, 12)
    pairs = candidate_pairs(bodies, frame_dt)
    touching = {id(b) for pair in pairs for b in pair}
    for b in bodies:
        if id(b) not in touching and b._contact_mesh is not None:  # back on its own: no contact corrections left over
            b._contact_mesh = None
            b.dxc.zero_()
    done: set[int] = set()
    for b in bodies:
        if id(b) in touching or id(b) in done:
            continue
        batch = b._batch  # a batch all of whose members are free this frame steps as one (wsim.pbd.batch)
        if batch is not None and not any(id(m) in touching for m in batch.bodies) and \
                all(any(m is c for c in bodies) for m in batch.bodies):
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
