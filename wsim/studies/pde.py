"""PDE-reconstruction knob study: keyframe curves through the posed creature of ``scenes/posed_neck.py``.

The source is the reconstruction paper's posed model (Fang et al. 2021, Fig. 2; ``scenes/posed_neck.py``,
rebuilt here from the package's ``wsim.mesh.neck_body``): a tetrahedral XPBD creature 1.6 m long
(E = 3e5 Pa, nu = 0.4), its torso pinned, its head carried by a handle that raises it by 70
degrees and twists it by 90 degrees over 100 frames (eased in and out), under gravity, 10
substeps x 2 iterations a frame; simulated for the study's frames at 30 fps and recorded
(``wsim.record``). A ``PbdReconstruction`` keeps every ``stride``-th frame as a keyframe, fits
curves of ``points_per_curve`` vertices in ``basis``, and a World plays it back. The error is
measured here, against the frames it rebuilds: the largest distance of any surface vertex from
the simulation's, over every frame, over the creature's length. The reference (every frame a
keyframe, linear: the recorded frames themselves) has error 0 by construction; it runs like every
variant, a check of the measurement.

Knobs (``PbdReconstruction``'s): ``stride`` (frames per keyframe), ``basis`` ("pde", "bezier",
"linear"; "bspline" is left out: it fits the same cubic curves as "bezier", so its results are
bezier's) and ``points_per_curve`` (the length of the automatic curves, in vertices).
Costs: playback milliseconds per frame (the reconstruction kernel) and the stored data over the
raw frames (``data_ratio``); the fit's seconds (``fit_s``) are in the records.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

import wsim
from wsim import mesh as wmesh
from wsim.studies.common import Mode, StudySpec, StudyWorld

FRAMES = 60
LENGTH = 1.6  # [m]
POSE_FRAMES = 100  # the head's motion, as in scenes/posed_neck.py

SPEC = StudySpec(
    name="pde",
    title="PDE reconstruction: keyframe stride, basis, curve length",
    scenario="Keyframe curves through the posed creature of scenes/posed_neck.py (1.6 m, tetrahedral XPBD, torso "
             "pinned, head raised by 70 and twisted by 90 degrees over 100 frames), played back as a World body; "
             "30 fps.",
    error="the largest distance, over every surface vertex and frame, between the reconstruction and the "
          "simulated frames it rebuilds, over the creature's length (1.6 m)",
    scale=None,
    costs={"ms_per_frame": "playback ms per frame", "data_ratio": "stored data / raw frames"},
    knobs={"stride": "PbdReconstruction(stride=...): frames per keyframe",
           "basis": "PbdReconstruction(basis=...): 'pde' (closed-form PDE curves), 'bezier', 'linear' ('bspline' "
                    "fits the same cubic curves as 'bezier': not studied apart)",
           "points_per_curve": "PbdReconstruction(points_per_curve=...): vertices per automatic curve"},
    quick=Mode(default={}, grid={"stride": [5, 20], "basis": ["bezier", "linear"], "points_per_curve": [6, 24]},
               reference={"stride": 1, "basis": "linear"}, frames=FRAMES),
    full=Mode(default={"rings": 96, "sectors": 32, "frames": 100},
              grid={"stride": [2, 5, 20], "basis": ["bezier", "linear"], "points_per_curve": [6, 24]},
              reference={"stride": 1, "basis": "linear"}, frames=100),
    check_note="the error is measured against the simulated frames themselves, not against the reference, which "
               "runs as a check of the measurement (its error is 0 up to float32 output)",
    exact_reference=True,
)


def posed_creature(rings: int, sectors: int) -> wsim.PbdBody:
    """``scenes/posed_neck.py``'s body: torso (first 40 % of the length) pinned, head (last 15 %)
    raised and twisted about the neck's base by a handle."""
    shape = wmesh.neck_body(length=LENGTH, rings=rings, sectors=sectors)
    u = shape.vertices[:, 0]
    torso = np.flatnonzero(u < 0.40 * LENGTH)
    head = np.flatnonzero(u > 0.85 * LENGTH)
    pivot = np.array([0.45 * LENGTH, 0.0, 0.0])
    long_axis, bend_axis = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    seconds = POSE_FRAMES / 30.0

    motion = wmesh.neck_pose(pivot, long_axis, bend_axis, seconds)

    return wsim.PbdBody(shape, wsim.ElasticMaterial(E=3.0e5, nu=0.4, rho=1000.0), name="creature", tets="auto",
                        pinned=torso, handles=[wsim.Handle(head, motion, name="head")], substeps=10, iterations=2,
                        cache=False)


def build(mesh: Any = None, device: str | None = None, stride: int = 10, basis: str = "pde",
          points_per_curve: int = 12, rings: int = 48, sectors: int = 16, frames: int = FRAMES) -> StudyWorld:
    """``rings``, ``sectors``: the creature's mesh (``wsim.mesh.neck_body``); ``frames``: frames
    recorded from it (at least those the sweep plays back)."""
    if mesh is not None:
        raise wsim.InvalidParameter("the PDE study reconstructs its own creature (mesh=None)")
    source = wsim.World(fps=30.0, device=device)
    source.add(posed_creature(rings, sectors))
    rec = wsim.record(source, source.bodies[0], frames)
    t = time.perf_counter()
    recon = wsim.PbdReconstruction(rec, stride=stride, basis=basis, points_per_curve=points_per_curve,
                                   name="creature")
    fit_s = time.perf_counter() - t
    world = StudyWorld(fps=rec.fps, gravity=(0.0, 0.0, 0.0), device=device, signature=lambda w: w.bodies[0].points())
    world.add(recon)
    world.extra.update(fit_s=fit_s, data_ratio=float(recon.model.data_ratio))
    world.context["recording"] = rec  # the frames the error is measured against (metrics)
    return world


def metrics(world: StudyWorld) -> dict:
    out = world.measures()
    rebuilt = np.asarray(out.pop("signature"))  # (frames, N, 3): every vertex, kept out of the record
    truth = world.context["recording"].frames[1:len(rebuilt) + 1]
    out["error"] = float(np.linalg.norm(rebuilt - truth, axis=2).max() / LENGTH)
    out["vertices"] = int(truth.shape[1])
    return out
