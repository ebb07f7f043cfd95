"""Headless quick-look of a wsim USD output: ``wsim preview OUT.usdc -o preview.png|.gif|.mp4``.

Renders on a machine with no display and no GPU: matplotlib's Agg backend (pure pip; no OpenGL,
EGL or OSMesa), imported only when a preview is made (``pip install "wsim[preview]"``).

What is drawn: every ``UsdGeom.Mesh`` under ``/World`` (bodies and ``/World/colliders/*``), its
points taken to world space at each time code (``UsdGeom.XformCache``: kinematic colliders carry a
time-sampled ``xformOp:transform``), turned upright from the stage's up axis (Y or Z), coloured
by ``primvars:displayColor``. Faces (polygons fan-triangulated) are drawn back to front (painter's
algorithm) with Lambert shading from one light; back faces of closed meshes are dropped. The
camera is fixed for the whole animation: a 3/4 view from the front-top framing the union of every
frame's extent. A large flat mesh (a ground plane) is cut to a margin around the other meshes so
it does not set the framing, drawn first as a light checkerboard, with the other meshes' shadows
cast straight down onto it.

Outputs, by extension: ``.png`` a contact sheet of ``frames`` evenly spaced frames (default 6,
frame number on each tile); ``.gif`` an animation (Pillow); ``.mp4`` an animation through
matplotlib's ``FFMpegWriter`` (needs ``ffmpeg`` on PATH). Files are written atomically (a temporary
file in the target folder, then renamed).
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import tempfile
import time as _time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wsim.errors import InvalidParameter, OutputError, WsimError
from wsim.validate import output_folder

FORMATS = (".png", ".gif", ".mp4")
DEFAULT_TILES = 6
DEFAULT_SIZE = {".png": (1200, 600), ".gif": (640, 400), ".mp4": (960, 540)}
MAX_ANIMATION_FRAMES = 150  # default cap of an animation's frames (evenly spaced)
MAX_FRAMING_SAMPLES = 200  # time codes read to frame the camera on a long animation
BACKGROUND = (0.95, 0.96, 0.975)
DEFAULT_COLOR = (0.7, 0.7, 0.7)  # a mesh without displayColor
INSTALL_HINT = 'wsim preview needs matplotlib: pip install "wsim[preview]"'

_AZIMUTH = math.radians(35.0)  # camera: from the front (+Z of a Y-up stage), turned towards +X
_ELEVATION = math.radians(27.0)
_FOV = math.radians(30.0)
_AMBIENT = 0.38
_USD_MAGIC = (b"PXR-USDC", b"#usda", b"PK\x03\x04")


@dataclass
class PreviewSummary:
    out: Path
    frames: int  # frames drawn (tiles of a PNG, frames of an animation)
    size: tuple[int, int]
    seconds: float

    def __str__(self) -> str:
        what = "tile" if self.out.suffix.lower() == ".png" else "frame"
        return f"wsim: preview ({self.frames} {what}{'s' if self.frames != 1 else ''}, {self.size[0]}x{self.size[1]}) written to {self.out} in {self.seconds:.1f} s"


@dataclass
class _Mesh:
    prim: object
    points_attr: object
    tris: np.ndarray  # (T, 3) point indices
    colors: np.ndarray  # (T, 3) base colour per triangle
    closed: bool  # every edge shared by two faces with opposite directions: back faces can be culled
    ground: bool = False
    # large faces split for the depth sort: sub-triangle s is weights[s] @ corners of triangle source[s]
    source: np.ndarray | None = None
    weights: np.ndarray | None = None


def parse_size(text: str) -> tuple[int, int]:
    """``"WxH"`` -> (W, H) in pixels."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InvalidParameter(f"--size '{text}' must be WIDTHxHEIGHT in pixels, e.g. 1200x600") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise InvalidParameter(f"--size '{text}': width and height must be within 16..8192 pixels")
    return w, h


def render(usd: str | os.PathLike, out: str | os.PathLike, frames: int | None = None,
           size: tuple[int, int] | str | None = None, fps: float | None = None) -> PreviewSummary:
    """Render a preview of the USD file ``usd`` to ``out`` (.png contact sheet, .gif or .mp4).

    Args:
        frames: tiles of a PNG (default 6), or the most frames of an animation (default all, up to
            ``MAX_ANIMATION_FRAMES``); evenly spaced over the stage's time samples.
        size: output size in pixels, (W, H) or ``"WxH"`` (default per format: ``DEFAULT_SIZE``).
        fps: playback rate of an animation (default: real time, the stage's time codes per second
            over the frames kept).
    """
    t0 = _time.perf_counter()
    usd, out = Path(usd), Path(out)
    ext = out.suffix.lower()
    if ext not in FORMATS:
        raise InvalidParameter(f"output '{out}': unknown extension '{out.suffix}'; use .png, .gif or .mp4")
    if frames is not None and frames < 1:
        raise InvalidParameter(f"--frames = {frames} must be >= 1")
    if fps is not None and not (fps > 0 and math.isfinite(fps)):
        raise InvalidParameter(f"--fps = {fps} must be > 0")
    w, h = parse_size(size) if isinstance(size, str) else (size or DEFAULT_SIZE[ext])
    if size is not None and not isinstance(size, str):
        w, h = parse_size(f"{int(w)}x{int(h)}")
    if ext == ".mp4":
        w, h = w - w % 2, h - h % 2  # H.264 (yuv420p) needs even sizes
    output_folder(out)
    try:
        import matplotlib

        matplotlib.use("Agg")
    except ImportError:
        raise WsimError(INSTALL_HINT) from None
    if ext == ".mp4":
        from matplotlib.animation import FFMpegWriter

        if not FFMpegWriter.isAvailable():
            raise OutputError(f"output '{out}': .mp4 needs ffmpeg on PATH (not found); write a .gif instead")

    scene = _Scene(usd)
    n_codes = len(scene.codes)
    if ext == ".png":
        n = min(frames or DEFAULT_TILES, n_codes)
    else:
        n = min(frames or MAX_ANIMATION_FRAMES, n_codes)
    picks = [scene.codes[i] for i in np.unique(np.round(np.linspace(0, n_codes - 1, n)).astype(int))]
    camera = scene.camera()
    if ext == ".png":
        _write_sheet(scene, camera, picks, out, (w, h))
    else:
        if fps is None:
            span = (scene.codes[-1] - scene.codes[0]) / scene.tcps
            fps = (len(picks) - 1) / span if len(picks) > 1 and span > 0 else scene.tcps
            fps = min(max(fps, 1.0), 50.0)
        _write_animation(scene, camera, picks, out, (w, h), fps)
    return PreviewSummary(out, len(picks), (w, h), _time.perf_counter() - t0)


# --- reading the stage --------------------------------------------------------------------------------


class _Scene:
    """The meshes of a stage, their world points per time code (Y up) and the ground planes."""

    def __init__(self, path: Path) -> None:
        stage = _open_stage(path)
        from pxr import Usd, UsdGeom

        self.stage = stage  # keeps the prims alive
        self.path = path
        self.tcps = float(stage.GetTimeCodesPerSecond() or 24.0)
        z_up = UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
        # to a Y-up frame: a Z-up stage's (x, y, z) is (x, z, -y) with Y up (front stays front)
        self._to_y_up = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]) if z_up else None
        root = stage.GetPrimAtPath("/World") or stage.GetPseudoRoot()
        self.meshes: list[_Mesh] = []
        codes: set[float] = set()
        for prim in Usd.PrimRange(root):
            if not prim.IsA(UsdGeom.Mesh):
                continue
            img = UsdGeom.Imageable(prim)
            if img.ComputeVisibility() == UsdGeom.Tokens.invisible or img.ComputePurpose() in (
                    UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy):
                continue
            mesh = _read_mesh(UsdGeom.Mesh(prim))
            if mesh is None:
                continue
            self.meshes.append(mesh)
            codes.update(mesh.points_attr.GetTimeSamples())
            p = prim
            while p and not p.IsPseudoRoot():
                codes.update(UsdGeom.Xformable(p).GetTimeSamples() if p.IsA(UsdGeom.Xformable) else ())
                p = p.GetParent()
        if not self.meshes:
            raise InvalidParameter(f"'{path}' has no mesh (UsdGeom.Mesh with faces) under {root.GetPath()}")
        self.codes = sorted(codes) or [float(stage.GetStartTimeCode()) if stage.HasAuthoredTimeCodeRange() else 0.0]
        self.static = not codes
        self._cache: dict[float, list[np.ndarray | None]] = {}
        self._find_grounds()

    def points(self, code: float) -> list[np.ndarray | None]:
        """World points (Y up, float64) of every mesh at ``code`` (None where it has none)."""
        if code in self._cache:
            return self._cache[code]
        from pxr import Usd, UsdGeom

        tc = Usd.TimeCode(code)
        xf = UsdGeom.XformCache(tc)
        result = []
        for m in self.meshes:
            pts = m.points_attr.Get(tc)
            if pts is None or len(pts) == 0:
                result.append(None)
                continue
            p = np.asarray(pts, dtype=np.float64)
            mat = np.asarray(xf.GetLocalToWorldTransform(m.prim), dtype=np.float64)  # row vectors: p M
            p = p @ mat[:3, :3] + mat[3, :3]
            if self._to_y_up is not None:
                p = p @ self._to_y_up.T
            result.append(p)
        if len(self._cache) < 512:
            self._cache[code] = result
        return result

    def _find_grounds(self) -> None:
        """Flag flat meshes much larger than the rest (ground planes); they do not set the framing."""
        pts = self.points(self.codes[0])
        flat = []
        for m, p in zip(self.meshes, pts):
            if p is None or len(p) < 3:
                flat.append(False)
                continue
            s = np.linalg.svd(p - p.mean(0), compute_uv=False)
            flat.append(bool(s[0] > 0 and s[-1] <= 1e-6 * s[0]))
        others = [p for p, f in zip(pts, flat) if not f and p is not None]
        if not others:
            return
        allp = np.concatenate(others)
        size = float(np.max(allp.max(0) - allp.min(0)))
        for m, p, f in zip(self.meshes, pts, flat):
            if f and float(np.max(p.max(0) - p.min(0))) > 1.5 * size:
                m.ground = True

    def camera(self) -> _Camera:
        """A fixed 3/4 camera framing every frame's non-ground points."""
        n = len(self.codes)
        sample = [self.codes[i] for i in np.unique(np.round(np.linspace(0, n - 1, min(n, MAX_FRAMING_SAMPLES))).astype(int))]
        clouds = []
        for code in sample:
            for m, p in zip(self.meshes, self.points(code)):
                if p is not None and (not m.ground or all(mm.ground for mm in self.meshes)):
                    clouds.append(p)
        allp = np.concatenate(clouds)
        allp = allp[np.isfinite(allp).all(axis=1)]  # a diverged frame's NaN points do not set the view
        if len(allp) == 0:
            raise InvalidParameter(f"'{self.path}': no finite mesh points to frame")
        lo, hi = allp.min(0), allp.max(0)
        cam = _Camera(lo, hi)
        # tight 2-D bounds: every point of the sampled frames (subsampled when huge)
        stack = allp if len(allp) <= 2_000_000 else allp[:: len(allp) // 2_000_000 + 1]
        xy, _ = cam.project(stack)
        cam.bounds = (*xy.min(0), *xy.max(0))
        first = self.points(self.codes[0])
        cam.grounds = {id(m): _ground_tiles(first[i], m, lo, hi) for i, m in enumerate(self.meshes) if m.ground}
        for m, p in zip(self.meshes, first):
            if not m.ground and p is not None and len(p) > m.tris.max():
                _split_large_faces(m, p, float(np.linalg.norm(hi - lo)) / 16.0)
        return cam


def _open_stage(path: Path):
    if not path.exists():
        raise InvalidParameter(f"USD file '{path}' not found")
    if path.is_dir():
        raise InvalidParameter(f"'{path}' is a folder, not a USD file")
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise InvalidParameter(f"'{path}' cannot be read ({exc.strerror or exc})") from None
    if not head.startswith(_USD_MAGIC):
        raise InvalidParameter(f"'{path}' is not a USD file (.usd, .usda, .usdc or .usdz)")
    from pxr import Usd

    try:
        stage = Usd.Stage.Open(str(path))
    except Exception as exc:  # noqa: BLE001 - pxr raises Tf.ErrorException on any unreadable layer
        raise InvalidParameter(f"'{path}' cannot be opened as USD ({_usd_reason(exc)})") from None
    if stage is None:
        raise InvalidParameter(f"'{path}' cannot be opened as USD")
    return stage


def _usd_reason(exc: BaseException) -> str:
    """The first of the errors in a pxr ``Tf.ErrorException``, in a few words."""
    msgs = [m.group(1) for m in re.finditer(r"Error in .*? : '(.*)'", str(exc))]
    if not msgs:
        return str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
    where = re.search(r":(\d+):(\d+): parse error", msgs[0])
    return f"parse error at line {where.group(1)}, column {where.group(2)}" if where else msgs[0][:200]


def _read_mesh(mesh) -> _Mesh | None:
    from pxr import UsdGeom

    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
    if len(counts) == 0 or counts.sum() != len(indices):
        return None
    # fan triangulation: face f with c corners -> (s, s+k, s+k+1) for k in 1..c-2
    starts = np.cumsum(counts) - counts
    ntri = np.maximum(counts - 2, 0)
    face = np.repeat(np.arange(len(counts)), ntri)
    if len(face) == 0:
        return None
    k = np.arange(len(face)) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
    s = starts[face]
    corners = np.stack([s, s + k, s + k + 1], axis=1)  # face-vertex slots
    tris = indices[corners]
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        tris = tris[:, ::-1]
        corners = corners[:, ::-1]
    colors = _face_colors(mesh, face, tris, corners, len(counts))
    # closed and consistently oriented: each directed edge once, its reverse once
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    key = e[:, 0] * (int(e.max()) + 1) + e[:, 1]
    rkey = e[:, 1] * (int(e.max()) + 1) + e[:, 0]
    closed = len(np.unique(key)) == len(key) and bool(np.all(np.isin(rkey, key)))
    return _Mesh(mesh.GetPrim(), mesh.GetPointsAttr(), tris, colors, closed)


def _face_colors(mesh, face: np.ndarray, tris: np.ndarray, corners: np.ndarray, n_faces: int) -> np.ndarray:
    from pxr import UsdGeom

    n = len(tris)
    pv = UsdGeom.PrimvarsAPI(mesh.GetPrim()).GetPrimvar("displayColor")
    values = pv.ComputeFlattened() if pv and pv.HasValue() else None
    if values is None or len(values) == 0:
        return np.tile(DEFAULT_COLOR, (n, 1))
    c = np.clip(np.asarray(values, dtype=np.float64).reshape(-1, 3), 0.0, 1.0)
    interp = pv.GetInterpolation()
    try:
        if interp == UsdGeom.Tokens.uniform and len(c) >= n_faces:
            return c[face]
        if interp in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying) and len(c) > tris.max():
            return c[tris].mean(1)
        if interp == UsdGeom.Tokens.faceVarying and len(c) > corners.max():
            return c[corners].mean(1)
    except IndexError:
        pass
    return np.tile(c[0], (n, 1))


# --- camera, ground and shading ---------------------------------------------------------------------


class _Camera:
    """Perspective camera looking at the centre of ``[lo, hi]`` from the front-top, 3/4 (Y up)."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray) -> None:
        self.lo, self.hi = lo, hi
        center = 0.5 * (lo + hi)
        radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
        to_eye = np.array([math.sin(_AZIMUTH) * math.cos(_ELEVATION), math.sin(_ELEVATION),
                           math.cos(_AZIMUTH) * math.cos(_ELEVATION)])
        self.eye = center + to_eye * radius / math.sin(0.5 * _FOV)
        fwd = -to_eye
        right = np.cross(fwd, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        self.rot = np.stack([right, up, fwd])  # rows: camera x, y, depth
        # one light from above, behind the camera and a little to its left: top, left and right faces
        # of a box get three distinct tones; ambient keeps the faces turned away readable
        light = 0.8 * np.array([0.0, 1.0, 0.0]) + 1.0 * to_eye - 0.3 * right
        self.light = light / np.linalg.norm(light)
        self.bounds = (-1.0, -1.0, 1.0, 1.0)
        self.grounds: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, float]] = {}

    def project(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points (..., 3) -> image plane (..., 2) and depth (...)."""
        c = (p - self.eye) @ self.rot.T
        z = np.maximum(c[..., 2], 1e-9)
        return c[..., :2] / z[..., None], c[..., 2]


def _nice(x: float) -> float:
    e = 10.0 ** math.floor(math.log10(x))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * e >= x:
            return m * e
    return 10.0 * e


def _clip(poly: list[np.ndarray], normal: np.ndarray, offset: float) -> list[np.ndarray]:
    """Sutherland-Hodgman: the part of a convex polygon where normal . p <= offset."""
    out = []
    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        da, db = float(a @ normal) - offset, float(b @ normal) - offset
        if da <= 0:
            out.append(a)
        if (da <= 0) != (db <= 0):
            out.append(a + (da / (da - db)) * (b - a))
    return out


def _ground_tiles(points: np.ndarray, mesh: _Mesh, lo: np.ndarray, hi: np.ndarray):
    """A ground mesh cut to a margin around ``[lo, hi]`` and split in checker tiles.

    Returns (triangles (T, 3, 3), colours (T, 3), plane normal (facing up), plane offset)."""
    margin = 0.35 * float(np.max(hi - lo)) + 1e-3
    blo, bhi = lo - margin, hi + margin
    base = np.asarray(mesh.colors[0], dtype=np.float64)
    light = 0.4 * base + 0.6  # the ground as a light backdrop, tinted by its colour
    tri_out, col_out = [], []
    e = mesh.tris
    normal = np.cross(points[e[0, 1]] - points[e[0, 0]], points[e[0, 2]] - points[e[0, 0]])
    normal /= np.linalg.norm(normal) or 1.0
    if normal[1] < 0:
        normal = -normal
    offset = float(points[e[0, 0]] @ normal)
    # in-plane axes: world X (or Z) projected on the plane
    a = np.array([1.0, 0, 0]) if abs(normal[0]) < 0.9 else np.array([0, 0, 1.0])
    a = a - (a @ normal) * normal
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    for t in e:
        poly = [points[i] for i in t]
        for axis in range(3):
            ax = np.eye(3)[axis]
            poly = _clip(poly, ax, float(bhi[axis]))
            if poly:
                poly = _clip(poly, -ax, float(-blo[axis]))
            if not poly:
                break
        if len(poly) < 3:
            continue
        uv = np.array([[p @ a, p @ b] for p in poly])
        cell = _nice(float(np.max(uv.max(0) - uv.min(0))) / 12.0)
        centroid = uv.mean(0)
        edges = []
        for i in range(len(uv)):
            d = uv[(i + 1) % len(uv)] - uv[i]
            n2 = np.array([d[1], -d[0]])
            off = float(n2 @ uv[i])
            if n2 @ centroid > off:
                n2, off = -n2, -off
            edges.append((n2, off))
        i0, j0 = np.floor(uv.min(0) / cell).astype(int)
        i1, j1 = np.ceil(uv.max(0) / cell).astype(int)
        origin = offset * normal
        for i in range(i0, i1):
            for j in range(j0, j1):
                sq = [np.array([i, j]) * cell, np.array([i + 1, j]) * cell,
                      np.array([i + 1, j + 1]) * cell, np.array([i, j + 1]) * cell]
                for n2, off in edges:
                    sq = _clip(sq, n2, off)
                    if not sq:
                        break
                if len(sq) < 3:
                    continue
                p3 = [origin + u * a + v * b for u, v in sq]
                shade = light if (i + j) % 2 == 0 else light * 0.94
                for k in range(1, len(p3) - 1):
                    tri_out.append([p3[0], p3[k], p3[k + 1]])
                    col_out.append(shade)
    if not tri_out:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), normal, offset
    return np.array(tri_out), np.clip(np.array(col_out), 0, 1), normal, offset


def _split_large_faces(mesh: _Mesh, points: np.ndarray, h: float, max_level: int = 4) -> None:
    """Plan the split of triangles with edges longer than ``h`` (a paddle's long faces) into 4**L
    sub-triangles, so that sorting faces by depth stays right next to smaller neighbours."""
    v = points[mesh.tris]
    longest = np.max(np.linalg.norm(v - v[:, [1, 2, 0]], axis=2), axis=1)
    level = np.clip(np.ceil(np.log2(np.maximum(longest / h, 1.0))), 0, max_level).astype(int)
    if not level.any():
        return
    source, weights = [], []
    for lev in np.unique(level):
        n = 2 ** int(lev)
        sub = []
        for i in range(n):
            for j in range(n - i):
                sub.append([(i, j), (i + 1, j), (i, j + 1)])
                if j < n - i - 1:
                    sub.append([(i + 1, j), (i + 1, j + 1), (i, j + 1)])
        ij = np.array(sub, dtype=np.float64) / n  # (k, 3 corners, 2)
        w = np.stack([1.0 - ij[..., 0] - ij[..., 1], ij[..., 0], ij[..., 1]], axis=-1)  # (k, 3, 3)
        tri = np.nonzero(level == lev)[0]
        source.append(np.repeat(tri, len(w)))
        weights.append(np.tile(w, (len(tri), 1, 1)))
    mesh.source, mesh.weights = np.concatenate(source), np.concatenate(weights)


def _frame_polygons(scene: _Scene, cam: _Camera, code: float) -> tuple[np.ndarray, np.ndarray]:
    """The 2-D triangles (P, 3, 2) of one frame in drawing order, and their colours (P, 3)."""
    back_t, back_c, tris, cols = [], [], [], []
    for m, p in zip(scene.meshes, scene.points(code)):
        if p is None or m.ground:
            continue
        if len(p) <= m.tris.max():
            continue
        v = p[m.tris]  # (T, 3, 3)
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
        c = v.mean(1)
        lam = n @ cam.light
        if m.closed:
            vol = float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum())
            if vol < 0:  # inward-oriented: flip
                n, lam = -n, -lam
            keep = np.einsum("ij,ij->i", n, cam.eye - c) > 0
            lam = np.maximum(lam, 0.0)
        else:
            keep = np.ones(len(v), dtype=bool)
            lam = np.abs(lam)
        color = m.colors * (_AMBIENT + (1.0 - _AMBIENT) * lam)[:, None]
        if m.source is None:
            tris.append(v[keep])
            cols.append(color[keep])
        else:
            sel = keep[m.source]
            src = m.source[sel]
            tris.append(np.einsum("sij,sjk->sik", m.weights[sel], v[src]))
            cols.append(color[src])
        # shadows on each ground plane: the faces turned up, dropped straight down onto it
        for gt, gc, gn, goff in cam.grounds.values():
            if len(gt) == 0 or gn[1] < 0.9:
                continue
            up = (n @ gn > 0) if m.closed else np.ones(len(v), dtype=bool)
            h = v[up] @ gn - goff  # (S, 3) heights
            sv = v[up] - h[..., None] * gn
            sv += 1e-4 * gn
            back_t.append(sv)
            back_c.append(np.tile(gc.mean(0) * 0.6 if len(gc) else (0.5, 0.5, 0.5), (len(sv), 1)))
    ground_t = [g[0] for g in cam.grounds.values() if len(g[0])]
    ground_c = [g[1] for g in cam.grounds.values() if len(g[0])]
    if tris:
        t3 = np.concatenate(tris)
        c3 = np.concatenate(cols)
        _, depth = cam.project(t3.mean(1))
        order = np.argsort(-depth, kind="stable")  # far first
        t3, c3 = t3[order], c3[order]
    else:
        t3, c3 = np.zeros((0, 3, 3)), np.zeros((0, 3))
    all_t = np.concatenate(ground_t + back_t + [t3]) if (ground_t or back_t) else t3
    all_c = np.concatenate(ground_c + back_c + [c3]) if (ground_c or back_c) else c3
    xy, _ = cam.project(all_t)
    return xy, np.clip(all_c, 0.0, 1.0)


# --- drawing ------------------------------------------------------------------------------------------


def _limits(cam: _Camera, aspect: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """Axis limits around the camera's bounds, padded and widened to a tile of width/height ``aspect``."""
    x0, y0, x1, y1 = cam.bounds
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    w, h = max(x1 - x0, 1e-9) * 1.08, max(y1 - y0, 1e-9) * 1.08
    if w / h < aspect:
        w = h * aspect
    else:
        h = w / aspect
    return (cx - 0.5 * w, cx + 0.5 * w), (cy - 0.5 * h, cy + 0.5 * h)


def _grid(n: int, size: tuple[int, int], cam: _Camera) -> tuple[int, int]:
    """Columns and rows of the contact sheet that show the content largest."""
    x0, y0, x1, y1 = cam.bounds
    cw, ch = max(x1 - x0, 1e-9), max(y1 - y0, 1e-9)
    best = (0.0, 1, n)
    for cols in range(1, n + 1):
        rows = math.ceil(n / cols)
        scale = min(size[0] / cols / cw, size[1] / rows / ch)
        if scale > best[0] * 1.0001:
            best = (scale, cols, rows)
    return best[1], best[2]


def _label(scene: _Scene, code: float) -> str:
    if scene.static:
        return ""
    frame = f"{int(code)}" if float(code).is_integer() else f"{code:g}"
    return f"frame {frame}  t = {code / scene.tcps:.2f} s"


def _new_figure(size: tuple[int, int]):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] / 100.0, size[1] / 100.0), dpi=100, facecolor=(1.0, 1.0, 1.0))  # gaps between tiles
    FigureCanvasAgg(fig)
    return fig


def _tile(fig, rect: tuple[float, float, float, float], cam: _Camera, pixels: tuple[float, float]):
    from matplotlib.collections import PolyCollection

    ax = fig.add_axes(rect)
    ax.set_axis_off()
    ax.set_facecolor(BACKGROUND)
    xlim, ylim = _limits(cam, pixels[0] / pixels[1])
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    coll = PolyCollection(np.zeros((0, 3, 2)), linewidths=0.7, antialiaseds=True)
    ax.add_collection(coll)
    fontsize = min(max(pixels[1] / 26.0, 6.0), 12.0)
    text = ax.text(0.02, 0.97, "", transform=ax.transAxes, ha="left", va="top", fontsize=fontsize,
                   color=(0.15, 0.15, 0.18), family="DejaVu Sans")
    return coll, text


def _fill(coll, text, scene: _Scene, cam: _Camera, code: float) -> None:
    xy, colors = _frame_polygons(scene, cam, code)
    coll.set_verts(xy)
    coll.set_facecolor(colors)
    coll.set_edgecolor(colors)  # the same colour: hides the seams between neighbouring faces
    text.set_text(_label(scene, code))


def _pixels(fig, size: tuple[int, int]) -> np.ndarray:
    """The drawn figure as an RGB array of exactly ``size``."""
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3]
    h, w = rgb.shape[:2]
    if (w, h) != size:  # float rounding of the figure size: pad or crop by a pixel
        out = np.empty((size[1], size[0], 3), dtype=np.uint8)
        out[...] = np.round(np.array(BACKGROUND) * 255).astype(np.uint8)
        out[: min(h, size[1]), : min(w, size[0])] = rgb[: size[1], : size[0]]
        rgb = out
    return np.ascontiguousarray(rgb)


def _write_sheet(scene: _Scene, cam: _Camera, picks: list[float], out: Path, size: tuple[int, int]) -> None:
    from PIL import Image

    cols, rows = _grid(len(picks), size, cam)
    fig = _new_figure(size)
    gap = 6.0 if cols * rows > 1 else 0.0  # pixels between tiles
    tw, th = (size[0] - gap * (cols - 1)) / cols, (size[1] - gap * (rows - 1)) / rows
    for k, code in enumerate(picks):
        r, c = divmod(k, cols)
        rect = (c * (tw + gap) / size[0], 1.0 - (r * (th + gap) + th) / size[1], tw / size[0], th / size[1])
        coll, text = _tile(fig, rect, cam, (tw, th))
        _fill(coll, text, scene, cam, code)
    image = Image.fromarray(_pixels(fig, size))
    _atomic(out, lambda tmp: image.save(tmp, format="PNG", optimize=True))


def _write_animation(scene: _Scene, cam: _Camera, picks: list[float], out: Path, size: tuple[int, int],
                     fps: float) -> None:
    fig = _new_figure(size)
    coll, text = _tile(fig, (0.0, 0.0, 1.0, 1.0), cam, size)
    if out.suffix.lower() == ".gif":
        from PIL import Image

        frames = []
        for code in picks:
            _fill(coll, text, scene, cam, code)
            frames.append(Image.fromarray(_pixels(fig, size)))
        # one palette for every frame (no flicker): median cut of the first, middle and last frames
        probe = [frames[0], frames[len(frames) // 2], frames[-1]]
        strip = Image.new("RGB", (size[0], size[1] * len(probe)))
        for i, f in enumerate(probe):
            strip.paste(f, (0, i * size[1]))
        palette = strip.quantize(colors=255, method=Image.Quantize.MEDIANCUT)
        frames = [f.quantize(palette=palette, dither=Image.Dither.NONE) for f in frames]
        duration = max(int(round(1000.0 / fps)), 20)
        _atomic(out, lambda tmp: frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:],
                                                duration=duration, loop=0))
        return
    from matplotlib.animation import FFMpegWriter

    def write(tmp: str) -> None:
        writer = FFMpegWriter(fps=fps, codec="h264", extra_args=["-pix_fmt", "yuv420p"])
        try:
            with writer.saving(fig, tmp, dpi=100):
                for code in picks:
                    _fill(coll, text, scene, cam, code)
                    writer.grab_frame(facecolor=BACKGROUND)
        except (RuntimeError, subprocess.SubprocessError) as exc:  # ffmpeg failed
            reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise OutputError(f"output '{out}': ffmpeg failed ({reason}); write a .gif instead") from None

    _atomic(out, write)


def _atomic(out: Path, write) -> None:
    """``write(tmp)`` a temporary file beside ``out``, then rename it onto ``out``."""
    folder = out.parent if str(out.parent) else Path(".")
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{out.name}.", suffix=out.suffix)
        os.close(fd)
    except OSError as exc:
        raise OutputError(f"output '{out}' cannot be written ({exc.strerror or exc})") from None
    try:
        write(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes it private; the output gets the usual mode
        os.replace(tmp, out)
    except OSError as exc:
        raise OutputError(f"output '{out}' cannot be written ({exc.strerror or exc})") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
