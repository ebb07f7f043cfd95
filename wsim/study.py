"""``wsim study``: the speed/accuracy report of every method's knobs, through the sweep engine.

Each study (``wsim.studies``: ``bem``, ``eol``, ``pbd``, ``pde``, ``coupling``) is a scene file
with a declared knob grid. For each, the variants are: the default, the reference (the finest
setting the study affords), the reference check (the reference refined one notch in its dominant
discretization, where one exists) and every knob of the grid varied alone from the default (one
knob at a time, not the product, so the cost grows with the sum of the grid's lengths). They run
through ``wsim.sweep.sweep``, in this process by default (after an unrecorded warm-up run that
also compiles every Warp module the build imported, so no variant's timing holds kernel
compilation) or as Ray tasks, without USD. A variant's error is the largest distance between its
signature (probe points after every frame) and the reference's, over the study's length scale;
the PDE study measures its own error against the frames it rebuilds. The reference check's error
is the reference's uncertainty: a variant's error below twice it is not resolved by the reference
(the report marks it, and names no setting for a target error below it). Costs are the study's own timing (frames after the first, probe reads
excluded), the bytes the bodies hold and a study's extra measures (the BEM operator build).

The report (``DIR/study.json``, ``DIR/study.md``, ``DIR/study_<name>.png``) holds, per study,
every variant's record, its error, how far it moved from the default, its costs, the Pareto front
per cost (the settings no other setting beats on both error and cost; the reference, being the
yardstick, is not on it) and the cheapest measured setting under 0.1 %, 1 % and 10 % error.
"""

from __future__ import annotations

import contextlib
import datetime
import importlib
import inspect
import io
import json
import math
import os
import platform
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from wsim.errors import InvalidParameter
from wsim.studies.common import Mode, StudySpec
from wsim.sweep import ENGINES, sweep, variant_name

STUDIES = ("bem", "eol", "pbd", "pde", "coupling")
RESOLVE = 2.0  # an error below RESOLVE x the reference's uncertainty is not resolved by the reference


@dataclass(frozen=True)
class Variant:
    """One setting of a study: ``role`` "reference", "check" (the reference check: the reference
    refined one notch), "default" or "knob" (``knob`` = ``value``, the others at the default);
    ``params`` are the build keywords that differ from build's own defaults (the sweep's variant,
    named by them)."""

    role: str
    knob: str | None
    value: Any
    params: dict[str, Any]


def load_study(name: str) -> tuple[ModuleType, StudySpec]:
    """The study's module (a scene file the sweep runs) and its ``SPEC``."""
    if name not in STUDIES:
        raise InvalidParameter(f"study {name!r} does not exist; the studies: {', '.join(STUDIES)}")
    module = importlib.import_module(f"wsim.studies.{name}")
    # the sweep names a variant after its scene file: the report finds the records by that name
    assert Path(module.__file__).stem == module.SPEC.name, f"study file {module.__file__} names itself {module.SPEC.name!r}"
    return module, module.SPEC


def _build_defaults(build: Callable[..., Any]) -> dict[str, Any]:
    return {n: p.default for n, p in inspect.signature(build).parameters.items()
            if n not in ("mesh", "device") and p.default is not inspect.Parameter.empty}


def plan(build: Callable[..., Any], spec: StudySpec, mode: Mode, knobs: Sequence[str] | None = None) -> list[Variant]:
    """The study's variants: default first (the in-process warm-up runs it), the reference, the
    reference check (where the mode has one), then each knob's values in the grid's order.
    ``knobs`` keeps only those knobs' variants."""
    defaults = _build_defaults(build)
    for what, names in (("default", mode.default), ("reference", mode.reference), ("reference check", mode.check),
                        ("grid", mode.grid)):
        for n in names:
            if n not in defaults:
                raise InvalidParameter(f"study '{spec.name}': {what} sets {n!r}, which its build() does not take "
                                       f"(its knobs: {', '.join(defaults)})")
    grid = dict(mode.grid)
    if knobs is not None:
        for k in knobs:
            if k not in grid:
                raise InvalidParameter(f"study '{spec.name}' has no knob {k!r} (its knobs: {', '.join(grid)})")
        grid = {k: v for k, v in grid.items() if k in knobs}

    def canonical(over: dict[str, Any]) -> dict[str, Any]:
        full = {**defaults, **mode.default, **over}
        return {n: full[n] for n in defaults if full[n] != defaults[n]}  # build's order: stable names

    out = [Variant("default", None, None, canonical({})), Variant("reference", None, None, canonical(mode.reference))]
    if mode.check:
        check = canonical({**mode.reference, **mode.check})
        if check == out[1].params:
            raise InvalidParameter(f"study '{spec.name}': the reference check {mode.check} is the reference itself")
        out.append(Variant("check", None, None, check))
    out += [Variant("knob", k, v, canonical({k: v})) for k, values in grid.items() for v in values]
    return out


def pareto_front(costs: Sequence[float], errors: Sequence[float]) -> list[int]:
    """Indices of the points no other point dominates (cost <= and error <= with one of them <),
    by increasing cost."""
    order = sorted(range(len(costs)), key=lambda i: (costs[i], errors[i]))
    front: list[int] = []
    best = math.inf
    for i in order:
        if errors[i] < best:
            front.append(i)
            best = errors[i]
    return front


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    """The largest distance between matching points of two signatures (frames x probes x 3)."""
    return float(np.linalg.norm(a - b, axis=-1).max()) if a.size else 0.0


def analyse(spec: StudySpec, variants: Sequence[Variant], records: dict[str, dict]) -> dict[str, Any]:
    """Errors, costs, Pareto fronts and advice from the sweep's records (by variant name)."""
    names = [variant_name(spec.name, v.params) for v in variants]
    ref_name, default_name = names[1], names[0]

    def signature(name: str) -> np.ndarray | None:
        r = records.get(name, {})
        sig = r.get("metrics", {}).get("signature") if r.get("status") == "ok" else None
        return None if sig is None else np.asarray(sig, dtype=np.float64)

    ref_sig, default_sig = signature(ref_name), signature(default_name)
    scale_note = None
    if spec.scale is None:
        scale = None
    elif spec.scale == "reference_peak":
        scale = float(np.linalg.norm(ref_sig, axis=-1).max()) if ref_sig is not None else None
        scale_note = f"{scale:.4g} m" if scale else None
    else:
        scale = float(spec.scale)
    rows = []
    for v, name in zip(variants, names):
        r = records.get(name, {"status": "missing"})
        m = {k: x for k, x in r.get("metrics", {}).items() if k != "signature"}
        row: dict[str, Any] = {"variant": name, "role": v.role, "knob": v.knob, "value": v.value, "params": v.params,
                               "status": r.get("status"), "error": None, "change_vs_default": None,
                               "costs": {k: m.get(k) for k in spec.costs}, "metrics": m,
                               "record": {k: x for k, x in r.items() if k not in ("metrics", "traceback")}}
        if r.get("status") != "ok":
            row["failure"] = (r.get("error") or "not run").splitlines()[0][:300]
        elif spec.scale is None:
            row["error"] = m.get("error")
        else:
            sig = signature(name)
            if ref_sig is not None and scale and sig is not None:
                row["error"] = _distance(sig, ref_sig) / scale if sig.shape == ref_sig.shape else None
            if default_sig is not None and scale and sig is not None and sig.shape == default_sig.shape:
                row["change_vs_default"] = _distance(sig, default_sig) / scale
        rows.append(row)
    # the reference's uncertainty: how far refining it one notch moves it (the reference check's
    # error); 0 where the study measures against the truth; None (unknown) where no check exists
    check_row = next((r for r in rows if r["role"] == "check"), None)
    if spec.exact_reference:
        uncertainty: float | None = 0.0
    elif check_row is not None and check_row["error"] is not None and math.isfinite(check_row["error"]):
        uncertainty = check_row["error"]
    else:
        uncertainty = None
    for row in rows:
        row["resolved"] = None
        if uncertainty is not None and row["role"] in ("default", "knob") and row["error"] is not None:
            row["resolved"] = bool(row["error"] >= RESOLVE * uncertainty)
    # the Pareto front per cost, over the measured settings (the reference is the yardstick, its
    # check measures the yardstick)
    fronts: dict[str, list[str]] = {}
    seen: set[str] = set()
    candidates = []
    special = {ref_name} | ({check_row["variant"]} if check_row is not None else set())
    for row in rows:
        if row["role"] in ("default", "knob") and row["variant"] not in seen and row["variant"] not in special \
                and row["error"] is not None and math.isfinite(row["error"]):
            seen.add(row["variant"])
            candidates.append(row)
    for cost in spec.costs:
        pts = [r for r in candidates if isinstance(r["costs"].get(cost), (int, float))]
        idx = pareto_front([r["costs"][cost] for r in pts], [r["error"] for r in pts])
        fronts[cost] = [pts[i]["variant"] for i in idx]
    for row in rows:
        row["on_front"] = [c for c, f in fronts.items() if row["variant"] in f]
    reference_ok = records.get(ref_name, {}).get("status") == "ok"
    return {"scale": scale, "scale_note": scale_note, "reference_ok": reference_ok,
            "reference_uncertainty": uncertainty, "check_ok": None if check_row is None else check_row["status"] == "ok",
            "variants": rows, "fronts": fronts, "advice": _advice(spec, candidates, uncertainty)}


def _setting(row: dict) -> str:
    return "the default" if row["role"] == "default" else f"{row['knob']}={_fmt_value(row['value'])}"


def _fmt_value(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return repr(v) if isinstance(v, str) else str(v)


def _pct(e: float | None) -> str:
    if e is None:
        return "-"
    if e == 0.0:
        return "0"
    return f"{100.0 * e:.3g} %"


def _advice(spec: StudySpec, candidates: list[dict], uncertainty: float | None = None) -> list[str]:
    """One sentence per target error: the cheapest measured setting (by the first cost) under it;
    none for a target below the reference's uncertainty (the reference cannot tell such errors
    apart), and a setting whose error the reference does not resolve is said to be so."""
    cost = next(iter(spec.costs))
    label = spec.costs[cost]
    priced = [r for r in candidates if isinstance(r["costs"].get(cost), (int, float))]
    if not priced:
        return []
    out = []
    for target in spec.advice_targets:
        if uncertainty is not None and target <= uncertainty:
            out.append(f"Error below {_pct(target)}: the reference cannot resolve it (its uncertainty, the reference "
                       f"check's distance from it, is {_pct(uncertainty)}).")
            continue
        ok = sorted((r for r in priced if r["error"] <= target), key=lambda r: r["costs"][cost])
        if ok:
            best = ok[0]
            caveat = "" if best.get("resolved") is not False else \
                f"; not resolved: below {RESOLVE:g}x the reference's uncertainty ({_pct(uncertainty)})"
            out.append(f"Error below {_pct(target)}: {_setting(best)} is the cheapest measured "
                       f"({_pct(best['error'])}, {best['costs'][cost]:.4g} {label}{caveat}).")
        else:
            low = min(priced, key=lambda r: r["error"])
            out.append(f"Error below {_pct(target)}: no setting measured reaches it (the lowest: {_pct(low['error'])}, "
                       f"{_setting(low)}).")
    if uncertainty is None:
        out.append("The reference's own error is unknown (it has no reference check): the errors are distances "
                   "from it, not from the exact answer.")
    return out


def run_study(name: str, out_dir: str | os.PathLike[str], *, quick: bool = False, device: str | None = None,
              engine: str = "local", address: str | None = None, gpus_per_task: float = 1.0,
              knobs: Sequence[str] | None = None, mode: Mode | None = None,
              log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run one study's variants through the sweep into ``out_dir/<name>/`` and analyse them.
    ``mode`` overrides the study's quick or full grid (tests, custom reports)."""
    say = log or (lambda s: print(s, file=sys.stderr))
    module, spec = load_study(name)
    mode = mode or (spec.quick if quick else spec.full)
    variants = plan(module.build, spec, mode, knobs)
    unique = list({variant_name(spec.name, v.params): v.params for v in variants}.items())
    say(f"wsim study: {name}: {len(unique)} runs ({sum(len(x) for x in mode.grid.values())} knob settings, the default, "
        f"the reference{' and its check' if mode.check else ''}), {mode.frames} frames each")
    runs = Path(out_dir) / name
    records = sweep(module.__file__, [p for _, p in unique], runs, device=device, frames=mode.frames,
                    engine=engine, address=address, gpus_per_task=gpus_per_task, usd=False, warm_full=True, log=lambda s: say(s.replace("wsim sweep:", f"wsim study: {name}:", 1)))
    # the variants' own run times as recorded: a re-run that skips finished variants reports the same
    seconds = sum(float(r.get("wall_s") or 0.0) for r in records)
    result = analyse(spec, variants, {r["variant"]: r for r in records})
    # the settings in full (build's defaults too) of the knobs the study varies or the reference sets
    shown = list(dict.fromkeys([*mode.grid, *mode.reference, *mode.default]))
    full = {**_build_defaults(module.build), **mode.default}
    result["default_settings"] = {k: full[k] for k in shown}
    result["reference_settings"] = {k: {**full, **mode.reference}[k] for k in shown}
    result["reference_check"] = {"settings": dict(mode.check), "note": spec.check_note,
                                 "uncertainty": result["reference_uncertainty"], "exact": spec.exact_reference}
    return {"name": spec.name, "title": spec.title, "scenario": spec.scenario, "error": spec.error, "notes": spec.notes,
            "knobs": spec.knobs, "costs": spec.costs, "frames": mode.frames, "default": mode.default,
            "reference": mode.reference, "check": mode.check, "grid": mode.grid, "seconds": round(seconds, 2), **result}


def run_studies(names: Sequence[str] | None, out_dir: str | os.PathLike[str], *, quick: bool = False,
                device: str | None = None, engine: str = "local", address: str | None = None,
                gpus_per_task: float = 1.0, knobs: Sequence[str] | None = None,
                modes: dict[str, Mode] | None = None, command: str | None = None,
                log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run the studies (all by default) and write ``study.json``, ``study.md`` and a PNG per study
    into ``out_dir``; returns the report. ``knobs`` keeps only those knobs (each must belong to one
    of the studies; studies with none of them are left out); ``modes`` overrides grids by study.
    ``engine``: "local" (default: one variant at a time in this process, so that no timing shares
    the machine with another), "ray" or "auto" (``wsim.sweep``)."""
    say = log or (lambda s: print(s, file=sys.stderr))
    names = list(STUDIES if names is None else names)
    if not names:
        raise InvalidParameter("no study named: give one or more of " + ", ".join(STUDIES))
    for n in names:
        load_study(n)  # an unknown name fails before anything runs
    if engine not in ENGINES:
        raise InvalidParameter(f"study engine {engine!r}: one of {', '.join(ENGINES)}")
    per_study: dict[str, list[str] | None] = {n: None for n in names}
    if knobs is not None:
        grids = {n: (modes or {}).get(n) or (load_study(n)[1].quick if quick else load_study(n)[1].full) for n in names}
        for k in knobs:
            if not any(k in g.grid for g in grids.values()):
                known = sorted({x for g in grids.values() for x in g.grid})
                raise InvalidParameter(f"no study of {', '.join(names)} has a knob {k!r} (their knobs: {', '.join(known)})")
        per_study = {n: [k for k in knobs if k in grids[n].grid] for n in names}
        left = [n for n in names if not per_study[n]]
        if left:
            say(f"wsim study: {', '.join(left)}: none of the knobs asked for, left out")
        names = [n for n in names if per_study[n]]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    studies = {}
    with _one_ray(engine, address):  # one Ray for every study's sweep, not one each
        for n in names:
            studies[n] = run_study(n, out, quick=quick, device=device, engine=engine, address=address,
                                   gpus_per_task=gpus_per_task, knobs=per_study[n], mode=(modes or {}).get(n), log=say)
    report = {"created": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
              "command": command, "quick": quick, "device": _devices(studies), "host": _host(),
              "versions": _versions(), "engine": engine,
              "seconds": round(sum(st["seconds"] for st in studies.values()), 1),
              "studies": studies}
    plots = write_plots(report, out)
    report["plots"] = plots
    _write_text(out / "study.json", json.dumps(report, indent=1, sort_keys=False, default=str))
    _write_text(out / "study.md", markdown(report))
    say(f"wsim study: report in {out / 'study.md'} ({report['seconds']:.0f} s)")
    return report


@contextlib.contextmanager
def _one_ray(engine: str, address: str | None) -> Iterator[None]:
    """Start Ray once around the studies when the sweep would use it (the sweep leaves a running
    Ray alone); stop it after, if started here."""
    started = False
    if engine in ("auto", "ray"):
        try:
            import ray
        except ImportError:
            ray = None  # the sweep says so, or refuses engine "ray"
        if ray is not None and not ray.is_initialized():
            ray.init(address=address, log_to_driver=False)
            started = True
    try:
        yield
    finally:
        if started:
            ray.shutdown()


def _devices(studies: dict[str, dict]) -> list[str]:
    found = {str(row["record"].get("device")) for s in studies.values() for row in s["variants"]
             if row["record"].get("device")}
    return sorted(found)


def _host() -> str:
    return f"{platform.system()} {platform.machine()}, {os.cpu_count()} CPU cores"


def _versions() -> dict[str, str]:
    import warp as wp

    import wsim

    return {"wsim": wsim.__version__, "warp": wp.__version__, "python": platform.python_version()}


def _write_bytes(path: Path, data: bytes) -> None:
    """Atomic: a reader never sees half a report. Readable by all (a report is shared), not
    mkstemp's owner-only mode."""
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=path.suffix, dir=path.parent)
    with os.fdopen(fd, "wb") as fh:
        fh.write(data)
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)


def _write_text(path: Path, text: str) -> None:
    _write_bytes(path, text.encode())


# ------------------------------------------------------------------------------------------------
# the report
# ------------------------------------------------------------------------------------------------
def write_plots(report: dict[str, Any], out: Path) -> dict[str, str]:
    """``study_<name>.png`` per study: error against each cost, the Pareto front drawn as a step
    line. Returns {study: file name}, empty (and says why in the report) without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib import ticker
    except ImportError:
        report["plots_skipped"] = "matplotlib is not installed (pip install 'wsim[preview]'): plots skipped"
        return {}
    files = {}
    for name, s in report["studies"].items():
        rows = [r for r in s["variants"] if r["error"] is not None and math.isfinite(r["error"])
                and r["role"] in ("default", "knob")]
        u = s.get("reference_uncertainty")
        if not rows:
            continue
        costs = list(s["costs"])
        fig, axes = plt.subplots(1, len(costs), figsize=(5.2 * len(costs), 4.2), squeeze=False)
        positive = [r["error"] for r in rows if r["error"] > 0]
        floor = min(positive) / 3.0 if positive else 1e-6  # an error of exactly 0 is drawn at the floor
        knobs = list(s["grid"])
        colours = {k: f"C{i % 10}" for i, k in enumerate(knobs)}
        for ax, cost in zip(axes[0], costs):
            pts = [r for r in rows if isinstance(r["costs"].get(cost), (int, float)) and r["costs"][cost] > 0]
            for r in pts:
                x, y = r["costs"][cost], 100.0 * max(r["error"], floor)
                if r["role"] == "default":
                    ax.plot(x, y, "k*", markersize=12, zorder=3)
                    ax.annotate("default", (x, y), fontsize=7, xytext=(4, -10), textcoords="offset points")
                else:
                    ax.plot(x, y, "o", color=colours[r["knob"]], markersize=6, zorder=2)
                    ax.annotate(f"{r['knob']}={_fmt_value(r['value'])}", (x, y), fontsize=6, xytext=(3, 3),
                                textcoords="offset points")
            front = [next(r for r in pts if r["variant"] == v) for v in s["fronts"].get(cost, [])
                     if any(r["variant"] == v for r in pts)]
            if front:
                xs = [r["costs"][cost] for r in front]
                ys = [100.0 * max(r["error"], floor) for r in front]
                ax.step(xs, ys, where="post", color="0.3", linewidth=1.2, zorder=1)
                ax.plot(xs, ys, "o", markerfacecolor="none", markeredgecolor="k", markersize=10, zorder=4)
            if u:  # errors under this line are not resolved by the reference
                ax.axhline(100.0 * RESOLVE * u, color="0.5", linestyle=":", linewidth=1.0, zorder=0)
            ax.set_xscale("log")
            ax.set_yscale("log")
            for axis in (ax.xaxis, ax.yaxis):  # plain numbers at 1, 2, 5 x 10^k: no crowded minor labels
                axis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
                axis.set_minor_locator(ticker.LogLocator(subs=(2.0, 5.0)))
                axis.set_minor_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
                axis.set_tick_params(which="minor", labelsize=7)
            ax.set_xlabel(s["costs"][cost])
            ax.set_ylabel("error against the reference [%]")
            ax.grid(True, which="both", alpha=0.3)
        handles = [plt.Line2D([], [], marker="o", linestyle="", color=colours[k], label=k) for k in knobs]
        handles += [plt.Line2D([], [], marker="*", linestyle="", color="k", markersize=10, label="default"),
                    plt.Line2D([], [], marker="o", markerfacecolor="none", markeredgecolor="k", color="0.3",
                               markersize=9, label="Pareto front")]
        if u:
            handles.append(plt.Line2D([], [], color="0.5", linestyle=":",
                                      label=f"{RESOLVE:g}x reference uncertainty (below: not resolved)"))
        fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
        fig.suptitle(f"{s['title']} ({'quick' if report['quick'] else 'full'}; {', '.join(report['device'])})",
                     fontsize=9)
        fig.tight_layout(rect=(0.0, 0.07, 1.0, 1.0))
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=110)
        plt.close(fig)
        path = out / f"study_{name}.png"
        _write_bytes(path, buf.getvalue())
        files[name] = path.name
    return files


def _num(v: Any) -> str:
    return "-" if not isinstance(v, (int, float)) else f"{v:.3g}"


def markdown(report: dict[str, Any]) -> str:
    """The Markdown report: how to read it, then per study its table, plot and advice."""
    lines = ["# wsim study report", ""]
    kind = "Quick report (CPU-sized grids)" if report["quick"] else "Full report"
    lines += [f"{kind}, {report['created']}, on {', '.join(report['device']) or 'no device'} "
              f"({report['host']}; wsim {report['versions']['wsim']}, Warp {report['versions']['warp']}); "
              f"{report['seconds']:.0f} s of runs in all, " + _engine_text(report["engine"]) + "."
              + (f" Command: `{report['command']}`." if report.get("command") else ""), ""]
    lines += ["**How to read it.** Each study simulates one scene with several settings of its method's knobs: "
              "the default, a reference (the finest setting the study affords), and each knob varied alone from the "
              "default (one at a time, not every combination). *Error* is how far a setting's result lies from the "
              "reference's (each "
              "study says what it measures and over which length); *vs default* is how far it moved from the "
              "default's, which shows a knob's own effect where the other knobs' error dominates. Costs are "
              "measured per setting: milliseconds per frame (mean over the frames after the first, which binds "
              "the bodies and loads the kernels; probe reads not counted), the bytes of the arrays the bodies hold "
              "(operators, model, grid, state), and where a study says so a one-off cost. The *Pareto front* of a "
              "cost is the settings that no other setting beats on both error and that cost (marked in the table "
              "and drawn as a step line): pick from it. The reference is not exact: the *reference check* refines "
              "it one notch in its dominant discretization (e.g. half its time step), and its distance from the "
              "reference is the reference's *uncertainty*. An error below "
              f"{RESOLVE:g}x the uncertainty is marked *(not resolved)*: the reference cannot tell that setting "
              "from the exact answer or from a setting as close, and no setting is named for a target error "
              "below the uncertainty. One knob at a time does not show how knobs interact.", ""]
    if report.get("plots_skipped"):
        lines += [f"*{report['plots_skipped']}.*", ""]
    for name, s in report["studies"].items():
        lines += [f"## {s['title']}", "", s["scenario"], ""]
        scale = f" ({s['scale_note']})" if s.get("scale_note") else ""
        lines += [f"Error: {s['error']}{scale}. Default: {_params(s['default_settings'])}; reference: "
                  f"{_params(s['reference_settings'])}; {s['frames']} frames; {s['seconds']:.0f} s of runs.", ""]
        lines += [_check_text(s), ""]
        cost_keys = list(s["costs"])
        vs = s.get("scale") is not None  # a signature to compare with the default's
        head = ["setting", "error"] + ["vs default"] * vs + [s["costs"][c] for c in cost_keys] + ["front"]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for r in s["variants"]:
            label = {"reference": "**reference**", "default": "**default**", "check": "**reference check**"}.get(
                r["role"]) or f"`{r['knob']}={_fmt_value(r['value'])}`"
            if r["status"] != "ok":
                cells = [label, f"failed: {r.get('failure', '')[:120]}"] + ["-"] * (vs + len(cost_keys)) + [""]
            else:
                front = ", ".join(s["costs"][c].split(" [")[0].split(",")[0] for c in r["on_front"])
                error = _pct(r["error"]) + {"check": " (uncertainty)"}.get(r["role"], "") + \
                    (" (not resolved)" if r.get("resolved") is False else "")
                cells = [label, error] + [_pct(r["change_vs_default"])] * vs + \
                    [_num(r["costs"].get(c)) for c in cost_keys] + [front]
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
        if name in report.get("plots", {}):
            lines += [f"![{name}]({report['plots'][name]})", ""]
        lines += [f"- {a}" for a in s["advice"]] + [""]
        if s.get("notes"):
            lines += [f"Note: {s['notes']}", ""]
        lines += ["Knobs: " + "; ".join(f"`{k}`: {v}" for k, v in s["knobs"].items() if k in s["grid"]) + ".", ""]
    return "\n".join(lines)


def _check_text(s: dict[str, Any]) -> str:
    """The sentence on the reference's uncertainty under a study's heading."""
    check = s.get("reference_check") or {}
    u, note = check.get("uncertainty"), check.get("note") or ""
    if check.get("exact"):
        return f"Reference check: none needed: {note or 'the error is measured against the truth'}."
    if not check.get("settings"):
        return (f"Reference check: {note or 'none declared'}. The reference's own error is unknown: the errors "
                "below are distances from it, not from the exact answer.")
    what = f"{_params(check['settings'])} over the reference" + (f" ({note})" if note else "")
    if u is None:
        return f"Reference check, {what}: it failed, so the reference's uncertainty is unknown."
    return (f"Reference check, {what}: it moves the reference by {_pct(u)}, the reference's uncertainty; errors "
            f"below {_pct(RESOLVE * u)} are not resolved.")


def _engine_text(engine: str) -> str:
    if engine == "local":
        return "the variants one at a time in one process (after a warm-up run)"
    return (f"engine {engine!r} (Ray, when installed: a fresh process per variant; tasks running side by side on "
            "a CPU share its cores, so their timings are higher than alone)")


def _params(p: dict[str, Any]) -> str:
    return ", ".join(f"`{k}={_fmt_value(v)}`" for k, v in p.items()) or "the build's defaults"
