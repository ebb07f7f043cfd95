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
    scaled = np.diag([2.0, 1.0, 1.0, 1.0])
    with pytest.raises(wsim.InvalidParameter, match="rigid"):
        wsim.MeshCollider((v, f), transform=scaled, name="squash")


def test_dt_gives_whole_substeps_per_frame():
    body = wsim.PbdBody(ico(), dt=0.004)
    assert body.substeps_for(1 / 30) == 9  # ceil(8.33): h = 3.7 ms <= dt
