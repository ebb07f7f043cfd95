"""Scene files: a Python file defining ``build(mesh=None, device=None, **params) -> wsim.World`` and,
optionally, ``FRAMES`` (its default frame count) and ``metrics(world) -> dict`` (its own measures,
recorded by ``wsim sweep``). Loaded here for ``wsim run`` (``wsim.cli``) and ``wsim sweep``
(``wsim.sweep``)."""

from __future__ import annotations

import os
import runpy
from pathlib import Path
from typing import Any, Callable

from wsim.errors import InvalidParameter

DEFAULT_FRAMES = 90


def load_scene(path: str | os.PathLike[str]) -> tuple[Callable[..., Any], int, str, Callable[..., dict] | None]:
    """(build, FRAMES, name, metrics or None) of a scene file."""
    p = Path(path)
    if not p.is_file():
        raise InvalidParameter(f"scene file '{path}' not found")
    ns = runpy.run_path(str(p), run_name="wsim_scene")
    build = ns.get("build")
    if not callable(build):
        raise InvalidParameter(f"scene '{path}' must define build(mesh=None, device=None, **params) -> wsim.World")
    metrics = ns.get("metrics")
    return build, int(ns.get("FRAMES", DEFAULT_FRAMES)), p.stem, metrics if callable(metrics) else None
