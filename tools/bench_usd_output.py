"""What crash-safe USD output costs (issue 19): per frame, the journal's record (``wsim.usd``)
against authoring the frame in the in-memory stage, which every run pays; at the end, writing the
file (.usda text against .usdc binary) and its size; and ``wsim recover`` from the journal.

    python tools/bench_usd_output.py [--vertices 10000,100000] [--frames 100] [--dir /tmp]

Bodies are synthetic (a sphere-like cloud of points moving each frame, triangles from a grid), so
the numbers are the writer's alone. Prints one JSON line per (vertices, format).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from wsim import usd


class _Body:
    def __init__(self, n: int, seed: int = 0) -> None:
        self.name = "body"
        side = int(np.ceil(np.sqrt(n)))
        self._p = np.random.default_rng(seed).standard_normal((side * side, 3))
        i, j = np.meshgrid(np.arange(side - 1), np.arange(side - 1), indexing="ij")
        a = (i * side + j).ravel()
        self.faces = np.concatenate([np.stack([a, a + 1, a + side], 1), np.stack([a + 1, a + side + 1, a + side], 1)])
        self.t = 0.0

    def points(self) -> np.ndarray:
        return self._p + self.t


class _Surfaces:
    colliders: list = []


def run(n: int, frames: int, ext: str, folder: Path, journal: bool) -> dict:
    body = _Body(n)
    out = folder / f"bench_{n}{ext}"
    w = usd.UsdWriter(out, fps=30)
    if not journal:  # the writer as before the journal: the stage in memory only
        w._start_journal = lambda: None
    w.begin([body], _Surfaces())
    if not journal:
        w._journal = type("NoJournal", (), {"append": lambda *a: None, "close": lambda *a, **k: None,
                                            "frames": 0, "last": None, "path": None})()
    t_frames = 0.0
    for k in range(frames):
        body.t = 0.01 * k
        t = time.perf_counter()
        w.write_frame(k, k / 30)
        t_frames += time.perf_counter() - t
    t = time.perf_counter()
    w.close()
    t_close = time.perf_counter() - t
    res = {"write_frame_ms": 1e3 * t_frames / frames, "close_s": t_close, "file_mb": out.stat().st_size / 1e6}
    out.unlink()
    return res


def recover_cost(n: int, frames: int, ext: str, folder: Path) -> dict:
    body = _Body(n)
    out = folder / f"rec_{n}{ext}"
    w = usd.UsdWriter(out, fps=30)
    w.begin([body], _Surfaces())
    for k in range(frames):
        body.t = 0.01 * k
        w.write_frame(k, k / 30)
    w._journal._fh.close()  # killed: the journal stays, no file
    size = usd.journal_path(out).stat().st_size / 1e6
    t = time.perf_counter()
    _, got = usd.recover(out)
    res = {"journal_mb": size, "recover_s": time.perf_counter() - t, "recovered_frames": got}
    out.unlink()
    return res


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--vertices", default="10000,100000")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--dir", default=None, help="folder to write in (default: a temporary one)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        folder = Path(tmp)
        for n in [int(v) for v in args.vertices.split(",")]:
            for ext in (".usdc", ".usda"):
                with_j = run(n, args.frames, ext, folder, journal=True)
                without = run(n, args.frames, ext, folder, journal=False)
                print(json.dumps({
                    "vertices": n, "frames": args.frames, "format": ext, "host": platform.processor() or platform.machine(),
                    "cpus": os.cpu_count(),
                    "write_frame_ms": round(with_j["write_frame_ms"], 3),
                    "write_frame_ms_without_journal": round(without["write_frame_ms"], 3),
                    "close_s": round(with_j["close_s"], 3), "file_mb": round(with_j["file_mb"], 2),
                    **{k: round(v, 3) if isinstance(v, float) else v for k, v in recover_cost(n, args.frames, ext, folder).items()},
                }), flush=True)


if __name__ == "__main__":
    main()
