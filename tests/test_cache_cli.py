"""Tests of the operator cache's size management: LRU eviction under $WSIM_CACHE_MAX_GB and
``wsim cache list|info|clear``. CPU only, small arrays, each test in its own folder."""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest

from wsim.cache import (
    CacheWarning,
    OperatorCache,
    cache_cap,
    cache_entries,
    cache_size,
    clear_cache,
    enforce_cap,
)

ROOT = pathlib.Path(__file__).resolve().parents[1]
KIND = "bem_operators"


@pytest.fixture(autouse=True)
def _no_cap_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test sets the cap it needs; a value in the developer's shell must not leak in."""
    monkeypatch.delenv("WSIM_CACHE_MAX_GB", raising=False)


def _key(i: int) -> str:
    return f"{i:02x}" * 32  # 64 hex digits; the file name holds the first 32


def _arrays(i: int) -> dict[str, np.ndarray]:
    return {"H": np.full(20_000, float(i)), "ids": np.arange(1000, dtype=np.int32)}  # ~164 kB


def _fill(folder: pathlib.Path, n: int = 3) -> tuple[OperatorCache, list[pathlib.Path]]:
    """n entries of equal size, last used 300, 200, 100... seconds ago (entry 0 is the oldest)."""
    cache = OperatorCache(folder)
    paths = [cache.store(KIND, _key(i), _arrays(i)) for i in range(n)]
    now = time.time()
    for i, p in enumerate(paths):
        os.utime(p, (now - 100 * (n - i), now - 100 * (n - i)))
    return cache, paths


def _foreign(folder: pathlib.Path, outside: pathlib.Path) -> list[pathlib.Path]:
    """Files a user (or another writer) put in the cache folder: none may ever be deleted."""
    old = time.time() - 30 * 86400
    files = [
        folder / "notes.txt",
        folder / "my_results.h5",
        folder / f"{KIND}-{_key(99)[:32]}.h5.bak",
        folder / f"{KIND}-{_key(98)[:31]}.h5",  # too short a key
        folder / f"{KIND}-{_key(0xAB)[:32].upper()}.h5",  # upper case: not what path_for makes
        folder / ".tmp-abc123.h5",  # a writer in progress
    ]
    for f in files:
        f.write_bytes(b"x" * 50_000)
        os.utime(f, (old, old))
    sub = folder / f"{KIND}-{_key(96)[:32]}.h5"  # a folder named like an entry
    sub.mkdir()
    (sub / "inner.txt").write_text("keep")
    outside.write_bytes(b"y" * 50_000)
    link = folder / f"{KIND}-{_key(95)[:32]}.h5"  # a symlink named like an entry
    link.symlink_to(outside)
    os.utime(link, (old, old), follow_symlinks=False)
    return files + [sub, sub / "inner.txt", link, outside]


def _cli(env_dir: pathlib.Path, *args: str, **env: str) -> subprocess.CompletedProcess:
    full_env = {k: v for k, v in os.environ.items() if k != "WSIM_CACHE_MAX_GB"}
    full_env.update(WSIM_CACHE_DIR=str(env_dir), **env)
    return subprocess.run([sys.executable, "-m", "wsim", "cache", *args], cwd=ROOT, env=full_env,
                          capture_output=True, text=True, timeout=120, check=False)


# --- the cap ------------------------------------------------------------------------------------

def test_cap_evicts_the_least_recently_used_entry(tmp_path: pathlib.Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    cache, (a, b, c) = _fill(tmp_path)
    size = a.stat().st_size
    assert b.stat().st_size == c.stat().st_size == size
    assert cache.load(KIND, _key(0)) is not None  # a is the oldest stored, but now the last used
    assert [e.path for e in cache_entries(tmp_path)] == [b, c, a]
    # room for 3.5 entries: storing a 4th must evict exactly one, the least recently used (b)
    monkeypatch.setenv("WSIM_CACHE_MAX_GB", repr(3.5 * size / 1e9))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d = cache.store(KIND, _key(3), _arrays(3))
    assert d is not None and d.exists()
    assert not b.exists() and a.exists() and c.exists()
    assert cache_size(tmp_path) == 3 * size
    np.testing.assert_array_equal(cache.load(KIND, _key(0))["H"], _arrays(0)["H"])


def test_cap_below_the_new_entry_keeps_only_the_new_entry(tmp_path: pathlib.Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    cache, paths = _fill(tmp_path)
    monkeypatch.setenv("WSIM_CACHE_MAX_GB", "1e-9")  # 1 byte
    d = cache.store(KIND, _key(3), _arrays(3))
    assert [e.path for e in cache_entries(tmp_path)] == [d]  # never the entry just stored
    assert not any(p.exists() for p in paths)


@pytest.mark.parametrize("value", ["0", "inf", "Infinity"])
def test_zero_or_inf_means_no_cap(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch,
                                  value: str) -> None:
    monkeypatch.setenv("WSIM_CACHE_MAX_GB", value)
    assert cache_cap()[0] is None
    cache, _ = _fill(tmp_path)
    cache.store(KIND, _key(3), _arrays(3))
    assert len(cache_entries(tmp_path)) == 4


def test_default_cap(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("WSIM_CACHE_MAX_GB", raising=False)
    assert cache_cap() == (10 * 10**9, "default")
    monkeypatch.setenv("WSIM_CACHE_MAX_GB", "2.5")
    assert cache_cap() == (25 * 10**8, "WSIM_CACHE_MAX_GB=2.5")


@pytest.mark.parametrize("value", ["lots", "-1", "nan", "10GB"])
def test_invalid_cap_warns_once_and_uses_the_default(tmp_path: pathlib.Path,
                                                     monkeypatch: pytest.MonkeyPatch,
                                                     value: str) -> None:
    cache, paths = _fill(tmp_path)
    monkeypatch.setenv("WSIM_CACHE_MAX_GB", value)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        d = cache.store(KIND, _key(3), _arrays(3))  # the simulation goes on, cached
    msgs = [str(w.message) for w in rec if issubclass(w.category, CacheWarning)]
    assert len(msgs) == 1 and "\n" not in msgs[0], msgs
    assert f"WSIM_CACHE_MAX_GB={value!r}" in msgs[0] and "default 10 GB" in msgs[0]
    assert d is not None and all(p.exists() for p in paths + [d])  # 10 GB: nothing evicted
    assert cache_cap(warn=False)[0] == 10 * 10**9
    res = _cli(tmp_path, "info", WSIM_CACHE_MAX_GB=value)
    assert res.returncode == 0, res.stderr
    assert f"cap: 10 GB (default; WSIM_CACHE_MAX_GB={value!r} is not a size in GB" in res.stdout


def test_eviction_never_touches_foreign_files(tmp_path: pathlib.Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    folder = tmp_path / "cache"
    cache, paths = _fill(folder)
    foreign = _foreign(folder, tmp_path / "outside.bin")
    monkeypatch.setenv("WSIM_CACHE_MAX_GB", "1e-9")
    d = cache.store(KIND, _key(3), _arrays(3))
    assert not any(p.exists() for p in paths) and d.exists()
    assert all(os.path.lexists(f) for f in foreign)
    # nor does an explicit enforce_cap or clear_cache
    assert enforce_cap(folder, 0, keep=d) == (0, 0, 0)
    assert clear_cache(folder).removed == 1 and not d.exists()
    assert all(os.path.lexists(f) for f in foreign)


def test_undeletable_entry_is_skipped(tmp_path: pathlib.Path,
                                      monkeypatch: pytest.MonkeyPatch) -> None:
    cache, (a, b, c) = _fill(tmp_path)
    real_unlink = os.unlink

    def unlink(path: os.PathLike[str] | str, *args: object, **kwargs: object) -> None:
        if pathlib.Path(path) == a:
            raise PermissionError(13, "Permission denied", str(path))
        real_unlink(path, *args, **kwargs)

    monkeypatch.setattr(os, "unlink", unlink)
    monkeypatch.setenv("WSIM_CACHE_MAX_GB", "1e-9")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        d = cache.store(KIND, _key(3), _arrays(3))
    assert a.exists() and d.exists() and not b.exists() and not c.exists()
    size = d.stat().st_size
    done = clear_cache(tmp_path)
    assert (done.removed, done.freed, done.skipped) == (1, size, 1)
    assert a.exists() and not d.exists()


def test_load_refreshes_last_use(tmp_path: pathlib.Path) -> None:
    cache, (a, b, c) = _fill(tmp_path)
    before = a.stat().st_mtime
    assert cache.load(KIND, _key(0)) is not None
    assert a.stat().st_mtime > before + 250  # now, not 300 s ago
    assert cache.load(KIND, _key(42)) is None  # a miss touches nothing
    assert [e.path for e in cache_entries(tmp_path)] == [b, c, a]


# --- the command line ---------------------------------------------------------------------------

def test_cli_clear_frees_the_space(tmp_path: pathlib.Path) -> None:
    folder = tmp_path / "cache"
    _, paths = _fill(folder)
    foreign = _foreign(folder, tmp_path / "outside.bin")
    total = sum(p.stat().st_size for p in paths)
    res = _cli(folder, "clear")
    assert res.returncode == 0, res.stderr
    assert "removed 3 entries" in res.stdout and f"({total} bytes)" in res.stdout
    assert f"freed {total / 1e6:.1f} MB" in res.stdout
    assert not any(p.exists() for p in paths) and cache_entries(folder) == []
    assert all(os.path.lexists(f) for f in foreign)
    res = _cli(folder, "clear")
    assert res.returncode == 0 and "removed 0 entries" in res.stdout and "(0 bytes)" in res.stdout


def test_cli_clear_filters(tmp_path: pathlib.Path) -> None:
    cache, (a, b, c) = _fill(tmp_path)
    old = time.time() - 3 * 86400
    os.utime(a, (old, old))
    other = cache.store("pbd_model", _key(7), _arrays(7))
    size = a.stat().st_size
    res = _cli(tmp_path, "clear", "--older-than", "2")
    assert res.returncode == 0, res.stderr
    assert "removed 1 entry" in res.stdout and f"({size} bytes)" in res.stdout
    assert not a.exists() and b.exists() and c.exists() and other.exists()
    size = other.stat().st_size
    res = _cli(tmp_path, "clear", "--kind", "pbd_model")
    assert res.returncode == 0 and "removed 1 entry" in res.stdout and f"({size} bytes)" in res.stdout
    assert not other.exists() and b.exists() and c.exists()
    res = _cli(tmp_path, "clear", "--older-than", "-1")
    assert res.returncode == 2 and "--older-than" in res.stderr and b.exists()


def test_cli_list_and_info_print_the_sizes(tmp_path: pathlib.Path) -> None:
    _, paths = _fill(tmp_path)
    _foreign(tmp_path, tmp_path / "outside.bin")  # not entries: neither listed nor counted
    total = sum(p.stat().st_size for p in paths)
    res = _cli(tmp_path, "list")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert "least recently used first" in lines[0]
    rows = [ln.split() for ln in lines[2:-1]]
    assert [r[1] for r in rows] == [_key(i)[:16] for i in range(3)]  # oldest used first
    assert all(r[0] == KIND and r[2] == f"{p.stat().st_size / 1e6:.1f}" for r, p in zip(rows, paths))
    assert lines[-1] == f"total: 3 entries, {total / 1e6:.1f} MB ({total} bytes)"

    res = _cli(tmp_path, "info", WSIM_CACHE_MAX_GB="2.5")
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines() == [
        f"folder: {tmp_path}",
        "entries: 3",
        f"total size: {total / 1e6:.1f} MB ({total} bytes)",
        "cap: 2.5 GB (WSIM_CACHE_MAX_GB=2.5)",
    ]
    res = _cli(tmp_path, "info", WSIM_CACHE_MAX_GB="0")
    assert "cap: none (WSIM_CACHE_MAX_GB=0)" in res.stdout

    res = subprocess.run([sys.executable, "-m", "wsim", "info"], cwd=ROOT, capture_output=True, text=True,
                         env={**os.environ, "WSIM_CACHE_DIR": str(tmp_path)}, timeout=120, check=False)
    assert res.returncode == 0, res.stderr
    assert f"cache size: 3 entries, {total / 1e6:.1f} MB (cap " in res.stdout


def test_cli_on_a_missing_folder(tmp_path: pathlib.Path) -> None:
    missing = tmp_path / "never-created"
    res = _cli(missing, "info")
    assert res.returncode == 0 and "(does not exist yet)" in res.stdout and "entries: 0" in res.stdout
    res = _cli(missing, "list")
    assert res.returncode == 0 and res.stdout.splitlines()[-1] == "total: 0 entries, 0.0 MB (0 bytes)"
    res = _cli(missing, "clear")
    assert res.returncode == 0 and "removed 0 entries" in res.stdout and not missing.exists()
