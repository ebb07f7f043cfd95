"""A free BEM step kept on the device: the error correction and frame update as one kernel after
the two passes, and on CUDA the step's launches replayed as one CUDA graph (issue 21, item 4).

The host path (``BemBody._finish_step``) copies u_n to the host after Eq. (12), corrects it in
numpy (``wsim.bem.correction``), writes the ring rows back and moves the frame: four small copies,
a synchronization and ~20 numpy calls per step, which cost more than the step's matrix passes at
N ~ 600 (0.33 ms of a 0.60 ms step on an H100). Here the same maths, in float64, runs in one block
(``kernels.bem_step.correct_step``) on the device's copy of the frame, and the host stays out of the
step: it evaluates the loads (when the body has any), launches, and reads the displacement, the
frame and a per-step log of max |u| and non-finite flags back once per batch
(``BemBody.advance``: a World frame or coupling interval), where the checks of ``_check_state`` run
on the log step by step. What the host path computes differently: the sums' order (round-off), and
R_e by a scaled Newton polar iteration instead of an SVD (both to float64 round-off).

``DeviceCorrection``: the correction's per-node pieces on the device, built once per operator set
on first use (``StepOperators.device_correction``). ``ResidentStep``: one body's launch state
(the device frame, the log, the page-locked load buffers and the captured graphs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from wsim.bem import stepper
from wsim.bem.correction import Correction
from wsim.kernels import bem_step as ks
from wsim.rigid import RigidFrame

CORRECT_BLOCK = 256  # threads of the correction block
LOG_ROWS = 256  # steps per batch at most: the log's rows (a longer advance reads back in between)


@dataclass(frozen=True)
class DeviceCorrection:
    """``Correction`` regrouped per node for ``kernels.bem_step.correct_step`` (all float64).

    Attributes:
        q, wq, cx: (N,) vec3d x_i - c_0, w_i (x_i - c_0) and c_0 - x_i.  w: (N,) the weights.
        PQH: (N,) mat33d, columns 3i..3i+2 of P_Q H_0.  Ea, Eb: (N,) mat33d, rows 3i..3i+2 of
            H_0^-1 D_0 and H_0^-1 Q_0.
        w_sum, sum_wq: sum_i w_i, sum_i w_i q_i (zero up to round-off).
        K_a, M_t, M_a: K_a, -P_Q H_0 (1 (x) I) and -P_Q D_0 (3 x 3).
    """

    q: wp.array
    wq: wp.array
    cx: wp.array
    w: wp.array
    PQH: wp.array
    Ea: wp.array
    Eb: wp.array
    w_sum: float
    sum_wq: np.ndarray
    K_a: np.ndarray
    M_t: np.ndarray
    M_a: np.ndarray

    @classmethod
    def build(cls, c: Correction, device: wp.Device) -> DeviceCorrection:
        n = c.x.shape[0]

        def vec(a: np.ndarray) -> wp.array:
            return wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=wp.vec3d, device=device)

        def blocks(a: np.ndarray) -> wp.array:  # (N, 3, 3) float64
            return wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=wp.mat33d, device=device)

        PQH = c.P_Q_H0.reshape(3, n, 3).transpose(1, 0, 2)  # [i, r, c] = P_Q H_0[r, 3 i + c]
        E = c.E.reshape(n, 3, 6)
        return cls(q=vec(c.q), wq=vec(c.wq), cx=vec(c.c0 - c.x), w=wp.array(c.w, dtype=wp.float64, device=device),
                   PQH=blocks(PQH), Ea=blocks(E[:, :, :3]), Eb=blocks(E[:, :, 3:]), w_sum=c.w_sum,
                   sum_wq=c.wq.sum(axis=0), K_a=c.K_a, M_t=-(c.P_Q @ c.H0_T), M_a=-(c.P_Q @ c.D0))


def frame_vector(f: RigidFrame) -> np.ndarray:
    """The (21,) layout of ``kernels.bem_step.FRAME_SIZE``: R row-major, T, T_dot, omega, L."""
    return np.concatenate([f.R.reshape(-1), f.T, f.velocity, f.omega, f.L])


def set_frame(f: RigidFrame, v: np.ndarray) -> None:
    f.R, f.T, f.velocity, f.omega, f.L = (v[:9].reshape(3, 3).copy(), v[9:12].copy(), v[12:15].copy(),
                                          v[15:18].copy(), v[18:21].copy())


class ResidentStep:
    """One body's free steps on the device (see the module docstring).

    Args:
        so: the body's (dense, Warp backend) step operators.
        rings: the body's (U, P, B) rings and their vec4 views (U_k, P_k).
        vectors: the step vectors p, h, u and the vec4 views p_k, h_k.
        inertia, gravity, dt, gyroscopic: the frame update's constants (Eq. 11).
    """

    def __init__(self, so: stepper.StepOperators, rings: tuple[wp.array, ...], vectors: tuple[wp.array, ...],
                 inertia: np.ndarray, gravity: np.ndarray, dt: float, gyroscopic: bool, divergence_limit: float) -> None:
        dev = so.device
        self.so = so
        self.settings = (bool(gyroscopic), float(divergence_limit))  # baked into the graphs
        self.dc: DeviceCorrection = so.device_correction
        self.U, self.P, self.B, self.U_k, self.P_k = rings
        self.p, self.h, self.u, self.p_k, self.h_k = vectors
        self.consts = (wp.mat33d(*np.asarray(inertia, dtype=np.float64).reshape(-1)),
                       wp.mat33d(*np.linalg.inv(inertia).reshape(-1)),
                       wp.vec3d(*np.asarray(gravity, dtype=np.float64)), wp.float64(dt), int(bool(gyroscopic)))
        self.u64 = wp.zeros(so.size, dtype=wp.float64, device=dev)
        self.frame = wp.zeros(21, dtype=wp.float64, device=dev)
        self.ext = wp.zeros(15, dtype=wp.float64, device=dev)
        self.log = wp.zeros((LOG_ROWS, 2), dtype=wp.float64, device=dev)
        self.counter = wp.zeros(1, dtype=wp.int32, device=dev)
        self.halt = wp.zeros(1, dtype=wp.int32, device=dev)  # set by a failing step: the rest of the batch does nothing
        pinned = dev.is_cuda
        # two load buffers, so the host fills one while the device still copies from the other;
        # an event per buffer says when its copy is done
        self.p_in = [wp.zeros(so.pitch, dtype=so.dtype, device="cpu", pinned=pinned) for _ in range(2)]
        self.ext_in = [wp.zeros(15, dtype=wp.float64, device="cpu", pinned=pinned) for _ in range(2)]
        self.events = [wp.Event(dev) if dev.is_cuda else None for _ in range(2)]
        self.used = [False, False]
        self.parity = 0
        self.graphs: dict[tuple[int, bool], object] = {}
        self.seen: set[tuple[int, bool]] = set()
        self.steps = 0  # steps launched since ``begin``

    # -- one batch ----------------------------------------------------------------------------
    def begin(self, frame: RigidFrame) -> None:
        """Start a batch from the host's frame (the host's state is the truth between batches)."""
        self.frame.assign(frame_vector(frame))
        self.counter.zero_()
        self.halt.zero_()
        self.steps = 0

    def load(self, p: np.ndarray, ext: np.ndarray) -> None:
        """This step's tractions p_n (3N,) and [A p_n, C p_n + f, X p_n, f] (15,) onto the device
        (``BemBody._frame_loads``)."""
        k = self.parity
        if self.used[k] and self.events[k] is not None:
            wp.synchronize_event(self.events[k])  # the copy two loads ago has left this buffer
        n3 = self.so.size
        self.p_in[k].numpy()[:n3] = p
        self.ext_in[k].numpy()[:] = ext
        wp.copy(self.p, self.p_in[k], count=n3)
        wp.copy(self.ext, self.ext_in[k])
        if self.events[k] is not None:
            wp.record_event(self.events[k])
        self.used[k] = True
        self.parity = 1 - k

    def step(self, ring: int, with_p: bool) -> None:
        """Launch step ``ring`` (the body's ring index: history slots (ring - k) mod n_max, its
        rows written at ring mod n_max); on CUDA a captured graph per (slot, with_p) replays it."""
        so = self.so
        slot = ring % so.n_max
        key = (slot, bool(with_p))
        self.steps += 1
        if so.device.is_cuda:
            graph = self.graphs.get(key)
            if graph is None and key in self.seen:  # launched once eagerly: its kernels are loaded
                wp.capture_begin(so.device, force_module_load=False)
                try:
                    self._launches(slot, with_p)
                finally:
                    graph = wp.capture_end(so.device)
                self.graphs[key] = graph
            if graph is not None:
                wp.capture_launch(graph)
                return
            self.seen.add(key)
        self._launches(slot, with_p)

    def _launches(self, slot: int, with_p: bool) -> None:
        so, dc = self.so, self.dc
        stepper.history(so, self.U_k, self.P_k, self.B, slot + so.n_max, self.h)
        stepper.solve(so, self.p_k if with_p else None, self.h_k, self.u)
        inertia, inertia_inv, gravity, dt, gyroscopic = self.consts
        wp.launch_tiled(ks.correct_step, dim=1, block_dim=CORRECT_BLOCK, device=so.device, inputs=[
            self.u, self.p, self.ext, int(with_p), dc.q, dc.wq, dc.w, dc.cx, dc.PQH, dc.Ea, dc.Eb,
            wp.float64(dc.w_sum), wp.vec3d(*dc.sum_wq), wp.mat33d(*dc.K_a.reshape(-1)), wp.mat33d(*dc.M_t.reshape(-1)),
            wp.mat33d(*dc.M_a.reshape(-1)), inertia, inertia_inv, gravity, dt, gyroscopic, slot,
            self.U, self.P, self.B, self.u64, self.frame, self.log, self.counter,
            wp.float64(self.settings[1]), self.halt])

    def reorthonormalize(self) -> None:
        wp.launch(ks.reorthonormalize, dim=1, inputs=[self.frame], device=self.so.device)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """(u_n float64 (3N,), frame (21,)) after the launched steps (synchronizes)."""
        return self.u64.numpy().copy(), self.frame.numpy().copy()

    def read_log(self) -> np.ndarray:
        """(steps, 2) [max |u|, flags] of this batch's steps, in order (up to a failing step:
        the rows after it are stale)."""
        return self.log.numpy()[: self.steps].copy()
