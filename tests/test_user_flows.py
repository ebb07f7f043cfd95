"""What an independent review of issue 19 found a new user would hit, each fixed and kept fixed:
a textured model (UV seams) through ``--mesh``, ``wsim.mesh`` right after ``import wsim``, a run
longer than a reconstruction stopping before the first frame, outputs under a file, and user
callbacks that raise."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from pxr import Usd, UsdGeom

import wsim

ROOT = Path(__file__).resolve().parents[1]


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "wsim", *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


def _seamed_obj(path: Path) -> np.ndarray:
    """A UV-mapped sphere written as OBJ the way exporters do: a vertex per (position, UV) pair, so
    its faces do not share vertices across seams. Returns the per-corner UVs, in face order."""
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    sphere.unmerge_vertices()  # every face its own corners
    corner_uv = np.random.default_rng(0).random((len(sphere.vertices), 2))
    trimesh.Trimesh(sphere.vertices, sphere.faces, process=False,
                    visual=trimesh.visual.TextureVisuals(uv=corner_uv)).export(path)
    return corner_uv[sphere.faces]


def test_a_textured_obj_with_uv_seams_runs_from_the_command_line(tmp_path: Path) -> None:
    want = _seamed_obj(tmp_path / "textured.obj")
    loaded = wsim.mesh.load(tmp_path / "textured.obj")
    assert loaded.is_watertight and len(loaded.vertices) == 42  # merged on load
    np.testing.assert_allclose(wsim.mesh.face_uvs(loaded), want, atol=1e-6)
    out = tmp_path / "t.usda"
    res = _cli("run", "scenes/soft_drop.py", "--mesh", str(tmp_path / "textured.obj"), "-o", str(out), "--frames", "1",
               "--device", "cpu", "--no-progress")
    assert res.returncode == 0, res.stderr
    stage = Usd.Stage.Open(str(out))
    st = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/World/textured")).GetPrimvar("st")
    np.testing.assert_allclose(np.asarray(st.Get()).reshape(-1, 3, 2), want, atol=1e-6)


def test_subpackages_resolve_right_after_import_wsim() -> None:
    code = "import wsim; print(wsim.mesh.load_usd.__name__, wsim.bem.build_operators.__name__)"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.split() == ["load_usd", "build_operators"], res.stderr
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        wsim.nothing  # noqa: B018


def test_a_run_longer_than_a_reconstruction_stops_before_the_first_frame(tmp_path: Path) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    sim = wsim.World(device="cpu")
    body = sim.add(wsim.PbdBody(sphere, name="ball", position=(0, 0.5, 0)))
    rec = wsim.record(sim, body, 6)
    world = wsim.World(device="cpu")
    world.add(wsim.PbdReconstruction(rec, stride=2, points_per_curve=4))
    with pytest.raises(wsim.InvalidParameter, match="covers frames 0..6; a run up to frame 9"):
        world.run(9, out=tmp_path / "r.usda", progress=False)
    assert world.frame == 0 and not (tmp_path / "r.usda").exists()
    world.run(6, out=tmp_path / "r.usda", progress=False)  # exactly what it covers
    assert world.frame == 6


def test_outputs_under_a_file_say_so(tmp_path: Path) -> None:
    afile = tmp_path / "afile"
    afile.write_text("x")
    usd = tmp_path / "one.usdc"
    sys.path.insert(0, str(ROOT / "scenes"))
    import soft_drop

    soft_drop.build(device="cpu").run(1, out=usd, progress=False)
    run = ("--device", "cpu", "--frames", "1", "--no-progress")
    for args in (("run", "scenes/soft_drop.py", "-o", str(afile / "o.usdc"), *run),
                 ("run", "scenes/soft_drop.py", "-o", str(tmp_path / "o.usdc"), "--checkpoint", str(afile / "c.h5"),
                  "--checkpoint-every", "1", *run),
                 ("preview", str(usd), "-o", str(afile / "p.png"))):
        res = _cli(*args)
        assert res.returncode != 0
        assert f"'{afile}' is a file, not a folder" in res.stderr, res.stderr


def test_a_callback_that_raises_is_reported_with_body_and_frame() -> None:
    def motion(t: float) -> np.ndarray:
        if t > 0.05:
            raise ValueError("boom")
        return np.eye(4)

    world = wsim.World(fps=30, device="cpu")
    world.add(wsim.PbdBody(trimesh.creation.icosphere(subdivisions=1), name="neck", handles=[wsim.Handle([0, 1], motion)]))
    with pytest.raises(wsim.InvalidParameter, match=r"body 'neck': .*motion at t = 0.05\d* s raised ValueError: boom; in frame 2") as exc:
        world.run(5, progress=False)
    assert isinstance(exc.value.__cause__, ValueError)


def test_sigterm_exits_143_and_keeps_the_frames(tmp_path: Path) -> None:
    out = tmp_path / "term.usdc"
    proc = subprocess.Popen([sys.executable, "-m", "wsim", "run", "scenes/soft_drop.py", "-o", str(out), "--frames", "2000",
                             "--device", "cpu", "--no-progress"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    journal = out.with_name(out.name + ".journal")
    import time

    deadline = time.time() + 300
    while time.time() < deadline and (not journal.exists() or journal.stat().st_size < 200_000):
        time.sleep(0.2)
    proc.terminate()
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 143, err
    assert "interrupted" in err and out.exists() and not journal.exists()
    stage = Usd.Stage.Open(str(out))
    assert len(UsdGeom.Mesh(stage.GetPrimAtPath("/World/fish")).GetPointsAttr().GetTimeSamples()) > 2
    assert os.path.getsize(out) > 0
