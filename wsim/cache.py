"""On-disk HDF5 cache for precomputed operators (BEM matrices, PBD constraint colourings...).

Design:

* **Content hashing.** A cache entry is named by a SHA-256 over everything the operator depends
  on: the input arrays (name, dtype, shape, bytes), the parameters (material, dt, options) as
  canonical JSON, the operator's own format ``version`` and this file layout's
  ``FORMAT_VERSION``. A key can therefore never point at an operator built from other inputs,
  and no invalidation logic is needed: changed inputs simply give another file name.
* **Per-dataset checksums.** The key says what *should* be in a file, not that the bytes on
  disk are still intact. Every dataset stores a SHA-256 of its dtype, shape and the SHA-256s of
  its ``CHUNK_BYTES`` pieces, verified on every load, so bit rot, a half-copied file or a
  hand-edited one is recomputed instead of silently feeding a wrong matrix to the solver.
* **Parallel I/O.** A dataset's contiguous storage is laid out by h5py, then its pieces are
  written (and on a load read) by threads at their file offsets with ``pwrite`` / ``preadv``,
  each piece hashed by the thread that moves it: one h5py call per dataset runs on one core.
  Where those calls are missing (Windows) h5py moves the datasets whole; the files and
  checksums are the same either way.
* **Atomic writes.** A file is written to a temporary name in the cache folder, then
  ``os.replace``-d onto its final name. Readers (other processes, a later run after a full disk
  or a killed writer) see either no file or a complete one; concurrent writers of the same key
  both write complete files and the last rename wins. The file is not fsynced: a power loss
  before the kernel writes it back can leave a renamed but torn file, which the checksums below
  catch on its next load (it is recomputed), and forcing a BEM set to the disk costs more than
  its build (the bunny's 7.9 GB: 8.2-10.5 s of store on an H100 host, issue 21).
* A cache is an optimisation: a bad file is reported in one warning line and recomputed, and an
  unwritable cache folder only costs the recomputation. Neither ever stops a simulation.
* **Size cap, least recently used eviction.** BEM operator sets are hundreds of MB per body, so
  the folder is capped at ``$WSIM_CACHE_MAX_GB`` gigabytes (decimal, 10**9 bytes; float;
  default :data:`DEFAULT_MAX_GB` = 10; ``0`` or ``inf`` means no cap). "Used" means stored or
  loaded: a successful ``load`` sets the file's mtime to now with ``os.utime`` (atime is
  useless on noatime/relatime mounts), so mtime is the time of last use. After every successful
  ``store`` the least recently used entries (oldest mtime first, ties by name) are deleted until
  the folder's total is within the cap; the entry just stored is never evicted, so a single
  entry larger than the cap stays (alone). Sizes are file sizes (``st_size``).
* **Only our own files are ever deleted.** Eviction and ``clear_cache`` consider only regular
  files (not symlinks, not folders) directly in the cache folder whose name is exactly
  ``<kind>-<32 lowercase hex>.h5`` (what ``path_for`` makes from a content key). Temporary files
  of writers in progress (``.tmp-*.h5``) and anything else a user put in the folder never match.
  A file that cannot be deleted (permissions, locked by another process on Windows, already
  removed by a concurrent eviction) is skipped without error.
* An invalid ``$WSIM_CACHE_MAX_GB`` (not a number, negative, NaN) is reported in one
  :class:`CacheWarning` line naming the variable and its value, and the default cap is used: a
  typo in a tuning variable must not stop a simulation, and the default still bounds the disk
  use. ``wsim cache info`` shows which cap is in force and where it comes from.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import math
import os
import pathlib
import re
import stat
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timezone
from typing import Any, NamedTuple

import h5py
import numpy as np

FORMAT_VERSION: int = 2
"""Version of the cache file layout itself (attributes, checksum definition, key recipe)."""

_KIND_RE = re.compile(r"[A-Za-z0-9_-]+")
_NAME_RE = re.compile(r"[A-Za-z0-9_.-]+")
# The only file names eviction and clear_cache may delete: what path_for makes of a content key.
_ENTRY_RE = re.compile(r"([A-Za-z0-9_-]+)-([0-9a-f]{32})\.h5")

MAX_GB_ENV: str = "WSIM_CACHE_MAX_GB"
DEFAULT_MAX_GB: float = 10.0
"""Default size cap of the cache folder in GB (10**9 bytes), used when ``$WSIM_CACHE_MAX_GB``
is unset, empty or invalid."""


class CacheWarning(UserWarning):
    """A cache file was unusable (and is recomputed) or a result could not be stored."""


def default_cache_dir() -> pathlib.Path:
    """``$WSIM_CACHE_DIR`` if set, else the platform's user cache folder plus ``wsim``."""
    env = os.environ.get("WSIM_CACHE_DIR")
    if env:
        return pathlib.Path(env).expanduser()
    home = pathlib.Path.home()
    if sys.platform == "win32":
        local = os.environ.get("LOCALAPPDATA")
        return (pathlib.Path(local) if local else home / "AppData" / "Local") / "wsim" / "Cache"
    if sys.platform == "darwin":
        return home / "Library" / "Caches" / "wsim"
    xdg = os.environ.get("XDG_CACHE_HOME")
    # The XDG spec says a relative value is invalid and must be ignored.
    base = pathlib.Path(xdg) if xdg and os.path.isabs(xdg) else home / ".cache"
    return base / "wsim"


def _feed(h: Any, *fields: bytes | str | memoryview) -> None:
    # Length-prefix every field so that ("ab", "c") and ("a", "bc") cannot hash alike.
    for field in fields:
        data = field.encode() if isinstance(field, str) else field
        h.update(memoryview(data).nbytes.to_bytes(8, "little"))
        h.update(data)


def _array_digest(h: Any, a: np.ndarray) -> None:
    if a.dtype.hasobject:
        raise TypeError(f"arrays of dtype {a.dtype} hold pointers, not data, and cannot be hashed")
    # a byte view, not tobytes(): operator sets are gigabytes, and a copy would double the memory
    data = memoryview(np.ascontiguousarray(a).reshape(-1)).cast("B")
    _feed(h, a.dtype.str, json.dumps(list(a.shape)), data)


CHUNK_BYTES: int = 64 << 20
"""Bytes per piece of a dataset: the unit of the parallel writes and reads and a leaf of its
checksum."""

# pwrite / preadv release the GIL, so threads move a dataset's pieces at once (POSIX; elsewhere
# h5py writes and reads every dataset whole)
_RAW_IO: bool = hasattr(os, "pwrite") and hasattr(os, "preadv")


def _workers() -> int:
    return max(1, min(16, os.cpu_count() or 1))


def _pieces(nbytes: int) -> list[tuple[int, int]]:
    return [(s, min(s + CHUNK_BYTES, nbytes)) for s in range(0, nbytes, CHUNK_BYTES)] or [(0, 0)]


def _byte_view(a: np.ndarray) -> memoryview:
    """The array's bytes in C order (a non-contiguous array is copied; any dtype, byte order)."""
    return memoryview(np.ascontiguousarray(a).reshape(-1).view(np.uint8))


def _hash_piece(piece: memoryview) -> bytes:
    return hashlib.sha256(piece).digest()


def _write_piece(fd: int, piece: memoryview, at: int) -> bytes:
    done = 0
    while done < len(piece):
        done += os.pwrite(fd, piece[done:], at + done)
    return _hash_piece(piece)


def _read_piece(fd: int, piece: memoryview, at: int) -> bytes:
    done = 0
    while done < len(piece):
        got = os.preadv(fd, [piece[done:]], at + done)
        if got <= 0:
            raise EOFError(f"file ends inside a dataset (byte {at + done})")
        done += got
    return _hash_piece(piece)


def _dataset_digest(name: str, dtype: np.dtype, shape: tuple[int, ...], leaves: list[bytes]) -> str:
    """A dataset's checksum: SHA-256 over its name, dtype, shape and the SHA-256 of each
    ``CHUNK_BYTES`` piece of its C-ordered bytes (pieces hash in parallel; one flipped bit in any
    piece changes it all the same; a flipped bit in the name, which HDF5 keeps apart from the
    data, too)."""
    h = hashlib.sha256()
    _feed(h, name, dtype.str, json.dumps(list(shape)))
    for leaf in leaves:
        h.update(leaf)
    return h.hexdigest()


def _raw(dtype: np.dtype, shape: tuple[int, ...]) -> bool:
    """Whether a dataset moves as raw bytes at its file offset: plain numbers, not empty, not 0-d
    (h5py stores these with their bytes unchanged, contiguous)."""
    return (_RAW_IO and dtype.kind in "fiu" and dtype.itemsize <= 8 and len(shape) >= 1
            and int(np.prod(shape)) > 0)


def _early_contiguous() -> Any:
    """Dataset creation: contiguous storage allocated at creation (so its file offset is known
    before any data is written) and never filled (every byte is written after)."""
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_layout(h5py.h5d.CONTIGUOUS)
    dcpl.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)
    dcpl.set_fill_time(h5py.h5d.FILL_TIME_NEVER)
    return dcpl


def _move_pieces(fd: int, arrays: Mapping[str, np.ndarray], offsets: Mapping[str, int],
                 move: Callable[..., bytes]) -> dict[str, list[bytes]]:
    """Each dataset's pieces moved (written from or read into ``arrays`` at ``offsets`` in the
    open file ``fd``) and hashed in threads; the datasets without an offset only hashed. Returns
    the pieces' digests per dataset. A non-contiguous array is copied to C order one at a time
    (scipy's solves give Fortran-ordered products: 7.3 GB each at N = 10k in float64). A failed
    piece cancels the pieces not started."""
    pool = ThreadPoolExecutor(max_workers=_workers())

    def submit(name: str, view: memoryview) -> list[Any]:
        return [pool.submit(move, fd, view[s:e], offsets[name] + s) if name in offsets
                else pool.submit(_hash_piece, view[s:e]) for s, e in _pieces(len(view))]

    try:
        futures = {name: submit(name, _byte_view(a)) for name, a in arrays.items() if a.flags.c_contiguous}
        leaves: dict[str, list[bytes]] = {}
        for name, a in arrays.items():
            if not a.flags.c_contiguous:
                leaves[name] = [f.result() for f in submit(name, _byte_view(a))]
        leaves.update({name: [f.result() for f in fs] for name, fs in futures.items()})
        return leaves
    except BaseException:
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    finally:
        pool.shutdown(wait=True)


def _canonical(value: Any, where: str) -> Any:
    """Map a parameter to plain JSON types, one representation per value, or raise TypeError."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        # Exact for float16/32/64. json writes floats with repr(), the shortest string that
        # round-trips, so 0.1 and 0.1000000001 differ (and nan/inf become NaN/Infinity).
        return float(value)
    if isinstance(value, np.ndarray):
        h = hashlib.sha256()
        try:
            _array_digest(h, value)
        except TypeError:
            raise TypeError(f"parameter '{where}': object arrays are not supported") from None
        return {"__ndarray__": [value.dtype.str, list(value.shape), h.hexdigest()]}
    if isinstance(value, (list, tuple)):
        return [_canonical(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"parameter '{where}': dict key {k!r} is not a str")
            out[k] = _canonical(v, f"{where}.{k}" if where else k)
        return out
    raise TypeError(f"parameter '{where}' has unsupported type {type(value).__name__}")


def content_key(kind: str, *, arrays: Mapping[str, np.ndarray], params: Mapping[str, Any],
                version: int) -> str:
    """Hex SHA-256 identifying an operator of ``kind`` built from ``arrays`` and ``params``."""
    h = hashlib.sha256()
    _feed(h, str(FORMAT_VERSION), kind, str(int(version)))
    for name in sorted(arrays):
        _feed(h, name)
        _array_digest(h, np.asarray(arrays[name]))
    _feed(h, json.dumps(_canonical(params, ""), sort_keys=True, separators=(",", ":")))
    return h.hexdigest()


def _h5open(path: str | pathlib.Path, mode: str) -> h5py.File:
    # HDF5 file locking fails on read-only folders and many NFS mounts; our files are never
    # modified in place (atomic rename), so locks buy nothing. (`locking`: h5py >= 3.5; we pin 3.8.)
    return h5py.File(path, mode, locking=False)


def _wsim_version() -> str:
    try:
        return importlib.metadata.version("wsim")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _warn(path: pathlib.Path, reason: str, tail: str) -> None:
    reason = " ".join(str(reason).split())  # HDF5 messages may span lines; the warning may not
    warnings.warn(f"wsim cache: {path}: {reason}; {tail}", CacheWarning, stacklevel=3)


class OperatorCache:
    """A folder of ``<kind>-<key prefix>.h5`` files, one per operator."""

    def __init__(self, directory: str | os.PathLike[str] | None = None) -> None:
        # Resolved now, so a later change of cwd or $WSIM_CACHE_DIR does not move the cache.
        base = default_cache_dir() if directory is None else pathlib.Path(directory)
        self.directory: pathlib.Path = base.expanduser().absolute()
        self.hits: int = 0
        self.misses: int = 0

    def path_for(self, kind: str, key: str) -> pathlib.Path:
        if not _KIND_RE.fullmatch(kind):
            raise ValueError(f"cache kind {kind!r} must match [A-Za-z0-9_-]+")
        return self.directory / f"{kind}-{key[:32]}.h5"

    def load(self, kind: str, key: str) -> dict[str, np.ndarray] | None:
        """The stored arrays, or None on a miss or an unusable file (warned about)."""
        path = self.path_for(kind, key)
        if not path.exists():
            return None
        out: dict[str, np.ndarray] = {}
        stored: dict[str, Any] = {}  # each dataset's recorded checksum
        offsets: dict[str, int] = {}  # the datasets read as raw pieces: their file offsets
        fd = -1
        reason: str | None = None
        try:
            with _h5open(path, "r") as f:
                a = f.attrs
                if a.get("format_version") != FORMAT_VERSION:
                    found = a.get("format_version")
                    reason = f"stale (format_version {found}, expected {FORMAT_VERSION})"
                elif a.get("kind") != kind:
                    reason = f"stale (kind {a.get('kind')!r}, expected {kind!r})"
                elif a.get("key") != key:
                    reason = "stale (stored key differs)"
                elif sorted(json.loads(a.get("datasets", "null")) or []) != sorted(f.keys()):
                    reason = "datasets missing or renamed (corrupt)"
                else:
                    for name, ds in f.items():
                        if not isinstance(ds, h5py.Dataset):
                            reason = f"unexpected group {name!r}"
                            break
                        stored[name] = ds.attrs.get("sha256")
                        offset = ds.id.get_offset() if _raw(ds.dtype, ds.shape) else None
                        if offset is not None and ds.chunks is None and ds.compression is None:
                            out[name] = np.empty(ds.shape, ds.dtype)  # read below, in pieces
                            offsets[name] = offset
                        else:
                            out[name] = np.asarray(ds[()])  # np.asarray: 0-d datasets read as scalars
                    if offsets:  # the file h5py read, not whatever a concurrent writer renamed onto its name since
                        fd = os.dup(f.id.get_vfd_handle())
            if reason is None:
                leaves = _move_pieces(fd, out, offsets, _read_piece)
                bad = [n for n, a in out.items() if stored[n] != _dataset_digest(n, a.dtype, a.shape, leaves[n])]
                if bad:
                    reason = f"dataset {bad[0]!r} failed its sha256 check (corrupt)"
        except Exception as exc:  # any unreadable file is just a cache miss
            reason = f"unreadable ({type(exc).__name__}: {exc})"
        finally:
            if fd >= 0:
                os.close(fd)
        if reason is not None:
            _warn(path, reason, "recomputing")
            return None
        try:
            os.utime(path)  # mtime = time of last use, the signal of least-recently-used eviction
        except OSError:
            pass  # a read-only shared cache: the entry just ages as if it were not used
        return out

    def store(self, kind: str, key: str, arrays: Mapping[str, np.ndarray],
              meta: Mapping[str, Any] | None = None) -> pathlib.Path | None:
        """Write ``arrays`` atomically; return the path, or None (warned) if the disk refused."""
        path = self.path_for(kind, key)
        data = {name: np.asarray(a) for name, a in arrays.items()}
        for name, a in data.items():  # validate before touching the disk
            if not _NAME_RE.fullmatch(name):
                raise ValueError(f"dataset name {name!r} must match [A-Za-z0-9_.-]+")
            if a.dtype.hasobject:
                raise TypeError(f"dataset {name!r}: dtype {a.dtype} cannot be cached")
        tmp: str | None = None
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".h5", dir=self.directory)
            os.close(fd)  # h5py opens by name; the empty file just reserves a unique one
            with _h5open(tmp, "w") as f:
                f.attrs["key"] = key
                f.attrs["kind"] = kind
                f.attrs["format_version"] = FORMAT_VERSION
                f.attrs["wsim_version"] = _wsim_version()
                f.attrs["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
                f.attrs["meta"] = json.dumps(dict(meta or {}), sort_keys=True, default=str)
                # The datasets' storage is laid out here and their bytes written after, in
                # ``CHUNK_BYTES`` pieces by threads at their file offsets, each piece hashed as it
                # goes: h5py writes one dataset at a time on one thread, and the bunny's 7.9 GB
                # took 5.5-6.6 s so on an H100 host with the checksums hashed alongside.
                # Contiguous and uncompressed: dense operators barely compress, and reads stay a
                # few large I/Os.
                offsets: dict[str, int] = {}
                for name, a in data.items():
                    if _raw(a.dtype, a.shape):
                        ds = f.create_dataset(name, shape=a.shape, dtype=a.dtype, dcpl=_early_contiguous())
                        offset = ds.id.get_offset()
                        if offset is not None:
                            offsets[name] = offset
                            continue
                        ds[...] = a
                    else:
                        f.create_dataset(name, data=a)
            fd = os.open(tmp, os.O_WRONLY | getattr(os, "O_BINARY", 0))
            try:
                leaves = _move_pieces(fd, data, offsets, _write_piece)
            finally:
                os.close(fd)
            with _h5open(tmp, "r+") as f:
                f.attrs["datasets"] = json.dumps(sorted(data))
                for name, a in data.items():
                    f[name].attrs["sha256"] = _dataset_digest(name, a.dtype, a.shape, leaves[name])
            os.chmod(tmp, 0o644)  # mkstemp makes 0600; a shared cache must stay readable
            os.replace(tmp, path)
            tmp = None
        except OSError as exc:  # unwritable folder, full disk...: the run goes on uncached
            _warn(path, f"cannot store ({type(exc).__name__}: {exc})", "continuing without cache")
            return None
        finally:
            if tmp is not None:
                try:
                    os.unlink(tmp)
                except OSError:
                    pass
        try:
            enforce_cap(self.directory, keep=path)
        except OSError:  # e.g. the folder vanished meanwhile: eviction is best effort
            pass
        return path

    def get_or_build(self, kind: str, *, arrays: Mapping[str, np.ndarray],
                     params: Mapping[str, Any], version: int,
                     build: Callable[[], Mapping[str, np.ndarray]],
                     meta: Mapping[str, Any] | None = None) -> dict[str, np.ndarray]:
        """The cached operator for these inputs, built and stored on a miss or bad file."""
        key = content_key(kind, arrays=arrays, params=params, version=version)
        cached = self.load(kind, key)
        if cached is not None:
            self.hits += 1
            return cached
        self.misses += 1
        result = {name: np.asarray(a) for name, a in build().items()}
        self.store(kind, key, result, meta)
        return result


# --- size: listing, clearing, the cap -----------------------------------------------------------

class CacheEntry(NamedTuple):
    """One operator file of a cache folder."""

    path: pathlib.Path
    kind: str
    key_prefix: str  # the 32 hex digits of the file name (the first half of the content key)
    size: int  # bytes on disk (st_size)
    last_used: float  # mtime, seconds since the epoch: when it was last stored or loaded


class Cleared(NamedTuple):
    """What ``clear_cache`` or ``enforce_cap`` did."""

    removed: int  # entries deleted
    freed: int  # bytes freed
    skipped: int  # entries that could not be deleted (permissions, in use on Windows...)


def _folder(directory: str | os.PathLike[str] | None) -> pathlib.Path:
    base = default_cache_dir() if directory is None else pathlib.Path(directory)
    return base.expanduser().absolute()


def cache_entries(directory: str | os.PathLike[str] | None = None) -> list[CacheEntry]:
    """The entries of a cache folder (default: ``default_cache_dir()``), least recently used first.

    That is the order eviction deletes them in. Only regular files directly in the folder named
    ``<kind>-<32 hex>.h5`` count: temporary files of writers in progress, symlinks, folders and
    anything else are not entries. A missing or unreadable folder has none.
    """
    folder = _folder(directory)
    out: list[CacheEntry] = []
    try:
        with os.scandir(folder) as it:
            for e in it:
                m = _ENTRY_RE.fullmatch(e.name)
                if m is None:
                    continue
                try:
                    st = e.stat(follow_symlinks=False)
                except OSError:  # deleted meanwhile by another process
                    continue
                if stat.S_ISREG(st.st_mode):
                    out.append(CacheEntry(folder / e.name, m.group(1), m.group(2), st.st_size, st.st_mtime))
    except OSError:
        return []
    out.sort(key=lambda e: (e.last_used, e.path.name))
    return out


def cache_size(directory: str | os.PathLike[str] | None = None) -> int:
    """Total bytes of the entries of a cache folder (default: ``default_cache_dir()``)."""
    return sum(e.size for e in cache_entries(directory))


def cache_cap(*, warn: bool = True) -> tuple[int | None, str]:
    """The size cap in bytes (None: no cap) read from ``$WSIM_CACHE_MAX_GB`` now, and its source.

    Unset or empty: :data:`DEFAULT_MAX_GB`. ``0`` or ``inf``: no cap. An invalid value (not a
    number, negative, NaN) gives the default cap and, with ``warn``, one ``CacheWarning`` line.
    """
    raw = os.environ.get(MAX_GB_ENV)
    default = round(DEFAULT_MAX_GB * 1e9)
    if raw is None or not raw.strip():
        return default, "default"
    try:
        gb = float(raw)
    except ValueError:
        gb = math.nan
    if math.isnan(gb) or gb < 0:
        problem = f"{MAX_GB_ENV}={raw!r} is not a size in GB (a number >= 0; 0 or inf: no cap)"
        if warn:
            warnings.warn(f"wsim cache: {problem}; using the default {DEFAULT_MAX_GB:g} GB",
                          CacheWarning, stacklevel=2)
        return default, f"default; {problem}, ignored"
    if gb == 0 or math.isinf(gb):
        return None, f"{MAX_GB_ENV}={raw.strip()}"
    return round(gb * 1e9), f"{MAX_GB_ENV}={raw.strip()}"


def _unlink(path: pathlib.Path) -> bool | None:
    """True if deleted, None if already gone (another process), False if it cannot be deleted."""
    try:
        os.unlink(path)
    except FileNotFoundError:
        return None
    except OSError:
        return False
    return True


def clear_cache(directory: str | os.PathLike[str] | None = None, *, kind: str | None = None,
                older_than_days: float | None = None) -> Cleared:
    """Delete the entries of a cache folder: all, or those of ``kind`` and/or last used more
    than ``older_than_days`` days ago. Files that are not entries are never touched."""
    now = time.time()
    removed = freed = skipped = 0
    for e in cache_entries(directory):
        if kind is not None and e.kind != kind:
            continue
        if older_than_days is not None and now - e.last_used <= older_than_days * 86400.0:
            continue
        done = _unlink(e.path)
        if done:
            removed += 1
            freed += e.size
        elif done is False:
            skipped += 1
    return Cleared(removed, freed, skipped)


def enforce_cap(directory: str | os.PathLike[str] | None = None, max_bytes: int | None = None, *,
                keep: str | os.PathLike[str] | None = None) -> Cleared:
    """Delete least recently used entries until the folder's total is within ``max_bytes``.

    ``max_bytes=None`` reads the cap with :func:`cache_cap` (which may say: no cap). ``keep``
    (a path in the folder, e.g. the entry just stored) is never deleted, nor is an entry that
    cannot be (skipped); so the total may stay above the cap.
    """
    if max_bytes is None:
        max_bytes, _ = cache_cap()
        if max_bytes is None:
            return Cleared(0, 0, 0)
    entries = cache_entries(directory)
    total = sum(e.size for e in entries)
    keep_name = pathlib.Path(keep).name if keep is not None else None
    removed = freed = skipped = 0
    for e in entries:  # least recently used first
        if total <= max_bytes:
            break
        if e.path.name == keep_name:
            continue
        done = _unlink(e.path)
        if done is False:
            skipped += 1
            continue
        total -= e.size  # deleted, here or by another process
        if done:
            removed += 1
            freed += e.size
    return Cleared(removed, freed, skipped)
