"""Whether a progress bar shows: one rule for every bar wsim draws (frames, BEM operators).

``WSIM_PROGRESS=0`` hides them all (``wsim run --no-progress`` sets it for the scene it runs, so
a scene that asks for a bar is silenced too); otherwise an explicit ``progress=True/False`` wins,
and ``None`` shows a bar when stderr is a terminal (not in logs, pipes or tests).
"""

from __future__ import annotations

import os
import sys

PROGRESS_ENV = "WSIM_PROGRESS"


def show_progress(progress: bool | None = None) -> bool:
    """The rule of the module docstring."""
    if os.environ.get(PROGRESS_ENV, "") == "0":
        return False
    if progress is not None:
        return bool(progress)
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed stderr
        return False
