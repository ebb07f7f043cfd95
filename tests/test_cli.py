"""End to end: the console script runs the shipped scenes and writes USD a DCC can open."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom

ROOT = Path(__file__).resolve().parents[1]


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "wsim", *args], cwd=ROOT, capture_output=True, text=True, timeout=600
    )


@pytest.mark.parametrize("scene, frames", [("soft_drop", 3), ("posed_neck", 2), ("pbd_reconstruction", 2)])
def test_scene_runs_and_writes_usd(tmp_path, scene, frames):
    out = tmp_path / f"{scene}.usda"
    res = run_cli("run", f"scenes/{scene}.py", "-o", str(out), "--frames", str(frames), "--device", "cpu", "--no-progress")
    assert res.returncode == 0, res.stderr
    stage = Usd.Stage.Open(str(out))
    assert stage.GetFramesPerSecond() == 30 and stage.GetEndTimeCode() == frames
    meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and "colliders" not in str(p.GetPath())]
    assert meshes and all(len(m.GetPointsAttr().GetTimeSamples()) == frames + 1 for m in meshes)


@pytest.mark.parametrize("scene", ["eol_spinning_sphere", "eol_plastic_cylinder"])
def test_eol_scenes_run_and_write_usd(tmp_path, scene):
    out = tmp_path / f"{scene}.usda"
    res = run_cli("run", f"scenes/{scene}.py", "-o", str(out), "--frames", "2", "--device", "cpu", "--no-progress")
    assert res.returncode == 0, res.stderr
    stage = Usd.Stage.Open(str(out))
    meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and "colliders" not in str(p.GetPath())]
    assert len(meshes) == 1 and len(meshes[0].GetPointsAttr().GetTimeSamples()) == 3
    p0, p2 = (np.array(meshes[0].GetPointsAttr().Get(t)) for t in (0, 2))
    assert np.all(np.isfinite(p2)) and np.abs(p2 - p0).max() > 0.0  # it moved


@pytest.mark.parametrize("scene", ["eol_two_spheres", "eol_pile"])
def test_eol_multi_body_scenes_run_and_write_usd(tmp_path, scene):
    """The EoL paper's multi-body scenes (contact between EoL bodies) end to end: every body
    written for every frame, finite, and moving."""
    out = tmp_path / f"{scene}.usda"
    res = run_cli("run", f"scenes/{scene}.py", "-o", str(out), "--frames", "2", "--device", "cpu", "--no-progress")
    assert res.returncode == 0, res.stderr
    stage = Usd.Stage.Open(str(out))
    meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and "colliders" not in str(p.GetPath())]
    assert len(meshes) == {"eol_two_spheres": 2, "eol_pile": 16}[scene]
    for m in meshes:
        assert len(m.GetPointsAttr().GetTimeSamples()) == 3
        p0, p2 = (np.array(m.GetPointsAttr().Get(t)) for t in (0, 2))
        assert np.all(np.isfinite(p2)) and np.abs(p2 - p0).max() > 0.0


@pytest.mark.parametrize("scene, floor", [("bem_cube_drop", 1e-4), ("bem_glued_cubes", 1e-4), ("bem_friction", 1e-4),
                                          ("bem_pile", 1e-4), ("bem_fish_bowl", 1e-4), ("mixed_drop", 1e-3),
                                          ("showcase", 1e-3)])
def test_bem_constraint_scenes_run_and_write_usd(tmp_path, scene, floor):
    """The BEM contact and joint scenes, and the three methods together, end to end with their
    procedural bodies (small enough for a CPU operator build): every body written for every frame,
    none below the ground by more than ``floor`` (the EoL block of the mixed scene rests 0.12 mm
    deep: its contact rows push existing overlap out over ``contact_relaxation``)."""
    out = tmp_path / f"{scene}.usda"
    res = run_cli("run", f"scenes/{scene}.py", "-o", str(out), "--frames", "2", "--device", "cpu", "--no-progress")
    assert res.returncode == 0, res.stderr
    stage = Usd.Stage.Open(str(out))
    meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and "colliders" not in str(p.GetPath())]
    assert meshes and all(len(m.GetPointsAttr().GetTimeSamples()) == 3 for m in meshes)
    for m in meshes:
        p = np.array(m.GetPointsAttr().Get(2))
        assert np.all(np.isfinite(p)) and p[:, 1].min() > -floor


@pytest.mark.parametrize("scene", ["bem_spinning_cube", "bem_squeeze"])
def test_bem_scenes_run_with_a_small_mesh(tmp_path, scene):
    """The BEM scenes end to end on a user mesh small enough for a CPU operator build."""
    import trimesh

    small = tmp_path / "small.obj"
    trimesh.creation.icosphere(subdivisions=1).export(small)
    out = tmp_path / f"{scene}.usda"
    res = run_cli("run", f"scenes/{scene}.py", "-o", str(out), "--frames", "2", "--device", "cpu", "--no-progress",
                  "--mesh", str(small))
    assert res.returncode == 0, res.stderr
    stage = Usd.Stage.Open(str(out))
    meshes = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert meshes and all(len(m.GetPointsAttr().GetTimeSamples()) == 3 for m in meshes)


def test_info_and_errors(tmp_path):
    res = run_cli("info")
    assert res.returncode == 0 and "warp" in res.stdout and "cpu" in res.stdout
    res = run_cli("run", "scenes/soft_drop.py", "-o", str(tmp_path / "nope" / "x.usda"), "--frames", "1", "--device", "cpu")
    assert res.returncode == 1 and "does not exist" in res.stderr
    res = run_cli("run", "scenes/no_such_scene.py")
    assert res.returncode != 0 and "not found" in res.stderr


def test_reconstruction_study_quick_prints_the_agreed_json():
    res = subprocess.run(
        [sys.executable, "tools/study_pbd_reconstruction.py", "--quick", "--stride", "10"],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )
    assert res.returncode == 0, res.stderr
    import json

    rows = [json.loads(line) for line in res.stdout.splitlines() if line.startswith("{")]
    assert {r["method"] for r in rows} == {"pde", "bezier", "bspline", "linear"}
    for r in rows:
        assert {"method", "stride", "data_ratio", "keyframe_err", "inbetween_err", "seconds_per_frame", "device"} <= r.keys()
        assert r["stride"] == 10 and r["device"] == "cpu" and 0 < r["data_ratio"] < 1 and r["inbetween_err"] < 0.2
