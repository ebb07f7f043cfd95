"""``wsim preview``: headless PNG contact sheets and GIF animations of a USD output (matplotlib Agg)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matplotlib")
import matplotlib.image as mpimg  # noqa: E402
from PIL import Image  # noqa: E402

from wsim import preview  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FRAMES = 4  # simulated frames: the file holds FRAMES + 1 time codes


def run_cli(*args: str, env: dict | None = None, code: str | None = None) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-c", code, *args] if code else [sys.executable, "-m", "wsim", *args]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120, env=env)


def _simulate(out: Path, up_axis: str | None = None) -> Path:
    sys.path.insert(0, str(ROOT / "scenes"))
    try:
        import soft_drop
    finally:
        sys.path.remove(str(ROOT / "scenes"))
    soft_drop.build(device="cpu").run(FRAMES, out=out, up_axis=up_axis, progress=False)
    return out


@pytest.fixture(scope="module")
def usd(tmp_path_factory) -> Path:
    return _simulate(tmp_path_factory.mktemp("preview") / "a.usdc")


def _body_fraction(rgb: np.ndarray) -> float:
    """Share of pixels of the bodies' orange (displayColor 0.85, 0.45, 0.25, shaded)."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return float(np.mean((r > 0.2) & (r > 1.6 * b) & (r > g + 0.08)))


def _not_background(rgb: np.ndarray) -> float:
    return float(np.mean(np.abs(rgb - np.asarray(preview.BACKGROUND)).max(axis=-1) > 0.03))


def test_png_contact_sheet_is_not_blank(usd, tmp_path):
    out = tmp_path / "sheet.png"
    res = run_cli("preview", str(usd), "-o", str(out), "--size", "600x300", "--frames", "4")
    assert res.returncode == 0, res.stderr
    assert "4 tiles" in res.stdout and str(out) in res.stdout
    rgb = mpimg.imread(out)[..., :3]
    assert rgb.shape[:2] == (300, 600)
    assert _not_background(rgb) > 0.3  # ground, bodies, shadows
    assert _body_fraction(rgb) > 0.003  # the fish, in its own colour
    assert [p.name for p in tmp_path.iterdir()] == ["sheet.png"]  # no temporary file left


def test_gif_has_several_frames(usd, tmp_path):
    out = tmp_path / "anim.gif"
    res = run_cli("preview", str(usd), "-o", str(out), "--size", "320x200", "--fps", "10")
    assert res.returncode == 0, res.stderr
    with Image.open(out) as im:
        assert im.n_frames == FRAMES + 1 and im.size == (320, 200)
        assert im.info["duration"] == 100
        im.seek(im.n_frames - 1)
        rgb = np.asarray(im.convert("RGB"), dtype=np.float64) / 255.0
    assert _not_background(rgb) > 0.3 and _body_fraction(rgb) > 0.003
    out2 = tmp_path / "short.gif"
    assert run_cli("preview", str(usd), "-o", str(out2), "--size", "160x100", "--frames", "2").returncode == 0
    with Image.open(out2) as im:
        assert im.n_frames == 2


def test_z_up_stage_renders_upright(usd, tmp_path):
    """The same run written with Z up gives the same picture (the view follows the stage's up axis)."""
    z_usd = _simulate(tmp_path / "z.usdc", up_axis="Z")
    preview.render(usd, tmp_path / "y.png", frames=2, size=(240, 120))
    preview.render(z_usd, tmp_path / "z.png", frames=2, size=(240, 120))
    y_img, z_img = mpimg.imread(tmp_path / "y.png"), mpimg.imread(tmp_path / "z.png")
    assert np.mean(np.abs(y_img - z_img) > 0.05) < 0.002


def test_static_quad_mesh_with_its_colour(tmp_path):
    """A hand-written stage: no time samples, quads (fan-triangulated), a Z-up green cube."""
    src = tmp_path / "cube.usda"
    src.write_text("""#usda 1.0
(
    upAxis = "Z"
)
def Xform "World"
{
    def Mesh "cube"
    {
        int[] faceVertexCounts = [4, 4, 4, 4, 4, 4]
        int[] faceVertexIndices = [0, 3, 2, 1, 4, 5, 6, 7, 0, 1, 5, 4, 1, 2, 6, 5, 2, 3, 7, 6, 3, 0, 4, 7]
        point3f[] points = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
        color3f[] primvars:displayColor = [(0.1, 0.7, 0.2)]
    }
}
""")
    out = tmp_path / "cube.png"
    summary = preview.render(src, out, size=(200, 150))
    assert summary.frames == 1
    rgb = mpimg.imread(out)[..., :3]
    green = (rgb[..., 1] > 1.5 * rgb[..., 0]) & (rgb[..., 1] > 1.5 * rgb[..., 2])
    assert rgb.shape[:2] == (150, 200) and green.mean() > 0.1
    # three faces in view, three tones (Lambert shading)
    tones = np.unique(np.round(rgb[green][:, 1], 2))
    assert len(tones) >= 3


@pytest.mark.parametrize("case", ["missing", "not_usd", "no_mesh", "extension", "size", "folder"])
def test_errors_are_one_line(usd, tmp_path, case):
    src, out, extra = str(usd), str(tmp_path / "p.png"), []
    if case == "missing":
        src = str(tmp_path / "nothing.usdc")
    elif case == "not_usd":
        src = str(tmp_path / "notes.usd")
        Path(src).write_text("not a stage\n")
    elif case == "no_mesh":
        src = str(tmp_path / "empty.usda")
        Path(src).write_text('#usda 1.0\ndef Xform "World"\n{\n}\n')
    elif case == "extension":
        out = str(tmp_path / "p.jpg")
    elif case == "size":
        extra = ["--size", "big"]
    elif case == "folder":
        out = str(tmp_path / "no" / "p.png")
    res = run_cli("preview", src, "-o", out, *extra)
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("wsim: error: "), res.stderr
    named = {"extension": out, "folder": out, "size": "big"}.get(case, src)
    assert named in lines[0]
    assert not Path(out).exists()


def test_without_matplotlib_says_what_to_install(usd, tmp_path):
    code = "import sys; sys.modules['matplotlib'] = None; from wsim.cli import main; raise SystemExit(main(sys.argv[1:]))"
    res = run_cli("preview", str(usd), "-o", str(tmp_path / "p.png"), code=code)
    assert res.returncode == 1
    assert res.stderr.strip().splitlines() == ['wsim: error: wsim preview needs matplotlib: pip install "wsim[preview]"']


def test_mp4_without_ffmpeg_suggests_gif(usd, tmp_path):
    env = dict(os.environ, PATH=str(tmp_path))  # no ffmpeg there
    res = run_cli("preview", str(usd), "-o", str(tmp_path / "p.mp4"), env=env)
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "ffmpeg" in lines[0] and ".gif" in lines[0] and "p.mp4" in lines[0]


@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="ffmpeg not on PATH")
def test_mp4_with_ffmpeg(usd, tmp_path):
    out = tmp_path / "p.mp4"
    res = run_cli("preview", str(usd), "-o", str(out), "--size", "321x200")
    assert res.returncode == 0, res.stderr
    assert out.stat().st_size > 1000 and "320x200" in res.stdout  # H.264 wants even sizes
