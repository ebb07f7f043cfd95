"""Checkpoint and resume (``World.checkpoint`` / ``World.restore`` / ``wsim run --resume``).

The scenes are ``tests/scenes/checkpoint_scene.py`` (one per method, and all methods in one World).
The acceptance test runs the CLI in fresh processes: 20 frames straight, against 10 frames with a
checkpoint and then ``--resume`` for the last 10; the two final checkpoints must hold the same
state bit for bit on the CPU, and the resumed USD must be the first run's file continued.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

import wsim
from wsim import checkpoint

SCENE = Path(__file__).parent / "scenes" / "checkpoint_scene.py"
KINDS = ("pbd", "bem", "eol", "recon", "all")


def _build(kind: str, monkeypatch: pytest.MonkeyPatch, device: str = "cpu") -> wsim.World:
    import runpy

    monkeypatch.setenv("WSIM_TEST_SCENE", kind)
    return runpy.run_path(str(SCENE))["build"](device=device)


def _cli(kind: str, cwd: Path, *args: str) -> str:
    env = {**os.environ, "WSIM_TEST_SCENE": kind}
    proc = subprocess.run([sys.executable, "-m", "wsim", "run", str(SCENE), "--no-progress", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout + proc.stderr


def _saved_states(path: Path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        return {f"{g}/{k}": np.array(f["bodies"][g][k]) for g in f["bodies"] for k in f["bodies"][g]}


@pytest.mark.parametrize("kind", KINDS)
def test_resume_in_a_fresh_process_is_bit_for_bit(kind: str, tmp_path: Path) -> None:
    from pxr import Usd, UsdGeom

    _cli(kind, tmp_path, "--frames", "20", "-o", "straight.usda", "--checkpoint", "straight.h5")
    _cli(kind, tmp_path, "--frames", "10", "-o", "resumed.usda", "--checkpoint-every", "5")
    ckpt = tmp_path / "resumed.ckpt.h5"
    with h5py.File(ckpt, "r") as f:
        assert int(f.attrs["frame"]) == 10
    out = _cli(kind, tmp_path, "--frames", "20", "-o", "resumed.usda", "--resume", str(ckpt))
    assert "appended to" in out
    a, b = _saved_states(tmp_path / "straight.h5"), _saved_states(ckpt)
    assert a.keys() == b.keys() and len(a) > 0
    different = [k for k in a if not np.array_equal(a[k], b[k])]
    assert not different, f"state differs after resume: {different}"
    # one file holds the whole animation, every frame as the straight run wrote it
    s1, s2 = Usd.Stage.Open(str(tmp_path / "straight.usda")), Usd.Stage.Open(str(tmp_path / "resumed.usda"))
    assert (s2.GetStartTimeCode(), s2.GetEndTimeCode()) == (0.0, 20.0)
    for prim in s1.Traverse():
        if prim.IsA(UsdGeom.Mesh) and "colliders" not in str(prim.GetPath()):
            p1, p2 = UsdGeom.Mesh(prim).GetPointsAttr(), UsdGeom.Mesh(s2.GetPrimAtPath(prim.GetPath())).GetPointsAttr()
            assert p2.GetTimeSamples() == p1.GetTimeSamples() == [float(i) for i in range(21)]
            for frame in (3, 10, 11, 20):
                assert np.array_equal(np.asarray(p1.Get(frame)), np.asarray(p2.Get(frame))), (prim.GetPath(), frame)


def test_resume_without_earlier_output_writes_a_new_file(tmp_path: Path) -> None:
    _cli("pbd", tmp_path, "--frames", "4", "-o", "first.usda", "--checkpoint", "c.h5")
    out = _cli("pbd", tmp_path, "--frames", "6", "-o", "second.usda", "--resume", "c.h5")
    assert "new file" in out
    from pxr import Usd

    stage = Usd.Stage.Open(str(tmp_path / "second.usda"))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (4.0, 6.0)


def test_restore_in_process(device: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """20 frames straight against 10 + checkpoint + restore into a new World + 10, all methods in
    one World: bit for bit on the CPU, to round-off on CUDA (atomics change the summation order)."""
    straight = _build("all", monkeypatch, device)
    for _ in range(20):
        straight.step()
    first = _build("all", monkeypatch, device)
    for _ in range(10):
        first.step()
    first.checkpoint(tmp_path / "c.h5")
    second = _build("all", monkeypatch, device)
    assert second.restore(tmp_path / "c.h5") == 10
    for _ in range(10):
        second.step()
    assert second.frame == straight.frame == 20
    for b1, b2 in zip(straight.bodies, second.bodies):
        if device == "cpu":
            assert np.array_equal(b1.points(), b2.points()), b1.name
        else:
            assert np.allclose(b1.points(), b2.points(), rtol=0, atol=1e-5), b1.name


def _stepped(kind: str, monkeypatch: pytest.MonkeyPatch, frames: int) -> wsim.World:
    world = _build(kind, monkeypatch)
    for _ in range(frames):
        world.step()
    return world


def _unchanged(world: wsim.World, before: list[dict[str, np.ndarray]], frame: int) -> bool:
    now = [b.get_state() for b in world.bodies]
    return world.frame == frame and all(
        a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a) for a, b in zip(before, now))


def test_truncated_checkpoint_is_refused_and_changes_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    saved = _stepped("pbd", monkeypatch, 6)
    path = saved.checkpoint(tmp_path / "c.h5")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    world = _stepped("pbd", monkeypatch, 2)
    before = [b.get_state() for b in world.bodies]
    with pytest.raises(wsim.CheckpointError, match="cannot be read"):
        world.restore(path)
    assert _unchanged(world, before, 2)
    with pytest.raises(wsim.CheckpointError, match="does not exist"):
        world.restore(tmp_path / "missing.h5")
    (tmp_path / "junk.h5").write_text("not a checkpoint")
    with pytest.raises(wsim.CheckpointError, match="cannot be read"):
        world.restore(tmp_path / "junk.h5")
    assert _unchanged(world, before, 2)


def test_foreign_checkpoint_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = _stepped("pbd", monkeypatch, 3).checkpoint(tmp_path / "pbd.h5")
    world = _stepped("bem", monkeypatch, 1)
    before = [b.get_state() for b in world.bodies]
    with pytest.raises(wsim.CheckpointError, match="another scene.*bodies: saved \\['pbd'\\]"):
        world.restore(path)
    assert _unchanged(world, before, 1)
    # same body names, another setting: the signature names it
    other = _build("pbd", monkeypatch)
    other.bodies[0].substeps = 5
    with pytest.raises(wsim.CheckpointError, match="body 'pbd' substeps: saved 4, this scene 5"):
        other.restore(path)
    # an EoL body of another material (its signature carries it, as PBD's and BEM's do)
    import dataclasses

    eol_path = _stepped("eol", monkeypatch, 1).checkpoint(tmp_path / "eol.h5")
    softer = _build("eol", monkeypatch)
    body = softer.bodies[0]
    body.material = dataclasses.replace(body.material, E=2.0 * body.material.E)
    with pytest.raises(wsim.CheckpointError, match=f"body '{body.name}' material: saved"):
        softer.restore(eol_path)
    # another format version
    with h5py.File(path, "r+") as f:
        f.attrs["version"] = checkpoint.FORMAT_VERSION + 1
    with pytest.raises(wsim.CheckpointError, match="format version"):
        _build("pbd", monkeypatch).restore(path)


def test_a_bad_body_state_rolls_back_the_bodies_already_loaded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = _stepped("all", monkeypatch, 4).checkpoint(tmp_path / "c.h5")
    with h5py.File(path, "r+") as f:  # the second body's (BEM) displacement with a wrong length
        del f["bodies/1/u"]
        f["bodies/1/u"] = np.zeros(7)
    world = _stepped("all", monkeypatch, 2)
    before = [b.get_state() for b in world.bodies]
    with pytest.raises(wsim.CheckpointError, match="body 'bem'.*'u'"):
        world.restore(path)
    assert _unchanged(world, before, 2)


def test_checkpoint_is_written_atomically(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    world = _stepped("pbd", monkeypatch, 2)
    path = world.checkpoint(tmp_path / "c.h5")
    good = path.read_bytes()
    monkeypatch.setattr(world.bodies[0], "get_state", lambda: (_ for _ in ()).throw(RuntimeError("boom")))
    with pytest.raises(RuntimeError, match="boom"):
        world.checkpoint(path)
    assert path.read_bytes() == good  # the earlier checkpoint survives a failed save
    assert [p.name for p in tmp_path.iterdir()] == ["c.h5"]  # no temporary file left behind
    with pytest.raises(wsim.OutputError, match="does not exist"):
        world.checkpoint(tmp_path / "no" / "such" / "c.h5")
