"""Crash-safe USD output (issue 19): the frame journal beside the output, ``wsim recover``, a full
disk, and the velocities written for motion blur.

The scene is the default one (``scenes/soft_drop.py``: a PBD body and a kinematic paddle, so a
record holds points and a transform) on the CPU, a few frames."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from wsim import usd
from wsim.errors import OutputError

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scenes"))
import soft_drop  # noqa: E402


def _frames(path: Path) -> tuple[list[float], dict[float, np.ndarray], dict[float, np.ndarray]]:
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/fish"))
    codes = mesh.GetPointsAttr().GetTimeSamples()
    points = {c: np.asarray(mesh.GetPointsAttr().Get(c)) for c in codes}
    paddle = UsdGeom.Xformable(stage.GetPrimAtPath("/World/colliders/paddle")).GetOrderedXformOps()[0]
    poses = {c: np.asarray(paddle.Get(c)) for c in paddle.GetAttr().GetTimeSamples()}
    return codes, points, poses


def _cli(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "wsim", *args], cwd=cwd, capture_output=True, text=True, timeout=600)


def _killed_run(out: Path, at: int, frames: int, extra: str = "") -> subprocess.CompletedProcess:
    """The default scene run to ``out`` in a fresh process that SIGKILLs itself while frame ``at``
    is being made (``on_frame`` runs before the frame is written): frames 0..at-1 were written."""
    script = textwrap.dedent(f"""
        import os, signal, sys
        sys.path.insert(0, {str(ROOT / 'scenes')!r})
        import soft_drop
        def kill(world):
            if world.frame == {at}:
                os.kill(os.getpid(), signal.SIGKILL)
        soft_drop.build(device="cpu").run({frames}, out={str(out)!r}, progress=False, on_frame=kill{extra})
    """)
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)


def test_a_killed_run_leaves_every_written_frame_in_its_journal(tmp_path: Path) -> None:
    """SIGKILL while frame 6 is being made (after frames 0-5 were written): ``wsim recover``
    writes frames 0-5, the same points and paddle poses as an uninterrupted run's."""
    out = tmp_path / "killed.usdc"
    proc = _killed_run(out, at=6, frames=20)
    assert proc.returncode == -9, proc.stderr
    assert not out.exists() and usd.journal_path(out).is_file()

    res = _cli("recover", str(out))
    assert res.returncode == 0, res.stderr
    assert "6 frames recovered" in res.stdout
    assert not usd.journal_path(out).exists()
    codes, points, poses = _frames(out)
    assert codes == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]

    ref = tmp_path / "straight.usdc"
    soft_drop.build(device="cpu").run(5, out=ref, progress=False)
    ref_codes, ref_points, ref_poses = _frames(ref)
    assert ref_codes == codes
    for c in codes:
        np.testing.assert_array_equal(points[c], ref_points[c])
        np.testing.assert_array_equal(poses[c], ref_poses[c])
    stage = Usd.Stage.Open(str(out))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 5.0)


def test_a_record_cut_short_is_dropped(tmp_path: Path) -> None:
    """The frame being written when the process died is incomplete: recovery stops before it."""
    out = tmp_path / "cut.usda"
    writer = usd.UsdWriter(out, fps=30)
    world = soft_drop.build(device="cpu")
    world._bind()
    writer.begin(world.bodies, world.surfaces)
    for k in range(3):
        writer.write_frame(k, k / 30)
    journal = writer._journal
    journal._fh.close()  # the process "dies": no close, and the last record is half written
    with open(journal.path, "rb+") as fh:
        fh.truncate(os.path.getsize(journal.path) - 100)
    path, frames = usd.recover(out)
    assert frames == 2 and _frames(path)[0] == [0.0, 1.0]


def test_a_full_disk_is_one_line_and_keeps_the_earlier_frames(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The disk fills while frame 4 goes to the journal, and the USD file cannot be written either:
    one line that names the output, the frame, the OS's reason and what to do; frames 0-3 stay
    in the journal and ``recover`` writes them once there is room."""
    out = tmp_path / "full.usda"
    append = usd._Journal.append

    def full_append(self, frame, arrays):
        if frame >= 4:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        append(self, frame, arrays)

    def full_export(layer, path):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(usd._Journal, "append", full_append)
    monkeypatch.setattr(usd, "_export", full_export)
    with pytest.raises(OutputError) as exc:
        soft_drop.build(device="cpu").run(10, out=out, progress=False)
    msg = str(exc.value)
    assert "\n" not in msg
    assert "No space left on device" in msg and "frames 0..3" in msg and f"wsim recover {out}" in msg
    assert not out.exists() and not list(tmp_path.glob(".full.*"))  # no half-written temporary file
    monkeypatch.undo()
    path, frames = usd.recover(out)
    assert frames == 4 and _frames(path)[0] == [0.0, 1.0, 2.0, 3.0]


def test_a_full_disk_in_a_real_file_system(tmp_path: Path) -> None:
    """The CLI on a 256 kB tmpfs (where this machine lets us mount one): exit 1 with the error in
    one line (no traceback), the journal keeps the frames written before the disk filled."""
    tiny = tmp_path / "tiny"
    tiny.mkdir()
    if shutil.which("mount") is None or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(tiny)],
                                                        capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        res = _cli("run", "scenes/soft_drop.py", "-o", str(tiny / "out.usda"), "--device", "cpu", "--no-progress")
        assert res.returncode == 1, res.stdout + res.stderr
        assert "Traceback" not in res.stderr
        lines = [ln for ln in res.stderr.splitlines() if ln.startswith("wsim:")]
        assert len(lines) >= 1 and "No space left on device" in lines[0], res.stderr
        assert len(res.stderr.strip().splitlines()) <= 2, res.stderr
        rec = _cli("recover", str(tiny / "out.usda"), "-o", str(tmp_path / "saved.usda"))
        assert rec.returncode == 0, rec.stderr
        codes = _frames(tmp_path / "saved.usda")[0]
        assert len(codes) >= 2 and codes == [float(k) for k in range(len(codes))]
    finally:
        subprocess.run(["umount", str(tiny)], capture_output=True)


def test_velocities_are_the_forward_difference_of_the_points(tmp_path: Path) -> None:
    out = tmp_path / "v.usda"
    soft_drop.build(device="cpu").run(8, out=out, progress=False)
    assert not usd.journal_path(out).exists()  # a normal end removes the journal
    stage = Usd.Stage.Open(str(out))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/fish"))
    codes, points, _ = _frames(out)
    assert mesh.GetVelocitiesAttr().GetTimeSamples() == codes
    fps = stage.GetTimeCodesPerSecond()
    for k, c in enumerate(codes):
        v = np.asarray(mesh.GetVelocitiesAttr().Get(c), dtype=np.float64)
        nxt, prv = (codes[k + 1], c) if k + 1 < len(codes) else (c, codes[k - 1])
        fd = (points[nxt].astype(np.float64) - points[prv].astype(np.float64)) * fps
        scale = np.abs(fd).max() + 1e-12
        assert np.abs(v - fd).max() <= 1e-6 * scale  # float32 round-off of the stored difference
    # the body falls: the velocities are not all zero, and point down at the start
    assert np.asarray(mesh.GetVelocitiesAttr().Get(1.0))[:, 1].mean() < -0.1


def test_usd_and_usdc_are_binary_usda_is_text(tmp_path: Path) -> None:
    for name, head in (("a.usd", b"PXR-USDC"), ("a.usdc", b"PXR-USDC"), ("a.usda", b"#usda")):
        soft_drop.build(device="cpu").run(1, out=tmp_path / name, progress=False)
        assert (tmp_path / name).read_bytes().startswith(head)


def test_a_journal_left_by_a_killed_run_stops_a_new_run(tmp_path: Path) -> None:
    """Rerunning over a killed run's output would lose its frames: the run refuses before simulating."""
    out = tmp_path / "again.usda"
    usd.journal_path(out).write_bytes(b"WSIMJRN1")
    world = soft_drop.build(device="cpu")
    with pytest.raises(OutputError, match="interrupted run.*wsim recover"):
        world.run(3, out=out, progress=False)
    assert world.frame == 0
    with pytest.raises(OutputError, match="header is incomplete"):
        usd.recover(out)
    res = _cli("recover", str(tmp_path / "none.usda"))
    assert res.returncode == 1 and "has no interrupted run" in res.stderr


def test_recover_then_resume_from_a_checkpoint_gives_the_whole_animation(tmp_path: Path) -> None:
    """The user's story after an out-of-memory kill: recover the frames, resume from the last
    checkpoint; the file holds every frame, equal to an uninterrupted run's."""
    out = tmp_path / "long.usdc"
    ckpt = tmp_path / "long.ckpt.h5"
    assert _killed_run(out, at=8, frames=12, extra=f", checkpoint={str(ckpt)!r}, checkpoint_every=5").returncode == -9
    usd.recover(out)
    res = _cli("run", "scenes/soft_drop.py", "-o", str(out), "--frames", "12", "--resume", str(ckpt), "--device", "cpu",
               "--no-progress")
    assert res.returncode == 0, res.stderr
    codes, points, _ = _frames(out)
    ref = tmp_path / "ref.usdc"
    soft_drop.build(device="cpu").run(12, out=ref, progress=False)
    ref_codes, ref_points, _ = _frames(ref)
    assert codes == ref_codes == [float(k) for k in range(13)]
    for c in codes:
        np.testing.assert_array_equal(points[c], ref_points[c])
