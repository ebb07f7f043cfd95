"""Command line: ``wsim run SCENE.py -o OUT.usdc``, ``wsim recover OUT.usdc``, ``wsim info``,
``wsim sweep SCENE.py --param NAME=V1,V2 -o DIR`` (``wsim.sweep``) and ``wsim study [--quick] -o DIR``
(``wsim.study``).

A scene is a plain Python file that defines ``build(mesh=None, device=None) -> wsim.World`` and,
optionally, ``FRAMES`` (its default frame count). It can also run standalone:
``python scenes/NAME.py -o out.usda`` through ``scene_main``, which takes the same options.

Long runs: ``--checkpoint-every N`` saves the World's state every N frames (to ``--checkpoint``,
default ``OUT.ckpt.h5``); ``--resume CKPT`` rebuilds the scene, restores the checkpoint and
continues up to ``--frames`` (the animation's last frame, as in the first run). The resumed
frames are appended to OUT when OUT is the file that run wrote (same prims and topology), so one
file holds the whole animation, with frames after the checkpoint replaced; when OUT is missing or
holds something else, a new file starts at the checkpoint's frame. Checkpoints keep being saved
to the resumed file unless ``--checkpoint`` names another.

A run killed outright (SIGKILL, out of memory) leaves its frames in ``OUT.journal``;
``wsim recover OUT`` writes them to OUT (``wsim.usd``).
"""

from __future__ import annotations

import argparse
import os
import platform
import signal
import sys
from pathlib import Path
from typing import Callable, Sequence

from wsim.errors import WsimError
from wsim.scene import DEFAULT_FRAMES



def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--out", help="output USD file: .usdc or .usd binary, .usda text (default: <scene>.usdc)")
    p.add_argument("--frames", type=int, default=None, help="frames to simulate (default: the scene's FRAMES)")
    p.add_argument("--device", default=None, help="cpu, cuda, cuda:N (default: cuda:0 if present, else cpu)")
    p.add_argument("--up-axis", default=None, choices=["Y", "Z", "y", "z"], help="up axis of the USD stage (Z for Blender)")
    p.add_argument("--mesh", default=None, help="path of a mesh file to use instead of the scene's procedural shape")
    p.add_argument("--mesh-scale", type=float, default=None, metavar="S",
                   help="use --mesh in its own units times S (default: fitted to the scene's size)")
    p.add_argument("--start-frame", type=int, default=0, metavar="K", help="USD time code of the first frame (e.g. 1001)")
    p.add_argument("--no-progress", action="store_true", help="hide every progress bar (frames, BEM operators)")
    p.add_argument("--verbose", action="store_true", help="show Warp's own output (banner, module loads, CUDA probe)")
    p.add_argument("--checkpoint", default=None, help="checkpoint file to save (default with --checkpoint-every: OUT.ckpt.h5)")
    p.add_argument("--checkpoint-every", type=int, default=0, metavar="N", help="save a checkpoint every N frames (and at the end)")
    p.add_argument("--resume", default=None, metavar="CKPT", help="continue from a checkpoint of this scene up to --frames")


def _run(build: Callable[..., object], frames_default: int, name: str, args: argparse.Namespace) -> int:
    import logging

    from wsim.device import compile_notice
    from wsim.mesh.surface import MESH_SCALE_ENV
    from wsim.progress import PROGRESS_ENV
    from wsim.world import World

    out = args.out or f"{name}.usdc"
    before = _mtime(out)

    terminated = []

    def on_sigterm(signum: int, frame: object) -> None:
        terminated.append(signum)
        raise KeyboardInterrupt  # unwinds through World.run, which saves the frames so far

    signal.signal(signal.SIGTERM, on_sigterm)
    if args.no_progress:  # for the scene's own bars too (wsim.progress)
        os.environ[PROGRESS_ENV] = "0"
    if args.mesh_scale is not None:  # read by the scene's wsim.mesh.load_fitted
        if not args.mesh_scale > 0:
            print(f"wsim: --mesh-scale = {args.mesh_scale} must be > 0", file=sys.stderr)
            return 2
        os.environ[MESH_SCALE_ENV] = repr(args.mesh_scale)
    log = logging.getLogger("wsim")  # library notes (how a --mesh model was placed) as "wsim: ..." lines
    if not log.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("wsim: %(message)s"))
        log.addHandler(handler)
        log.setLevel(logging.INFO)
    try:
        with compile_notice():
            world = build(mesh=args.mesh, device=args.device)
        if not isinstance(world, World):
            print(f"wsim: scene '{name}': build() must return a wsim.World, got {type(world).__name__}", file=sys.stderr)
            return 2
        frames = args.frames if args.frames is not None else frames_default
        if args.checkpoint_every < 0:
            print(f"wsim: --checkpoint-every = {args.checkpoint_every} must be >= 0", file=sys.stderr)
            return 2
        checkpoint = args.checkpoint
        if checkpoint is None and args.checkpoint_every:
            checkpoint = f"{Path(out).with_suffix('')}.ckpt.h5"
        if args.resume is not None:
            start = world.restore(args.resume)
            checkpoint = checkpoint or args.resume
            if frames <= start:
                print(f"wsim: checkpoint '{args.resume}' is at frame {start}; nothing to do up to frame {frames}",
                      file=sys.stderr)
                return 0
            frames -= start
        with compile_notice():
            summary = world.run(frames, out, up_axis=args.up_axis.upper() if args.up_axis else None,
                                progress=not args.no_progress, append=args.resume is not None,
                                checkpoint=checkpoint, checkpoint_every=args.checkpoint_every,
                                start_frame=args.start_frame)
        if args.resume is not None:
            how = "appended to" if summary.appended else "written as a new file (no earlier output of this scene) to"
            resumed = f"wsim: resumed at frame {start}; frames {start}..{world.frame} {how} {summary.out}"
    except (WsimError, KeyboardInterrupt) as exc:
        reason = "interrupted" if isinstance(exc, KeyboardInterrupt) else f"error: {exc}"
        print(f"wsim: {reason}", file=sys.stderr)
        if _mtime(out) != before:  # this run wrote it
            print(f"wsim: frames computed before that are in {out}", file=sys.stderr)
        return 1 if isinstance(exc, WsimError) else 128 + (terminated[0] if terminated else signal.SIGINT)
    print(summary)
    if args.resume is not None:
        print(resumed)
    return 0


def _mtime(path: str) -> int | None:
    try:
        return os.stat(path).st_mtime_ns
    except OSError:
        return None


def _load_scene(path: str) -> tuple[Callable[..., object], int, str]:
    from wsim.scene import load_scene

    try:
        build, frames, name, _ = load_scene(path)
    except WsimError as exc:
        raise SystemExit(f"wsim: error: {exc}") from None
    return build, frames, name


def _sweep(args: argparse.Namespace) -> int:
    from wsim.errors import InvalidParameter
    from wsim.sweep import parse_param, summary_table, sweep

    try:
        pairs = [parse_param(p) for p in args.param]
        names = [n for n, _ in pairs]
        if len(set(names)) != len(names):
            raise InvalidParameter(f"--param names one parameter twice ({', '.join(sorted({n for n in names if names.count(n) > 1}))}): "
                                   "give all its values in one --param NAME=V1,V2")
        params = dict(pairs)
        records = sweep(args.scene, params, args.out, device=args.device, frames=args.frames, engine=args.engine,
                        address=args.address, gpus_per_task=args.gpus_per_task)
    except WsimError as exc:
        print(f"wsim: error: {exc}", file=sys.stderr)
        return 2
    print(summary_table(records))
    failed = sum(r["status"] != "ok" for r in records)
    if failed:
        print(f"wsim sweep: {failed} of {len(records)} variants failed (their errors: {args.out}/<variant>.json)",
              file=sys.stderr)
    return 1 if failed else 0


def _study(args: argparse.Namespace, argv: Sequence[str]) -> int:
    """``wsim study``: the knob studies through the sweep engine, one report (``wsim.study``)."""
    import shlex

    from wsim.study import run_studies

    names = None if args.studies is None else [n.strip() for n in args.studies.split(",") if n.strip()]
    knobs = None if args.knobs is None else [k.strip() for k in args.knobs.split(",") if k.strip()]
    command = "wsim " + " ".join(shlex.quote(a) for a in argv)  # recorded in the report
    try:
        engine = args.engine or ("ray" if args.address else "local")
        report = run_studies(names, args.out, quick=args.quick, device=args.device, engine=engine,
                             address=args.address, gpus_per_task=args.gpus_per_task, knobs=knobs, command=command)
    except WsimError as exc:
        print(f"wsim: error: {exc}", file=sys.stderr)
        return 2
    print(f"wsim study: {Path(args.out) / 'study.md'}, {Path(args.out) / 'study.json'}"
          + ("" if report.get("plots") else " (no plots: " + report.get("plots_skipped", "no results") + ")"))
    failed = [n for n, s in report["studies"].items() if not s["reference_ok"]]
    if failed:
        print(f"wsim study: the reference of {', '.join(failed)} failed: no errors for them (see the report)",
              file=sys.stderr)
    return 1 if failed else 0


def info() -> str:
    import warp as wp

    import wsim
    from wsim.cache import cache_entries, default_cache_dir
    from wsim.device import available_devices, quiet_warp

    quiet_warp()
    lines = [
        f"wsim {wsim.__version__}",
        f"warp {wp.__version__}",
        f"python {platform.python_version()} on {platform.system()} {platform.machine()}",
        f"devices: {', '.join(available_devices())}",
        f"cache: {default_cache_dir()}",
    ]
    entries = cache_entries()
    lines.append(f"cache size: {_entries(len(entries))}, {_mb(sum(e.size for e in entries))} (cap {_cap_text()})")
    return "\n".join(lines)


def _entries(n: int) -> str:
    return f"{n} entr{'y' if n == 1 else 'ies'}"


def _mb(nbytes: int) -> str:
    return f"{nbytes / 1e6:.1f} MB"


def _cap_text() -> str:
    from wsim.cache import cache_cap

    cap, source = cache_cap(warn=False)
    return f"none ({source})" if cap is None else f"{cap / 1e9:g} GB ({source})"


def _cache(args: argparse.Namespace) -> int:
    """``wsim cache list|info|clear``: the operator cache folder (``wsim.cache``)."""
    from datetime import datetime

    from wsim.cache import cache_entries, clear_cache, default_cache_dir

    folder = default_cache_dir()
    if args.cache_command == "clear":
        if args.older_than is not None and not args.older_than >= 0:
            print(f"wsim: --older-than = {args.older_than} must be >= 0 (days)", file=sys.stderr)
            return 2
        if args.kind is not None and not any(e.kind == args.kind for e in cache_entries(folder)):
            kinds = sorted({e.kind for e in cache_entries(folder)})
            print(f"wsim: no entries of kind '{args.kind}' in {folder}" + (f" (kinds: {', '.join(kinds)})" if kinds else ""))
            return 0
        done = clear_cache(folder, kind=args.kind, older_than_days=args.older_than)
        msg = f"wsim: removed {_entries(done.removed)} from {folder}, freed {_mb(done.freed)} ({done.freed} bytes)"
        if done.skipped:
            msg += f"; {done.skipped} could not be deleted"
        print(msg)
        return 0
    entries = cache_entries(folder)
    total = sum(e.size for e in entries)
    if args.cache_command == "info":
        print(f"folder: {folder}" + ("" if folder.is_dir() else " (does not exist yet)"))
        print(f"entries: {len(entries)}")
        print(f"total size: {_mb(total)} ({total} bytes)")
        print(f"cap: {_cap_text()}")
        return 0
    # list: least recently used first, i.e. in the order the size cap evicts them
    width = max([len("kind")] + [len(e.kind) for e in entries])
    print(f"# {folder}: least recently used first (evicted first)")
    print(f"{'kind':<{width}}  {'key':<16}  {'size MB':>9}  last used")
    for e in entries:
        used = datetime.fromtimestamp(e.last_used).strftime("%Y-%m-%d %H:%M")
        print(f"{e.kind:<{width}}  {e.key_prefix[:16]}  {e.size / 1e6:>9.1f}  {used}")
    print(f"total: {_entries(len(entries))}, {_mb(total)} ({total} bytes)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="wsim", description="wsim: physics simulation exported as animated USD")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run a scene script and write USD")
    run.add_argument("scene", help="path of a scene script (defines build(mesh=None, device=None))")
    _add_run_options(run)
    rec = sub.add_parser("recover", help="write the frames of a killed run (OUT.journal) to its USD file")
    rec.add_argument("out", help="the killed run's output file (its journal is OUT.journal)")
    rec.add_argument("-o", "--to", default=None, help="write them here instead of OUT")
    sub.add_parser("info", help="print versions, devices and the cache folder")
    swp = sub.add_parser("sweep", help="run every combination of a scene's parameters (one task each; Ray if installed)")
    swp.add_argument("scene", help="path of a scene script (build(mesh=None, device=None, **params))")
    swp.add_argument("--param", action="append", default=[], metavar="NAME=V1,V2,...",
                     help="a keyword of the scene's build and its values (repeat for more)")
    swp.add_argument("-o", "--out", required=True, help="output folder: a USD file and a JSON line per variant")
    swp.add_argument("--device", default=None, help="device of the in-process runner (Ray tasks get their own GPU, or the CPU)")
    swp.add_argument("--frames", type=int, default=None, help="frames per variant (default: the scene's FRAMES)")
    swp.add_argument("--engine", default="auto", choices=["auto", "local", "ray"],
                     help="auto: Ray if installed, else one after another in this process")
    swp.add_argument("--address", default=None, help="a Ray cluster's address (default: a local Ray)")
    swp.add_argument("--gpus-per-task", type=float, default=1.0, help="GPUs a Ray task takes (0.25: four small scenes a GPU)")
    sty = sub.add_parser("study", help="speed/accuracy report of every method's knobs (through the sweep engine)")
    sty.add_argument("-o", "--out", default="wsim_study", help="report folder: study.md, study.json, PNGs, runs (default: wsim_study)")
    sty.add_argument("--quick", action="store_true", help="CPU-sized grids (minutes); without it the full grids, for a GPU")
    sty.add_argument("--studies", default=None, metavar="NAME,...", help="bem, eol, pbd, pde, coupling (default: all)")
    sty.add_argument("--knobs", default=None, metavar="KNOB,...", help="only these knobs (e.g. dt,compression)")
    sty.add_argument("--device", default=None, help="device of the in-process runner (default: cuda:0 if present, else cpu)")
    sty.add_argument("--engine", default=None, choices=["auto", "local", "ray"],
                     help="local (default): one after another in this process, so no timing shares the machine; "
                          "ray: a task per variant (one GPU each; on a CPU one core each); auto: Ray if installed")
    sty.add_argument("--address", default=None, help="a Ray cluster's address (implies --engine ray)")
    sty.add_argument("--gpus-per-task", type=float, default=1.0, help="GPUs a Ray task takes")
    pre = sub.add_parser("preview", help="render a quick-look of a USD output (.png contact sheet, .gif, .mp4); no display or GPU needed")
    pre.add_argument("usd", help="a USD file written by wsim (any stage with meshes under /World)")
    pre.add_argument("-o", "--out", default=None, help="output .png (contact sheet), .gif or .mp4 (needs ffmpeg) (default: <usd>.png)")
    pre.add_argument("--frames", type=int, default=None, metavar="N", help="tiles of a .png (default 6) or most frames of an animation (default all, up to 150)")
    pre.add_argument("--size", default=None, metavar="WxH", help="output size in pixels (default 1200x600 .png, 640x400 .gif, 960x540 .mp4)")
    pre.add_argument("--fps", type=float, default=None, help="playback rate of a .gif/.mp4 (default: real time)")
    cache = sub.add_parser("cache", help="list, size up or clear the operator cache (cap: $WSIM_CACHE_MAX_GB)")
    cache_sub = cache.add_subparsers(dest="cache_command", required=True)
    cache_sub.add_parser("list", help="one line per entry, least recently used (next evicted) first, and the total")
    cache_sub.add_parser("info", help="folder, entry count, total size and the size cap")
    clear = cache_sub.add_parser("clear", help="delete entries (all, or as filtered) and print the space freed")
    clear.add_argument("--kind", default=None, help="only entries of this kind (e.g. bem_operators)")
    clear.add_argument("--older-than", type=float, default=None, metavar="DAYS",
                       help="only entries last used more than DAYS days ago")
    args = parser.parse_args(argv)
    if args.command == "info":
        print(info())
        return 0
    if args.command == "preview":
        from wsim.preview import render

        try:
            print(render(args.usd, args.out or str(Path(args.usd).with_suffix(".png")), args.frames, args.size, args.fps))
        except WsimError as exc:
            print(f"wsim: error: {exc}", file=sys.stderr)
            return 1
        return 0
    if args.command == "cache":
        return _cache(args)
    if args.command == "sweep":
        from wsim.device import quiet_warp

        quiet_warp()
        return _sweep(args)
    if args.command == "study":
        from wsim.device import quiet_warp

        quiet_warp()
        return _study(args, sys.argv[1:] if argv is None else argv)
    if args.command == "recover":
        from wsim.usd import recover

        try:
            path, frames = recover(args.out, args.to)
        except WsimError as exc:
            print(f"wsim: error: {exc}", file=sys.stderr)
            return 1
        print(f"wsim: {frames} frames recovered into {path}")
        return 0
    from wsim.device import VERBOSE_ENV, quiet_warp

    if args.verbose:
        os.environ[VERBOSE_ENV] = "1"
    quiet_warp()
    build, frames, name = _load_scene(args.scene)
    return _run(build, frames, name, args)


def scene_main(build: Callable[..., object], frames: int = DEFAULT_FRAMES, name: str | None = None) -> None:
    """Entry point of a scene script run standalone: ``python scenes/NAME.py [-o OUT] [--frames N] ...``."""
    from wsim.device import VERBOSE_ENV, quiet_warp

    scene = name or Path(sys.argv[0]).stem
    parser = argparse.ArgumentParser(prog=scene, description=f"run the wsim scene '{scene}'")
    _add_run_options(parser)
    args = parser.parse_args()
    if args.verbose:
        os.environ[VERBOSE_ENV] = "1"
    quiet_warp()
    raise SystemExit(_run(build, frames, scene, args))
