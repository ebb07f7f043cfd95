"""wsim: physics simulation for technical animators, on NVIDIA Warp, exported as animated USD.

The scene API::

    import wsim
    world = wsim.World(fps=30, gravity=(0.0, -9.81, 0.0), device=None)
    world.add_collider(wsim.GroundPlane(height=0.0, friction=0.5))
    body = world.add(wsim.PbdBody(mesh, material=wsim.ElasticMaterial(E=1e5, nu=0.3, rho=1000.0)))
    world.run(frames=90, out="out.usda")
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# Names resolve on first use (PEP 562), so ``wsim --help`` and ``wsim.errors`` do not import
# Warp, scipy and trimesh (0.8 s) before they are needed.
_EXPORTS = {
    "BemBody": "wsim.bem.body",
    "Body": "wsim.body",
    "Collider": "wsim.colliders",
    "GroundPlane": "wsim.colliders",
    "MeshCollider": "wsim.colliders",
    "PointJoint": "wsim.constraints",
    "EolBody": "wsim.eol.body",
    "Plasticity": "wsim.eol.body",
    "CheckpointError": "wsim.errors",
    "InvalidMaterial": "wsim.errors",
    "InvalidMesh": "wsim.errors",
    "InvalidParameter": "wsim.errors",
    "OutputError": "wsim.errors",
    "SimulationDiverged": "wsim.errors",
    "WsimError": "wsim.errors",
    "Handle": "wsim.handles",
    "ElasticMaterial": "wsim.materials",
    "PbdBody": "wsim.pbd.body",
    "PbdReconstruction": "wsim.pbd.reconstruction",
    "PbdRecording": "wsim.pbd.reconstruction",
    "record": "wsim.pbd.reconstruction",
    "RunSummary": "wsim.world",
    "World": "wsim.world",
}

if TYPE_CHECKING:
    from wsim.bem.body import BemBody
    from wsim.body import Body
    from wsim.colliders import Collider, GroundPlane, MeshCollider
    from wsim.constraints import PointJoint
    from wsim.eol.body import EolBody, Plasticity
    from wsim.errors import (CheckpointError, InvalidMaterial, InvalidMesh, InvalidParameter, OutputError,
                             SimulationDiverged, WsimError)
    from wsim.handles import Handle
    from wsim.materials import ElasticMaterial
    from wsim.pbd.body import PbdBody
    from wsim.pbd.reconstruction import PbdReconstruction, PbdRecording, record
    from wsim.world import RunSummary, World


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:  # a subpackage or module: wsim.mesh, wsim.bem, ...
        try:
            value = importlib.import_module(f"wsim.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"wsim.{name}":
                raise
            raise AttributeError(f"module 'wsim' has no attribute '{name}'") from None
        globals()[name] = value
        return value
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


try:
    from importlib.metadata import version as _version

    __version__ = _version("wsim")
except Exception:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = [
    "World",
    "RunSummary",
    "Body",
    "PbdBody",
    "BemBody",
    "EolBody",
    "Plasticity",
    "PbdReconstruction",
    "PbdRecording",
    "record",
    "ElasticMaterial",
    "Collider",
    "GroundPlane",
    "MeshCollider",
    "Handle",
    "PointJoint",
    "WsimError",
    "InvalidMesh",
    "InvalidMaterial",
    "InvalidParameter",
    "OutputError",
    "SimulationDiverged",
    "CheckpointError",
    "__version__",
]
