"""What a DCC tool reads from wsim's USD besides points (issue 19, point 2): vertex normals, a
display colour per body, and a start-frame offset of the time codes (kept by ``wsim recover``)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh
from pxr import Usd, UsdGeom

import wsim
from wsim import usd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scenes"))
import soft_drop  # noqa: E402


def _two_balls() -> wsim.World:
    world = wsim.World(fps=30, device="cpu")
    world.add_collider(wsim.GroundPlane(0.0))
    for k in range(2):
        world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=2, radius=0.1), name=f"ball{k}",
                               position=(0.3 * k, 0.3, 0.0)))
    return world


def test_normals_are_outward_unit_vertex_normals(tmp_path: Path) -> None:
    out = tmp_path / "n.usdc"
    _two_balls().run(3, out=out, progress=False)
    stage = Usd.Stage.Open(str(out))  # held: prims expire with their stage
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ball0"))
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex
    for code in (0.0, 3.0):
        p = np.asarray(mesh.GetPointsAttr().Get(code), dtype=np.float64)
        n = np.asarray(mesh.GetNormalsAttr().Get(code), dtype=np.float64)
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
        radial = p - p.mean(axis=0)
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        assert (n * radial).sum(axis=1).min() > 0.95  # a sphere's normals are radial and outward


def test_each_body_has_its_own_display_color(tmp_path: Path) -> None:
    world = _two_balls()
    out = tmp_path / "c.usda"
    world.run(1, out=out, progress=False)
    stage = Usd.Stage.Open(str(out))
    colors = [tuple(UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/ball{k}")).GetDisplayColorAttr().Get()[0]) for k in range(2)]
    assert colors[0] != colors[1]
    world = _two_balls()
    world.bodies[1].display_color = (0.1, 0.2, 0.9)
    out = tmp_path / "chosen.usda"  # another file: USD keeps the first one's layer open in this process
    world.run(1, out=out, progress=False)
    stage = Usd.Stage.Open(str(out))
    got = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ball1")).GetDisplayColorAttr().Get()[0]
    np.testing.assert_allclose(tuple(got), (0.1, 0.2, 0.9), atol=1e-6)


def test_start_frame_offsets_every_time_code_and_survives_recovery(tmp_path: Path) -> None:
    out = tmp_path / "film.usdc"
    soft_drop.build(device="cpu").run(4, out=out, progress=False, start_frame=1001)
    stage = Usd.Stage.Open(str(out))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1001.0, 1005.0)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/fish"))
    assert mesh.GetPointsAttr().GetTimeSamples() == [1001.0 + k for k in range(5)]
    paddle = UsdGeom.Xformable(stage.GetPrimAtPath("/World/colliders/paddle")).GetOrderedXformOps()[0]
    assert paddle.GetAttr().GetTimeSamples()[0] == 1001.0

    killed = tmp_path / "killed.usdc"
    writer = usd.UsdWriter(killed, fps=30, start_frame=1001)
    world = soft_drop.build(device="cpu")
    world._bind()
    writer.begin(world.bodies, world.surfaces)
    for k in range(3):
        writer.write_frame(k, k / 30)
    writer._journal._fh.close()  # killed before close
    usd.recover(killed)
    st = Usd.Stage.Open(str(killed))
    assert UsdGeom.Mesh(st.GetPrimAtPath("/World/fish")).GetPointsAttr().GetTimeSamples() == [1001.0, 1002.0, 1003.0]
    assert (st.GetStartTimeCode(), st.GetEndTimeCode()) == (1001.0, 1003.0)


def _with_uv(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, np.ndarray]:
    """The mesh with per-vertex texture coordinates from its rest positions; (mesh, uv per corner)."""
    v = np.asarray(mesh.vertices)
    uv = (v[:, :2] - v[:, :2].min(0)) / np.ptp(v[:, :2], axis=0)
    out = trimesh.Trimesh(v, mesh.faces, process=False, visual=trimesh.visual.TextureVisuals(uv=uv))
    return out, uv[np.asarray(mesh.faces)]


def _written_st(path: Path, prim: str) -> tuple[np.ndarray, str]:
    stage = Usd.Stage.Open(str(path))
    st = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath(prim)).GetPrimvar("st")
    return np.asarray(st.Get()).reshape(-1, 3, 2), st.GetInterpolation()


def test_uvs_of_the_input_mesh_survive_for_every_method(tmp_path: Path) -> None:
    sphere, want = _with_uv(trimesh.creation.icosphere(subdivisions=1, radius=0.1))
    world = wsim.World(fps=30, device="cpu")
    material = wsim.ElasticMaterial(E=1e5, nu=0.3, rho=1000.0)
    world.add(wsim.PbdBody(sphere, material, name="pbd", position=(0, 1, 0)))
    world.add(wsim.EolBody(sphere, material, resolution=6, name="eol", position=(1, 1, 0)))
    world.add(wsim.BemBody(sphere, wsim.ElasticMaterial(mu=1e5, nu=0.45, rho=1000.0), 0.01, name="bem", position=(2, 1, 0)))
    out = tmp_path / "uv.usda"
    world.run(1, out=out, progress=False)
    for name in ("pbd", "eol", "bem"):
        st, interp = _written_st(out, f"/World/{name}")
        assert interp == UsdGeom.Tokens.faceVarying
        np.testing.assert_allclose(st, want, atol=1e-6, err_msg=name)
    # a mesh without UVs gets no st primvar
    plain = tmp_path / "plain.usda"
    _two_balls().run(1, out=plain, progress=False)
    stage = Usd.Stage.Open(str(plain))
    assert not UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/World/ball0")).GetPrimvar("st")


def test_a_uv_seam_survives_merging_its_vertices(tmp_path: Path) -> None:
    """A box whose faces have their own corners (as a UV-mapped OBJ loads): each corner keeps its
    UV after ``merge_vertices=True`` joins the vertices at the seams."""
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    box.unmerge_vertices()
    corner_uv = np.tile(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=np.float32), (len(box.faces), 1))
    corner_uv += np.repeat(np.arange(len(box.faces)), 3)[:, None] * 0.01  # every corner of every face its own UV
    uv = np.empty_like(corner_uv)
    uv[box.faces.ravel()] = corner_uv  # unmerged: each vertex is one corner
    mesh = trimesh.Trimesh(box.vertices, box.faces, process=False, visual=trimesh.visual.TextureVisuals(uv=uv))
    world = wsim.World(fps=30, device="cpu")
    body = world.add(wsim.PbdBody(mesh, name="box", position=(0, 1, 0), merge_vertices=True))
    assert int(body.faces.max()) + 1 == 8  # merged: a closed box
    out = tmp_path / "seam.usda"
    world.run(1, out=out, progress=False)
    st, _ = _written_st(out, "/World/box")
    np.testing.assert_allclose(st.reshape(-1, 2), corner_uv, atol=1e-6)


def test_vertex_colours_of_a_mesh_file_reach_the_usd(tmp_path: Path) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    rgba = (np.random.default_rng(4).random((len(sphere.vertices), 4)) * 255).astype(np.uint8)
    sphere.visual.vertex_colors = rgba
    sphere.export(tmp_path / "painted.ply")
    mesh = wsim.mesh.load(tmp_path / "painted.ply")
    world = wsim.World(fps=30, device="cpu")
    world.add(wsim.PbdBody(mesh, name="painted", position=(0, 1, 0)))
    out = tmp_path / "painted.usda"
    world.run(1, out=out, progress=False)
    stage = Usd.Stage.Open(str(out))
    dc = UsdGeom.Mesh(stage.GetPrimAtPath("/World/painted")).GetDisplayColorPrimvar()
    assert dc.GetInterpolation() == UsdGeom.Tokens.faceVarying
    want = rgba[:, :3][np.asarray(mesh.faces)].reshape(-1, 3) / 255.0
    np.testing.assert_allclose(np.asarray(dc.Get()), want, atol=1e-6)
