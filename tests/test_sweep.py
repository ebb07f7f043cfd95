"""``wsim sweep``: the cartesian product of a scene's parameters, in-process and (where installed)
through Ray, failures reported, finished variants skipped on a re-run (issue 22)."""

from __future__ import annotations

import json

import pytest

from wsim.errors import InvalidParameter
from wsim.sweep import parse_param, summary_table, sweep, variant_name, variants

SCENE = '''
import os
import trimesh
import wsim

FRAMES = 3


def build(mesh=None, device=None, size=0.2, fail=False):
    with open(os.path.join(os.path.dirname(__file__), "builds.txt"), "a") as fh:
        fh.write(f"{size} {fail}\\n")
    if fail:
        raise ValueError("this variant was asked to fail")
    w = wsim.World(fps=30, device=device)
    w.add_collider(wsim.GroundPlane(name="ground"))
    box = trimesh.creation.box(extents=(size, size, size))
    w.add(wsim.PbdBody(box, wsim.ElasticMaterial(E=1e5, nu=0.3, rho=500.0), name="box", position=(0, 0.5, 0)))
    return w


def metrics(world):
    if os.path.exists(os.path.join(os.path.dirname(__file__), "bad_metrics")):
        raise RuntimeError("metrics broke")
    return {"height": float(world.bodies[0].points()[:, 1].mean())}
'''


@pytest.fixture
def scene(tmp_path):
    path = tmp_path / "tiny.py"
    path.write_text(SCENE)
    return path


def _builds(scene) -> list[str]:
    f = scene.parent / "builds.txt"
    return f.read_text().splitlines() if f.exists() else []


def test_parameters_parse_and_multiply():
    assert parse_param("resolution=16,32") == ("resolution", [16, 32])
    assert parse_param("mu = 0.5, 1e-2 ,True,soft") == ("mu", [0.5, 0.01, True, "soft"])
    for bad in ("resolution", "=1,2", "2x=1", "a="):
        with pytest.raises(InvalidParameter):
            parse_param(bad)
    v = variants({"a": [1, 2], "b": ["x", "y", "z"]})
    assert v == [{"a": 1, "b": "x"}, {"a": 1, "b": "y"}, {"a": 1, "b": "z"},
                 {"a": 2, "b": "x"}, {"a": 2, "b": "y"}, {"a": 2, "b": "z"}]
    assert variant_name("pile", {"resolution": 32, "mesh dir": "a/b"}) == "pile__resolution=32__mesh_dir=a_b"


def test_sweep_in_process_reports_a_failure_and_skips_finished_variants(scene, tmp_path):
    """Four variants in-process: the two that raise are reported ("failed", the error) while the
    others run, write their USD and carry the scene's own metrics; a second run of the same sweep
    builds only the failed ones again."""
    out = tmp_path / "out"
    params = {"size": [0.1, 0.2], "fail": [False, True]}
    records = sweep(str(scene), params, out, device="cpu", engine="local", warm=False, log=lambda s: None)
    assert [r["params"] for r in records] == variants(params)
    ok = [r for r in records if r["status"] == "ok"]
    failed = [r for r in records if r["status"] == "failed"]
    assert [r["params"]["fail"] for r in ok] == [False, False]
    assert all("asked to fail" in r["error"] for r in failed) and len(failed) == 2
    for r in ok:
        assert (out / f"{r['variant']}.usdc").is_file() and r["frames"] == 3 and r["ms_per_frame"] > 0
        assert 0.0 < r["metrics"]["height"] < 0.5  # it fell
    assert [json.loads(line)["variant"] for line in (out / "sweep.jsonl").read_text().splitlines()] == \
        [r["variant"] for r in records]
    assert "asked to fail" in summary_table(records)
    assert len(_builds(scene)) == 4
    again = sweep(str(scene), params, out, device="cpu", engine="local", warm=False, log=lambda s: None)
    assert _builds(scene)[4:] == ["0.1 True", "0.2 True"]  # only the failed ones ran again
    assert [r["metrics"] for r in again if r["status"] == "ok"] == [r["metrics"] for r in ok]


def test_a_failing_metrics_fails_the_variant_and_a_changed_run_is_not_skipped(scene, tmp_path):
    """The scene's own metrics are part of the variant: when they raise, the variant failed (and
    runs again next time); a finished variant runs again when the frames asked for differ."""
    out = tmp_path / "out"
    (scene.parent / "bad_metrics").touch()
    first = sweep(str(scene), {"size": [0.1]}, out, device="cpu", engine="local", warm=False, log=lambda s: None)
    assert first[0]["status"] == "failed" and "metrics broke" in first[0]["error"]
    (scene.parent / "bad_metrics").unlink()
    ok = sweep(str(scene), {"size": [0.1]}, out, device="cpu", engine="local", warm=False, log=lambda s: None)
    assert ok[0]["status"] == "ok" and len(_builds(scene)) == 2
    sweep(str(scene), {"size": [0.1]}, out, device="cpu", engine="local", warm=False, log=lambda s: None)
    assert len(_builds(scene)) == 2  # the same sweep: skipped
    longer = sweep(str(scene), {"size": [0.1]}, out, device="cpu", frames=4, engine="local", warm=False,
                   log=lambda s: None)
    assert len(_builds(scene)) == 3 and longer[0]["frames"] == 4


def test_sweep_refuses_a_parameter_the_scene_does_not_take(scene, tmp_path):
    with pytest.raises(InvalidParameter, match="no parameter 'resolution'.*size, fail"):
        sweep(str(scene), {"resolution": [8, 16]}, tmp_path / "out", engine="local", log=lambda s: None)
    with pytest.raises(InvalidParameter, match="set by the sweep"):
        sweep(str(scene), {"device": ["cpu"]}, tmp_path / "out", engine="local", log=lambda s: None)
    with pytest.raises(InvalidParameter, match="engine"):
        sweep(str(scene), {"size": [0.1]}, tmp_path / "out", engine="slurm", log=lambda s: None)


def test_sweep_command_line(scene, tmp_path, capsys):
    from wsim.cli import main

    out = tmp_path / "cli"
    assert main(["sweep", str(scene), "--param", "size=0.1,0.2", "-o", str(out), "--device", "cpu",
                 "--engine", "local", "--frames", "2"]) == 0
    table = capsys.readouterr().out
    assert "tiny__size=0.1" in table and "tiny__size=0.2" in table
    assert main(["sweep", str(scene), "--param", "fail=True", "-o", str(out), "--engine", "local"]) == 1
    assert main(["sweep", str(scene), "--param", "nothing=1", "-o", str(out), "--engine", "local"]) == 2
    assert main(["sweep", str(scene), "--param", "size=0.1", "--param", "size=0.2", "-o", str(out)]) == 2


def test_sweep_through_ray_gives_the_in_process_metrics(scene, tmp_path):
    """Through Ray in local mode (each variant in its own worker process) the records match the
    in-process runner's: the same statuses and the same simulated result."""
    ray = pytest.importorskip("ray")
    params = {"size": [0.1, 0.2], "fail": [False, True]}
    local = sweep(str(scene), params, tmp_path / "local", device="cpu", engine="local", warm=False, log=lambda s: None)
    try:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        remote = sweep(str(scene), params, tmp_path / "ray", device="cpu", engine="ray", warm=False, log=lambda s: None)
    finally:
        ray.shutdown()
    assert [r["status"] for r in remote] == [r["status"] for r in local]
    for a, b in zip(local, remote):
        if a["status"] == "ok":
            assert b["metrics"]["height"] == pytest.approx(a["metrics"]["height"], rel=1e-6)
            assert (tmp_path / "ray" / f"{b['variant']}.usdc").is_file()


def test_sweep_leaves_the_environment_as_it_was(scene, tmp_path, monkeypatch):
    """The in-process runner hides the scenes' progress bars while a variant runs, and only then."""
    from wsim.progress import PROGRESS_ENV

    monkeypatch.delenv(PROGRESS_ENV, raising=False)
    sweep(str(scene), {"size": [0.1]}, tmp_path / "out", device="cpu", engine="local", warm=False, log=lambda s: None)
    assert PROGRESS_ENV not in __import__("os").environ
