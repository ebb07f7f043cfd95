"""On-disk HDF5 cache for precomputed operators (BEM matrices, PBD constraint colourings...).

Design:

* **Content hashing.** A cache entry is named by a SHA-256 over everything the operator depends
  on: the input arrays (name, dtype, shape, bytes), the parameters (material, dt, options) as
  canonical JSON, the operator's own format ``version`` and this file layout's
  ``FORMAT_VERSION``. A key can therefore never point at an operator built from other inputs,
  and no invalidation logic is needed: changed inputs simply give another file name.
* **Per-dataset checksums.** The key says what *should* be in a file, not that the bytes on
  disk are still intact. Every dataset stores a SHA-256 of its dtype, shape and data, verified
  on every load, so bit rot, a half-copied file or a hand-edited one is recomputed instead of
  silently feeding a wrong matrix to the solver.
* **Atomic writes.** A file is written to a temporary name in the cache folder, fsynced, then
  ``os.replace``-d onto its final name. Readers (other processes, a later run after a crash or
  a full disk) see either no file or a complete one; concurrent writers of the same key both
  write complete files and the last rename wins.
* A cache is an optimisation: a bad file is reported in one warning line and recomputed, and an
  unwritable cache folder only costs the recomputation. Neither ever stops a simulation.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
import pathlib
import re
import sys
import tempfile
import warnings
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timezone
from typing import Any

import h5py
import numpy as np

FORMAT_VERSION: int = 1
"""Version of the cache file layout itself (attributes, checksum definition, key recipe)."""

_KIND_RE = re.compile(r"[A-Za-z0-9_-]+")
_NAME_RE = re.compile(r"[A-Za-z0-9_.-]+")


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


def _parallel_sha256(arrays: Mapping[str, np.ndarray]) -> dict[str, str]:
    """Per-dataset checksums in threads (hashlib releases the GIL on large buffers)."""
    if len(arrays) < 2:
        return {name: _dataset_sha256(a) for name, a in arrays.items()}
    with ThreadPoolExecutor(max_workers=min(len(arrays), os.cpu_count() or 1)) as pool:
        return dict(zip(arrays, pool.map(_dataset_sha256, arrays.values())))


def _dataset_sha256(a: np.ndarray) -> str:
    h = hashlib.sha256()
    _array_digest(h, a)
    return h.hexdigest()


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
                else:
                    stored: dict[str, Any] = {}
                    for name, ds in f.items():
                        if not isinstance(ds, h5py.Dataset):
                            reason = f"unexpected group {name!r}"
                            break
                        out[name] = np.asarray(ds[()])  # np.asarray: 0-d datasets read as scalars
                        stored[name] = ds.attrs.get("sha256")
                    if reason is None:
                        digests = _parallel_sha256(out)
                        bad = [name for name in out if stored[name] != digests[name]]
                        if bad:
                            reason = f"dataset {bad[0]!r} failed its sha256 check (corrupt)"
        except Exception as exc:  # any unreadable file is just a cache miss
            reason = f"unreadable ({type(exc).__name__}: {exc})"
        if reason is not None:
            _warn(path, reason, "recomputing")
            return None
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
                digests = _parallel_sha256(data)
                for name, a in data.items():
                    # Contiguous and uncompressed: dense operators barely compress, and reads
                    # stay a single memcpy-sized I/O.
                    f.create_dataset(name, data=a).attrs["sha256"] = digests[name]
            with open(tmp, "r+b") as fh:  # data must be on disk before the rename publishes it
                os.fsync(fh.fileno())
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
