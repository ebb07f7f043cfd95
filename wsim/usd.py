"""Animated USD export: one ``UsdGeom.Mesh`` per body, colliders as meshes, written atomically.

Layout of a written stage (default prim ``/World``):

- ``/World/<body>``: Mesh; topology (faceVertexCounts/Indices) written once, ``points`` and
  ``extent`` time-sampled per frame; ``subdivisionScheme = none`` so DCC tools show the
  simulated polygons instead of a Catmull-Clark limit surface.
- ``/World/colliders/<collider>``: Mesh; a static collider's points are written in stage
  coordinates; a kinematic collider's points are local and its pose a time-sampled
  ``xformOp:transform``; a ground plane is a square quad. Colliders are read through the World's
  ``Surfaces`` (``display_mesh`` and poses), whatever their type.

Stage metadata: ``timeCodesPerSecond = framesPerSecond = fps``, start/end time codes = first and
last written frames, ``metersPerUnit = 1`` (wsim is SI), ``upAxis`` Y or Z. The simulation is
computed in the World's up axis; exporting to the other axis rotates every point and transform
by +-90 degrees about X, so a Y-up scene opens upright in Blender when written with Z up.

The stage lives in memory while frames are added; ``close`` exports it to a temporary file in
the target folder and renames it onto the target, so a reader never sees a half-written file and
a run that stops early with an exception, Ctrl-C or (through the CLI) SIGTERM still leaves every
frame computed so far. A process killed outright (SIGKILL, out of memory) writes nothing: run
long jobs with checkpoints (``wsim run --checkpoint-every N``) and resume them; a resumed run
continues the same file (``begin(append_from=frame)``).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from wsim.errors import InvalidParameter, OutputError

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

_BODY_COLOR = (0.85, 0.45, 0.25)
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
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.is_dir():
        raise OutputError(f"output '{p}': the folder '{folder}' does not exist")
    try:  # os.access is wrong for root and for some network file systems: try a real file
        fd, probe = tempfile.mkstemp(prefix=".wsim-probe-", dir=folder)
        os.close(fd)
        os.remove(probe)
    except OSError as exc:
        raise OutputError(f"output '{p}': the folder '{folder}' is not writable ({exc.strerror})") from None
    if p.exists() and not os.access(p, os.W_OK):
        raise OutputError(f"output '{p}' exists and is read-only")
    return p


def _to_usd_matrix(m: np.ndarray):
    """Column-vector 4x4 -> Gf.Matrix4d (USD multiplies row vectors: p' = p M, so transpose)."""
    from pxr import Gf

    return Gf.Matrix4d(*np.asarray(m, dtype=np.float64).T.ravel().tolist())


class UsdWriter:
    """Writes bodies and colliders frame by frame; see the module docstring.

    Args:
        path: target .usd/.usda/.usdc file (checked now, written at ``close``).
        fps: frames per second (time code = frame index).
        up_axis: the stage's up axis, "Y" or "Z".
        world_up_axis: the up axis the simulation was computed in.
    """

    def __init__(self, path: str | os.PathLike, fps: float, up_axis: str = "Y", world_up_axis: str = "Y") -> None:
        self.path = check_output_path(path)
        self.fps = float(fps)
        self.up_axis = check_up_axis(up_axis)
        self._R = _AXIS_ROTATION[(check_up_axis(world_up_axis), self.up_axis)]
        self._A = np.eye(4)
        self._A[:3, :3] = self._R
        self._stage = None
        self._first: int | None = None
        self._last: int | None = None
        self._meshes: dict[str, object] = {}
        self._kinematic: dict[str, object] = {}
        self.appended = False  # True when ``begin`` continued an existing file

    def begin(self, bodies: Sequence[Body], surfaces: Surfaces, append_from: int | None = None) -> None:
        """Create the stage and every prim's static data (topology, static collider geometry).

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

        for body, path in zip(bodies, body_paths):
            self._meshes[path] = (body, define_mesh(path, body.faces, _BODY_COLOR))
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
            meshes[path] = (body, mesh)
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
        attrs = [m.GetPointsAttr() for _, m in meshes.values()] + [m.GetExtentAttr() for _, m in meshes.values()]
        attrs += [op.GetAttr() for _, op in kinematic.values()]
        for attr in attrs:
            for code in attr.GetTimeSamples():
                if code > frame:
                    attr.ClearAtTime(code)
        start = stage.GetStartTimeCode() if stage.HasAuthoredTimeCodeRange() else float(frame)
        self._stage, self._meshes, self._kinematic = stage, meshes, kinematic
        self._first, self._last = int(round(min(start, frame))), frame
        self.appended = True
        return True

    def write_frame(self, frame: int, time: float) -> None:
        """Time-sample every body's points and extent, and kinematic collider poses, at ``frame``."""
        from pxr import Usd, Vt

        if self._stage is None:
            raise RuntimeError("UsdWriter.begin must be called before write_frame")
        code = Usd.TimeCode(float(frame))
        for body, mesh in self._meshes.values():
            pts = body.points() @ self._R.T
            mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)), code)
            mesh.GetExtentAttr().Set(Vt.Vec3fArray.FromNumpy(np.array([pts.min(0), pts.max(0)], dtype=np.float32)), code)
        for i, op in self._kinematic.values():
            op.Set(_to_usd_matrix(self._A @ self._surfaces.matrix(i, time)), code)
        self._first = frame if self._first is None else self._first
        self._last = frame

    def close(self) -> Path | None:
        """Write the stage atomically (temp file + rename); returns the path, or None if nothing was begun."""
        stage, self._stage = self._stage, None
        if stage is None:
            return None
        if self._first is not None:
            stage.SetStartTimeCode(float(self._first))
            stage.SetEndTimeCode(float(self._last))
        folder = self.path.parent if str(self.path.parent) else Path(".")
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.stem}.", suffix=self.path.suffix, dir=folder)
        os.close(fd)
        try:
            if not stage.GetRootLayer().Export(tmp):
                raise OutputError(f"output '{self.path}': USD could not write the file")
            with open(tmp, "rb+") as fh:  # on disk before the rename makes it visible
                os.fsync(fh.fileno())
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)  # mkstemp made it 0600; give it a normal file's mode
            os.replace(tmp, self.path)
        except BaseException:
            if os.path.exists(tmp):
                os.remove(tmp)
            raise
        return self.path
