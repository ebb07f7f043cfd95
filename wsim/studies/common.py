"""What every knob study shares: its declaration (``StudySpec``, ``Mode``), a World that samples the
study's signature after each frame and times the frames (``StudyWorld``), probes that name the
same material points on meshes of different sizes, and the bytes a World's bodies hold.

A study file (``wsim/studies/<name>.py``) is a scene file that ``wsim.sweep`` runs: ``build(mesh=None,
device=None, **knobs) -> StudyWorld``, ``FRAMES`` and ``metrics(world) -> dict``, plus ``SPEC``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from wsim.errors import InvalidParameter
from wsim.world import World

Signature = Callable[[World], np.ndarray]


@dataclass(frozen=True)
class Mode:
    """One size of a study (``--quick`` on a CPU, or the full one on a GPU).

    Attributes:
        default: the default variant's knobs, where they differ from ``build``'s own defaults.
        grid: knob -> values; each knob is varied alone from the default (not a product).
        reference: the reference's knobs (over the default's): the finest setting the study
            affords, which is only as accurate as ``check`` shows.
        frames: frames every variant simulates.
        check: the reference check: knobs over the reference's that refine it one notch in its
            dominant discretization (BEM: dt halved). The study runs it too and reports its
            distance from the reference (the same error) as the reference's uncertainty: errors
            below twice that are not resolved by the reference. Empty where no finer setting
            exists or none is needed (``StudySpec.check_note`` says which).
    """

    default: dict[str, Any]
    grid: dict[str, list[Any]]
    reference: dict[str, Any]
    frames: int
    check: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class StudySpec:
    """A knob study: its scenario, what its error measures, its cost axes and its two sizes.

    Attributes:
        name: the study's name on the command line (``--studies NAME``).
        title: a heading for the report.
        scenario: what is simulated, in a sentence or two.
        error: what the error is, in words (the report prints it above the table).
        scale: the length [m] that the signature's distances are divided by; "reference_peak":
            the largest probe distance from the origin in the reference's signature (for a
            signature of displacements: its largest displacement); None where the study's
            ``metrics`` measures its own ``error`` (the PDE reconstruction, against the frames it
            rebuilds).
        costs: record key -> axis label, one plot panel each; the first is the one the report's
            advice ranks by.
        knobs: knob -> the API setting it is (the report's glossary).
        quick, full: the two sizes.
        notes: what the report should say besides the numbers (a caveat measured elsewhere).
        advice_targets: the errors the report names the cheapest setting under.
        check_note: what the reference check is, or why a study has none (the report prints it).
        exact_reference: the study's ``metrics`` measures the error against the truth itself (the
            PDE reconstruction against the frames it rebuilds): the reference's uncertainty is 0.
    """

    name: str
    title: str
    scenario: str
    error: str
    scale: float | str | None
    costs: dict[str, str]
    knobs: dict[str, str]
    quick: Mode
    full: Mode
    notes: str = ""
    advice_targets: tuple[float, ...] = field(default=(0.001, 0.01, 0.1))
    check_note: str = ""
    exact_reference: bool = False


def match_points(vertices: np.ndarray, points: np.ndarray, what: str, tol: float = 1e-9) -> np.ndarray:
    """Indices of ``points`` among ``vertices`` (each must be a vertex, to ``tol`` of the mesh's
    size): the same material points on a coarse and a refined mesh whose refinement keeps the
    coarse vertices (icospheres, ``wsim.mesh.beam`` grids)."""
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, dtype=np.float64)
    d, idx = cKDTree(v).query(np.asarray(points, dtype=np.float64))
    size = float(np.ptp(v, axis=0).max())
    if d.max() > tol * size:
        raise InvalidParameter(f"{what}: a probe point is {d.max():.3g} m from the nearest vertex; the meshes of "
                               "a study must keep the coarsest mesh's vertices")
    return idx.astype(np.int64)


def bytes_held(root: Any, max_depth: int = 6) -> tuple[int, int]:
    """(device, host) bytes of the Warp, NumPy and SciPy sparse arrays reachable from ``root``
    through wsim objects, dataclasses, lists, tuples and dicts: what a body's operators, model and
    state take. Memory is counted once by its address (a NumPy view counts its base; a Warp array
    on the CPU that aliases a NumPy array, as the BEM stepper's do, is not counted twice). A Warp
    array on a CUDA device counts as device bytes; one on the CPU, and NumPy's, as host bytes."""
    import dataclasses

    import warp as wp

    seen: set[int] = set()
    spans: dict[str, list[tuple[int, int]]] = {}  # memory space -> (start address, end address)
    stack: list[tuple[Any, int]] = [(root, 0)]
    while stack:
        obj, depth = stack.pop()
        if isinstance(obj, np.ndarray):
            while isinstance(obj.base, np.ndarray):
                obj = obj.base
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        if isinstance(obj, wp.array):
            if obj.ptr:
                space = str(obj.device) if obj.device is not None and obj.device.is_cuda else "host"
                spans.setdefault(space, []).append((int(obj.ptr), int(obj.ptr) + int(obj.capacity or 0)))
            continue
        if isinstance(obj, np.ndarray):
            if obj.nbytes:
                ptr = int(obj.__array_interface__["data"][0])
                spans.setdefault("host", []).append((ptr, ptr + int(obj.nbytes)))
            continue
        if type(obj).__module__.startswith("scipy.sparse"):
            # a sparse matrix's arrays count at any depth: the compressed BEM operators sit one level
            # below max_depth (body, stepper, history, tuple, CompressedMatrix, C), and skipping them
            # made compression look cheaper than the dense operators it costs more than
            stack.extend((c, depth) for c in vars(obj).values() if isinstance(c, np.ndarray))
            continue
        if depth >= max_depth or isinstance(obj, World):
            continue
        if isinstance(obj, dict):
            children: list[Any] = list(obj.values())
        elif isinstance(obj, (list, tuple)):
            children = list(obj)
        elif dataclasses.is_dataclass(obj) or type(obj).__module__.startswith("wsim"):
            children = list(getattr(obj, "__dict__", {}).values())
            children += [getattr(obj, s) for s in getattr(type(obj), "__slots__", ()) if hasattr(obj, s)]
        else:
            continue
        stack.extend((c, depth + 1) for c in children)
    total = {space: _union_length(v) for space, v in spans.items()}
    return sum(n for space, n in total.items() if space != "host"), total.get("host", 0)


def _union_length(spans: list[tuple[int, int]]) -> int:
    """Bytes covered by address ranges that may overlap (an array and a view of part of it)."""
    total, end = 0, -1
    for a, b in sorted(spans):
        if b > end:
            total += b - max(a, end)
            end = b
    return total


class StudyWorld(World):
    """A World that records a study's signature after every frame and times the frames.

    ``signature(world)`` returns a (K, 3) array (e.g. probe points [m]); ``run`` appends it after
    each frame, outside the timing: a frame's time runs from the end of the previous frame's
    sampling to the end of its own stepping (the device synchronized), so reading the probes back
    costs nothing measured. ``extra`` holds a study's own measures for the record (e.g. the
    operator build time), ``context`` what its ``metrics`` needs and the record does not keep.
    """

    def __init__(self, *args: Any, signature: Signature | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.signature = signature
        self.samples: list[np.ndarray] = []
        self.frame_seconds: list[float] = []
        self.extra: dict[str, Any] = {}
        self.context: dict[str, Any] = {}

    def run(self, frames: int, out: Any = None, *, on_frame: Callable[[World], None] | None = None,
            **kwargs: Any) -> Any:
        import warp as wp

        last = [time.perf_counter()]

        def sample(world: World) -> None:
            if self.device.is_cuda:
                wp.synchronize_device(self.device)
            self.frame_seconds.append(time.perf_counter() - last[0])
            if self.signature is not None:
                self.samples.append(np.asarray(self.signature(self), dtype=np.float64))
            if on_frame is not None:
                on_frame(world)
            last[0] = time.perf_counter()

        return super().run(frames, out, on_frame=sample, **kwargs)

    def measures(self) -> dict[str, Any]:
        """The record a study's ``metrics`` returns: the signature per frame, the simulation's
        milliseconds per frame (frames after the first: the first binds the bodies and loads the
        kernels), the first frame's, and the bytes the bodies hold [MB] (``model_mb``: device and
        host together; ``device_mb``, ``host_mb``)."""
        secs = self.frame_seconds
        out: dict[str, Any] = {
            "ms_per_frame": 1e3 * float(np.mean(secs[1:])) if len(secs) > 1 else None,
            "first_frame_ms": 1e3 * secs[0] if secs else None,
            "timed_frames": max(len(secs) - 1, 0),
            **self._memory(),
            **self.extra,
        }
        if self.signature is not None:
            out["signature"] = np.asarray(self.samples).tolist()  # full precision: float32 vs float64 differences count
        return out

    def _memory(self) -> dict[str, float]:
        """The bodies' arrays [MB]: on the device, on the host, and both (``model_mb``)."""
        dev, host = bytes_held(self.bodies)
        return {"model_mb": (dev + host) / 2**20, "device_mb": dev / 2**20, "host_mb": host / 2**20}
