"""The posed-model scene reconstructed from keyframes, beside the simulation it replaces.

The creature of scenes/posed_neck.py is simulated with XPBD; an identical twin is simulated
privately by ``wsim.PbdReconstruction``, which keeps every 10th frame as a keyframe, fits the
dynamic-PDE closed forms of Fang et al. (2021) along automatic curves, and rebuilds every frame
from the formulas. Both go to USD, the reconstruction 1 m along +z, for side-by-side comparison.

    wsim run scenes/pbd_reconstruction.py -o pbd_reconstruction.usda
    wsim run scenes/pbd_reconstruction.py -o rec.usda --mesh model.obj
"""

from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the scene reuses posed_neck.py beside it

import posed_neck  # noqa: E402

import wsim  # noqa: E402

FRAMES = posed_neck.FRAMES
STRIDE = 10


def build(mesh: str | None = None, device: str | None = None) -> wsim.World:
    world = posed_neck.build(mesh=mesh, device=device)
    twin = posed_neck.make_body(mesh)  # named like the simulated body: creature, or the --mesh file's stem
    world.add(
        wsim.PbdReconstruction(twin, stride=STRIDE, basis="pde", frames=FRAMES, fps=world.fps, offset=(0.0, 0.0, 1.0))
    )
    return world


if __name__ == "__main__":
    from wsim.cli import scene_main

    scene_main(build, FRAMES)
