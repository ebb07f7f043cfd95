"""``wsim study`` (issue 22 item 3): knob studies through the sweep engine, errors against a
reference whose uncertainty a reference check measures, Pareto fronts, one report (Markdown,
JSON, PNG).

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
from wsim.study import RESOLVE, Variant, analyse, load_study, pareto_front, plan, run_studies
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
    deep: list = [m]
    for _ in range(5):  # at the depth bound (6), where the compressed BEM operators sit: counted in full
        deep = [deep]
    assert bytes_held(deep) == bytes_held([m])


def test_a_compressed_bem_body_counts_its_compressed_operators(device):
    """The compressed history sits below the walk's depth bound (body, stepper, history, tuple,
    matrix, sparse C): it counts in full, as its own ``nbytes`` says, on top of the dense operators
    the body keeps."""
    import trimesh

    import wsim

    world = wsim.World(fps=50.0, gravity=(0.0, 0.0, 0.0), device=device)
    body = world.add(wsim.BemBody(trimesh.creation.icosphere(subdivisions=1, radius=0.1),
                                  wsim.ElasticMaterial(mu=3.0e4, nu=0.45, rho=1000.0), 0.004, compression=4,
                                  cache=False, progress=False))
    history = body._so.compressed
    assert history is not None and history.nbytes > 0
    assert bytes_held(history) == (0, history.nbytes)
    dense = sum(bytes_held(body.operators))
    assert dense > 0 and sum(bytes_held(body)) >= dense + history.nbytes


def test_a_tiny_pbd_study_end_to_end(device, tmp_path):
    """Reference, its check (substeps doubled), default (10 substeps) and 3 and 20 substeps of the
    beam at one mesh: the error falls as substeps rise (XPBD converges to the reference's many
    substeps), the reference check moves the reference less than any variant lies from it (the
    reference resolves them), the JSON and Markdown parse, each front is non-dominated, the errors
    are the stored signatures' largest distance over the beam's length."""
    mode = Mode(default={"divisions": 1}, grid={"substeps": [3, 20]}, reference={"substeps": 80, "iterations": 4},
                frames=8, check={"substeps": 160})
    report = run_studies(["pbd"], tmp_path, device=device, engine="local", modes={"pbd": mode}, log=lambda s: None)
    on_disk = json.loads((tmp_path / "study.json").read_text())
    assert on_disk["studies"]["pbd"]["fronts"] == report["studies"]["pbd"]["fronts"]
    s = on_disk["studies"]["pbd"]
    rows = {(r["role"], r["value"]): r for r in s["variants"]}
    assert all(r["status"] == "ok" for r in s["variants"])
    ref, default, check = rows[("reference", None)], rows[("default", None)], rows[("check", None)]
    worse, better = rows[("knob", 3)], rows[("knob", 20)]
    assert ref["error"] == 0.0
    assert worse["error"] > default["error"] > better["error"] > 0.0
    # the uncertainty is the check's distance from the reference, and the variants stand clear of it
    assert s["reference_uncertainty"] == check["error"] == s["reference_check"]["uncertainty"]
    assert 0.0 < check["error"] < better["error"] / RESOLVE
    assert all(r["resolved"] is True for r in (default, worse, better)) and check["resolved"] is None
    assert all(check["variant"] not in front for front in s["fronts"].values())
    # the error is what the sweep stored: largest probe distance over the beam's length
    runs = tmp_path / "pbd"
    sig = {r["variant"]: np.asarray(json.loads((runs / f"{r['variant']}.json").read_text())["metrics"]["signature"])
           for r in s["variants"]}
    assert sig[worse["variant"]].shape == (8, 28, 3)
    expect = np.linalg.norm(sig[worse["variant"]] - sig[ref["variant"]], axis=-1).max() / pbd.LENGTH
    assert worse["error"] == pytest.approx(expect, rel=1e-12)
    assert len((runs / "sweep.jsonl").read_text().splitlines()) == 5  # the warm-up run is not recorded
    assert not list(runs.glob("*.usdc"))  # studies write no USD
    for cost, front in s["fronts"].items():
        pts = [r for r in s["variants"] if r["role"] in ("default", "knob") and r["error"] is not None]
        costs, errors = [r["costs"][cost] for r in pts], [r["error"] for r in pts]
        for name in front:
            i = next(k for k, r in enumerate(pts) if r["variant"] == name)
            assert not _dominated(i, costs, errors)
        assert ref["variant"] not in front
    md = (tmp_path / "study.md").read_text()
    assert "## PBD" in md and "| **reference** | 0 |" in md and "`substeps=3`" in md
    assert "| **reference check** |" in md and "Reference check, `substeps=160` over the reference" in md
    assert all(math.isfinite(r["costs"]["ms_per_frame"]) and r["costs"]["ms_per_frame"] > 0 for r in s["variants"])
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        assert "plots skipped" in md
    else:
        assert (tmp_path / "study_pbd.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "![pbd](study_pbd.png)" in md


def test_errors_within_twice_the_reference_uncertainty_are_not_resolved():
    """From records alone: the check's distance from the reference is the uncertainty u; an error
    below 2u is marked not resolved, one above resolved; no setting is named for a target error
    below u, and a setting named under a target but below 2u is said to be unresolved."""
    _, spec = load_study("pbd")
    u = 0.004  # [fraction of the beam's length]: the check lies 0.4 % from the reference
    offsets = {"reference": 0.0, "check": u, "default": 10 * u, "close": 1.5 * u, "far": 3 * u}
    variants = [Variant("default", None, None, {"substeps": 10}), Variant("reference", None, None, {"substeps": 100}),
                Variant("check", None, None, {"substeps": 200}), Variant("knob", "substeps", 60, {"substeps": 60}),
                Variant("knob", "substeps", 20, {"substeps": 20})]
    keys = ["default", "reference", "check", "close", "far"]
    cost = {"default": 1.0, "reference": 9.0, "check": 18.0, "close": 6.0, "far": 2.0}
    records = {}
    for v, k in zip(variants, keys):
        sig = np.zeros((3, 28, 3))
        sig[1, 5, 0] = offsets[k] * spec.scale  # one probe, one frame, offset along x
        records[variant_name("pbd", v.params)] = {"status": "ok", "metrics": {
            "signature": sig.tolist(), "ms_per_frame": cost[k], "model_mb": 1.0}}
    result = analyse(spec, variants, records)
    rows = dict(zip(keys, result["variants"]))
    assert result["reference_uncertainty"] == pytest.approx(u, rel=1e-12)
    assert rows["close"]["error"] < RESOLVE * u < rows["far"]["error"]
    assert (rows["close"]["resolved"], rows["far"]["resolved"], rows["default"]["resolved"]) == (False, True, True)
    below, at_1, at_10 = result["advice"]  # targets 0.1 %, 1 %, 10 %; u = 0.4 %
    assert "cannot resolve" in below and "substeps" not in below
    assert "substeps=60" in at_1 and "not resolved" in at_1  # 0.6 %: under 1 %, but under 2u too
    assert "the default" in at_10 and "not resolved" not in at_10
    # with no check the uncertainty is unknown, and the advice says so
    unknown = analyse(spec, [variants[i] for i in (0, 1, 3, 4)],
                      {variant_name("pbd", variants[i].params): records[variant_name("pbd", variants[i].params)]
                       for i in (0, 1, 3, 4)})
    assert unknown["reference_uncertainty"] is None and all(r["resolved"] is None for r in unknown["variants"])
    assert "unknown" in unknown["advice"][-1]


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
    assert s["reference_uncertainty"] == 0.0 and s["reference_check"]["exact"]  # measured against the truth
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
    """``wsim study --quick`` on the CPU: every study's reference, check and variants run, and
    each reference with a check resolves its default: the check moves the reference by less than
    half the default's distance from it (else the study's errors would measure the reference)."""
    report = run_studies(None, tmp_path, quick=True, device="cpu", engine="local", log=lambda s: None)
    assert list(report["studies"]) == ["bem", "eol", "pbd", "pde", "coupling"]
    for name, s in report["studies"].items():
        assert s["reference_ok"], name
        assert all(r["status"] == "ok" for r in s["variants"]), name
        default = next(r for r in s["variants"] if r["role"] == "default")
        u = s["reference_uncertainty"]
        if s["check"]:
            assert u is not None and default["error"] > RESOLVE * u, name
            assert default["resolved"] is True, name
        else:  # PDE: exact; coupling: unknown, and said so
            assert (u == 0.0) if s["reference_check"]["exact"] else (u is None), name
