"""Scene sweeps: every combination of a scene's parameters, one task each (``wsim sweep``).

A scene's ``build(mesh=None, device=None, **params)`` takes its knobs as keywords; a sweep runs the
cartesian product of the values given for each (``--param NAME=V1,V2``), each variant a task that
builds the World, simulates the scene's frames, writes its USD and a JSON line of metrics (wall
time, build and run time, device, memory, the scene's own measures from an optional
``metrics(world) -> dict`` in the scene file) into the output folder, and prints a summary table
at the end.

Engines: Ray (the optional ``cluster`` extra) when it is installed, one GPU a task by default
(``gpus_per_task`` below 1 packs small scenes onto a GPU; CPU tasks where no GPU exists), locally
(``ray.init()``) or on a cluster (``address``); each task runs in a fresh worker process. Without
Ray, or with ``engine="local"``, the variants run one after another in this process, which says
so. Before Ray's tasks start, the first variant's World is built and stepped one frame here, so
Warp's kernels are compiled once into its on-disk cache (shared by the processes of one host;
point ``WARP_CACHE_PATH`` at shared storage on a cluster) instead of once per task.

A variant that raises (or whose metrics do, or whose Ray worker dies) is reported (status
"failed", the error) and the others finish; a variant whose JSON says "ok" for the same
parameters, frames, device and USD output is skipped when the sweep runs again. Results are
written atomically: ``DIR/<variant>.json`` per variant and ``DIR/sweep.jsonl`` (all of them) at
the end.

For other engines on top of this one (``wsim.study``): ``params`` may also be an explicit list of
variants (one dict each) instead of a product, ``usd=False`` simulates without writing USD (the
timing then holds no output), and ``warm_full=True`` makes the warm-up run the first variant's
every frame, unrecorded, before Ray's tasks and before the in-process runner too, then compile
every module its build imported, so that no recorded variant pays for compiling kernels (those
only other variants reach, such as the compression kernels, included).
"""

from __future__ import annotations

import ast
import contextlib
import gc
import hashlib
import inspect
import itertools
import json
import os
import re
import resource
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

from wsim.errors import InvalidParameter
from wsim.progress import PROGRESS_ENV
from wsim.scene import load_scene

ENGINES = ("auto", "local", "ray")
_UNSAFE = re.compile(r"[^A-Za-z0-9_.=+-]+")


def parse_param(text: str) -> tuple[str, list[Any]]:
    """``"NAME=V1,V2,..."`` -> (NAME, [V1, V2, ...]): each value a Python literal where it reads as
    one (``32``, ``0.5``, ``True``, ``'a'``), else the text itself."""
    name, sep, values = text.partition("=")
    name = name.strip()
    if not sep or not name.isidentifier() or not values.strip():
        raise InvalidParameter(f"sweep parameter {text!r}: expected NAME=V1,V2,... (a keyword of the scene's build)")
    out = []
    for raw in values.split(","):
        raw = raw.strip()
        try:
            out.append(ast.literal_eval(raw))
        except (ValueError, SyntaxError):
            out.append(raw)
    return name, out


def variants(params: dict[str, Sequence[Any]]) -> list[dict[str, Any]]:
    """The cartesian product of the parameters' values, in the order given (the last varies fastest)."""
    names = list(params)
    return [dict(zip(names, combo)) for combo in itertools.product(*(params[n] for n in names))]


def variant_name(scene: str, params: dict[str, Any]) -> str:
    """A file-safe, stable name: ``scene__a=1__b=0.5`` (the scene's name alone without parameters)."""
    parts = [scene] + [f"{k}={v}" for k, v in params.items()]
    name = "__".join(_UNSAFE.sub("_", str(p)) for p in parts)
    if len(name) > 150:  # file-name limits: a long list of values keeps a prefix and a digest of the rest
        name = name[:130] + "__" + hashlib.sha256(name.encode()).hexdigest()[:16]
    return name


def check_params(build: Callable[..., Any], scene: str, names: Sequence[str]) -> None:
    """Every swept name must be a keyword of ``build`` (unless it takes ``**kwargs``)."""
    for n in names:
        if n in ("mesh", "device"):
            raise InvalidParameter(f"scene '{scene}': {n!r} is set by the sweep, not swept (--device, the scene's own mesh)")
    sig = inspect.signature(build)
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in sig.parameters.values()):
        return
    knobs = [n for n, p in sig.parameters.items() if n not in ("mesh", "device")
             and p.kind in (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)]
    for n in names:
        if n not in knobs:
            raise InvalidParameter(f"scene '{scene}': build() has no parameter {n!r} to sweep "
                                   f"(its parameters: {', '.join(knobs) or 'none besides mesh and device'})")


@contextlib.contextmanager
def _no_progress() -> Iterator[None]:
    """No progress bars from a scene's build (BEM operators) while it runs, the setting restored after."""
    before = os.environ.get(PROGRESS_ENV)
    os.environ[PROGRESS_ENV] = "0"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(PROGRESS_ENV, None)
        else:
            os.environ[PROGRESS_ENV] = before


def _write_json(path: Path, record: dict) -> None:
    """Atomic: a killed sweep never leaves half a file that a re-run would take as done."""
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".json", dir=path.parent)
    with os.fdopen(fd, "w") as fh:
        json.dump(record, fh, sort_keys=True, default=str)
    os.replace(tmp, path)


def run_variant(scene_path: str, params: dict[str, Any], out_dir: str, device: str | None = None,
                frames: int | None = None, usd: bool = True) -> dict:
    """Build, simulate and write one variant; returns (and writes) its metrics record. Never raises
    for a failure of the scene: the record says "failed" with the error. ``usd=False``: no USD file
    (the record's ``usd`` is None)."""
    t_enter = time.perf_counter()
    import warp as wp

    from wsim.device import quiet_warp

    quiet_warp()
    build, default_frames, scene, metrics = load_scene(scene_path)
    name = variant_name(scene, params)
    out = Path(out_dir)
    n = frames if frames is not None else default_frames
    # what a re-run compares before it skips this variant (``_finished_record``)
    record: dict[str, Any] = {"variant": name, "scene": scene, "params": params, "status": "failed",
                              "frames": n, "device_requested": device}
    t0 = time.perf_counter()
    # imports and the scene file: what a fresh Ray worker pays before the build
    record["startup_s"] = round(t0 - t_enter, 4)
    try:
        with _no_progress():
            world = build(mesh=None, device=device, **params)
        t1 = time.perf_counter()
        world.run(n, out / f"{name}.usdc" if usd else None, progress=False)
        t2 = time.perf_counter()
        measures = None if metrics is None else json.loads(json.dumps(metrics(world), default=str))
        dev = world.device
        record.update(build_s=round(t1 - t0, 4), run_s=round(t2 - t1, 4),
                      ms_per_frame=round(1e3 * (t2 - t1) / max(n, 1), 3), usd=str(out / f"{name}.usdc") if usd else None,
                      device=dev.name if dev.is_cuda else "cpu",
                      # high-water marks of the process: per variant in a Ray task, cumulative in-process
                      device_mem_high_mb=round(wp.get_mempool_used_mem_high(dev) / 2**20, 1) if dev.is_cuda else None)
        if measures is not None:
            record["metrics"] = measures
        record["status"] = "ok"  # only once everything above, the scene's own metrics too, went through
    except Exception as exc:  # a variant's failure is data, not the sweep's end
        record.update(status="failed", error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc(limit=6))
    record["wall_s"] = round(time.perf_counter() - t0, 4)
    world = None  # (as after the warm-up: the next in-process variant starts from nothing of this one's)
    gc.collect()
    record["host_rss_high_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    try:
        _write_json(out / f"{name}.json", record)
    except (OSError, TypeError, ValueError) as exc:  # e.g. parameters JSON cannot hold: reported, not raised
        record = {k: record[k] for k in ("variant", "scene", "frames", "device_requested", "wall_s")}
        record.update(status="failed", params={k: repr(v) for k, v in params.items()},
                      error=f"the record could not be written: {type(exc).__name__}: {exc}")
    return record


def _finished_record(out: Path, name: str, params: dict[str, Any], frames: int, device: str | None,
          usd: bool = True) -> dict | None:
    """The variant's record if a finished run of the same parameters, frames, device and USD
    output (written or not) is on disk."""
    try:
        record = json.loads((out / f"{name}.json").read_text())
    except (OSError, ValueError):
        return None
    same = (record.get("params") == json.loads(json.dumps(params, default=str)) and record.get("frames") == frames
            and record.get("device_requested") == device and bool(record.get("usd")) == usd)
    return record if record.get("status") == "ok" and same else None


def warm_kernels(scene_path: str, params: dict[str, Any], device: str | None, frames: int = 1, load_all: bool = True) -> float:
    """Compile the scene's kernels once (Warp's on-disk cache) by building the first variant,
    stepping it ``frames`` frames and (``load_all``) then compiling every Warp module its build
    imported; returns the seconds it took."""
    import warp as wp

    from wsim.device import quiet_warp

    quiet_warp()
    build, _, _, _ = load_scene(scene_path)
    t = time.perf_counter()
    try:
        with _no_progress():
            world = build(mesh=None, device=device, **params)
            world.run(frames, None, progress=False)
        # kernels a scene reaches only later (contact, once bodies touch) too: one frame left them
        # to the first task, which compiled them for 32 s on an H200 while the others waited on
        # the cache (tools/results/bench_sweep_h200x2_first.jsonl)
        if load_all:
            wp.force_load(device=world.device)
    except Exception:  # the variant's own run reports it
        pass
    # collected now, not when the cycle collector next runs: the next variant in this process
    # must not find this one's device copies (shared by content: ``stepper.step_operators``)
    world = None
    gc.collect()
    return time.perf_counter() - t


def _ray_run(todo: list[dict[str, Any]], scene_path: str, out_dir: str, device: str | None, frames: int | None,
             address: str | None, gpus_per_task: float, usd: bool = True) -> list[dict]:
    import ray

    started = not ray.is_initialized()
    if started:
        ray.init(address=address, log_to_driver=False)
    try:
        return _ray_tasks(ray, todo, scene_path, out_dir, device, frames, gpus_per_task, usd)
    finally:
        if started:  # a Ray this sweep started is not left running
            ray.shutdown()


def _ray_tasks(ray: Any, todo: list[dict[str, Any]], scene_path: str, out_dir: str, device: str | None,
               frames: int | None, gpus_per_task: float, usd: bool = True) -> list[dict]:
    gpus = ray.cluster_resources().get("GPU", 0.0)
    want_gpu = gpus > 0 and device not in ("cpu",)
    options = {"num_gpus": gpus_per_task, "num_cpus": 1} if want_gpu else {"num_cpus": 1}
    # a fresh worker process per task, not retried: a variant that kills its worker (a crash, out
    # of memory) would do it again
    task = ray.remote(max_calls=1, max_retries=0)(run_variant).options(**options)
    # Ray gives each GPU task its own CUDA_VISIBLE_DEVICES: inside, the GPU is cuda:0
    task_device = "cuda:0" if want_gpu else "cpu"
    refs = [task.remote(scene_path, p, out_dir, task_device, frames, usd) for p in todo]
    records = []
    for p, ref in zip(todo, refs):
        try:
            records.append(ray.get(ref))
        except Exception as exc:  # the worker died: the variant failed, the others go on
            records.append({"variant": variant_name(Path(scene_path).stem, p), "params": p, "status": "failed",
                            "error": f"its worker died: {type(exc).__name__}: {exc}"[:2000]})
    return records


def sweep(scene_path: str, params: dict[str, Sequence[Any]] | Sequence[dict[str, Any]], out_dir: str | os.PathLike[str],
          *, device: str | None = None, frames: int | None = None, engine: str = "auto", address: str | None = None,
          gpus_per_task: float = 1.0, warm: bool = True, log: Callable[[str], None] | None = None,
          usd: bool = True, warm_full: bool = False) -> list[dict]:
    """Run every variant of ``params`` (NAME -> values: their cartesian product; or a list of
    variants, one dict of parameters each) of the scene file; returns the records (skipped
    variants' from their JSON), also written to ``out_dir/sweep.jsonl``.

    ``usd=False`` writes no USD. ``warm_full`` (with ``warm``): the warm-up runs the first
    pending variant for all its frames, unrecorded, before the in-process runner too, so that
    the recorded variants' timings hold no kernel compilation (a Ray task's fresh process then
    only loads the compiled kernels from the cache)."""
    say = log or (lambda s: print(s, file=sys.stderr))
    if engine not in ENGINES:
        raise InvalidParameter(f"sweep engine {engine!r}: one of {', '.join(ENGINES)}")
    if not gpus_per_task > 0:
        raise InvalidParameter(f"gpus_per_task = {gpus_per_task}: must be > 0 (e.g. 0.25 for four small scenes a GPU)")
    build, default_frames, scene, _ = load_scene(scene_path)
    if isinstance(params, dict):
        allv, swept = variants(dict(params)), list(params)
    else:
        if not all(isinstance(p, dict) for p in params):
            raise InvalidParameter(f"scene '{scene}': a list of variants must hold one dict of parameters each")
        allv = [dict(p) for p in params]
        swept = list(dict.fromkeys(n for p in allv for n in p))
    check_params(build, scene, swept)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = [variant_name(scene, p) for p in allv]
    if len(set(names)) != len(names):
        raise InvalidParameter(f"scene '{scene}': two variants would share a file name; give distinct values")
    n_frames = frames if frames is not None else default_frames
    done = {n: r for n, r in ((n, _finished_record(out, n, p, n_frames, device, usd)) for n, p in zip(names, allv)) if r is not None}
    todo = [p for p, n in zip(allv, names) if n not in done]
    if done:
        say(f"wsim sweep: {len(done)} of {len(allv)} variants already done in {out}, skipped")
    use_ray = False
    if todo and engine in ("auto", "ray"):
        try:
            import ray  # noqa: F401
            use_ray = True
        except ImportError:
            if engine == "ray":
                raise InvalidParameter("engine 'ray' needs Ray: pip install 'wsim[cluster]'") from None
            say("wsim sweep: Ray is not installed (pip install 'wsim[cluster]'): running the variants one "
                "after another in this process")
    scene_abs = str(Path(scene_path).resolve())
    fresh: dict[str, dict] = {}
    if todo:
        if warm and use_ray:  # in-process, the first variant compiles them for the rest
            secs = warm_kernels(scene_abs, todo[0], device, n_frames if warm_full else 1)
            say(f"wsim sweep: compiling the scene's kernels once ({secs:.1f} s)")
        elif warm and warm_full:  # the whole run, then every module its build imported (``warm_kernels``)
            say(f"wsim sweep: a warm-up run of {variant_name(scene, todo[0])} and every Warp module its build "
                f"imported ({warm_kernels(scene_abs, todo[0], device, n_frames):.1f} s, not recorded)")
        t = time.perf_counter()
        if use_ray:
            records = _ray_run(todo, scene_abs, str(out.resolve()), device, frames, address, gpus_per_task, usd)
        else:
            records = []
            for i, p in enumerate(todo):
                say(f"wsim sweep: [{i + 1}/{len(todo)}] {variant_name(scene, p)}")
                records.append(run_variant(scene_abs, p, str(out), device, frames, usd))
        say(f"wsim sweep: {len(todo)} variants in {time.perf_counter() - t:.1f} s ({'Ray' if use_ray else 'in-process'})")
        fresh = {r["variant"]: r for r in records}
    results = [fresh.get(n) or done[n] for n in names]
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".jsonl", dir=out)
    with os.fdopen(fd, "w") as fh:
        for r in results:
            fh.write(json.dumps(r, sort_keys=True, default=str) + "\n")
    os.replace(tmp, out / "sweep.jsonl")
    return results


def summary_table(records: Sequence[dict]) -> str:
    """A plain-text table: one row per variant (status, ms per frame, wall time, device, error)."""
    rows = [("variant", "status", "ms/frame", "wall s", "device", "error")]
    for r in records:
        rows.append((r["variant"], r["status"], str(r.get("ms_per_frame", "")), str(r.get("wall_s", "")),
                     str(r.get("device", "")), (r.get("error") or "")[:60]))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in rows)
