"""What a user sees on the terminal (issue 19, point 4): Warp's banner, module-load lines and the
missing-driver warning only with ``--verbose``; one line while kernels compile for the first time;
every progress bar obeys ``--no-progress``; ``wsim --help`` without importing the simulator."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from wsim.progress import PROGRESS_ENV, show_progress

ROOT = Path(__file__).resolve().parents[1]


def _cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "wsim", *args], cwd=ROOT, capture_output=True, text=True, timeout=600,
                          env={**os.environ, **(env or {})})


def test_help_does_not_import_the_simulator() -> None:
    """``wsim --help`` parses arguments only: Warp, scipy and trimesh (0.8 s of imports) stay out."""
    code = ("import sys\nfrom wsim.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in ('warp', 'scipy', 'trimesh', 'pxr', 'h5py') if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().splitlines()[-1] == "[]"
    assert "recover" in res.stdout and "run" in res.stdout


def test_a_cpu_run_prints_no_warp_output_unless_verbose(tmp_path: Path) -> None:
    res = _cli("run", "scenes/soft_drop.py", "-o", str(tmp_path / "a.usdc"), "--frames", "2", "--device", "cpu",
               "--no-progress")
    assert res.returncode == 0, res.stderr
    assert "Warp" not in res.stderr and "Module" not in res.stderr, res.stderr
    assert res.stdout.strip().startswith("2 frames")
    loud = _cli("run", "scenes/soft_drop.py", "-o", str(tmp_path / "b.usdc"), "--frames", "1", "--device", "cpu",
                "--no-progress", "--verbose")
    assert loud.returncode == 0, loud.stderr
    assert "Warp" in loud.stdout + loud.stderr and "initialized" in loud.stdout + loud.stderr


def test_first_compilation_is_announced_in_one_line(tmp_path: Path) -> None:
    """An empty Warp kernel cache: the kernels compile (seconds) and one line says so; the next run,
    with the cache filled, prints nothing."""
    env = {"WARP_CACHE_PATH": str(tmp_path / "warp-cache")}
    first = _cli("run", "scenes/soft_drop.py", "-o", str(tmp_path / "a.usdc"), "--frames", "1", "--device", "cpu",
                 "--no-progress", env=env)
    assert first.returncode == 0, first.stderr
    notes = [ln for ln in first.stderr.splitlines() if "compiling Warp kernels" in ln]
    assert len(notes) == 1, first.stderr
    again = _cli("run", "scenes/soft_drop.py", "-o", str(tmp_path / "b.usdc"), "--frames", "1", "--device", "cpu",
                 "--no-progress", env=env)
    assert again.returncode == 0 and "compiling" not in again.stderr, again.stderr


def test_progress_rule(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(PROGRESS_ENV, raising=False)
    assert show_progress(True) and not show_progress(False)
    assert show_progress(None) == sys.stderr.isatty()
    monkeypatch.setenv(PROGRESS_ENV, "0")  # what --no-progress sets: wins over a scene's progress=True
    assert not show_progress(True) and not show_progress(None)


def test_no_progress_hides_the_bem_operator_bar(monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture,
                                                tmp_path: Path) -> None:
    import trimesh

    import wsim
    from wsim.bem.operators import build_operators

    monkeypatch.setenv("WSIM_CACHE_DIR", str(tmp_path / "cache"))
    shape = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    material = wsim.ElasticMaterial(mu=1.0e5, nu=0.45, rho=1000.0)
    build_operators(shape, material, 0.01, device="cpu", progress=True, cache=False)
    assert "BEM operators" in capfd.readouterr().err
    monkeypatch.setenv(PROGRESS_ENV, "0")
    build_operators(shape, material, 0.01, device="cpu", progress=True, cache=False)
    assert "BEM operators" not in capfd.readouterr().err


def test_mesh_is_fitted_and_says_so_or_kept_in_its_own_units(tmp_path: Path) -> None:
    """``--mesh``: fitted to the scene's size with one line saying so; ``--mesh-scale S``: the
    file's own units times S (a 100 m ball at S = 0.004 is 0.4 m across in the USD)."""
    import numpy as np
    import trimesh
    from pxr import Usd, UsdGeom

    ball = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=2, radius=50.0).export(ball)
    fitted = _cli("run", "scenes/soft_drop.py", "--mesh", str(ball), "-o", str(tmp_path / "f.usdc"), "--frames", "1",
                  "--device", "cpu", "--no-progress")
    assert fitted.returncode == 0, fitted.stderr
    assert "mesh 'ball.obj': fitted: longest side 0.8 m" in fitted.stderr
    kept = _cli("run", "scenes/soft_drop.py", "--mesh", str(ball), "--mesh-scale", "0.004", "-o", str(tmp_path / "k.usdc"),
                "--frames", "1", "--device", "cpu", "--no-progress")
    assert kept.returncode == 0, kept.stderr
    assert "its own units x 0.004" in kept.stderr
    stage = Usd.Stage.Open(str(tmp_path / "k.usdc"))
    p = np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath("/World/ball")).GetPointsAttr().Get(0.0))  # named after the file
    np.testing.assert_allclose(np.ptp(p, axis=0), 0.4, rtol=0.02)
    bad = _cli("run", "scenes/soft_drop.py", "--mesh", str(ball), "--mesh-scale", "-1", "--frames", "1", "--device", "cpu")
    assert bad.returncode == 2 and "--mesh-scale" in bad.stderr
