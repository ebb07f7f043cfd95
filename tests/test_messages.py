"""Error messages name the body, the frame and the quantity (issue 19, point 5).

Bad materials, bad handle motions and loads, meshes of several pieces and meshes whose vertices are
split at the same position: each raises the project's error class with a message that says which
body, which quantity, when (the World frame where there is one) and how to fix it. CPU only, small
procedural meshes.
"""

from __future__ import annotations

import re
import time

import numpy as np
import pytest
import trimesh

import wsim
from wsim import mesh as wm

BEM_DT = 1.0e-3


def ico() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=1, radius=0.1)


def two_spheres() -> trimesh.Trimesh:
    """Two disjoint closed spheres in one mesh."""
    return trimesh.util.concatenate([ico(), ico().apply_translation([0.5, 0.0, 0.0])])


def split_box() -> trimesh.Trimesh:
    """A closed box whose faces each have their own three corners (36 vertices at 8 positions)."""
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    box.unmerge_vertices()
    assert len(box.vertices) == 36 and not box.is_watertight
    return box


# -- 1. materials ---------------------------------------------------------------------------------
BAD_MATERIALS = [
    (dict(E=-1.0e5, nu=0.3, rho=1000.0), "Young's modulus E = -100000.0 Pa must be > 0"),
    (dict(E=1.0e5, nu=0.3, rho=0.0), "density rho = 0.0"),
    (dict(E=1.0e5, nu=0.7, rho=1000.0, name="rubber"), "material 'rubber': Poisson's ratio nu = 0.7"),
    (dict(young=1.0e5), "unexpected keyword argument 'young'"),
]


@pytest.mark.parametrize("kind", ["bem", "eol", "pbd"])
@pytest.mark.parametrize("material, words", BAD_MATERIALS)
def test_bad_material_names_the_body(kind, material, words):
    make = {
        "bem": lambda: wsim.BemBody(ico(), material, BEM_DT, name="jelly"),
        "eol": lambda: wsim.EolBody(ico(), material, resolution=6, name="jelly"),
        "pbd": lambda: wsim.PbdBody(ico(), material, name="jelly"),
    }[kind]
    with pytest.raises(wsim.InvalidMaterial) as info:
        make()
    msg = str(info.value)
    assert msg.startswith("body 'jelly': material"), msg
    assert words in msg, msg


def test_material_that_is_not_one_names_the_body():
    with pytest.raises(wsim.InvalidParameter, match=r"body 'jelly': material must be a wsim.ElasticMaterial or a dict"):
        wsim.PbdBody(ico(), 1.0e5, name="jelly")


def test_material_dict_is_the_same_material():
    body = wsim.PbdBody(ico(), dict(E=2.0e5, nu=0.25, rho=800.0), name="jelly", cache=False)
    assert body.material == wsim.ElasticMaterial(E=2.0e5, nu=0.25, rho=800.0)


def test_incompressible_material_refused_by_eol_names_body_and_material():
    soft = wsim.ElasticMaterial(E=1.0e5, nu=0.5, rho=1000.0, incompressible=True, name="gel")
    with pytest.raises(wsim.InvalidParameter, match=r"body 'jelly': material 'gel' is incompressible"):
        wsim.EolBody(ico(), soft, resolution=6, name="jelly")


# -- 2. handle motions and loads: body, frame and quantity ---------------------------------------
def test_nan_handle_motion_names_body_handle_time_and_frame():
    def motion(t):  # fine for two frames, NaN from the middle of frame 3 on
        return np.eye(4) if t < 2.25 / 30.0 else np.full((4, 4), np.nan)

    world = wsim.World(device="cpu", fps=30)
    world.add(wsim.PbdBody(ico(), name="neck", substeps=2, cache=False,
                           handles=[wsim.Handle([0, 1], motion, name="tip")]))
    with pytest.raises(wsim.InvalidParameter) as info:
        world.run(5, progress=False)
    msg = str(info.value)
    assert msg.startswith("body 'neck': handle 'tip' (handles[0]) motion at t = 0.0833333 s is not finite"), msg
    assert msg.endswith("in frame 3"), msg
    assert world.frame == 2  # frames 1 and 2 were computed


def test_wrong_shape_handle_motion_names_body_handle_and_frame():
    world = wsim.World(device="cpu", fps=30)
    world.add(wsim.PbdBody(ico(), name="neck", substeps=2, cache=False,
                           handles=[wsim.Handle([0, 1], lambda t: np.zeros(3))]))
    with pytest.raises(wsim.InvalidParameter,
                       match=r"body 'neck': handles\[0\] motion at t = 0.0166667 s has shape \(3,\); "
                             r"expected \(4, 4\) or \(2, 3\); in frame 1"):
        world.step()


def test_handle_targets_outside_a_body_name_the_handle():
    handle = wsim.Handle([0], lambda t: "up", name="h")
    with pytest.raises(wsim.InvalidParameter, match=r"handle 'h' motion at t = 0.5 s is not numeric"):
        handle.targets(0.5, np.zeros((1, 3)))


def test_nan_traction_names_body_time_and_frame():
    world = wsim.World(device="cpu", fps=30)
    body = world.add(wsim.EolBody(ico(), dict(E=5.0e4, nu=0.3, rho=500.0), resolution=6, name="ball"))
    world.step()
    body.add_traction(lambda t: np.full((len(ico().vertices), 3), np.nan))
    with pytest.raises(wsim.InvalidParameter) as info:
        world.step()
    msg = str(info.value)
    assert re.match(r"body 'ball': a traction \[Pa\] at t = 0.0333333 s is not finite: \d+ non-finite values", msg), msg
    assert msg.endswith("in frame 2"), msg


def test_bem_traction_and_driven_target_name_body_load_and_frame():
    """A 12-vertex BEM body (operators in a fraction of a second): two steps per frame."""
    world = wsim.World(device="cpu", fps=30, gravity=(0.0, 0.0, 0.0))
    body = world.add(wsim.BemBody(trimesh.creation.icosphere(subdivisions=0, radius=0.1),
                                  dict(E=1.0e5, nu=0.3, rho=1000.0), 1.0 / 60.0, name="drum", cache=False))
    world.step()
    body.add_traction(lambda t: np.full((12, 3), np.nan) if t > 0.06 else np.zeros((12, 3)))
    with pytest.raises(wsim.InvalidParameter, match=r"^body 'drum': traction load 0 .* at t = 0.0666667 s is not "
                                                    r"finite: 36 non-finite values.*; in frame 2$"):
        world.step()
    body._loads.clear()
    body.fix([0, 1], lambda t: np.zeros((3, 3)))
    with pytest.raises(wsim.InvalidParameter, match=r"^body 'drum': fix\(\) handle 0 target .* at t = 0.0666667 s "
                                                    r"has shape \(3, 3\); expected \(2, 3\); in frame 2$"):
        world.step()


def test_callback_check_reads_the_value_it_is_given():
    from wsim.validate import callback_array

    good = callback_array([[1.0, 2.0, 3.0]], ((1, 3),), "body 'b': thing", 0.1, 4)
    assert good.dtype == np.float64 and good.shape == (1, 3)
    with pytest.raises(wsim.InvalidParameter, match=r"body 'b': thing at t = 0.1 s is not finite: 1 non-finite "
                                                     r"values, e.g. row 1 = \[0.0, inf, 0.0\]; in frame 4"):
        callback_array([[0.0, 0.0, 0.0], [0.0, np.inf, 0.0]], ((2, 3),), "body 'b': thing", 0.1, 4)


# -- 3. meshes of several pieces -------------------------------------------------------------------
def test_pieces_are_counted_on_faces():
    count, label = wm.pieces(two_spheres().faces)
    assert count == 2
    n = len(ico().faces)
    assert (label[:n] == 0).all() and (label[n:] == 1).all()
    assert wm.pieces(ico().faces)[0] == 1
    assert wm.pieces(np.zeros((0, 3), dtype=int))[0] == 0


def test_bem_refuses_pieces_before_any_precompute():
    t = time.perf_counter()
    with pytest.raises(wsim.InvalidMesh) as info:
        wsim.BemBody(two_spheres(), dict(E=1.0e5, nu=0.3, rho=1000.0), BEM_DT, name="pair")
    assert time.perf_counter() - t < 2.0
    msg = str(info.value)
    assert msg == ("body 'pair': the mesh has 2 separate pieces; make one body per piece (trimesh: mesh.split())"), msg


def test_eol_refuses_pieces():
    with pytest.raises(wsim.InvalidMesh, match=r"body 'pair': the mesh has 2 separate pieces; make one body per "
                                               r"piece \(trimesh: mesh.split\(\)\)$"):
        wsim.EolBody(two_spheres(), dict(E=5.0e4, nu=0.3, rho=500.0), resolution=6, name="pair")


def test_pbd_takes_pieces_only_when_asked():
    with pytest.raises(wsim.InvalidMesh, match=r"body 'pair': the mesh has 2 separate pieces; .*mesh.split\(\).* "
                                               r"allow_pieces=True"):
        wsim.PbdBody(two_spheres(), name="pair", cache=False)
    world = wsim.World(device="cpu", fps=30)
    body = world.add(wsim.PbdBody(two_spheres(), name="pair", allow_pieces=True, cache=False))
    world.step()
    assert world.frame == 1
    p = body.points()
    assert p.shape == (2 * len(ico().vertices), 3) and np.all(np.isfinite(p))


# -- 4. vertices split at the same position ---------------------------------------------------------
MERGE_HINT = ("28 of its 36 vertices are duplicates at the same position (merged, it is watertight): "
              "pass merge_vertices=True or merge them (trimesh: mesh.merge_vertices())")


@pytest.mark.parametrize("kind", ["bem", "eol", "pbd"])
def test_split_vertices_give_the_merge_hint(kind):
    make = {
        "bem": lambda: wsim.BemBody(split_box(), dict(E=1.0e5), BEM_DT, name="crate"),
        "eol": lambda: wsim.EolBody(split_box(), dict(E=5.0e4), resolution=6, name="crate"),
        "pbd": lambda: wsim.PbdBody(split_box(), name="crate"),
    }[kind]
    t = time.perf_counter()
    with pytest.raises(wsim.InvalidMesh) as info:
        make()
    assert time.perf_counter() - t < 2.0
    msg = str(info.value)
    assert msg.startswith("body 'crate': not watertight"), msg
    assert msg.endswith(MERGE_HINT), msg


def test_split_open_surface_is_not_called_many_pieces():
    """An open PBD surface (mass given) of split vertices: the hint is to merge, not to split."""
    with pytest.raises(wsim.InvalidMesh) as info:
        wsim.PbdBody(split_box(), name="crate", mass=1.0, volume=False)
    msg = str(info.value)
    assert "12 separate pieces" in msg and "merged, it is one piece" in msg and "merge_vertices=True" in msg, msg
    assert "mesh.split()" not in msg


def test_glued_closed_pieces_are_not_told_to_merge():
    """Two closed boxes touching face to face (coincident vertices): merging would not make one
    closed surface, so the message says to make one body per piece."""
    a = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    b = a.copy().apply_translation([0.2, 0.0, 0.0])
    with pytest.raises(wsim.InvalidMesh, match=r"2 separate pieces; make one body per piece"):
        wsim.EolBody(trimesh.util.concatenate([a, b]), dict(E=5.0e4), resolution=6, name="glued")


def test_merge_coincident_vertices_matches_trimesh():
    box = split_box()
    v, f, n = wm.merge_coincident_vertices(box.vertices, box.faces)
    assert n == 28 and v.shape == (8, 3) and f.dtype == np.int32
    ref = trimesh.Trimesh(v, f, process=False)
    assert ref.is_watertight and ref.volume == pytest.approx(0.008)
    wm.check_surface(v, f, "crate", one_piece=True)
    v2, f2 = wm.surface_arrays(box, "crate", merge_vertices=True)
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_array_equal(f2, f)


@pytest.mark.parametrize("kind", ["bem", "eol", "pbd"])
def test_merge_vertices_gives_the_merged_body(kind):
    make = {
        "bem": lambda: wsim.BemBody(split_box(), dict(E=1.0e5), BEM_DT, name="crate", merge_vertices=True),
        "eol": lambda: wsim.EolBody(split_box(), dict(E=5.0e4), resolution=6, name="crate", merge_vertices=True),
        "pbd": lambda: wsim.PbdBody(split_box(), name="crate", merge_vertices=True, cache=False),
    }[kind]
    body = make()  # BEM: no operators are built until the body joins a World
    assert body.faces.shape == (12, 3) and body.faces.max() == 7


@pytest.mark.parametrize("kind", ["eol", "pbd"])
def test_merged_body_runs_and_writes_the_merged_topology(kind, tmp_path):
    from pxr import Usd, UsdGeom

    world = wsim.World(device="cpu", fps=30)
    if kind == "eol":
        body = world.add(wsim.EolBody(split_box(), dict(E=5.0e4, nu=0.3, rho=500.0), resolution=6, name="crate",
                                      merge_vertices=True))
    else:
        body = world.add(wsim.PbdBody(split_box(), name="crate", merge_vertices=True, cache=False))
    out = tmp_path / "crate.usda"
    world.run(1, out, progress=False)
    assert np.all(np.isfinite(body.points())) and body.points().shape == (8, 3)
    stage = Usd.Stage.Open(str(out))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/crate"))
    assert len(mesh.GetPointsAttr().Get(1)) == 8
    assert list(mesh.GetFaceVertexIndicesAttr().Get()) == body.faces.reshape(-1).tolist()
