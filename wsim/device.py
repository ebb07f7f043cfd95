"""Device choice: the dispatcher, not the caller, picks the backend.

``None`` means ``cuda:0`` when Warp sees a CUDA device, else ``cpu``; a user can pin any device
Warp knows ("cpu", "cuda", "cuda:1"). Solver code receives a resolved ``warp.context.Device``
and never branches on "is this the CPU" except where a measured CPU fast path exists.
"""

from __future__ import annotations

import warp as wp

from wsim.errors import InvalidParameter


def resolve_device(device: str | wp.Device | None = None) -> wp.Device:
    """Return the Warp device to run on (see module docstring); a clear error for unknown names."""
    wp.init()
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
    wp.init()
    return [d.alias for d in wp.get_devices()]


def quiet_warp() -> None:
    """Silence Warp's start-up banner and module-load lines (warnings still show).

    For the CLI, tools that print JSON, and tests; a library import never changes Warp's settings.
    """
    wp.config.log_level = 30  # warp._src.logger.LOG_WARNING
