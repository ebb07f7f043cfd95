"""Shared test set-up: device parametrization and an isolated operator cache.

Every test that takes the ``device`` fixture runs once per device: ``cpu`` always, ``cuda:0``
where a GPU is present (skipped otherwise, so the GPU path is never silently missing from a run
on a GPU machine).
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import warp as wp

from wsim.device import quiet_warp  # noqa: E402

quiet_warp()
wp.init()

HAS_CUDA = wp.get_cuda_device_count() > 0
DEVICES = [
    pytest.param("cpu", id="cpu"),
    pytest.param("cuda:0", id="cuda_0", marks=pytest.mark.skipif(not HAS_CUDA, reason="no CUDA device")),
]


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    return request.param


@pytest.fixture(autouse=True, scope="session")
def _isolated_cache(tmp_path_factory):
    """Never read or write the user's real cache folder from tests, nor obey the user's cache cap
    or progress and verbosity settings (``WSIM_CACHE_MAX_GB``, ``WSIM_PROGRESS``, ``WSIM_VERBOSE``)."""
    names = ("WSIM_CACHE_DIR", "WSIM_CACHE_MAX_GB", "WSIM_PROGRESS", "WSIM_VERBOSE")
    old = {k: os.environ.get(k) for k in names}
    for k in names[1:]:
        os.environ.pop(k, None)
    os.environ["WSIM_CACHE_DIR"] = str(tmp_path_factory.mktemp("wsim-cache"))
    yield
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def box_ops():
    """Operators of the shared 26-node BEM cube (``bem_box``), built once per session on the CPU."""
    from bem_box import BOX, DT, MAT

    from wsim.bem import build_operators

    return build_operators(BOX, MAT, DT, cache=False, device="cpu")
