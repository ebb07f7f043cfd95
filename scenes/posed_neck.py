"""Posed-model scene: the neck of an elongated creature is bent and twisted by kinematic handles.

Like the horse of the PBD-reconstruction paper (Fang et al. 2021, Fig. 2): the torso is held,
the head is carried along a path over 100 frames (raised by 70 degrees and twisted by 90
degrees about the neck), and the tetrahedral XPBD body fills in the stretched, twisted neck.

    wsim run scenes/posed_neck.py -o posed_neck.usda
    wsim run scenes/posed_neck.py -o posed.usda --mesh model.obj   # torso = first 40 % of the
                                                                   # longest axis, head = last 15 %
"""

from __future__ import annotations

import numpy as np

import wsim
from wsim import mesh as wmesh

FRAMES = 100
DURATION = FRAMES / 30.0


def head_motion(pivot: np.ndarray, long_axis: np.ndarray, bend_axis: np.ndarray):
    """t -> 4x4: raise the head about ``bend_axis`` through ``pivot`` and twist it about the neck."""
    return wmesh.neck_pose(pivot, long_axis, bend_axis, DURATION)


def make_body(mesh: str | None = None, name: str | None = None) -> wsim.PbdBody:
    """The posed creature: torso pinned, head driven by a handle, tetrahedral XPBD body; named
    ``name``, else "creature" (a ``--mesh`` model: its file's stem)."""
    if mesh is None:
        shape = wmesh.neck_body(length=1.6, rings=48, sectors=16)
    else:
        shape = wmesh.load_fitted(mesh, 1.6)  # as long as the procedural creature, like every scene's --mesh
    name = wmesh.display_name(shape, "creature") if name is None else name
    v = np.asarray(shape.vertices)
    long_axis = np.eye(3)[int(np.argmax(np.ptp(v, axis=0)))]
    u = v @ long_axis
    lo, hi = u.min(), u.max()
    torso = np.flatnonzero(u < lo + 0.40 * (hi - lo))
    head = np.flatnonzero(u > lo + 0.85 * (hi - lo))
    pivot = v.mean(0) + long_axis * ((lo + 0.45 * (hi - lo)) - v.mean(0) @ long_axis)
    bend_axis = np.cross(long_axis, [0.0, 1.0, 0.0])
    if np.linalg.norm(bend_axis) < 1e-6:
        bend_axis = np.array([0.0, 0.0, 1.0])
    return wsim.PbdBody(
        shape,
        wsim.ElasticMaterial(E=3.0e5, nu=0.4, rho=1000.0),
        name=name,
        tets="auto",
        pinned=torso,
        handles=[wsim.Handle(head, head_motion(pivot, long_axis, bend_axis), name="head")],
        substeps=10,
        iterations=2,
    )


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = wsim.World(fps=30, gravity=(0.0, -9.81, 0.0), device=device)
    world.add(make_body(mesh))
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
