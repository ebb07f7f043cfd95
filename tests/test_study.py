"""``wsim study`` (issue 22 item 3): knob studies through the sweep engine, errors against a
high-accuracy reference, Pareto fronts, one report (Markdown, JSON, PNG).

The end-to-end tests run tiny grids of the PBD and PDE studies (a few frames, coarse meshes) on
the device; the physics they assert is convergence (more substeps, denser keyframes: closer to
the reference), not a number the code printed. The whole quick report runs under ``-m slow``.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from wsim.errors import InvalidParameter
from wsim.studies import pbd
from wsim.studies.common import Mode, bytes_held, match_points
from wsim.study import load_study, pareto_front, plan, run_studies
from wsim.sweep import sweep, variant_name


def _dominated(i: int, costs, errors) -> bool:
    return any(costs[j] <= costs[i] and errors[j] <= errors[i] and (costs[j] < costs[i] or errors[j] < errors[i])
               for j in range(len(costs)) if j != i)


def test_pareto_front_keeps_exactly_the_non_dominated_points(rng):
    for n in (1, 2, 7, 40):
        costs = rng.uniform(0.1, 10.0, n).round(1)  # ties in cost happen at one decimal
        errors = rng.uniform(0.0, 1.0, n).round(1)
        front = pareto_front(list(costs), list(errors))
        assert front == sorted(front, key=lambda i: costs[i])
        for i in range(n):
            # on the front iff nothing dominates it (of points equal in both, one is kept)
            twins = [j for j in range(n) if costs[j] == costs[i] and errors[j] == errors[i]]
            if _dominated(i, costs, errors):
                assert i not in front
            else:
                assert len(set(twins) & set(front)) == 1


def test_plan_varies_one_knob_at_a_time_and_refuses_unknown_names():
    module, spec = load_study("pbd")
    mode = Mode(default={"divisions": 1}, grid={"substeps": [5, 10, 40], "iterations": [4]},
                reference={"substeps": 100, "iterations": 4}, frames=3)
    v = plan(module.build, spec, mode)
    assert [x.role for x in v[:2]] == ["default", "reference"]
    assert v[0].params == {"divisions": 1}  # build's own defaults are left out of the names
    assert v[1].params == {"substeps": 100, "iterations": 4, "divisions": 1}
    for x in v[2:]:
        changed = {k for k in set(x.params) | set(v[0].params) if x.params.get(k) != v[0].params.get(k)}
        assert changed <= {x.knob}  # substeps=10 is build's default: the same variant as the default
    assert v[3].params == v[0].params
    assert [x.knob for x in plan(module.build, spec, mode, knobs=["iterations"])[2:]] == ["iterations"]
    with pytest.raises(InvalidParameter, match="no knob 'dt'.*substeps, iterations"):
        plan(module.build, spec, mode, knobs=["dt"])
    with pytest.raises(InvalidParameter, match="'resolution', which its build"):
        plan(module.build, spec, Mode(default={}, grid={"resolution": [8]}, reference={}, frames=3))
    with pytest.raises(InvalidParameter, match="study 'fem' does not exist.*bem, eol, pbd, pde, coupling"):
        load_study("fem")
    with pytest.raises(InvalidParameter, match="no study of pbd, pde has a knob 'cfl'"):
        run_studies(["pbd", "pde"], "unused", knobs=["cfl"])


def test_probes_are_the_coarse_mesh_vertices_on_every_refinement():
    coarse, fine = pbd.beam(1), pbd.beam(3)
    idx = match_points(fine.vertices, coarse.vertices, "test")
    np.testing.assert_allclose(fine.vertices[idx], coarse.vertices, rtol=0, atol=1e-12)  # grid round-off
    with pytest.raises(InvalidParameter, match="probe point"):
        match_points(fine.vertices, coarse.vertices + 0.01, "test")


def test_bytes_held_counts_each_array_once():
    import warp as wp

    a = np.zeros(1000)  # 8000 bytes
    w = wp.zeros(250, dtype=wp.vec3, device="cpu")  # 3000 bytes
    alias = wp.array(a.reshape(-1, 4), dtype=wp.float64, device="cpu", copy=False)  # a's memory again
    tail = wp.array(a[8:].reshape(-1, 4), dtype=wp.float64, device="cpu", copy=False)  # part of it, offset
    holder = {"a": a, "view": a[10:], "again": [a, (w, w)], "w": w, "alias": alias, "tail": tail}
    assert bytes_held(holder) == (0, 8000 + 3000)  # the Warp array is on the CPU: host bytes
    from scipy import sparse

    m = sparse.random(50, 50, density=0.1, format="csr", random_state=0)
    assert bytes_held([m]) == (0, m.data.nbytes + m.indices.nbytes + m.indptr.nbytes)


def test_a_tiny_pbd_study_end_to_end(device, tmp_path):
    """Reference, default (10 substeps) and 3 and 20 substeps of the beam at one mesh: the error
    falls as substeps rise (XPBD converges to the reference's many substeps), the reference's is
    0, the JSON and Markdown parse, each front is non-dominated, the errors are the stored
    signatures' largest distance over the beam's length."""
    mode = Mode(default={"divisions": 1}, grid={"substeps": [3, 20]}, reference={"substeps": 80, "iterations": 4},
                frames=8)
    report = run_studies(["pbd"], tmp_path, device=device, engine="local", modes={"pbd": mode}, log=lambda s: None)
    on_disk = json.loads((tmp_path / "study.json").read_text())
    assert on_disk["studies"]["pbd"]["fronts"] == report["studies"]["pbd"]["fronts"]
    s = on_disk["studies"]["pbd"]
    rows = {(r["role"], r["value"]): r for r in s["variants"]}
    assert all(r["status"] == "ok" for r in s["variants"])
    ref, default = rows[("reference", None)], rows[("default", None)]
    worse, better = rows[("knob", 3)], rows[("knob", 20)]
    assert ref["error"] == 0.0
    assert worse["error"] > default["error"] > better["error"] > 0.0
    # the error is what the sweep stored: largest probe distance over the beam's length
    runs = tmp_path / "pbd"
    sig = {r["variant"]: np.asarray(json.loads((runs / f"{r['variant']}.json").read_text())["metrics"]["signature"])
           for r in s["variants"]}
    assert sig[worse["variant"]].shape == (8, 28, 3)
    expect = np.linalg.norm(sig[worse["variant"]] - sig[ref["variant"]], axis=-1).max() / pbd.LENGTH
    assert worse["error"] == pytest.approx(expect, rel=1e-12)
    assert len((runs / "sweep.jsonl").read_text().splitlines()) == 4  # the warm-up run is not recorded
    assert not list(runs.glob("*.usdc"))  # studies write no USD
    for cost, front in s["fronts"].items():
        pts = [r for r in s["variants"] if r["role"] != "reference" and r["error"] is not None]
        costs, errors = [r["costs"][cost] for r in pts], [r["error"] for r in pts]
        for name in front:
            i = next(k for k, r in enumerate(pts) if r["variant"] == name)
            assert not _dominated(i, costs, errors)
        assert ref["variant"] not in front
    md = (tmp_path / "study.md").read_text()
    assert "## PBD" in md and "| **reference** | 0 |" in md and "`substeps=3`" in md
    assert all(math.isfinite(r["costs"]["ms_per_frame"]) and r["costs"]["ms_per_frame"] > 0 for r in s["variants"])
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        assert "plots skipped" in md
    else:
        assert (tmp_path / "study_pbd.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "![pbd](study_pbd.png)" in md


def test_the_pde_study_measures_its_own_error(device, tmp_path):
    """The reconstruction's error is measured against the frames it rebuilds: the reference
    (every frame a keyframe, linear) reproduces them, and sparser keyframes lose more."""
    mode = Mode(default={"rings": 12, "sectors": 8, "frames": 12}, grid={"stride": [2, 6]},
                reference={"stride": 1, "basis": "linear"}, frames=12)
    s = run_studies(["pde"], tmp_path, device=device, engine="local", modes={"pde": mode},
                    log=lambda s: None)["studies"]["pde"]
    rows = {(r["role"], r["value"]): r for r in s["variants"]}
    assert rows[("reference", None)]["error"] < 1e-6  # a micrometre over the 1.6 m creature: float32 output
    assert rows[("knob", 6)]["error"] > rows[("knob", 2)]["error"] > 0.0
    assert rows[("knob", 6)]["costs"]["data_ratio"] < rows[("knob", 2)]["costs"]["data_ratio"] < 1.0
    assert "| setting | error | playback ms per frame |" in (tmp_path / "study.md").read_text()  # no "vs default"


def test_sweep_takes_a_list_of_variants_without_usd(tmp_path):
    """The sweep additions the study relies on: an explicit list of variants, no USD (and such a
    record is not reused for a run that wants USD)."""
    path = pbd.__file__
    variants = [{"divisions": 1, "substeps": 4}, {"divisions": 1, "iterations": 1}]
    log: list[str] = []
    records = sweep(path, variants, tmp_path, device="cpu", frames=2, engine="local", usd=False, warm_full=True,
                    log=log.append)
    assert [r["params"] for r in records] == variants and all(r["status"] == "ok" for r in records)
    assert all(r["usd"] is None for r in records) and not list(tmp_path.glob("*.usdc"))
    assert any("warm-up run" in line for line in log)
    again = sweep(path, variants, tmp_path, device="cpu", frames=2, engine="local", usd=False, log=log.append)
    assert any("2 of 2 variants already done" in line for line in log)  # nothing ran again
    assert [r["metrics"]["signature"] for r in again] == [r["metrics"]["signature"] for r in records]
    with_usd = sweep(path, variants[:1], tmp_path, device="cpu", frames=2, engine="local", log=log.append)
    assert (tmp_path / f"{variant_name('pbd', variants[0])}.usdc").is_file() and with_usd[0]["usd"]


def test_study_command_line_refuses_bad_names(tmp_path, capsys):
    from wsim.cli import main

    assert main(["study", "--studies", "fem", "-o", str(tmp_path)]) == 2
    assert "study 'fem' does not exist" in capsys.readouterr().err
    assert main(["study", "--studies", "pbd", "--knobs", "dt", "-o", str(tmp_path)]) == 2
    assert "no study of pbd has a knob 'dt'" in capsys.readouterr().err
    assert main(["study", "--studies", "pbd", "--engine", "local", "--knobs", "substeps", "--quick", "--device", "cpu",
                 "-o", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "study.json").read_text())
    assert list(report["studies"]) == ["pbd"] and report["command"].startswith("wsim study --studies pbd")
    assert {r["knob"] for r in report["studies"]["pbd"]["variants"]} == {None, "substeps"}


@pytest.mark.slow
def test_the_quick_report_runs_every_study(tmp_path):
    """``wsim study --quick`` on the CPU: every study's reference and variants run (about 1.5
    minutes on a 2-core CPU with Warp's kernels compiled)."""
    report = run_studies(None, tmp_path, quick=True, device="cpu", engine="local", log=lambda s: None)
    assert list(report["studies"]) == ["bem", "eol", "pbd", "pde", "coupling"]
    for name, s in report["studies"].items():
        assert s["reference_ok"], name
        ref = next(r for r in s["variants"] if r["role"] == "reference")
        assert ref["error"] == pytest.approx(0.0, abs=1e-6)
        assert all(r["status"] == "ok" for r in s["variants"]), name
