"""Body state as data: what changes when a body steps, apart from its immutable operators.

Every method keeps its per-instance state in one dataclass (``PbdState``, ``BemState``,
``EolState``) beside its operators, following the Model/State split of Newton and mujoco_warp.
This module turns such a dataclass into named numpy arrays and back, which is all a checkpoint
(``wsim.checkpoint``) needs:

- a ``wp.array`` field is read back to the host and written into in place on load (a CUDA graph
  recorded on it stays valid);
- a numpy array or a number is copied; a nested dataclass (a ``RigidFrame``) is flattened with
  dotted names (``frame.R``).

Loading checks every array's shape and dtype against the live state first and changes nothing
when one does not fit, so a bad file cannot leave a body half restored. A state class may name
host fields of variable length in a class attribute ``_ragged`` (e.g. ``("active_rows",)``): for
those only the number of dimensions and the kind of dtype must match (the length may differ), and
the saved values are cast to the live field's dtype.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import warp as wp

from wsim.errors import WsimError


class StateMismatch(WsimError, ValueError):
    """Saved state that does not fit the body it is loaded into (another scene, mesh or setting)."""


def _fields(state: Any, prefix: str = "") -> list[tuple[str, Any, Any, str]]:
    """(dotted name, owner object, value, attribute) of every leaf field of a state dataclass."""
    out = []
    for f in dataclasses.fields(state):
        value = getattr(state, f.name)
        name = prefix + f.name
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            out.extend(_fields(value, name + "."))
        else:
            out.append((name, state, value, f.name))
    return out


def state_arrays(state: Any) -> dict[str, np.ndarray]:
    """Every leaf field of ``state`` as a host numpy array (copies)."""
    out: dict[str, np.ndarray] = {}
    for name, _, value, _ in _fields(state):
        if isinstance(value, wp.array):
            out[name] = value.numpy().copy()
        else:
            out[name] = np.array(value)
    return out


def load_state_arrays(state: Any, arrays: dict[str, np.ndarray], what: str) -> None:
    """Write ``arrays`` into ``state`` in place; every field is checked before any is written.

    Raises ``StateMismatch`` naming ``what`` and the field when a field is missing or extra, or its
    shape or dtype differs from the live state's.
    """
    leaves = _fields(state)
    names = {name for name, *_ in leaves}
    missing = sorted(names - set(arrays))
    extra = sorted(set(arrays) - names)
    if missing or extra:
        detail = "; ".join(p for p in (f"missing {', '.join(missing)}" if missing else "",
                                       f"unexpected {', '.join(extra)}" if extra else "") if p)
        raise StateMismatch(f"{what}: the saved state does not match this body ({detail})")
    staged = []
    for name, owner, value, attr in leaves:
        saved = np.asarray(arrays[name])
        live = value.numpy() if isinstance(value, wp.array) else np.asarray(value)
        if attr in getattr(type(owner), "_ragged", ()) and not isinstance(value, wp.array):
            if saved.ndim != live.ndim or saved.dtype.kind != live.dtype.kind:
                raise StateMismatch(
                    f"{what}: saved '{name}' has {saved.ndim} dimensions and dtype {saved.dtype}, this body's has "
                    f"{live.ndim} and {live.dtype}")
            staged.append((owner, value, attr, saved.astype(live.dtype) if isinstance(value, np.ndarray) else saved))
            continue
        if saved.shape != live.shape or saved.dtype != live.dtype:
            raise StateMismatch(
                f"{what}: saved '{name}' has shape {saved.shape} and dtype {saved.dtype}, this body's has "
                f"{live.shape} and {live.dtype} (another mesh or setting?)")
        staged.append((owner, value, attr, saved))
    for owner, value, attr, saved in staged:
        if isinstance(value, wp.array):
            value.assign(saved)
        elif isinstance(value, np.ndarray):
            setattr(owner, attr, saved.copy())
        else:  # a Python number or flag: keep its type
            setattr(owner, attr, type(value)(saved.item()))
