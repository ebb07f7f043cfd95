"""Bad input to bodies and colliders gets a clear error naming the object and the quantity."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import wsim


def ico():
    m = trimesh.creation.icosphere(subdivisions=1)
    return np.array(m.vertices), np.array(m.faces)


def test_open_mesh_is_rejected():
    v, f = ico()
    with pytest.raises(wsim.InvalidMesh, match=r"body 'holey'.*watertight"):
        wsim.PbdBody((v, f[:-1]), name="holey")


def test_inconsistently_oriented_mesh_is_rejected():
    v, f = ico()
    f = f.copy()
    f[7] = f[7, ::-1]
    with pytest.raises(wsim.InvalidMesh, match=r"body 'flip'.*orient"):
        wsim.PbdBody((v, f), name="flip")


def test_degenerate_face_is_rejected():
    v, f = ico()
    f = f.copy()
    f[3, 1] = f[3, 0]
    with pytest.raises(wsim.InvalidMesh, match=r"body 'degen'.*degenerate"):
        wsim.PbdBody((v, f), name="degen")


@pytest.mark.parametrize(
    "kwargs, words",
    [
        (dict(dt=0.0), "dt = 0.0 s must be > 0"),
        (dict(dt=-1e-3), "dt"),
        (dict(substeps=0), "substeps"),
        (dict(iterations=0), "iterations"),
        (dict(dt=1e-3, substeps=4), "not both"),
        (dict(damping=-1.0), "damping"),
        (dict(pinned=[10_000]), "pinned"),
        (dict(stretch_compliance=-1.0), "stretch_compliance"),
        (dict(thickness=0.0), "thickness"),
        (dict(velocity=(0, np.inf, 0)), "velocity"),
        (dict(tets="delaunay"), "tets"),
    ],
)
def test_invalid_body_parameters(kwargs, words):
    with pytest.raises(wsim.InvalidParameter, match=words):
        wsim.PbdBody(ico(), name="p", **kwargs)


def test_handle_and_collider_validation():
    v, f = ico()
    with pytest.raises(wsim.InvalidParameter, match="handle 'h'"):
        wsim.PbdBody((v, f), handles=[wsim.Handle([0, 999], lambda t: np.eye(4), name="h")])
    with pytest.raises(wsim.InvalidParameter, match="repeated"):
        wsim.Handle([1, 1], lambda t: np.eye(4))
    with pytest.raises(wsim.InvalidParameter, match="friction"):
        wsim.GroundPlane(friction=-0.1)
    with pytest.raises(wsim.InvalidParameter, match="collider 'ground': friction = nan is not finite"):
        wsim.GroundPlane(friction=float("nan"))
    with pytest.raises(wsim.InvalidParameter, match="friction must be a number, got 'rough'"):
        wsim.MeshCollider((v, f), friction="rough")
    scaled = np.diag([2.0, 1.0, 1.0, 1.0])
    with pytest.raises(wsim.InvalidParameter, match="rigid"):
        wsim.MeshCollider((v, f), transform=scaled, name="squash")


def test_dt_gives_whole_substeps_per_frame():
    body = wsim.PbdBody(ico(), dt=0.004)
    assert body.substeps_for(1 / 30) == 9  # ceil(8.33): h = 3.7 ms <= dt


def test_closed_but_broken_mesh_is_rejected_even_with_mass():
    """mass= allows an open surface, not a closed one with flipped faces."""
    v, f = ico()
    f = f.copy()
    f[7] = f[7, ::-1]
    with pytest.raises(wsim.InvalidMesh, match="orient"):
        wsim.PbdBody((v, f), name="flip", mass=1.0, volume=False)
    open_body = wsim.PbdBody((v, f[:-1]), name="cup", mass=1.0, volume=False)  # really open: allowed
    assert open_body.model.volume is None


def test_index_inputs_are_checked():
    v, f = ico()
    mask = np.zeros(len(v), dtype=bool)
    mask[[3, 5, 9]] = True
    body = wsim.PbdBody((v, f), pinned=mask)  # a boolean mask pins its True entries
    assert body.pinned.tolist() == [3, 5, 9]
    with pytest.raises(wsim.InvalidParameter, match="integer indices"):
        wsim.PbdBody((v, f), pinned=[1.7])
    with pytest.raises(wsim.InvalidParameter, match=r"\(S, 2\)"):
        wsim.PbdBody((v, f), springs=np.zeros((2, 3), dtype=int))
    assert wsim.Handle(mask, lambda t: np.eye(4)).vertices.tolist() == [3, 5, 9]


@pytest.mark.parametrize("kwargs, words", [
    (dict(thickness="a"), "thickness"), (dict(damping=None), "damping"), (dict(mass="a"), "mass"),
    (dict(contact_margin=float("nan")), "contact_margin"), (dict(inflation=0.0), "inflation"),
])
def test_numbers_are_checked(kwargs, words):
    with pytest.raises(wsim.InvalidParameter, match=words):
        wsim.PbdBody(ico(), name="n", **kwargs)


def test_bad_handle_motion_and_collider_pose_are_named():
    v, f = ico()
    world = wsim.World(device="cpu")
    world.add(wsim.PbdBody((v, f), name="b", handles=[wsim.Handle([0], lambda t: np.full((1, 3), np.nan), name="h")]))
    with pytest.raises(wsim.InvalidParameter, match="handle 'h'.*non-finite"):
        world.step()
    world = wsim.World(device="cpu")
    world.add_collider(wsim.MeshCollider(trimesh.creation.box(), transform=lambda t: "up", name="lift"))
    world.add(wsim.PbdBody((v, f), name="b"))
    with pytest.raises(wsim.InvalidParameter, match="collider 'lift'.*in frame 1.*4x4"):
        world.step()
    # a transform that raises: named like a handle's motion (collider, t, frame), the cause chained

    def lift(t: float) -> np.ndarray:
        if t > 0.05:
            raise RuntimeError("rig lost")
        return np.eye(4)

    world = wsim.World(device="cpu")
    world.add_collider(wsim.MeshCollider(trimesh.creation.box(), transform=lift, name="lift"))
    world.add(wsim.PbdBody((v, f), name="b"))
    world.step()
    with pytest.raises(wsim.InvalidParameter, match=r"collider 'lift': transform at t = 0.0\d* s raised RuntimeError: "
                       r"rig lost; in frame 2") as info:
        world.step()
    assert isinstance(info.value.__cause__, RuntimeError)


def test_inward_collider_and_unused_tet_particles_are_rejected():
    box = trimesh.creation.box()
    with pytest.raises(wsim.InvalidMesh, match="collider 'inside-out'.*inwards"):
        wsim.MeshCollider((box.vertices, box.faces[:, ::-1]), name="inside-out")
    sheet = wsim.MeshCollider((box.vertices, box.faces[:10]), name="sheet")  # open: one-sided, allowed
    assert not sheet.kinematic
    v, f = ico()
    interior = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    tets = np.array([[len(v), f[0, 0], f[0, 1], f[0, 2]]])  # uses interior point 0, not point 1
    with pytest.raises(wsim.InvalidMesh, match="belong to no tet"):
        wsim.PbdBody((v, f), tets=tets, interior_points=interior)


def test_missing_mesh_file_is_named(tmp_path):
    from wsim import mesh as wmesh

    with pytest.raises(wsim.InvalidMesh, match="not found"):
        wmesh.load(tmp_path / "nope.obj")
