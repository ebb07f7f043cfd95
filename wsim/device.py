"""Warp's start and the device choice: the dispatcher, not the caller, picks the backend.

``None`` means ``cuda:0`` when Warp sees a CUDA device, else ``cpu``; a user can pin any device
Warp knows ("cpu", "cuda", "cuda:1"). Solver code receives a resolved ``warp.context.Device``
and never branches on "is this the CPU" except where a measured CPU fast path exists.

When wsim starts Warp (``init_warp``: the first World or device lookup, unless the user's code
started Warp already, whose settings then stand) it starts it quietly: no banner, no "Module ...
load" lines, and no "CUDA driver not found" warning on a machine without one (the CPU is then
simply the device). ``WSIM_VERBOSE=1`` (``wsim run --verbose``) keeps all of Warp's output.
Kernels compiled on first use take seconds to a minute; ``compile_notice`` says so in one line
while it happens.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
from pathlib import Path
from typing import IO, Iterator

import warp as wp

from wsim.errors import InvalidParameter

VERBOSE_ENV = "WSIM_VERBOSE"
_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"


def verbose() -> bool:
    """Whether Warp's own output is wanted (``WSIM_VERBOSE`` set, not 0)."""
    return os.environ.get(VERBOSE_ENV, "") not in ("", "0")


def _warp_started() -> bool:
    try:
        from warp._src import context
    except ImportError:  # another Warp layout: treat as started, leave its settings alone
        return True
    return getattr(context, "runtime", None) is not None


@contextlib.contextmanager
def _stderr_captured() -> Iterator[IO[bytes]]:
    """File descriptor 2 (where Warp's native code prints) into a temporary file for the block."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield tmp
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def init_warp() -> None:
    """Start Warp once, quietly unless ``verbose()`` (see the module docstring); any other line
    Warp's start prints to stderr is passed on."""
    if _warp_started():
        return
    if verbose():
        wp.init()
        return
    wp.config.log_level = 30  # warp._src.logger.LOG_WARNING: no banner, no module-load lines
    with _stderr_captured() as tmp:
        wp.init()
        tmp.seek(0)
        text = tmp.read().decode(errors="replace")
    for line in text.splitlines():
        if line.strip() and _NO_DRIVER not in line:
            print(line, file=sys.stderr)


@contextlib.contextmanager
def compile_notice(enabled: bool = True, stream: IO[str] | None = None, poll: float = 0.25) -> Iterator[None]:
    """Print one line (to ``stream``, default stderr) if Warp compiles kernels during the block:
    its kernel cache folder changes when a module is built. A watcher thread, so the line shows
    while the compiler runs, not after."""
    if not enabled:
        yield
        return
    init_warp()
    folder = Path(wp.config.kernel_cache_dir)

    def stamp() -> float | None:
        try:
            return folder.stat().st_mtime_ns
        except OSError:
            return None

    start, stop = stamp(), threading.Event()

    def watch() -> None:
        while not stop.wait(poll):
            if stamp() != start:
                from tqdm import tqdm  # write() clears and redraws a progress bar on that stream

                tqdm.write("wsim: compiling Warp kernels (first use on this machine or after an update: seconds to a "
                           "minute; cached for later runs)", file=stream or sys.stderr)
                return

    thread = threading.Thread(target=watch, name="wsim-compile-notice", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


def resolve_device(device: str | wp.Device | None = None) -> wp.Device:
    """Return the Warp device to run on (see module docstring); a clear error for unknown names."""
    init_warp()
    if device is None:
        return wp.get_device("cuda:0" if wp.get_cuda_device_count() > 0 else "cpu")
    if isinstance(device, wp.Device):
        return device
    try:
        return wp.get_device(str(device))
    except (RuntimeError, ValueError) as exc:
        names = ", ".join(d.alias for d in wp.get_devices())
        raise InvalidParameter(f"device '{device}' is not available (available: {names}): {exc}") from None


def available_devices() -> list[str]:
    """Aliases of the devices Warp can run on here, CPU first."""
    init_warp()
    return [d.alias for d in wp.get_devices()]


def quiet_warp() -> None:
    """Start Warp quietly now (``init_warp``) and keep its module-load lines off even if it had
    started (warnings still show; ``WSIM_VERBOSE=1`` keeps everything). For the CLI and the tools
    that print JSON."""
    if not verbose():
        wp.config.log_level = 30  # warp._src.logger.LOG_WARNING
    init_warp()
