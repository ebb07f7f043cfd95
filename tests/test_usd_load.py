"""Meshes read from USD stages (``wsim.mesh.load_usd`` and ``wsim.mesh.load("file.usd:/prim")``):
units, axes, transforms, winding, texture coordinates, errors, and bodies / colliders made from them."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

import wsim
from wsim import mesh as wm
from wsim.errors import InvalidMesh
from wsim.mesh.stage import split_prim_path

ROOT = Path(__file__).resolve().parents[1]

# unit cube, 8 corners, 6 outward counter-clockwise quads (right-handed)
CUBE_POINTS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                        [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.float64)
CUBE_QUADS = np.array([[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4],
                       [2, 3, 7, 6], [0, 4, 7, 3], [1, 2, 6, 5]])
# faceVarying st: a distinct value at every face corner
CUBE_ST = np.array([[k / 6 + 0.01 * j, 0.1 + 0.2 * j] for k in range(6) for j in range(4)], dtype=np.float32)


def new_stage(path: Path, up: str = "Y", mpu: float = 1.0) -> Usd.Stage:
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    return stage


def add_cube(stage: Usd.Stage, path: str, points=CUBE_POINTS, quads=CUBE_QUADS, st=CUBE_ST,
             interpolation=UsdGeom.Tokens.faceVarying, name: str = "st", indices=None,
             left: bool = False) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(points, dtype=np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([len(q) for q in quads]))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for q in quads for i in q]))
    if left:
        mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    if st is not None:
        pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(name, Sdf.ValueTypeNames.TexCoord2fArray, interpolation)
        pv.Set(Vt.Vec2fArray.FromNumpy(np.asarray(st, dtype=np.float32)))
        if indices is not None:
            pv.SetIndices(Vt.IntArray([int(i) for i in indices]))
    return mesh


def expected_fan_uv(st: np.ndarray, quads=CUBE_QUADS) -> np.ndarray:
    """Per-corner UVs of the quads' fan triangles (c0, c1, c2), (c0, c2, c3) for faceVarying st."""
    out = []
    for k in range(len(quads)):
        c = st[4 * k: 4 * k + 4]
        out += [[c[0], c[1], c[2]], [c[0], c[2], c[3]]]
    return np.array(out, dtype=np.float32)


@pytest.fixture
def cube_file(tmp_path: Path) -> Path:
    path = tmp_path / "cube.usda"
    stage = new_stage(path)
    add_cube(stage, "/World/cube")
    stage.Save()
    return path


def test_cube_quads_are_fan_triangulated_with_face_varying_uvs(cube_file: Path) -> None:
    m = wm.load_usd(cube_file)
    assert isinstance(m, trimesh.Trimesh) and m.faces.shape == (12, 3)
    np.testing.assert_allclose(m.vertices, CUBE_POINTS)  # process=False: USD's point order kept
    np.testing.assert_array_equal(m.faces[:2], [[0, 3, 2], [0, 2, 1]])
    assert m.volume == pytest.approx(1.0) and wm.signed_volume(m.vertices, m.faces) == pytest.approx(1.0)
    uv = m.metadata["wsim_face_uv"]
    assert uv.dtype == np.float32 and uv.shape == (12, 3, 2)
    np.testing.assert_array_equal(uv, expected_fan_uv(CUBE_ST))
    np.testing.assert_array_equal(wm.face_uvs(m), uv)
    assert wm.display_name(m, "x") == "cube"  # no prim named: the file's stem


def test_transform_centimetres_and_z_up_give_metres_y_up(tmp_path: Path) -> None:
    path = tmp_path / "zup.usdc"
    stage = new_stage(path, up="Z", mpu=0.01)
    parent = UsdGeom.Xform.Define(stage, "/World/set")
    parent.AddTranslateOp().Set(Gf.Vec3d(10.0, 20.0, 300.0))
    parent.AddScaleOp().Set(Gf.Vec3f(2.0, 2.0, 2.0))
    add_cube(stage, "/World/set/box", points=CUBE_POINTS * 50.0)  # 50 units, x2 = 100 cm
    stage.Save()
    m = wm.load_usd(path, "/World/set/box")
    world_cm = CUBE_POINTS * 100.0 + (10.0, 20.0, 300.0)
    x, y, z = (world_cm * 0.01).T
    np.testing.assert_allclose(m.vertices, np.stack([x, z, -y], axis=1), atol=1e-9)
    assert m.volume == pytest.approx(1.0)  # 1 m^3, still outward after the axis rotation
    assert m.bounds[0][1] == pytest.approx(3.0)  # the stage's z = 300 cm is wsim's height y = 3 m
    np.testing.assert_array_equal(m.metadata["wsim_face_uv"], expected_fan_uv(CUBE_ST))
    assert wm.display_name(m, "x") == "box"


def test_left_handed_and_mirrored_prims_come_out_outward(tmp_path: Path) -> None:
    path = tmp_path / "hands.usda"
    stage = new_stage(path)
    reversed_quads = CUBE_QUADS[:, ::-1]
    st = CUBE_POINTS[:, :2] * 0.5 + 0.25  # vertex-interpolated: each corner's UV follows its point
    add_cube(stage, "/World/left", quads=reversed_quads, st=st, interpolation=UsdGeom.Tokens.vertex, left=True)
    add_cube(stage, "/World/wrong", quads=reversed_quads, st=None)  # clockwise, claimed right-handed
    mirror = UsdGeom.Xform.Define(stage, "/World/mirror")
    mirror.AddScaleOp().Set(Gf.Vec3f(-1.0, 1.0, 1.0))
    add_cube(stage, "/World/mirror/cube", st=st, interpolation=UsdGeom.Tokens.vertex)
    stage.Save()
    left = wm.load_usd(path, "/World/left")
    assert left.volume == pytest.approx(1.0)
    np.testing.assert_allclose(left.metadata["wsim_face_uv"], st[left.faces].astype(np.float32))
    assert wm.load_usd(path, "/World/wrong").volume == pytest.approx(-1.0)  # nothing said: kept as authored
    mirrored = wm.load_usd(path, "/World/mirror/cube")
    assert mirrored.volume == pytest.approx(1.0)
    assert mirrored.vertices[:, 0].max() == pytest.approx(0.0)
    np.testing.assert_allclose(mirrored.metadata["wsim_face_uv"], st[mirrored.faces].astype(np.float32))


@pytest.mark.parametrize("case", ["vertex_uv_name", "indexed_face_varying_st0", "uniform", "constant"])
def test_uv_interpolations(tmp_path: Path, case: str) -> None:
    path = tmp_path / f"{case}.usda"
    stage = new_stage(path)
    if case == "vertex_uv_name":
        st = CUBE_POINTS[:, :2] * 0.5
        add_cube(stage, "/World/c", st=st, interpolation=UsdGeom.Tokens.vertex, name="uv")
    elif case == "indexed_face_varying_st0":
        st = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32)  # every quad mapped to [0, 1]^2
        add_cube(stage, "/World/c", st=st, name="st0", indices=[0, 1, 2, 3] * 6)
    elif case == "uniform":
        st = np.array([[k, -k] for k in range(6)], dtype=np.float32)
        add_cube(stage, "/World/c", st=st, interpolation=UsdGeom.Tokens.uniform)
    else:
        st = np.array([[0.3, 0.7]], dtype=np.float32)
        add_cube(stage, "/World/c", st=st, interpolation=UsdGeom.Tokens.constant)
    stage.Save()
    m = wm.load_usd(path)
    uv = m.metadata["wsim_face_uv"]
    assert uv.shape == (12, 3, 2) and uv.dtype == np.float32
    if case == "vertex_uv_name":
        want = st[m.faces]
    elif case == "indexed_face_varying_st0":
        want = expected_fan_uv(np.tile(st, (6, 1)))
    elif case == "uniform":
        want = np.repeat(np.repeat(st, 2, axis=0)[:, None, :], 3, axis=1)
    else:
        want = np.broadcast_to(st[0], (12, 3, 2))
    np.testing.assert_allclose(uv, want)


def test_no_primvar_no_uvs_and_points_at_a_time(tmp_path: Path) -> None:
    path = tmp_path / "anim.usda"
    stage = new_stage(path)
    mesh = add_cube(stage, "/World/c", st=None)
    pts = mesh.GetPointsAttr()
    pts.Set(Vt.Vec3fArray.FromNumpy(CUBE_POINTS.astype(np.float32)), Usd.TimeCode(5))
    pts.Set(Vt.Vec3fArray.FromNumpy((CUBE_POINTS + 1).astype(np.float32)), Usd.TimeCode(6))
    stage.Save()
    first = wm.load_usd(path)  # no time range authored: the first sample
    assert "wsim_face_uv" not in first.metadata and wm.face_uvs(first) is None
    np.testing.assert_allclose(first.vertices, CUBE_POINTS)
    np.testing.assert_allclose(wm.load_usd(path, time=6).vertices, CUBE_POINTS + 1)


def test_several_meshes_need_a_prim_and_the_error_lists_them(tmp_path: Path) -> None:
    path = tmp_path / "two.usda"
    stage = new_stage(path)
    add_cube(stage, "/World/bunny")
    add_cube(stage, "/World/props/table", points=CUBE_POINTS * 2)
    stage.Save()
    with pytest.raises(InvalidMesh) as info:
        wm.load_usd(path)
    msg = str(info.value)
    assert "\n" not in msg and "two.usda" in msg and "/World/bunny" in msg and "/World/props/table" in msg
    bunny = wm.load_usd(path, "/World/bunny")
    table = wm.load_usd(path, "/World/props/table")
    assert table.volume == pytest.approx(8.0) and bunny.volume == pytest.approx(1.0)
    assert wm.display_name(bunny, "x") == "bunny" and wm.display_name(table, "x") == "table"
    # the file.usd:/prim form through wsim.mesh.load
    via_load = wm.load(f"{path}:/World/props/table")
    np.testing.assert_array_equal(via_load.vertices, table.vertices)
    np.testing.assert_array_equal(via_load.faces, table.faces)
    assert wm.display_name(via_load, "x") == "table"
    with pytest.raises(InvalidMesh, match="/World/bunny"):
        wm.load(path)  # a bare USD file goes to load_usd too
    fitted = wm.load_fitted(f"{path}:/World/bunny", 0.5)  # how a scene's --mesh is read
    assert max(fitted.extents) == pytest.approx(0.5)


def test_load_dispatches_a_single_mesh_usd_file(cube_file: Path) -> None:
    m = wm.load(cube_file)
    assert m.faces.shape == (12, 3) and "wsim_face_uv" in m.metadata
    assert wm.display_name(m, "x") == "cube"


def test_split_prim_path() -> None:
    assert split_prim_path("set.usd:/World/table") == ("set.usd", "/World/table")
    assert split_prim_path("C:/models/set.usdc:/World/a") == ("C:/models/set.usdc", "/World/a")
    assert split_prim_path("C:/models/set.usd") == ("C:/models/set.usd", None)  # a drive letter
    assert split_prim_path("C:\\models\\set.usda") == ("C:\\models\\set.usda", None)
    assert split_prim_path("model.obj") == ("model.obj", None)
    assert split_prim_path(Path("set.usd")) == (Path("set.usd"), None)


def test_clear_errors(tmp_path: Path, cube_file: Path) -> None:
    def error(*args, **kw) -> str:
        with pytest.raises(InvalidMesh) as info:
            wm.load_usd(*args, **kw)
        msg = str(info.value)
        assert "\n" not in msg, msg
        return msg

    msg = error(tmp_path / "missing.usda")
    assert "missing.usda" in msg and "not found" in msg
    bad = tmp_path / "bad.usda"
    bad.write_text("#usda 1.0\nthis is not usd (((\n")
    msg = error(bad)
    assert "bad.usda" in msg and "cannot read" in msg
    msg = error(cube_file, "/World/nothing")
    assert "/World/nothing" in msg and "/World/cube" in msg  # the available meshes are named
    msg = error(cube_file, "/World")
    assert "/World" in msg and "Xform" in msg and "not a Mesh" in msg
    empty = tmp_path / "empty.usda"
    new_stage(empty).Save()
    assert "no mesh prims" in error(empty)
    holes = tmp_path / "holes.usda"
    stage = new_stage(holes)
    add_cube(stage, "/World/c").CreateHoleIndicesAttr(Vt.IntArray([2]))
    stage.Save()
    msg = error(holes)
    assert "holeIndices" in msg and "/World/c" in msg
    with pytest.raises(InvalidMesh, match="missing.usd"):
        wm.load(f"{tmp_path / 'missing.usd'}:/World/a")


def test_a_pbd_body_from_usd_runs_a_frame(tmp_path: Path) -> None:
    path = tmp_path / "ball.usda"
    stage = new_stage(path, up="Z", mpu=0.01)
    ico = trimesh.creation.icosphere(subdivisions=2, radius=20.0)  # 20 cm
    mesh = UsdGeom.Mesh.Define(stage, "/World/ball")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(ico.vertices, dtype=np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(ico.faces)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(np.asarray(ico.faces).ravel().tolist()))
    stage.Save()
    m = wm.load_usd(path, "/World/ball")
    assert np.linalg.norm(m.vertices, axis=1).max() == pytest.approx(0.2, rel=1e-5) and m.volume > 0
    world = wsim.World(fps=30, device="cpu")
    body = world.add(wsim.PbdBody(m, name=wm.display_name(m, "body"), position=(0, 1, 0)))
    world.step()
    p = body.points()
    assert np.isfinite(p).all() and p[:, 1].mean() < 1.0  # fell under gravity


def test_a_mesh_collider_from_a_usd_prim(tmp_path: Path) -> None:
    path = tmp_path / "set.usda"
    stage = new_stage(path)
    add_cube(stage, "/World/ball_stand", points=CUBE_POINTS * 0.1)
    add_cube(stage, "/World/table", points=(CUBE_POINTS - (0.5, 1.0, 0.5)) * (2.0, 0.5, 2.0))  # top at y = 0
    stage.Save()
    table = wm.load_usd(path, "/World/table")
    collider = wsim.MeshCollider(table, name=wm.display_name(table, "table"), friction=0.4)
    assert collider.name == "table" and collider.closed
    world = wsim.World(fps=30, device="cpu")
    world.add_collider(collider)
    body = world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1, radius=0.1), name="ball",
                                  position=(0, 0.12, 0)))
    for _ in range(5):
        world.step()
    assert body.points()[:, 1].min() > -0.05  # held up by the table


def test_round_trip_of_the_default_scene(tmp_path: Path) -> None:
    sys.path.insert(0, str(ROOT / "scenes"))
    try:
        import soft_drop
    finally:
        sys.path.remove(str(ROOT / "scenes"))
    out = tmp_path / "a.usdc"
    soft_drop.build(device="cpu").run(2, out=out, progress=False)
    with pytest.raises(InvalidMesh, match="/World/fish"):  # the fish and the colliders
        wm.load_usd(out)
    fish = wm.load_usd(out, "/World/fish")
    stage = Usd.Stage.Open(str(out))
    usd_fish = UsdGeom.Mesh(stage.GetPrimAtPath("/World/fish"))
    start = Usd.TimeCode(stage.GetStartTimeCode())
    np.testing.assert_allclose(fish.vertices, np.asarray(usd_fish.GetPointsAttr().Get(start)), atol=1e-7)
    faces = np.asarray(usd_fish.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    np.testing.assert_array_equal(fish.faces, faces)
    assert fish.volume > 0 and wm.display_name(fish, "x") == "fish"
    later = wm.load_usd(out, "/World/fish", time=2)
    np.testing.assert_allclose(later.vertices, np.asarray(usd_fish.GetPointsAttr().Get(2)), atol=1e-7)
    assert not np.allclose(later.vertices, fish.vertices)


def test_uvs_survive_a_run(tmp_path: Path, cube_file: Path) -> None:
    m = wm.load_usd(cube_file, "/World/cube")
    world = wsim.World(fps=30, device="cpu")
    world.add(wsim.PbdBody(m, name=wm.display_name(m, "body"), position=(0, 1, 0)))
    out = tmp_path / "cube_run.usda"
    world.run(1, out, progress=False)
    back = wm.load_usd(out, "/World/cube")  # the body's prim, named after the source prim
    np.testing.assert_array_equal(back.faces, m.faces)
    np.testing.assert_allclose(back.metadata["wsim_face_uv"], expected_fan_uv(CUBE_ST))
