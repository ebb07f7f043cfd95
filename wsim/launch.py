"""Recorded kernel launches: a step's fixed launch sequence without the cost of packing every argument.

``wp.launch`` converts every argument to its C form on every call. On an H100 that was 52-96 us
(two runs) for an EoL kernel of 13 arguments (a ``Grid`` struct, four 3x3 matrices) whose GPU
time is ~5 us, and an EoL step makes ~30 launches: the host, not the GPU, set the step's pace
(``tools/bench_launch.py``). A ``Launcher`` records one command per call site
(``wp.launch(..., record_cmd=True)``) and on later calls re-packs only the arguments that differ
from the last call there: 7-9 us for a replay, 17-40 us with two small arguments changed.

What counts as unchanged:
* the same object (arrays, structs; a struct is passed by its live C struct, so a field set
  since the last call still reaches the kernel, exactly as with ``wp.launch``);
* an array with the same data pointer, shape, strides and dtype (a fresh ``reshape`` view of
  the same memory);
* a value of the same type and the same bytes (vectors, matrices) or equal (Python and NumPy
  scalars).
Anything else is re-packed, so a replay launches exactly what ``wp.launch`` would.
"""

from __future__ import annotations

import ctypes
import math
import sys
from typing import Any

import numpy as np
import warp as wp

from wsim.kernels import copy as kcopy


_COPY = {wp.float64: kcopy.copy_float64, wp.vec3d: kcopy.copy_vec3d}
_ARRAY = wp.array
_WARP_SCALAR = type(wp.float64(0.0)).__mro__[-2]  # warp's scalar_base


def _same(new: Any, old: Any) -> bool:
    """True when the kernel would receive the same argument (see the module docstring)."""
    if new is old:
        return True
    if type(new) is not type(old):
        return False
    if isinstance(new, _ARRAY):
        return (new.ptr == old.ptr and new.shape == old.shape and new.strides == old.strides
                and new.dtype == old.dtype)
    if isinstance(new, ctypes.Array):
        return bytes(new) == bytes(old)
    if isinstance(new, _WARP_SCALAR):  # wp.float64(x) and kin
        new, old = new.value, old.value
    if isinstance(new, (int, float, bool, np.number)):
        # equal and of the same sign: -0.0 == 0.0, but a kernel can tell them apart (1 / x)
        return bool(new == old) and math.copysign(1.0, new) == math.copysign(1.0, old)
    return False


#: recorded commands kept per call site (one per distinct set of arrays and sizes it launches with)
VARIANTS = 8


class Launcher:
    """``launch(kernel, dim, inputs)`` on one device, replaying a recorded command per call site.

    A call site is the calling function's code and line. A site that launches with several sets of
    arrays (a helper called for two fields, a loop over layers) keeps one command per set: its
    arrays' addresses, its Python ints and its size pick the command, so a step's replays re-pack
    only the values that change from step to step (an EoL step re-packed 28 arguments and set 4
    sizes while one command per site alternated between its uses). One Launcher per object that
    owns the arrays (a body): the recorded commands keep references to the last arguments."""

    def __init__(self, device: wp.Device) -> None:
        self.device = device
        self._cmds: dict[tuple, dict[tuple, tuple[Any, list[Any], Any]]] = {}

    def __call__(self, kernel: Any, dim: Any, inputs: list[Any], depth: int = 1, block_dim: int = 0) -> None:
        """``depth``: which caller's line is the call site (1: the caller; 2: its caller).
        ``block_dim``: a tiled launch (``wp.launch_tiled``) of ``dim`` blocks of that many threads."""
        frame = sys._getframe(depth)
        site = (kernel, frame.f_code, frame.f_lineno)
        variants = self._cmds.get(site)
        if variants is None:
            variants = self._cmds[site] = {}
        sig = (int(dim) if isinstance(dim, (int, np.integer)) else tuple(int(d) for d in dim),
               *[a.ptr if isinstance(a, _ARRAY) else (a if type(a) is int else None) for a in inputs])
        entry = variants.get(sig)
        if entry is None:
            if block_dim:
                cmd = wp.launch_tiled(kernel, dim=dim, block_dim=block_dim, inputs=inputs, device=self.device,
                                      record_cmd=True)
            else:
                cmd = wp.launch(kernel, dim=dim, inputs=inputs, device=self.device, record_cmd=True)
            if len(variants) >= VARIANTS:
                del variants[next(iter(variants))]
            variants[sig] = (cmd, list(inputs), [dim])
            cmd.launch()
            return
        cmd, last, last_dim = entry
        for i, value in enumerate(inputs):
            if not _same(value, last[i]):
                cmd.set_param_at_index(i, value)
                last[i] = value
        cmd.launch()

    def copy(self, dst: wp.array, src: wp.array) -> None:
        """dst = src for contiguous 1-D float64 or vec3d arrays of one length, as a replayed kernel
        (``wp.copy`` costs a launch's packing on the host); other arrays go to ``wp.copy``."""
        kernel = _COPY.get(src.dtype)
        if (kernel is None or dst.dtype != src.dtype or src.ndim != 1 or dst.shape != src.shape
                or not (src.is_contiguous and dst.is_contiguous)):
            wp.copy(dst, src)
            return
        self(kernel, src.shape[0], [src, dst], depth=2)

    def clear(self) -> None:
        """Forget the recorded commands (their arrays can then be freed)."""
        self._cmds.clear()


def launch_on(device: wp.Device, launcher: Launcher | None, kernel: Any, dim: Any, inputs: list[Any],
              block_dim: int = 0) -> None:
    """``launcher(kernel, dim, inputs)`` when one is given, else a plain ``wp.launch`` on ``device``
    (helpers that bodies call every step and tests call once); ``block_dim``: tiled (``Launcher``)."""
    if launcher is not None:
        launcher(kernel, dim, inputs, depth=2, block_dim=block_dim)
    elif block_dim:
        wp.launch_tiled(kernel, dim=dim, block_dim=block_dim, inputs=inputs, device=device)
    else:
        wp.launch(kernel, dim=dim, inputs=inputs, device=device)


_CONCRETE: dict[tuple, Any] = {}
_ARRAYS = {1: wp.array, 2: wp.array2d, 3: wp.array3d}


def concrete(kernel: Any, **args: tuple[int, Any]) -> Any:
    """The overload of a generic kernel (arguments of ``dtype=Any``) for the given argument types,
    each (ndim, dtype): launching the generic kernel makes Warp infer its argument types and look
    the overload up on every call (35 against 13 us of host a launch on the CPU, measured), which a
    step that launches it every time need not pay. Made once per kernel and types."""
    key = (kernel, tuple(sorted((name, ndim, dtype) for name, (ndim, dtype) in args.items())))
    found = _CONCRETE.get(key)
    if found is None:
        found = _CONCRETE[key] = wp.overload(kernel, {name: _ARRAYS[ndim](dtype=dtype) for name, (ndim, dtype) in args.items()})
    return found
