"""Animated USD export: one ``UsdGeom.Mesh`` per body, colliders as meshes, written atomically.

Layout of a written stage (default prim ``/World``):

- ``/World/<body>``: Mesh; topology (faceVertexCounts/Indices), ``displayColor`` (the body's
  ``display_color``, else a palette colour) and the input model's texture coordinates
  (``primvars:st``, faceVarying, when it has them: ``Body.face_uv``) and vertex colours (a
  faceVarying ``displayColor``: ``Body.face_color``) written once; ``points``, ``extent``,
  ``velocities`` and vertex ``normals`` (area-weighted, for smooth shading) time-sampled per
  frame; ``subdivisionScheme = none`` so DCC tools show the simulated polygons instead of a
  Catmull-Clark limit surface.
- ``/World/colliders/<collider>``: Mesh; a static collider's points are written in stage
  coordinates; a kinematic collider's points are local and its pose a time-sampled
  ``xformOp:transform``; a ground plane is a square quad. Colliders are read through the World's
  ``Surfaces`` (``display_mesh`` and poses), whatever their type.

Stage metadata: ``timeCodesPerSecond = framesPerSecond = fps``; the time code of World frame k
is k + ``start_frame`` (0 by default; e.g. 1001 for a film pipeline); start/end time codes =
first and last written frames, ``metersPerUnit = 1`` (wsim is SI), ``upAxis`` Y or Z. The simulation is
computed in the World's up axis; exporting to the other axis rotates every point and transform
by +-90 degrees about X, so a Y-up scene opens upright in Blender when written with Z up.

The stage lives in memory while frames are added; ``close`` exports it to a temporary file in
the target folder and renames it onto the target, so a reader never sees a half-written file and
a run that stops early with an exception, Ctrl-C or (through the CLI) SIGTERM still leaves every
frame computed so far. The format follows the extension: ``.usda`` text, ``.usdc`` and ``.usd``
binary (crate: about a fifth of the text's size and much faster to load, for large outputs).

Crash safety: a process killed outright (SIGKILL, out of memory, a lost SSH session) cannot run
``close``. So every frame also goes, as it is written, to a journal beside the target
(``OUT.journal``: the stage without its frames once, then one checksummed record of points per
frame, flushed to the operating system each frame and to the disk at most once a second). A
killed run leaves the journal with every frame written before the kill (the frame being written
when it died may be lost: at most one); ``wsim recover OUT`` (``recover``) turns it into OUT. A
normal end, or a stop by an exception, writes OUT and removes the journal; if OUT cannot be
written (a full disk) the journal stays and the error says so in one line. A new run refuses to
start over a journal it did not write, so an interrupted run's frames are not lost to a rerun.

``velocities`` (m/s in the stage's axes, for motion blur) are the forward difference of the
written points, (p[k+1] - p[k]) fps, so that p[k] + v[k] (t - t_k) is the linear interpolation
between the samples; the last frame gets the backward difference.
"""

from __future__ import annotations

import errno
import json
import os
import re
import struct
import tempfile
import time as _time
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Iterator, Sequence

import numpy as np

from wsim.errors import InvalidParameter, OutputError
from wsim.validate import output_folder

if TYPE_CHECKING:
    from wsim.body import Body
    from wsim.colliders import Surfaces

USD_EXTENSIONS = (".usd", ".usda", ".usdc")

# rotation taking world coordinates with the first up axis to the second (column vectors)
_AXIS_ROTATION = {
    ("Y", "Y"): np.eye(3),
    ("Z", "Z"): np.eye(3),
    ("Y", "Z"): np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),  # (x, y, z) -> (x, -z, y)
    ("Z", "Y"): np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),  # (x, y, z) -> (x, z, -y)
}

JOURNAL_SUFFIX = ".journal"
_JOURNAL_MAGIC = b"WSIMJRN1"
_RECORD_MAGIC = 0x454D5246  # b"FRME" little-endian: the start of one frame's record
_FSYNC_SECONDS = 1.0  # the journal reaches the disk (not only the OS) at most this often

# bodies without a ``display_color`` take these in turn: distinct, not too dark, not grey (the colliders)
_BODY_COLORS = ((0.85, 0.45, 0.25), (0.25, 0.55, 0.85), (0.45, 0.75, 0.35), (0.85, 0.7, 0.25),
                (0.65, 0.4, 0.8), (0.3, 0.75, 0.75), (0.85, 0.4, 0.55), (0.55, 0.5, 0.35))
_COLLIDER_COLOR = (0.55, 0.58, 0.62)


def check_up_axis(axis: str) -> str:
    a = str(axis).upper()
    if a not in ("Y", "Z"):
        raise InvalidParameter(f"up axis must be 'Y' or 'Z', got {axis!r}")
    return a


def check_output_path(path: str | os.PathLike) -> Path:
    """Fail before any simulation if ``path`` cannot receive a USD file."""
    p = Path(path).expanduser()
    if p.is_dir():
        raise OutputError(f"output '{p}' is a directory")
    if p.suffix.lower() not in USD_EXTENSIONS:
        raise OutputError(f"output '{p}': the extension must be one of {', '.join(USD_EXTENSIONS)}")
    folder = output_folder(p)
    journal = journal_path(p)
    if journal.exists():
        raise OutputError(f"output '{p}': '{journal}' holds the frames of an interrupted run; write them with "
                          f"`wsim recover {p}` (or delete it) before writing '{p}' again")
    try:  # os.access is wrong for root and for some network file systems: try a real file
        fd, probe = tempfile.mkstemp(prefix=".wsim-probe-", dir=folder)
        os.close(fd)
        os.remove(probe)
    except OSError as exc:
        raise OutputError(f"output '{p}': the folder '{folder}' is not writable ({exc.strerror})") from None
    if p.exists() and not os.access(p, os.W_OK):
        raise OutputError(f"output '{p}' exists and is read-only")
    return p


def journal_path(path: str | os.PathLike) -> Path:
    """The journal of the USD output ``path`` (``OUT.journal``, beside it)."""
    p = Path(path).expanduser()
    return p.with_name(p.name + JOURNAL_SUFFIX)


def _os_reason(exc: BaseException) -> str:
    """The operating system's words for a failed write (USD's exception holds dozens of lines)."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    text = str(exc)
    m = re.search(r"writing file: ([^'\n]+)", text)
    if m:
        return m.group(1).strip()
    first = next((ln.strip() for ln in text.splitlines() if ln.strip()), type(exc).__name__)
    return first[:200]


def _export(layer: object, path: str) -> None:
    """Write ``layer`` to ``path`` (format by extension); raises on failure."""
    if not layer.Export(path):
        raise OSError(errno.EIO, "USD could not write the file")


def _atomic_export(layer: object, path: Path) -> None:
    """``layer`` to ``path`` through a temporary file in its folder, fsync'd and renamed onto it;
    nothing is left behind on failure."""
    folder = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=folder)
    os.close(fd)
    try:
        _export(layer, tmp)
        with open(tmp, "rb+") as fh:  # on disk before the rename makes it visible
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp made it 0600; give it a normal file's mode
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


class _Journal:
    """The append-only frame journal of one output (see the module docstring). Layout: magic,
    u32 + JSON header (the blocks of a record: ("points", prim, n) or ("xform", prim)), u64 +
    the stage without frames (USD text), then per frame: u32 record magic, u32 CRC-32 of the
    payload, payload = i64 frame + each block (points float32 n x 3, a transform float64 4 x 4)."""

    def __init__(self, path: Path, blocks: list[tuple], base: str, offset: int = 0) -> None:
        self.path = path
        self.blocks = blocks
        self.frames = 0
        self.last: int | None = None
        header = json.dumps({"blocks": blocks, "start_frame": offset}).encode()
        data = base.encode()
        self._synced = 0.0  # monotonic time of the last fsync
        self._fh = open(path, "wb")
        self._write(_JOURNAL_MAGIC + struct.pack("<I", len(header)) + header + struct.pack("<Q", len(data)) + data)
        self._sync(force=True)

    def _write(self, data: bytes) -> None:
        self._fh.write(data)
        self._fh.flush()  # with the OS: a killed process loses nothing written so far

    def _sync(self, force: bool = False) -> None:
        now = _time.monotonic()
        if force or now - self._synced >= _FSYNC_SECONDS:
            os.fsync(self._fh.fileno())
            self._synced = now

    def append(self, frame: int, arrays: list[np.ndarray]) -> None:
        payload = struct.pack("<q", frame) + b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)
        self._write(struct.pack("<II", _RECORD_MAGIC, zlib.crc32(payload)) + payload)
        self._sync()
        self.frames += 1
        self.last = frame

    def close(self, remove: bool) -> None:
        if self._fh.closed:
            return
        try:
            self._fh.close()
        except OSError:
            pass
        if remove and self.path.exists():
            self.path.unlink()


def _record_layout(blocks: list) -> list[tuple[str, int, tuple[int, ...], type]]:
    out = []
    for b in blocks:
        if b[0] == "points":
            out.append((b[1], 12 * int(b[2]), (int(b[2]), 3), np.float32))
        else:
            out.append((b[1], 128, (4, 4), np.float64))
    return out


def read_journal(path: str | os.PathLike) -> tuple[dict, str, Iterator[tuple[int, list[np.ndarray]]]]:
    """(header: the record's blocks and the start frame, the stage without frames as USD text, the
    frames' (World frame, arrays) in order) of a journal; a record cut short or failing its
    checksum (the frame being written when the process died) ends the frames."""
    p = Path(path)
    with open(p, "rb") as fh:
        data = fh.read()
    if not data.startswith(_JOURNAL_MAGIC):
        raise OutputError(f"'{p}' is not a wsim journal")
    at = len(_JOURNAL_MAGIC)
    try:
        (n,) = struct.unpack_from("<I", data, at)
        header = json.loads(data[at + 4:at + 4 + n])
        blocks = header["blocks"]
        at += 4 + n
        (nb,) = struct.unpack_from("<Q", data, at)
        base = data[at + 8:at + 8 + nb].decode()
        if len(base.encode()) != nb:
            raise ValueError
        at += 8 + nb
    except (struct.error, ValueError, KeyError):
        raise OutputError(f"'{p}': the journal's header is incomplete (the run died while starting): no frames to recover") from None
    layout = _record_layout(blocks)
    size = 8 + sum(nbytes for _, nbytes, _, _ in layout)

    def records() -> Iterator[tuple[int, list[np.ndarray]]]:
        pos = at
        while pos + 8 + size <= len(data):
            magic, crc = struct.unpack_from("<II", data, pos)
            payload = data[pos + 8:pos + 8 + size]
            if magic != _RECORD_MAGIC or zlib.crc32(payload) != crc:
                return
            (frame,) = struct.unpack_from("<q", payload, 0)
            arrays, off = [], 8
            for _, nbytes, shape, dtype in layout:
                arrays.append(np.frombuffer(payload, dtype=dtype, count=nbytes // np.dtype(dtype).itemsize,
                                            offset=off).reshape(shape))
                off += nbytes
            yield int(frame), arrays
            pos += 8 + size

    return header, base, records()


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 unit vertex normals: the sum of the adjacent triangles' area vectors,
    normalized (zero for a vertex on no triangle)."""
    p = points.astype(np.float64)
    a = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    n = np.stack([np.bincount(faces.ravel(), np.repeat(a[:, d], 3), minlength=len(p)) for d in range(3)], axis=1)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.where(length > 0.0, length, 1.0)).astype(np.float32)


def _to_usd_matrix(m: np.ndarray):
    """Column-vector 4x4 -> Gf.Matrix4d (USD multiplies row vectors: p' = p M, so transpose)."""
    from pxr import Gf

    return Gf.Matrix4d(*np.asarray(m, dtype=np.float64).T.ravel().tolist())


class UsdWriter:
    """Writes bodies and colliders frame by frame; see the module docstring.

    Args:
        path: target .usd/.usda/.usdc file (checked now, written at ``close``; its journal as frames come).
        fps: frames per second (time code = frame index).
        up_axis: the stage's up axis, "Y" or "Z".
        world_up_axis: the up axis the simulation was computed in.
        start_frame: the time code of the World's frame 0 (an offset added to every frame).
    """

    def __init__(self, path: str | os.PathLike, fps: float, up_axis: str = "Y", world_up_axis: str = "Y",
                 start_frame: int = 0) -> None:
        if isinstance(start_frame, bool) or not isinstance(start_frame, (int, np.integer)):
            raise InvalidParameter(f"start_frame must be an integer frame number, got {start_frame!r}")
        up = check_up_axis(up_axis)
        self._init(check_output_path(path), float(fps), int(start_frame), up,
                   _AXIS_ROTATION[(check_up_axis(world_up_axis), up)])

    def _init(self, path: Path, fps: float, offset: int, up_axis: str, R: np.ndarray) -> None:
        """Every field of a writer with no stage yet (``__init__``, and ``recover``'s replay)."""
        self.path, self.fps, self.offset, self.up_axis, self._R = path, fps, offset, up_axis, R
        self._faces: dict[str, np.ndarray] = {}
        self._A = np.eye(4)
        self._A[:3, :3] = self._R
        self._stage = None
        self._first: int | None = None
        self._last: int | None = None
        self._meshes: dict[str, object] = {}  # prim path -> UsdGeom.Mesh of a body
        self._bodies: dict[str, Body] = {}
        self._kinematic: dict[str, tuple[int, object]] = {}  # prim path -> (collider index, transform op)
        self._prev: dict[str, tuple[int, np.ndarray]] = {}  # the last two frames' points, for velocities
        self._prev2: dict[str, tuple[int, np.ndarray]] = {}
        self._journal: _Journal | None = None
        self.appended = False  # True when ``begin`` continued an existing file

    def begin(self, bodies: Sequence[Body], surfaces: Surfaces, append_from: int | None = None) -> None:
        """Create the stage and every prim's static data (topology, static collider geometry), and
        start the journal.

        A static collider is written in stage coordinates; a kinematic one in its local
        coordinates under a time-sampled transform (``write_frame``). With ``append_from`` (a
        frame) and an existing target that holds the same prims with the same topology (what an
        earlier run of this scene wrote), that file is continued instead: its samples up to
        ``append_from`` are kept, later ones dropped (they are about to be recomputed), and
        ``appended`` is set. Otherwise a new stage is made."""
        from pxr import Sdf, Usd, UsdGeom, Vt

        colliders = surfaces.colliders
        self._surfaces = surfaces
        body_paths, collider_paths = self._prim_paths(bodies, colliders)
        if append_from is not None and self.path.is_file():
            if self._continue(bodies, body_paths, colliders, collider_paths, append_from):
                self._start_journal()
                return

        stage = Usd.Stage.CreateInMemory()
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if self.up_axis == "Y" else UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        stage.SetTimeCodesPerSecond(self.fps)
        stage.SetFramesPerSecond(self.fps)
        root = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(root.GetPrim())
        stage.SetMetadata("comment", "written by wsim")

        def define_mesh(path: str, faces: np.ndarray, color: tuple[float, float, float]):
            mesh = UsdGeom.Mesh.Define(stage, Sdf.Path(path))
            counts = np.full(len(faces), faces.shape[1], dtype=np.int32)  # triangles, or a ground quad
            mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(counts))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, dtype=np.int32).ravel()))
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            mesh.CreateDisplayColorAttr([tuple(color)])
            return mesh

        for k, (body, path) in enumerate(zip(bodies, body_paths)):
            color = getattr(body, "display_color", None) or _BODY_COLORS[k % len(_BODY_COLORS)]
            self._meshes[path] = define_mesh(path, body.faces, tuple(float(c) for c in color))
            self._meshes[path].CreateNormalsAttr()
            self._meshes[path].SetNormalsInterpolation(UsdGeom.Tokens.vertex)
            self._bodies[path] = body
            self._faces[path] = np.asarray(body.faces, dtype=np.int64)
            rgb = getattr(body, "face_color", None)
            if rgb is not None and len(rgb) == len(body.faces) and getattr(body, "display_color", None) is None:
                dc = self._meshes[path].GetDisplayColorPrimvar()  # the input model's colours, per corner
                dc.SetInterpolation(UsdGeom.Tokens.faceVarying)
                dc.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(rgb, dtype=np.float32).reshape(-1, 3)))
            uv = getattr(body, "face_uv", None)
            if uv is not None and len(uv) == len(body.faces):  # the input model's UVs, per face corner
                st = UsdGeom.PrimvarsAPI(self._meshes[path].GetPrim()).CreatePrimvar(
                    "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
                st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(uv, dtype=np.float32).reshape(-1, 2)))
        if colliders:
            UsdGeom.Scope.Define(stage, "/World/colliders")
        for i, (c, path) in enumerate(zip(colliders, collider_paths)):
            points, faces = c.display_mesh(surfaces.up)
            mesh = define_mesh(path, faces, _COLLIDER_COLOR)
            if c.kinematic:
                op = mesh.AddTransformOp()
                self._kinematic[path] = (i, op)
            else:
                points = points @ surfaces.matrix(i, 0.0)[:3, :3].T + surfaces.matrix(i, 0.0)[:3, 3]
                points = points @ self._R.T
            mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
            mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.array([points.min(0), points.max(0)], dtype=np.float32)))
        self._stage = stage
        self._start_journal()

    def _start_journal(self) -> None:
        """The journal: this stage without frames, then a record per ``write_frame``."""
        blocks = [("points", path, len(self._bodies[path].points())) for path in self._meshes]
        blocks += [("xform", path) for path in self._kinematic]
        try:
            self._journal = _Journal(journal_path(self.path), blocks, self._stage.GetRootLayer().ExportToString(),
                                     self.offset)
        except OSError as exc:
            self._stage = None
            journal_path(self.path).unlink(missing_ok=True)
            raise OutputError(f"output '{self.path}': cannot write its journal '{journal_path(self.path)}' "
                              f"({_os_reason(exc)})") from None

    @staticmethod
    def _prim_paths(bodies: Sequence[Body], colliders: Sequence[object]) -> tuple[list[str], list[str]]:
        """Every prim path, decided (and checked for clashes) before anything is written."""
        from pxr import Tf

        body_paths = [f"/World/{Tf.MakeValidIdentifier(b.name)}" for b in bodies]
        collider_paths = [f"/World/colliders/{Tf.MakeValidIdentifier(c.name)}" for c in colliders]
        seen: dict[str, str] = {"/World/colliders": "the colliders scope"} if colliders else {}
        for path, what in [*zip(body_paths, (f"body '{b.name}'" for b in bodies)),
                           *zip(collider_paths, (f"collider '{c.name}'" for c in colliders))]:
            if path in seen:
                raise InvalidParameter(f"{what} and {seen[path]} would both be written as USD prim {path}; rename one")
            seen[path] = what
        return body_paths, collider_paths

    def _continue(self, bodies: Sequence[Body], body_paths: list[str], colliders: Sequence[object],
                  collider_paths: list[str], frame: int) -> bool:
        """Open the existing target for appending after ``frame``; False (nothing kept) when it is
        not a file of this scene: another up axis or fps, a prim missing, other topology."""
        from pxr import Sdf, Usd, UsdGeom

        try:
            layer = Sdf.Layer.OpenAsAnonymous(str(self.path))  # a copy: the file changes only at close
        except Exception:  # noqa: BLE001 - any unreadable file just means "write a new one"
            return False
        if layer is None:
            return False
        stage = Usd.Stage.Open(layer)
        want_up = UsdGeom.Tokens.y if self.up_axis == "Y" else UsdGeom.Tokens.z
        if UsdGeom.GetStageUpAxis(stage) != want_up or stage.GetTimeCodesPerSecond() != self.fps:
            return False
        meshes, kinematic = {}, {}
        for body, path in zip(bodies, body_paths):
            mesh = UsdGeom.Mesh(stage.GetPrimAtPath(path))
            if not mesh or not np.array_equal(np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or []),
                                              np.asarray(body.faces).ravel()):
                return False
            meshes[path] = mesh
            self._bodies[path] = body
        for i, (c, path) in enumerate(zip(colliders, collider_paths)):
            prim = stage.GetPrimAtPath(path)
            if not prim:
                return False
            if c.kinematic:
                ops = UsdGeom.Xformable(prim).GetOrderedXformOps()
                if len(ops) != 1:
                    return False
                kinematic[path] = (i, ops[0])
        # samples after the checkpoint frame are recomputed: drop them
        attrs = [a for m in meshes.values() for a in (m.GetPointsAttr(), m.GetExtentAttr(), m.GetVelocitiesAttr())]
        attrs += [op.GetAttr() for _, op in kinematic.values()]
        attrs += [m.GetNormalsAttr() for m in meshes.values()]
        for attr in attrs:
            for code in attr.GetTimeSamples():
                if code > frame + self.offset:
                    attr.ClearAtTime(code)
        start = stage.GetStartTimeCode() - self.offset if stage.HasAuthoredTimeCodeRange() else float(frame)
        self._stage, self._meshes, self._kinematic = stage, meshes, kinematic
        self._faces = {path: np.asarray(self._bodies[path].faces, dtype=np.int64) for path in meshes}
        self._first, self._last = int(round(min(start, frame))), frame
        self.appended = True
        return True

    def write_frame(self, frame: int, time: float) -> None:
        """Time-sample every body's points, extent and (the frame before's) velocities, and
        kinematic collider poses, at ``frame``; the frame goes to the journal first."""
        if self._stage is None:
            raise RuntimeError("UsdWriter.begin must be called before write_frame")
        arrays = [(body.points() @ self._R.T).astype(np.float32) for body in self._bodies.values()]
        arrays += [self._A @ self._surfaces.matrix(i, time) for i, _ in self._kinematic.values()]
        try:
            self._journal.append(frame, arrays)
        except OSError as exc:
            raise OutputError(f"output '{self.path}': frame {frame} could not be saved to the journal "
                              f"'{self._journal.path}' ({_os_reason(exc)})") from None
        self._apply(frame, arrays)

    def _apply(self, frame: int, arrays: list[np.ndarray]) -> None:
        """Author one frame's samples (``write_frame``'s arrays: points per body in stage axes, float32,
        then each kinematic collider's 4 x 4 transform)."""
        from pxr import Usd, Vt

        code = Usd.TimeCode(float(frame + self.offset))
        for (path, mesh), pts in zip(self._meshes.items(), arrays):
            mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts), code)
            mesh.GetExtentAttr().Set(Vt.Vec3fArray.FromNumpy(np.array([pts.min(0), pts.max(0)], dtype=np.float32)), code)
            mesh.GetNormalsAttr().Set(Vt.Vec3fArray.FromNumpy(vertex_normals(pts, self._faces[path])), code)
            prev = self._prev.get(path)
            if prev is not None and prev[0] < frame:  # the frame before: forward difference
                self._set_velocity(mesh, prev[0], pts, prev[1], frame - prev[0])
            self._prev2[path], self._prev[path] = prev, (frame, pts)
        for (i, op), m in zip(self._kinematic.values(), arrays[len(self._meshes):]):
            op.Set(_to_usd_matrix(m), code)
        self._first = frame if self._first is None else self._first
        self._last = frame

    def _set_velocity(self, mesh: object, frame: int, later: np.ndarray, earlier: np.ndarray, frames: int) -> None:
        from pxr import Usd, Vt

        v = (later.astype(np.float64) - earlier.astype(np.float64)) * (self.fps / frames)
        mesh.GetVelocitiesAttr().Set(Vt.Vec3fArray.FromNumpy(v.astype(np.float32)), Usd.TimeCode(float(frame + self.offset)))

    def close(self) -> Path | None:
        """Write the stage atomically (temp file + rename) and remove the journal; returns the path,
        or None if nothing was begun. If the file cannot be written the journal is kept and the
        ``OutputError`` says how to recover it."""
        stage, self._stage = self._stage, None
        if stage is None:
            return None
        for path, mesh in self._meshes.items():  # the last frame: backward difference
            last, before = self._prev.get(path), self._prev2.get(path)
            if last is not None and before is not None:
                self._set_velocity(mesh, last[0], last[1], before[1], last[0] - before[0])
            elif last is not None and not mesh.GetVelocitiesAttr().GetTimeSamples():
                self._set_velocity(mesh, last[0], last[1], last[1], 1)  # one frame: at rest
        if self._first is not None:
            stage.SetStartTimeCode(float(self._first + self.offset))
            stage.SetEndTimeCode(float(self._last + self.offset))
        journal = self._journal
        try:
            _atomic_export(stage.GetRootLayer(), self.path)
        except Exception as exc:  # noqa: BLE001 - USD raises Tf.ErrorException with the OS error inside
            if journal is None:
                raise OutputError(f"output '{self.path}' could not be written ({_os_reason(exc)})") from None
            journal.close(remove=False)
            kept = (f"frames {self._first}..{journal.last} are kept in '{journal.path}'" if journal.frames
                    else f"'{journal.path}' holds no frame")
            raise OutputError(f"output '{self.path}' could not be written ({_os_reason(exc)}); {kept}: "
                              f"make room, then `wsim recover {self.path}`") from None
        if journal is not None:
            journal.close(remove=True)
        return self.path


def recover(path: str | os.PathLike, out: str | os.PathLike | None = None) -> tuple[Path, int]:
    """Write the frames of an interrupted run's journal (``OUT.journal``) as the USD file ``out``
    (default: the run's own output ``path``), atomically, and remove the journal. Returns (the
    file, the frames recovered)."""
    from pxr import Sdf, Usd, UsdGeom

    target = Path(path).expanduser()
    journal = journal_path(target)
    if not journal.is_file():
        raise OutputError(f"'{journal}' does not exist: '{target}' has no interrupted run to recover")
    header, base, records = read_journal(journal)
    blocks = header["blocks"]
    dest = Path(out).expanduser() if out is not None else target
    if out is not None:
        check_output_path(dest)
    layer = Sdf.Layer.CreateAnonymous(".usda")
    if not layer.ImportFromString(base):
        raise OutputError(f"'{journal}': the stage it holds is not valid USD")
    stage = Usd.Stage.Open(layer)
    writer = UsdWriter.__new__(UsdWriter)  # not __init__: the target's journal exists (it is what we read)
    up = "Z" if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z else "Y"
    writer._init(dest, float(stage.GetTimeCodesPerSecond()), int(header.get("start_frame", 0)), up, np.eye(3))
    writer._stage = stage
    writer._first = int(stage.GetStartTimeCode()) - writer.offset if stage.HasAuthoredTimeCodeRange() else None
    writer._meshes = {b[1]: UsdGeom.Mesh(stage.GetPrimAtPath(b[1])) for b in blocks if b[0] == "points"}
    writer._faces = {p: np.asarray(m.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
                     for p, m in writer._meshes.items()}
    writer._kinematic = {b[1]: (k, UsdGeom.Xformable(stage.GetPrimAtPath(b[1])).GetOrderedXformOps()[0])
                         for k, b in enumerate(blk for blk in blocks if blk[0] == "xform")}
    frames = 0
    for frame, arrays in records:
        writer._apply(frame, arrays)
        frames += 1
    if frames == 0:
        raise OutputError(f"'{journal}' holds no complete frame: nothing to recover")
    writer.close()
    journal.unlink()
    return dest, frames
