"""Instances: BEM bodies on one operator set stepped together (issue 21 item 5).

Bodies built from one operator set (the BEM paper's 25 fish of Fig. 1) share the device copy of
their matrices (``stepper.step_operators``), but each step used to stream all 2 n_max + 2 dense
3N x 3N matrices once per body: the step is bandwidth bound, so K bodies cost K times one. Here
their rings live side by side in one (K, n_max, pitch) array per quantity (each body's ring is a
view of its row, so every one-body path and the checkpoint see the same memory) and the history
and solve passes (Eqs. 9 and 12) of all K run as matrix-matrix products (``stepper.history_many``,
``stepper.solve_many``): each matrix is read once per step for all K bodies.

What stays per body: the loads (user callbacks), the frame update (O(N) host work) and the
constraint solve of bodies that are held or touch something; free bodies that step as a set
(``advance``) are error-corrected as one stack and write their ring rows in three launches.
``predict`` computes the coming step's unconstrained displacement of every body of the set; a
body's own ``unconstrained_solve`` then returns it instead of running its passes, so the rest of
the step (free, constrained, in a contact group) is unchanged. Results equal the one-body passes'
to the round-off of the summation order (``tests/test_bem_instances.py``).

Sets are formed only where the products can run together (``StepOperators.many_backend``:
numpy's BLAS on the CPU, cuBLAS through CuPy on CUDA); elsewhere (compressed sets, CUDA without
CuPy) each body keeps its own passes.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Sequence

import numpy as np
import warp as wp

from wsim.bem import stepper
from wsim.kernels import bem_step as ks

if TYPE_CHECKING:
    from wsim.bem.body import BemBody

DEVICE_APART_BYTES = 256 << 20  # see ``Instances.steps_apart``


class Instances:
    """K >= 2 bound BEM bodies on one ``StepOperators``: their stacked rings and step vectors."""

    def __init__(self, bodies: Sequence[BemBody]) -> None:
        so = bodies[0]._so
        if any(b._so is not so for b in bodies):
            raise ValueError("Instances: the bodies must share one StepOperators")
        self.bodies = list(bodies)
        self.so = so
        K, n_max, pitch, dev = len(bodies), so.n_max, so.pitch, so.device
        self.U = wp.zeros((K, n_max, pitch), dtype=so.dtype, device=dev)
        self.P = wp.zeros_like(self.U)
        self.B = wp.zeros((K, n_max, 6), dtype=so.dtype, device=dev)
        self.p, self.h, self.u = (wp.zeros((K, pitch), dtype=so.dtype, device=dev) for _ in range(3))
        self._u_host = wp.zeros((K, pitch), dtype=so.dtype, device="cpu", pinned=dev.is_cuda)
        self._b = wp.zeros((K, 6), dtype=so.dtype, device=dev)
        self._b_host = wp.zeros((K, 6), dtype=so.dtype, device="cpu", pinned=dev.is_cuda)
        self._row = {id(b): i for i, b in enumerate(self.bodies)}
        for i, b in enumerate(self.bodies):
            b._adopt_rings(self.U[i], self.P[i], self.B[i], self.p[i], self.h[i], self.u[i])
            b._set = self

    @property
    def steps_apart(self) -> bool:
        """Whether the members' free steps may run on the device one body at a time
        (``BemBody.device_window``, ``wsim.bem.device_step``): dense Warp operators small enough
        that reading them once per member (``DEVICE_APART_BYTES`` for all members together, about
        0.1 ms of an H100's bandwidth) costs less than the set's host round trip."""
        so = self.so
        return (so.backend == "warp" and so.packed is None and so.compressed is None
                and len(self.bodies) * so.matrix_bytes <= DEVICE_APART_BYTES)

    def predict(self, bodies: Sequence[BemBody]) -> None:
        """The coming step's unconstrained solve of ``bodies`` (members of the set that step now;
        each at its own step) in one pass over the matrices; each body's next
        ``unconstrained_solve`` returns its share."""
        if not bodies:
            return
        so, n3 = self.so, self.so.size
        t0 = time.perf_counter()
        steps = np.array([b.state.ring for b in self.bodies], dtype=np.int64)
        # the history first: it needs only past steps, so the loads are evaluated meanwhile
        stepper.history_many(so, self.U, self.P, self.B, steps, self.h)
        if any(b.profile for b in bodies) and so.device.is_cuda:  # GPU time in its own stage
            wp.synchronize_device(so.device)
        t1 = time.perf_counter()
        loads = []
        for b in bodies:  # each body's own loads on its own clock
            t = time.perf_counter()
            loads.append(b._step_loads())
            b.timings["loads"] = b.timings.get("loads", 0.0) + time.perf_counter() - t
        # a member not stepping now keeps its traction row: its product is computed and dropped
        # (a failed member's too, but it alone does not make the set multiply tractions)
        loaded = any(b._p_live and not b.failed for b in self.bodies)
        t2 = time.perf_counter()
        stepper.solve_many(so, self.p if loaded else None, self.h, self.u)
        wp.copy(self._u_host, self.u)
        wp.synchronize_device(so.device)
        U = self._u_host.numpy()
        t3 = time.perf_counter()
        # the set's passes serve every member: their seconds are split evenly over the bodies
        # that stepped (``BemBody.timings``; a user's load shows on the body it loads)
        share = 1.0 / len(bodies)
        for b, (a_ext, alpha_ext) in zip(bodies, loads):
            b._predicted = (b.steps, b._balanced(U[self._row[id(b)], :n3].astype(np.float64)), a_ext, alpha_ext)
            b.timings["history"] = b.timings.get("history", 0.0) + share * (t1 - t0)
            b.timings["solve"] = b.timings.get("solve", 0.0) + share * (t3 - t2)

    def advance(self, t0: float, t1: float) -> None:
        """Step every member (not in a contact or joint group) to the nearest multiple of dt to t1
        (``t0``, the interval's start, is the members' own time: the World's signature for sets):
        one shared prediction a step; free bodies then finish together (``finish_free``), held
        or touching ones through their own constraint solve."""
        dt = self.bodies[0].dt
        target = int(math.floor(t1 / dt + 0.5))
        while True:
            live = [b for b in self.bodies if not b.failed and b.steps < target]
            if not live:
                return
            # free steps on which nothing can reach any member run on the device, body by body
            together = all(b.steps == live[0].steps for b in live)
            if together and self.steps_apart and type(live[0]).steps_on_device(live, target):
                continue
            self.predict(live)
            free = [b for b in live if not b.constrained and b.frame_update and b.error_correction]
            for b in live:
                if not any(b is f for f in free):
                    b.step()
            self.finish_free(free)

    def finish_free(self, bodies: Sequence[BemBody], got: Sequence[tuple] | None = None) -> None:
        """The rest of a free step (no point forces) of ``bodies`` (error correction, rings, frame),
        with the correction of all of them in one stacked pass (``Correction.apply`` on (K, 3N))
        and their ring rows written in three launches. ``got``: each body's (u, a_ext, alpha_ext)
        (from its closed constraint solve), else its share of ``predict``."""
        if not bodies:
            return
        t0 = time.perf_counter()
        so, n3 = self.so, self.so.size
        if got is None:
            got = [b.unconstrained_solve() for b in bodies]
        U = np.stack([g[0] for g in got])
        # each body on its own: the non-finite one reports itself; one body alone (e.g. each
        # member touching the ground in its own solve) writes its rows with its own copies
        if len(bodies) == 1 or not np.all(np.isfinite(U)):
            for b, (u, a_ext, alpha_ext) in zip(bodies, got):
                b._finish_step(u, a_ext, alpha_ext, t0)
            return
        da, dalpha, U_c = so.correction.apply(U)
        rows = np.array([self._row[id(b)] for b in bodies], dtype=np.int32)
        slots = np.array([b.state.ring % so.n_max for b in bodies], dtype=np.int32)
        u_host, b_host = self._u_host.numpy(), self._b_host.numpy()
        share = (time.perf_counter() - t0) / len(bodies)
        for i, (b, (u, a_ext, alpha_ext)) in enumerate(zip(bodies, got)):
            b.timings["correction"] = b.timings.get("correction", 0.0) + share
            b_host[rows[i]] = b._finish_step(u, a_ext, alpha_ext, time.perf_counter(), corrected=(da[i], dalpha[i], U_c[i]),
                                             write_rings=False)
            u_host[rows[i], :n3] = b.state.u
        dev = so.device
        t_rings = time.perf_counter()
        wp.copy(self.u, self._u_host)
        wp.copy(self._b, self._b_host)
        r, s = wp.array(rows, dtype=wp.int32, device=dev), wp.array(slots, dtype=wp.int32, device=dev)
        for src, ring in ((self.u, self.U), (self.p, self.P), (self._b, self.B)):
            wp.launch(ks.write_ring_rows, dim=(len(rows), src.shape[1]), inputs=[src, r, s, ring], device=dev)
        share = (time.perf_counter() - t_rings) / len(bodies)
        for b in bodies:  # the stage that writes a lone body's rows (``BemBody._finish_step``)
            b.timings["frame"] = b.timings.get("frame", 0.0) + share


def instance_sets(bodies: Sequence[BemBody]) -> list[Instances]:
    """``Instances`` of the bodies (bound BEM bodies) that share an operator set whose passes can
    run together (``StepOperators.many_backend``), two or more to a set; the others are left alone."""
    by_so: dict[int, list[BemBody]] = {}
    for b in bodies:
        if b._so.many_backend != "each":
            by_so.setdefault(id(b._so), []).append(b)
    return [Instances(group) for group in by_so.values() if len(group) > 1]
