"""Memory between test modules: give back what a module's tests left behind.

A module-scoped autouse fixture (loaded by tests/conftest.py) runs after each test module:

- FastAPI (0.165) keeps every endpoint callable it has classified in module-level
  ``functools.lru_cache``s (4096 entries) of ``fastapi.dependencies.models``. An endpoint
  defined inside ``create_app`` (the API fallback, the viewer relay) closes over its app, so
  every app a test built — its Instrument, devices, results and recorder, 100–300 MB — stayed
  alive until the end of the session. Those caches are emptied (FastAPI refills them as it
  goes; only the classification of a callable is cached).
- Cyclic garbage is collected: an Instrument, its threads' queues and its result slot form
  cycles the collector reaches by allocation counts, not by size.
- The simulator's shared scene renderers are forgotten when the process is still above
  ``RENDERERS_ABOVE_MB`` (two xdist workers keeping three each: ~1.8 GB of the sum).
- The freed heap goes back to the system (glibc ``malloc_trim``); large blocks are mapped
  one by one from the start (:func:`bound_the_heap`).

The same release also runs after any single test that left the process more than
``TEST_GROWTH_MB`` larger than it found it (a live app, a calibration solve): without it a
module's next test built its app beside the last one's (the calibration wizard module went
from 2.1 to 4.3 GB). A test that leaves less costs one read of /proc/self/status.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import gc
import sys
from collections.abc import Iterator

import pytest

from tests.helpers.rss import status_mb

# glibc mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD, _M_ARENA_MAX = -3, -8
MMAP_THRESHOLD_BYTES = 1 << 20
ARENA_MAX = 2


def bound_the_heap() -> None:
    """Blocks of 1 MB and more (frames, maps, tables) are mapped and unmapped one by one, in at
    most two arenas: a freed array goes back to the system at once.

    glibc's default raises its mapping threshold to the largest block freed (up to 32 MB), so
    after the first map the arrays came from per-thread heaps that a free does not shrink: a
    calibration wizard test peaked at 2.28 GB, 1.94 GB with these settings. Called when the
    plugin loads, before the tests start their threads; only the pytest processes, never the
    servers they start.
    """
    name = ctypes.util.find_library("c")
    if name is None:
        return
    with contextlib.suppress(OSError, AttributeError):  # not glibc: its defaults stay
        libc = ctypes.CDLL(name)
        libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
        libc.mallopt(_M_ARENA_MAX, ARENA_MAX)


def _malloc_trim() -> None:
    name = ctypes.util.find_library("c")
    if name is None:
        return
    with contextlib.suppress(OSError, AttributeError):  # not glibc: nothing to trim
        ctypes.CDLL(name).malloc_trim(0)


def fastapi_callable_caches() -> list[functools._lru_cache_wrapper[object]]:
    """The ``lru_cache``s of ``fastapi.dependencies.models`` (they hold endpoint callables)."""
    from fastapi.dependencies import models

    return [f for f in vars(models).values() if isinstance(f, functools._lru_cache_wrapper)]


TEST_GROWTH_MB = 200.0
# the simulator keeps up to 3 scene renderers for the next world (~0.3 GB each): a process
# above this after collecting gives them back (rebuilt in seconds from the geometry cache)
RENDERERS_ABOVE_MB = 1000.0


def rss_mb() -> float:
    """This process's resident set now, MB (0 where /proc is absent)."""
    return status_mb("VmRSS")


def release_memory() -> None:
    """Forget FastAPI's classified endpoints, collect cycles, trim the heap; above
    ``RENDERERS_ABOVE_MB`` also forget the simulator's shared renderers."""
    for cache in fastapi_callable_caches():
        cache.cache_clear()
    gc.collect()
    world = sys.modules.get("app.devices.sim.world")
    if world is not None and rss_mb() > RENDERERS_ABOVE_MB:
        world.release_shared_renderers()
        gc.collect()
    _malloc_trim()


@pytest.fixture(autouse=True, scope="module")
def _release_after_module() -> Iterator[None]:
    yield
    release_memory()


@pytest.fixture(autouse=True)
def _release_after_a_large_test() -> Iterator[None]:
    before_mb = rss_mb()
    yield
    if rss_mb() - before_mb > TEST_GROWTH_MB:
        release_memory()


def pytest_configure(config: pytest.Config) -> None:
    bound_the_heap()
