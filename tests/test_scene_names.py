"""Scene body names (issue 19): a ``--mesh bunny.obj`` model's bodies are named after the file
(USD prims ``/World/bunny``, ``/World/bunny_0``, ...), bodies not made from it keep their names,
and without ``--mesh`` every name is exactly what it always was (prim paths users and tools rely on).

The scenes are only built, never stepped; the BEM ones build their operators (a tiny mesh, and the
procedural shapes of these scenes, take seconds on a CPU).
"""

from __future__ import annotations

import runpy
from pathlib import Path

import pytest
import trimesh

ROOT = Path(__file__).resolve().parents[1]

# scene -> (body names without --mesh, body names with --mesh .../bunny.obj)
NAMES = {
    "soft_drop": (["fish"], ["bunny"]),  # PBD
    "bem_cube_drop": (["cube"], ["bunny"]),  # BEM, one body
    "eol_spinning_sphere": (["ball"], ["bunny"]),  # EoL
    "bem_pile": ([f"cube_{k}" for k in range(6)], [f"bunny_{k}" for k in range(6)]),  # six bodies of one model
    "mixed_drop": (["bem_cube", "eol_block", "ball_on_cube", "ball_on_block", "ball_on_ball"],  # only the balls
                   ["bem_cube", "eol_block", "bunny_on_cube", "bunny_on_block", "bunny_on_ball"]),  # are the model
}


def _build(scene: str, mesh: str | None):
    return runpy.run_path(str(ROOT / "scenes" / f"{scene}.py"))["build"](mesh=mesh, device="cpu")


@pytest.fixture(scope="module")
def bunny(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("model") / "bunny.obj"
    trimesh.creation.icosphere(subdivisions=1).export(path)
    return str(path)


@pytest.mark.parametrize("scene", sorted(NAMES))
def test_bodies_of_a_mesh_model_are_named_after_its_file(scene, bunny):
    assert [b.name for b in _build(scene, bunny).bodies] == NAMES[scene][1]


@pytest.mark.parametrize("scene", sorted(NAMES))
def test_procedural_bodies_keep_their_names(scene):
    assert [b.name for b in _build(scene, None).bodies] == NAMES[scene][0]
