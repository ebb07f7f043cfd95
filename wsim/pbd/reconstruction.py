"""PbdReconstruction: a World body that plays back a keyframe-curve reconstruction of a PBD run.

Simulate (or take recorded frames), keep every ``stride``-th frame as a keyframe, fit curves
(``wsim.pbd.fit``), and produce every frame from the fitted formulas with a Warp kernel
(``kernels/pbd_reconstruct.py``, CPU or GPU). As a World body it exports to USD like any other,
beside or instead of the simulated body.

Sources:
- recorded frames: an (F, N, 3) array with ``faces`` (and ``rest``, default the first frame), or a
  ``PbdRecording`` from ``record(world, body, frames)``;
- an unbound ``PbdBody`` with ``frames=`` the number of frames to simulate: the reconstruction
  binds it to the World's device, gravity and colliders and simulates it privately before the
  first frame is needed (the World's fps must equal ``fps``).
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import warp as wp

from wsim.body import Body
from wsim.errors import InvalidParameter, SimulationDiverged
from wsim.kernels import pbd_reconstruct as kr
from wsim.pbd import fit as pf
from wsim.pbd.body import PbdBody
from wsim.pbd.curves import Curve
from wsim.validate import as_vec3

_BASIS = {"pde": kr.BASIS_PDE, "bezier": kr.BASIS_BEZIER, "bspline": kr.BASIS_BSPLINE}


@dataclass(frozen=True)
class PbdRecording:
    """Frames of a simulated body: ``frames`` (F, N, 3) [m] at ``fps``, with ``faces`` and ``rest``."""

    frames: np.ndarray
    faces: np.ndarray
    rest: np.ndarray
    fps: float
    name: str = "recording"


def record(world, body: Body, frames: int) -> PbdRecording:
    """Step ``world`` ``frames`` times and keep ``body``'s surface points (frame 0 = the current state)."""
    out = [body.points()]
    for _ in range(int(frames)):
        world.step()
        out.append(body.points())
    return PbdRecording(np.array(out), np.asarray(body.faces), out[0].copy(), world.fps, body.name)


def paper_errors(rec: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """The paper's Eqs. (23)-(24) at one frame: (E_a, E_m), the mean and max over vertices of
    |x_rec - x| / |x|. |x| is the distance from the origin, so the value depends on where the
    model sits (it is not translation-invariant) and is undefined for a vertex at the origin:
    vertices closer to it than 1e-6 of the farthest one are left out."""
    d = np.linalg.norm(rec - truth, axis=1)
    dbar = np.linalg.norm(truth, axis=1)
    ok = dbar > 1e-6 * dbar.max()
    r = d[ok] / dbar[ok]
    return float(r.mean()), float(r.max())


def relative_error(rec: np.ndarray, truth: np.ndarray) -> float:
    """max over vertices of |x_rec - x| divided by the bounding-box diagonal of ``truth`` (translation-invariant)."""
    diag = float(np.linalg.norm(np.ptp(truth, axis=0)))
    return float(np.linalg.norm(rec - truth, axis=1).max() / diag)



@dataclass
class ReconstructionState:
    """A reconstruction's only state: the frame it last evaluated (the curves are fixed once fitted)."""

    frame: int = 0

class PbdReconstruction(Body):
    """Keyframe-curve reconstruction of a PBD animation, usable as a World body.

    Args:
        source: (F, N, 3) frames, a ``PbdRecording``, or an unbound ``PbdBody`` (with ``frames=``).
        stride: keep every ``stride``-th frame (and the last) as a keyframe (>= 1).
        curves: "auto" (meridian curves covering every vertex) or a list of vertex-index lists.
        basis: "pde" (the paper's dynamic-PDE closed forms), "bezier", "bspline" or "linear".
        frames: frames to simulate when ``source`` is a PbdBody.
        faces: (M, 3) triangles when ``source`` is an array.
        rest: rest positions for an array source (default: the first frame).
        fps: frames per second of the source (a World playing it back must use the same).
        points_per_curve: vertices per automatic curve.
        closed: whether plain index-list curves are closed.
        mode: "displacement" (fit x - x_rest, default) or "position" (the paper).
        parametrization: "chord" (arc length on the rest shape) or "paper" (Eqs. 9-10).
        name: USD prim name (default: the source's name + "_reconstructed").
        offset: translation applied to the output (to show it beside the simulation) [m].
    """

    def __init__(
        self,
        source: np.ndarray | PbdRecording | PbdBody,
        stride: int = 10,
        curves: str | Sequence[Curve | Sequence[int]] = "auto",
        basis: str = "pde",
        *,
        frames: int | None = None,
        faces: np.ndarray | None = None,
        rest: np.ndarray | None = None,
        fps: float = 30.0,
        points_per_curve: int = 12,
        closed: bool = False,
        mode: str = "displacement",
        parametrization: str = "chord",
        name: str | None = None,
        offset: Sequence[float] = (0.0, 0.0, 0.0),
    ) -> None:
        base_name = getattr(source, "name", "pbd")
        super().__init__(name or f"{base_name}_reconstructed")
        if basis not in pf.METHODS:
            raise InvalidParameter(f"reconstruction '{self.name}': basis = {basis!r} must be one of {', '.join(pf.METHODS)}")
        pf.keyframe_indices(2, stride)  # validates stride now
        self.basis = basis
        self.stride = int(stride)
        self.fit_options = dict(
            curves=curves, points_per_curve=points_per_curve, closed=closed, mode=mode, parametrization=parametrization
        )
        self.offset = as_vec3(offset, f"reconstruction '{self.name}': offset")
        self.fps = float(fps)
        self._body: PbdBody | None = None
        self._frames_to_run = None
        if isinstance(source, PbdBody):
            if source._device is not None:
                raise InvalidParameter(
                    f"reconstruction '{self.name}': body '{source.name}' already belongs to a World; pass a body of its "
                    "own (the reconstruction simulates it privately), or record(world, body, frames) and pass that"
                )
            if frames is None or isinstance(frames, bool) or int(frames) < 1:
                raise InvalidParameter(f"reconstruction '{self.name}': frames= (>= 1) is needed to simulate body '{source.name}'")
            self._body = source
            self._frames_to_run = int(frames)
            self._faces = source.faces
            self.recording: PbdRecording | None = None
        else:
            if isinstance(source, PbdRecording):
                rec = source
            else:
                arr = np.asarray(source, dtype=np.float64)
                if faces is None:
                    raise InvalidParameter(f"reconstruction '{self.name}': faces= is needed with an array of frames")
                rec = PbdRecording(arr, np.asarray(faces), arr[0] if rest is None else np.asarray(rest, dtype=np.float64), fps)
            self.recording = rec
            self.fps = float(rec.fps)
            self._faces = np.asarray(rec.faces, dtype=np.int32)
            self._fit()
        self._device: wp.Device | None = None
        self._out: wp.array | None = None

    # ---------------------------------------------------------------- fitting
    def _fit(self) -> None:
        rec = self.recording
        t0 = _time.perf_counter()
        self.model = pf.fit(rec.frames, rec.rest, self.stride, method=self.basis, **self.fit_options)
        self.fit_seconds = _time.perf_counter() - t0

    @property
    def n_frames(self) -> int:
        """Frames the reconstruction covers (frame 0 .. n_frames - 1)."""
        return self._frames_to_run + 1 if self.recording is None else len(self.recording.frames)

    # ---------------------------------------------------------------- Body interface
    @property
    def faces(self) -> np.ndarray:
        return self._faces

    def bind(self, device: wp.Device, gravity: np.ndarray, up: np.ndarray) -> None:
        if self._device is not None:
            raise InvalidParameter(f"reconstruction '{self.name}' already belongs to a World")
        self._device = device
        self.state = ReconstructionState()
        if self._body is not None:
            self._body.bind(device, gravity, up)
        else:
            self._upload()

    def attach_colliders(self, surfaces) -> None:
        if self._body is not None:
            self._body.attach_colliders(surfaces)

    def _state_loaded(self) -> None:
        if self.state.frame > 0:
            self.evaluate(self.state.frame)  # fits first if the source body has not been simulated yet

    def signature(self) -> dict:
        return {**super().signature(), "stride": self.stride, "basis": self.basis, "fps": self.fps,
                "frames": self.n_frames}

    def _ensure_fitted(self) -> None:
        if self.recording is not None:
            return
        body, n = self._body, self._frames_to_run
        out = [body.points()]
        dt = 1.0 / self.fps
        for f in range(n):
            body.advance(f * dt, (f + 1) * dt)
            body.check_finite(f + 1, (f + 1) * dt)
            out.append(body.points())
        self.recording = PbdRecording(np.array(out), np.asarray(body.faces), out[0].copy(), self.fps, body.name)
        self._fit()
        self._upload()

    def _upload(self) -> None:
        m = self.model
        with wp.ScopedDevice(self._device):
            self._out = wp.zeros(len(m.rest), dtype=wp.vec3)
            self._flag = wp.zeros(1, dtype=int)
            if m.method == "linear":
                self._keys = wp.array(m.key_positions, dtype=wp.vec3d)
                return
            lay = m.layout
            self._vertex_curve = wp.array(lay.vertex_curve.astype(np.int32), dtype=int)
            self._vertex_u = wp.array(lay.vertex_u, dtype=wp.vec3d)
            self._rest = wp.array(m.rest, dtype=wp.vec3d)
            self._coef = wp.array(np.ascontiguousarray(m.coef), dtype=wp.vec4d)
            C = lay.n_curves
            lam = m.lam if m.lam is not None else np.zeros((C, 3))
            mm = m.m if m.m is not None else np.zeros((len(m.keyframes) - 1, C, 3))
            self._lam = wp.array(lam, dtype=wp.vec3d)
            self._m = wp.array(np.ascontiguousarray(mm), dtype=wp.vec3d)

    def evaluate(self, frame: float) -> wp.array:
        """Reconstruct ``frame`` into the device output buffer (returned; no host copy)."""
        self._ensure_fitted()
        j, tau = self.model.segment(frame)
        m = self.model
        if m.method == "linear":
            wp.launch(kr.reconstruct_linear, dim=len(m.rest), inputs=[self._keys, j, wp.float64(tau), self._out], device=self._device)
        else:
            wp.launch(
                kr.reconstruct_curves,
                dim=len(m.rest),
                inputs=[
                    self._vertex_curve, self._vertex_u, self._rest, self._coef, self._lam, self._m,
                    j, wp.float64(tau), _BASIS[m.method], int(m.mode == "displacement"), self._out,
                ],
                device=self._device,
            )
        return self._out

    def check_frames(self, last: int, fps: float) -> None:
        if abs(fps - self.fps) <= 1e-9 * self.fps and last > self.n_frames - 1:
            raise InvalidParameter(f"reconstruction '{self.name}' covers frames 0..{self.n_frames - 1}; a run up to "
                                   f"frame {last} was asked for (at most {self.n_frames - 1})")

    def advance(self, t0: float, t1: float) -> None:
        if abs((t1 - t0) * self.fps - 1.0) > 1e-6:
            raise InvalidParameter(
                f"reconstruction '{self.name}' was made at {self.fps:g} fps; the World steps {1.0 / (t1 - t0):g} fps"
            )
        frame = int(round(t1 * self.fps))
        if frame > self.n_frames - 1:
            raise InvalidParameter(
                f"reconstruction '{self.name}' covers frames 0..{self.n_frames - 1}; frame {frame} was asked for"
            )
        self.state.frame = frame
        self.evaluate(frame)

    def points(self) -> np.ndarray:
        if self._device is None:
            raise InvalidParameter(f"reconstruction '{self.name}': add it to a World before reading its state")
        if self.state.frame == 0:
            if self.recording is None:
                # frame 0 is the source body's start: simulating it now, before the World has
                # attached its colliders (first step), would record a body falling through them
                return self._body.points() + self.offset
            self.evaluate(0)
        return self._out.numpy().astype(np.float64) + self.offset

    def check_finite(self, frame: int, time: float) -> None:
        self._flag.zero_()
        wp.launch(kr.check_finite_points, dim=len(self.model.rest), inputs=[self._out, self._flag], device=self._device)
        if self._flag.numpy()[0]:
            raise SimulationDiverged(self.name, frame, "reconstructed positions", time)
