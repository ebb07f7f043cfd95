"""USD export through the World: stage metadata, time samples, axes, colliders, atomic writes,
and the frames kept when a run diverges."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from pxr import Usd, UsdGeom

import wsim


def small_world(device: str, **kw) -> tuple[wsim.World, wsim.PbdBody]:
    world = wsim.World(fps=24, device=device, **kw)
    world.add_collider(wsim.GroundPlane(friction=0.4))

    def slide(t: float) -> np.ndarray:
        m = np.eye(4)
        m[:3, 3] = (-1.0 + t, 0.1, 0.0)
        return m

    world.add_collider(wsim.MeshCollider(trimesh.creation.box(extents=(0.1, 0.2, 0.5)), transform=slide, name="pusher"))
    body = world.add(
        wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1, radius=0.2), name="soft ball", position=(0, 0.5, 0))
    )
    return world, body


def test_stage_metadata_and_time_samples(device, tmp_path):
    world, body = small_world(device)
    out = tmp_path / "run.usda"
    summary = world.run(6, out, progress=False)
    assert summary.frames == 6 and summary.out == out
    stage = Usd.Stage.Open(str(out))
    assert stage.GetTimeCodesPerSecond() == 24 and stage.GetFramesPerSecond() == 24
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 6)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/soft_ball"))
    assert mesh.GetPointsAttr().GetTimeSamples() == [0, 1, 2, 3, 4, 5, 6]
    assert len(mesh.GetExtentAttr().GetTimeSamples()) == 7
    assert not mesh.GetFaceVertexIndicesAttr().ValueMightBeTimeVarying()
    np.testing.assert_array_equal(np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), body.faces)
    last = np.array(mesh.GetPointsAttr().Get(6))
    np.testing.assert_allclose(last, body.points(), atol=1e-6)
    assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    # kinematic collider: time-sampled transform matching its pose function
    pusher = UsdGeom.Xformable(stage.GetPrimAtPath("/World/colliders/pusher"))
    m3 = np.array(pusher.ComputeLocalToWorldTransform(Usd.TimeCode(3))).T
    np.testing.assert_allclose(m3[:3, 3], (-1.0 + 3 / 24, 0.1, 0.0), atol=1e-12)
    assert stage.GetPrimAtPath("/World/colliders/ground").IsValid()
    assert [p.name for p in tmp_path.iterdir()] == ["run.usda"]  # no temp files left


def test_up_axis_z_rotates_points(tmp_path):
    world, body = small_world("cpu")
    out = tmp_path / "z.usdc"
    world.run(2, out, up_axis="Z", progress=False)
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    pts = np.array(UsdGeom.Mesh(stage.GetPrimAtPath("/World/soft_ball")).GetPointsAttr().Get(2))
    y_up = body.points()
    np.testing.assert_allclose(pts, np.stack([y_up[:, 0], -y_up[:, 2], y_up[:, 1]], axis=1), atol=1e-6)
    ground = np.array(UsdGeom.Mesh(stage.GetPrimAtPath("/World/colliders/ground")).GetPointsAttr().Get())
    assert np.allclose(ground[:, 2], 0.0)  # the ground plane lies in z = 0 in a Z-up file


def test_divergence_keeps_earlier_frames(device, tmp_path):
    world, body = small_world(device)
    out = tmp_path / "nan.usda"

    def poison(w: wsim.World) -> None:
        if w.frame == 5:
            x = body.x.numpy()
            x[3] = np.nan
            body.x.assign(x)

    with pytest.raises(wsim.SimulationDiverged) as info:
        world.run(10, out, progress=False, on_frame=poison)
    err = info.value
    assert (err.body, err.step, err.quantity) == ("soft ball", 5, "positions")
    assert "soft ball" in str(err) and "frame 5" in str(err)
    stage = Usd.Stage.Open(str(out))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/soft_ball"))
    assert mesh.GetPointsAttr().GetTimeSamples() == [0, 1, 2, 3, 4]
    assert stage.GetEndTimeCode() == 4
    assert np.all(np.isfinite(np.array(mesh.GetPointsAttr().Get(4))))


def test_unwritable_output_fails_before_simulating(tmp_path):
    world, _ = small_world("cpu")
    for bad, words in [
        (tmp_path / "missing" / "a.usda", "does not exist"),
        (tmp_path / "a.obj", "extension"),
        (tmp_path, "directory"),
    ]:
        with pytest.raises(wsim.OutputError, match=words):
            world.run(3, bad, progress=False)
    assert world.frame == 0  # nothing was simulated


def test_world_parameters_are_validated():
    with pytest.raises(wsim.InvalidParameter, match="fps"):
        wsim.World(fps=0)
    with pytest.raises(wsim.InvalidParameter, match="gravity"):
        wsim.World(gravity=(0, float("nan"), 0))
    with pytest.raises(wsim.InvalidParameter, match="device"):
        wsim.World(device="tpu:3")
    world = wsim.World(device="cpu")
    world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1), name="a"))
    with pytest.raises(wsim.InvalidParameter, match="already exists"):
        world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1), name="a"))
    with pytest.raises(wsim.InvalidParameter, match="frames"):
        world.run(0)


def test_up_axis_z_world_falls_along_minus_z():
    world = wsim.World(device="cpu", up_axis="Z")
    assert np.allclose(world.gravity, (0.0, 0.0, -9.81))
    world.add_collider(wsim.GroundPlane())
    body = world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1, radius=0.2), name="b", position=(0, 0, 1.0)))
    for _ in range(30):
        world.step()
    p = body.points()
    assert p[:, 2].min() >= -1e-6 and p[:, 2].min() < 0.05  # landed on the z = 0 ground
    assert np.abs(p[:, 1].mean()) < 1e-3  # and did not slide along y


def test_prim_name_clashes_fail_before_simulating(tmp_path):
    world = wsim.World(device="cpu")
    world.add_collider(wsim.GroundPlane(name="a b"))
    world.add_collider(wsim.MeshCollider(trimesh.creation.box(), name="a_b"))
    world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1), name="ball"))
    with pytest.raises(wsim.InvalidParameter, match="collider 'a_b' and collider 'a b'"):
        world.run(2, tmp_path / "x.usda", progress=False)
    assert world.frame == 0 and not (tmp_path / "x.usda").exists()
    world = wsim.World(device="cpu")
    world.add_collider(wsim.GroundPlane())
    world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1), name="colliders"))
    with pytest.raises(wsim.InvalidParameter, match="colliders scope"):
        world.run(2, tmp_path / "y.usda", progress=False)


def test_written_file_has_a_normal_mode(tmp_path):
    import os
    import stat

    world, _ = small_world("cpu")
    out = tmp_path / "mode.usda"
    world.run(1, out, progress=False)
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~umask
