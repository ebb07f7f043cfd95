"""Small checks for user input, shared by every public constructor.

Each raises the wsim error class its caller names, with a message that names the object and the
quantity, so a scene script says exactly what to fix.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from wsim.errors import InvalidParameter, WsimError


def finite_number(value: object, what: str, error: type[WsimError] = InvalidParameter) -> float:
    """``value`` as a finite float, or ``error`` naming ``what``."""
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise error(f"{what} must be a number, got {value!r}") from None
    if not math.isfinite(out):
        raise error(f"{what} = {out} is not finite")
    return out


def as_vec3(value: Sequence[float] | np.ndarray, what: str) -> np.ndarray:
    """A finite 3-vector as float64, or InvalidParameter naming ``what``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InvalidParameter(f"{what} must be 3 finite numbers, got {value!r}")
    return a


def as_rotation(value: object, what: str) -> np.ndarray:
    """A proper 3x3 rotation matrix (None means the identity), or InvalidParameter naming ``what``."""
    try:
        R = np.eye(3) if value is None else np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        R = np.zeros(0)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) \
            or np.linalg.det(R) <= 0.0:
        raise InvalidParameter(f"{what} must be a proper 3x3 rotation matrix")
    return R


def positive_int(value: object, what: str, minimum: int = 1) -> int:
    """``value`` as an int >= ``minimum`` (bools refused: ``True`` is not a count), or InvalidParameter
    naming ``what``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise InvalidParameter(f"{what} = {value!r} must be an integer >= {minimum}")
    return int(value)


def callback_array(value: object, shapes: Sequence[tuple[int, ...]], what: str, t: float,
                   frame: int | None = None, error: type[WsimError] = InvalidParameter) -> np.ndarray:
    """What a user's function of time returned (a handle's motion, a load, a driven target), as a
    finite float64 array of one of ``shapes``; else ``error`` naming ``what`` (the body and the
    quantity, e.g. ``body 'neck': handle 'tip' (handles[0]) motion``), the time ``t`` [s] and the
    World ``frame`` being computed when there is one:
    ``body 'neck': handle 'tip' (handles[0]) motion at t = 1.23333 s is not finite: 3 non-finite
    values, e.g. row 0 = [nan, nan, nan]; in frame 37``. Reads only the host value it is given."""
    where = "" if frame is None else f"; in frame {frame}"
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise error(f"{what} at t = {t:.6g} s is not numeric: got {type(value).__name__} {value!r:.60}{where}") from None
    if a.shape not in [tuple(s) for s in shapes]:
        expected = " or ".join(str(tuple(s)) for s in shapes)
        raise error(f"{what} at t = {t:.6g} s has shape {a.shape}; expected {expected}{where}")
    bad = ~np.isfinite(a)
    if bad.any():
        example = ""
        if a.ndim == 2:
            i = int(np.argmax(bad.any(axis=1)))
            example = f", e.g. row {i} = {a[i].tolist()}"
        raise error(f"{what} at t = {t:.6g} s is not finite: {int(bad.sum())} non-finite values{example}{where}")
    return a


def output_folder(path: Path, what: str = "output") -> Path:
    """The folder a file ``path`` will be written in, or ``OutputError`` naming ``what`` and the
    path: the path is a folder, a part of it is a file, or the folder does not exist."""
    from wsim.errors import OutputError

    if path.is_dir():
        raise OutputError(f"{what} '{path}' is a directory")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        up = folder if folder.exists() else next((a for a in folder.parents if a.exists()), None)
        if up is not None and not up.is_dir():
            raise OutputError(f"{what} '{path}': '{up}' is a file, not a folder")
        raise OutputError(f"{what} '{path}': the folder '{folder}' does not exist")
    return folder


def call_user(fn: object, t: float, what: str, frame: int | None = None) -> object:
    """``fn(t)`` for a user's function of time; an exception it raises comes back as
    ``InvalidParameter`` naming ``what`` (the body and the quantity), t and the World ``frame``,
    with the user's exception chained (its traceback stays visible)."""
    try:
        return fn(t)  # type: ignore[operator]
    except WsimError:
        raise
    except Exception as exc:  # noqa: BLE001 - any error of user code, reported with its context
        where = "" if frame is None else f"; in frame {frame}"
        raise InvalidParameter(f"{what} at t = {t:.6g} s raised {type(exc).__name__}: {exc}{where}") from exc
