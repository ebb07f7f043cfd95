"""Tests of wsim.cache: round trip, corruption and staleness detection, keys, atomic writes."""

from __future__ import annotations

import os
import pathlib
import sys
import warnings
from typing import Any

import h5py
import numpy as np
import pytest

from wsim import cache as wc
from wsim.cache import CacheWarning, OperatorCache, content_key, default_cache_dir

KIND = "bem_H"


def _operator() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1234)
    return {
        "H": rng.standard_normal((300, 300)),  # float64
        "constraints": rng.integers(0, 5000, size=(1000, 4), dtype=np.int32),
        "colours": rng.random(777).astype(np.float32),
        "volume": np.array(0.12345678901234567),  # 0-d scalar
    }


def _inputs() -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    rng = np.random.default_rng(7)
    arrays = {
        "vertices": rng.random((500, 3)),
        "triangles": rng.integers(0, 500, size=(996, 3), dtype=np.int32),
    }
    params = {"E": 1e6, "nu": 0.3, "rho": 1000.0, "dt": 0.1, "options": {"n_max": 8, "tol": 1e-9}}
    return arrays, params


class Builder:
    """A build() callable that counts its calls."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self) -> dict[str, np.ndarray]:
        self.calls += 1
        return _operator()


def _assert_identical(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    assert set(got) == set(want)
    for name, w in want.items():
        g = got[name]
        assert isinstance(g, np.ndarray), name
        assert g.dtype == w.dtype and g.shape == w.shape, name
        assert g.tobytes() == w.tobytes(), name


def _build_twice(cache: OperatorCache, builder: Builder) -> tuple[dict, dict]:
    arrays, params = _inputs()
    kw: dict[str, Any] = dict(arrays=arrays, params=params, version=3, build=builder)
    return cache.get_or_build(KIND, **kw), cache.get_or_build(KIND, **kw)


def _key() -> str:
    arrays, params = _inputs()
    return content_key(KIND, arrays=arrays, params=params, version=3)


def _files(d: pathlib.Path) -> list[str]:
    return sorted(p.name for p in d.iterdir()) if d.exists() else []


def _one_warning(rec: list[warnings.WarningMessage]) -> str:
    cw = [w for w in rec if issubclass(w.category, CacheWarning)]
    assert len(cw) == 1, [str(w.message) for w in cw]
    msg = str(cw[0].message)
    assert "\n" not in msg and msg.startswith("wsim cache: ")
    return msg


def _flip_byte(path: pathlib.Path, offset: int, mask: int) -> None:
    with open(path, "r+b") as fh:
        fh.seek(offset)
        b = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([b[0] ^ mask]))


# --- round trip ---------------------------------------------------------------------------------

def test_store_load_round_trip_is_bit_identical(tmp_path: pathlib.Path) -> None:
    cache = OperatorCache(tmp_path)
    op = _operator()
    path = cache.store(KIND, "ab" * 32, op, meta={"mesh": "sphere", "n": np.int64(3)})
    assert path == tmp_path / f"{KIND}-{'ab' * 16}.h5" and path.is_file()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = cache.load(KIND, "ab" * 32)
    _assert_identical(got, op)
    assert got["volume"].shape == () and got["volume"].dtype == np.float64
    with h5py.File(path, "r") as f:
        assert f.attrs["key"] == "ab" * 32 and f.attrs["kind"] == KIND
        assert f.attrs["format_version"] == wc.FORMAT_VERSION
        assert '"mesh": "sphere"' in f.attrs["meta"] and f.attrs["created"].endswith("+00:00")
        assert all(len(f[n].attrs["sha256"]) == 64 for n in op)
    assert _files(tmp_path) == [path.name]  # no temp file left behind
    assert cache.load(KIND, "cd" * 32) is None  # plain miss: no file, no warning


def test_get_or_build_second_call_is_a_hit(tmp_path: pathlib.Path) -> None:
    cache, builder = OperatorCache(tmp_path), Builder()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        first, second = _build_twice(cache, builder)
    assert builder.calls == 1 and (cache.hits, cache.misses) == (1, 1)
    _assert_identical(first, _operator())
    _assert_identical(second, _operator())


def test_bad_names_are_rejected(tmp_path: pathlib.Path) -> None:
    cache = OperatorCache(tmp_path)
    with pytest.raises(ValueError):
        cache.path_for("bem/H", "00" * 32)
    with pytest.raises(ValueError):
        cache.store(KIND, "00" * 32, {"a/b": np.zeros(3)})
    assert _files(tmp_path) == []


# --- corrupt and stale files --------------------------------------------------------------------

def test_flipped_data_byte_is_detected_and_rebuilt(tmp_path: pathlib.Path) -> None:
    cache, builder = OperatorCache(tmp_path), Builder()
    _build_twice(cache, builder)
    path = cache.path_for(KIND, _key())
    with h5py.File(path, "r") as f:
        ds = f["H"]
        assert ds.chunks is None and ds.compression is None
        offset = ds.id.get_offset() + 12345  # a byte well inside the 720 kB of H
    _flip_byte(path, offset, 0x10)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        got = cache.get_or_build(KIND, arrays=_inputs()[0], params=_inputs()[1], version=3,
                                 build=builder)
    msg = _one_warning(rec)
    assert str(path) in msg and "'H'" in msg and msg.endswith("; recomputing")
    assert builder.calls == 2 and cache.misses == 2
    _assert_identical(got, _operator())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _assert_identical(cache.load(KIND, _key()), _operator())  # rewritten, loads cleanly


def test_datasets_move_in_pieces_and_a_flip_in_any_piece_is_caught(tmp_path: pathlib.Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """Datasets larger than a piece are written and read by threads piece by piece, a Fortran-
    ordered array comes back with its values, and a flipped byte in a late piece fails the
    checksum like one in the first."""
    monkeypatch.setattr(wc, "CHUNK_BYTES", 4096)  # H's 720 kB: 176 pieces
    cache = OperatorCache(tmp_path)
    op = {**_operator(), "lu": np.asfortranarray(np.random.default_rng(3).standard_normal((40, 30)))}
    path = cache.store(KIND, "ab" * 32, op)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = cache.load(KIND, "ab" * 32)
    assert set(got) == set(op)
    for name, want in op.items():
        assert got[name].dtype == want.dtype and np.array_equal(got[name], want), name
    with h5py.File(path, "r") as f:
        offset = f["H"].id.get_offset() + f["H"].id.get_storage_size() - 100  # the last piece
    _flip_byte(path, offset, 0x01)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        assert cache.load(KIND, "ab" * 32) is None
    assert "'H'" in _one_warning(rec)


@pytest.mark.parametrize("write_raw", [True, False])
def test_piecewise_and_whole_dataset_io_read_each_others_files(tmp_path: pathlib.Path,
                                                             monkeypatch: pytest.MonkeyPatch,
                                                             write_raw: bool) -> None:
    """Where pwrite/preadv are missing (Windows) h5py moves every dataset whole: the same file
    format and checksums, so a cache folder shared between the two loads either way."""
    cache = OperatorCache(tmp_path)
    monkeypatch.setattr(wc, "_RAW_IO", write_raw)
    cache.store(KIND, "ab" * 32, _operator())
    monkeypatch.setattr(wc, "_RAW_IO", not write_raw)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _assert_identical(cache.load(KIND, "ab" * 32), _operator())


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty"])
def test_truncated_or_garbage_file_is_detected(tmp_path: pathlib.Path, damage: str) -> None:
    cache, builder = OperatorCache(tmp_path), Builder()
    _build_twice(cache, builder)
    path = cache.path_for(KIND, _key())
    if damage == "truncate":
        os.truncate(path, path.stat().st_size // 2)
    elif damage == "garbage":
        path.write_bytes(np.random.default_rng(0).bytes(4096))
    else:
        path.write_bytes(b"")
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        assert cache.load(KIND, _key()) is None
    assert _one_warning(rec).endswith("; recomputing")
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        got = _build_twice(cache, builder)[1]
    assert len(rec) == 1  # the bad file once; then rewritten, so the second call hits
    assert builder.calls == 2
    _assert_identical(got, _operator())


@pytest.mark.parametrize("attr,value", [("key", "ff" * 32), ("key", "same 32-char prefix"),
                                        ("format_version", 0), ("kind", "pbd_constraints")])
def test_stale_file_is_detected(tmp_path: pathlib.Path, attr: str, value: Any) -> None:
    cache, builder = OperatorCache(tmp_path), Builder()
    _build_twice(cache, builder)
    path = cache.path_for(KIND, _key())
    if value == "same 32-char prefix":  # the file name only holds key[:32]; the rest must count
        value = _key()[:32] + "0" * 32
    with h5py.File(path, "r+") as f:
        f.attrs[attr] = value
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        _build_twice(cache, builder)
    assert "stale" in _one_warning(rec)
    assert builder.calls == 2 and (cache.hits, cache.misses) == (2, 2)


def test_missing_checksum_counts_as_corrupt(tmp_path: pathlib.Path) -> None:
    cache = OperatorCache(tmp_path)
    path = cache.store(KIND, "ab" * 32, _operator())
    with h5py.File(path, "r+") as f:
        del f["colours"].attrs["sha256"]
    with pytest.warns(CacheWarning, match="'colours'"):
        assert cache.load(KIND, "ab" * 32) is None


# --- keys ---------------------------------------------------------------------------------------

def test_content_key_changes_with_every_input() -> None:
    arrays, params = _inputs()
    base = content_key(KIND, arrays=arrays, params=params, version=3)
    assert len(base) == 64 and int(base, 16) >= 0
    assert content_key(KIND, arrays=dict(arrays), params=dict(params), version=3) == base

    flipped = arrays["vertices"].copy()
    flipped.reshape(-1).view(np.uint8)[1000] ^= 1
    retyped = arrays["triangles"].astype(np.int64)
    reshaped = arrays["vertices"].reshape(3, 500)  # same bytes, other shape
    variants = [
        dict(arrays={**arrays, "vertices": flipped}, params=params, version=3),
        dict(arrays={**arrays, "triangles": retyped}, params=params, version=3),
        dict(arrays={**arrays, "vertices": arrays["vertices"].view(np.int64)},  # same bytes
             params=params, version=3),
        dict(arrays={**arrays, "vertices": reshaped}, params=params, version=3),
        dict(arrays={"verts": arrays["vertices"], "triangles": arrays["triangles"]},
             params=params, version=3),
        dict(arrays=arrays, params={**params, "dt": 0.1000000001}, version=3),
        dict(arrays=arrays, params={**params, "options": {"n_max": 9, "tol": 1e-9}}, version=3),
        dict(arrays=arrays, params={**params, "extra": None}, version=3),
        dict(arrays=arrays, params=params, version=4),
    ]
    keys = {content_key(KIND, **v) for v in variants} | {base}
    keys.add(content_key("bem_G", arrays=arrays, params=params, version=3))
    assert len(keys) == len(variants) + 2


def test_content_key_is_canonical() -> None:
    arrays, _ = _inputs()

    def key(params: dict[str, Any]) -> str:
        return content_key(KIND, arrays=arrays, params=params, version=1)

    a = {"dt": 0.01, "options": {"tol": 1e-9, "n_max": 8}, "axis": (0.0, 1.0, 0.0)}
    b = {"axis": [0.0, 1.0, 0.0], "options": {"n_max": 8, "tol": 1e-9}, "dt": 0.01}
    assert key(a) == key(b)  # dict order and tuple/list do not matter
    assert key({"dt": np.float64(0.01), "n": np.int32(8), "on": np.bool_(True)}) == \
        key({"dt": 0.01, "n": 8, "on": True})
    assert key({"g": np.array([0.0, -9.81, 0.0])}) == key({"g": np.array([0.0, -9.81, 0.0])})
    assert key({"g": np.array([0.0, -9.81, 0.0])}) != key({"g": np.array([0.0, -9.81, 0.1])})
    assert key({"x": "0.1"}) != key({"x": 0.1}) and key({"x": True}) != key({"x": 1})
    # reordering the arrays mapping must not matter either
    assert content_key(KIND, arrays=dict(reversed(list(arrays.items()))), params={}, version=1) \
        == content_key(KIND, arrays=arrays, params={}, version=1)


def test_content_key_rejects_unsupported_param_types() -> None:
    with pytest.raises(TypeError, match="mesh_file"):
        content_key(KIND, arrays={}, params={"mesh_file": pathlib.Path("a.obj")}, version=1)
    with pytest.raises(TypeError, match="options.flags"):
        content_key(KIND, arrays={}, params={"options": {"flags": {1, 2}}}, version=1)


# --- atomic writes ------------------------------------------------------------------------------

def test_failing_build_leaves_nothing(tmp_path: pathlib.Path) -> None:
    cache = OperatorCache(tmp_path / "c")

    def build() -> dict[str, np.ndarray]:
        raise RuntimeError("solver exploded")

    with pytest.raises(RuntimeError, match="exploded"):
        cache.get_or_build(KIND, arrays=_inputs()[0], params={}, version=1, build=build)
    assert _files(tmp_path / "c") == []


@pytest.mark.parametrize("exc", [RuntimeError, OSError])
def test_failure_midway_through_write_is_atomic(tmp_path: pathlib.Path,
                                                monkeypatch: pytest.MonkeyPatch,
                                                exc: type[Exception]) -> None:
    cache = OperatorCache(tmp_path)
    old = {"H": np.arange(10.0)}
    path = cache.store(KIND, "ab" * 32, old)  # an older complete file must survive

    temps: list[str] = []
    real_mkstemp = wc.tempfile.mkstemp
    real_create = h5py.Group.create_dataset

    def mkstemp(*a: Any, **k: Any) -> tuple[int, str]:
        fd, name = real_mkstemp(*a, **k)
        temps.append(name)
        return fd, name

    def create_dataset(self: h5py.Group, name: str, *a: Any, **k: Any) -> h5py.Dataset:
        if len(self) >= 2:  # two datasets are written, the third one fails
            raise exc("disk went away")
        return real_create(self, name, *a, **k)

    monkeypatch.setattr(wc.tempfile, "mkstemp", mkstemp)
    monkeypatch.setattr(h5py.Group, "create_dataset", create_dataset)
    if exc is OSError:  # I/O trouble: warn and go on uncached
        with pytest.warns(CacheWarning, match="cannot store"):
            assert cache.store(KIND, "ab" * 32, _operator()) is None
    else:  # a bug: propagate, but still clean up
        with pytest.raises(RuntimeError):
            cache.store(KIND, "ab" * 32, _operator())
    monkeypatch.undo()

    assert len(temps) == 1 and not os.path.exists(temps[0])
    assert _files(tmp_path) == [path.name]
    _assert_identical(cache.load(KIND, "ab" * 32), old)


# --- location and unwritable folders ------------------------------------------------------------

def test_cache_dir_env_is_honoured(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("WSIM_CACHE_DIR", str(tmp_path / "env-cache"))
    assert default_cache_dir() == tmp_path / "env-cache"
    cache = OperatorCache()
    assert cache.directory == tmp_path / "env-cache"
    _build_twice(cache, Builder())
    assert len(list((tmp_path / "env-cache").glob(f"{KIND}-*.h5"))) == 1
    monkeypatch.setenv("WSIM_CACHE_DIR", "~/wsim-test-cache")
    assert default_cache_dir() == pathlib.Path.home() / "wsim-test-cache"
    # resolved at construction: changing the variable later does not move an existing cache
    assert cache.directory == tmp_path / "env-cache"


@pytest.mark.skipif(sys.platform in ("win32", "darwin"), reason="XDG layout is Linux's")
def test_default_cache_dir_without_env(tmp_path: pathlib.Path,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("WSIM_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "wsim"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/ignored")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_cache_dir() == tmp_path / "home" / ".cache" / "wsim"


def _check_uncached_run(cache: OperatorCache) -> None:
    builder = Builder()
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        got = cache.get_or_build(KIND, arrays=_inputs()[0], params=_inputs()[1], version=3,
                                 build=builder)
    assert "continuing without cache" in _one_warning(rec)
    assert builder.calls == 1
    _assert_identical(got, _operator())


def test_directory_blocked_by_a_file(tmp_path: pathlib.Path) -> None:
    (tmp_path / "blocker").write_text("not a folder")  # stops root too
    cache = OperatorCache(tmp_path / "blocker" / "cache")
    with pytest.warns(CacheWarning, match="cannot store"):
        assert cache.store(KIND, "ab" * 32, _operator()) is None
    _check_uncached_run(cache)


def test_permission_denied_is_a_warning(tmp_path: pathlib.Path,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    def denied(*a: Any, **k: Any) -> tuple[int, str]:
        raise PermissionError(13, "Permission denied", str(tmp_path))

    monkeypatch.setattr(wc.tempfile, "mkstemp", denied)
    _check_uncached_run(OperatorCache(tmp_path))
    assert _files(tmp_path) == []


def test_read_only_directory(tmp_path: pathlib.Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        if os.access(ro, os.W_OK):
            pytest.skip("chmod does not stop this user (root)")
        _check_uncached_run(OperatorCache(ro))
        assert _files(ro) == []
    finally:
        ro.chmod(0o755)


# --- review findings (parallel I/O) -------------------------------------------------------------

def test_a_flipped_byte_in_a_dataset_name_is_caught(tmp_path: pathlib.Path) -> None:
    """HDF5 keeps names apart from the data: a renamed dataset must fail the load, not hand the
    caller a dict without the key it needs."""
    cache = OperatorCache(tmp_path)
    path = cache.store("k", "ab" * 32, {"Hq7zname": np.arange(10.0), "other": np.ones(3)})
    raw = bytearray(path.read_bytes())
    i = raw.index(b"Hq7zname")
    raw[i] ^= 0x01  # 'H' -> 'I'
    path.write_bytes(bytes(raw))
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        assert cache.load("k", "ab" * 32) is None
    assert "renamed" in _one_warning(rec) or "sha256" in _one_warning(rec)


def test_an_entry_replaced_by_a_concurrent_writer_mid_load_still_loads(tmp_path: pathlib.Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A concurrent writer of the same key renames its valid file, laid out differently, onto the
    entry between the load's h5py pass and its piecewise reads: the reader keeps reading the file
    it opened and loads cleanly."""
    if not wc._RAW_IO:
        pytest.skip("piecewise reads need pwrite/preadv")
    op = {"H": np.arange(1000.0)}
    cache = OperatorCache(tmp_path / "a")
    path = cache.store("k", "ab" * 32, op, meta={"m": "x"})
    other = OperatorCache(tmp_path / "b").store("k", "ab" * 32, op, meta={"m": "x" * 5000})  # other offsets
    real = wc._move_pieces

    def racing(fd: int, arrays: Any, offsets: Any, move: Any) -> Any:
        if move is wc._read_piece and other is not None and other.exists():
            os.replace(other, path)
        return real(fd, arrays, offsets, move)

    monkeypatch.setattr(wc, "_move_pieces", racing)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = cache.load("k", "ab" * 32)
    assert got is not None and np.array_equal(got["H"], op["H"])
    assert not other.exists()  # the rename did happen mid-load


@pytest.mark.skipif(np.dtype(np.longdouble).itemsize == 8, reason="long double is double here")
def test_long_double_round_trips(tmp_path: pathlib.Path) -> None:
    cache = OperatorCache(tmp_path)
    a = np.linspace(0, 1, 7).astype(np.longdouble)
    cache.store("k", "ab" * 32, {"x": a})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = cache.load("k", "ab" * 32)
    assert got["x"].dtype == a.dtype and np.array_equal(got["x"], a)


def test_a_failed_piece_write_leaves_no_temp_file_and_the_old_entry(tmp_path: pathlib.Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    if not wc._RAW_IO:
        pytest.skip("piecewise writes need pwrite/preadv")
    monkeypatch.setattr(wc, "CHUNK_BYTES", 4096)
    cache = OperatorCache(tmp_path)
    cache.store("k", "ab" * 32, {"H": np.arange(100_000.0)})
    real, calls = os.pwrite, []

    def full_disk(fd: int, data: Any, at: int) -> int:
        calls.append(at)
        if len(calls) == 40:
            raise OSError(28, "No space left on device")
        return real(fd, data, at)

    monkeypatch.setattr(os, "pwrite", full_disk)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        assert cache.store("k", "ab" * 32, {"H": -np.arange(100_000.0)}) is None
    monkeypatch.setattr(os, "pwrite", real)
    assert "No space left" in _one_warning(rec)
    assert _files(tmp_path) == [cache.path_for("k", "ab" * 32).name]
    assert np.array_equal(cache.load("k", "ab" * 32)["H"], np.arange(100_000.0))


@pytest.mark.parametrize("target", ["scalar", "bools", "sha256 attribute"])
def test_flips_outside_the_piecewise_datasets_are_caught(tmp_path: pathlib.Path, target: str) -> None:
    cache = OperatorCache(tmp_path)
    op = {"H": np.arange(50.0), "scalar": np.array(1234.5678), "bools": np.array([True, False] * 8)}
    path = cache.store("k", "ab" * 32, op)
    with h5py.File(path, "r") as f:
        if target == "sha256 attribute":
            needle = f["H"].attrs["sha256"].encode()
        else:
            needle = np.ascontiguousarray(f[target][()]).tobytes()
    raw = bytearray(path.read_bytes())
    i = raw.index(needle)
    raw[i + len(needle) // 2] ^= 0x01
    path.write_bytes(bytes(raw))
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        assert cache.load("k", "ab" * 32) is None
    _one_warning(rec)


def test_fortran_ordered_arrays_are_not_all_copied_at_once(tmp_path: pathlib.Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """scipy's solves give Fortran-ordered H0_inv and H0_inv_Gp: the store holds a C-ordered copy
    of one such dataset at a time (2 x 7.3 GB at N = 10k, float64)."""
    import tracemalloc

    monkeypatch.setattr(wc, "CHUNK_BYTES", 1 << 20)
    rng = np.random.default_rng(0)
    op = {n: np.asfortranarray(rng.standard_normal((1024, 1024))) for n in ("H0_inv", "H0_inv_Gp", "X")}  # 8 MB each
    cache = OperatorCache(tmp_path)
    tracemalloc.start()
    try:
        cache.store("k", "ab" * 32, op)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1.5 * (8 << 20), f"{peak / 2**20:.1f} MiB"
    got = cache.load("k", "ab" * 32)
    assert all(np.array_equal(got[n], op[n]) for n in op)
