"""Memory and time per test: a pytest plugin that logs the process's resident set and the
test's wall and CPU time after each test.

Enabled by ``FRINGESCOPE_TEST_RSS=FILE`` (tests/conftest.py loads it): one tab-separated
line per test, ``nodeid  rss_mb  peak_mb  children_mb  worker  wall_s  cpu_s  child_cpu_s``,
where
``rss_mb`` is the pytest process now, ``peak_mb`` its high-water mark so far (``VmHWM``),
``children_mb`` the summed resident set of its live child processes (servers, browsers,
builds) and ``worker`` the pytest-xdist worker (the workers append to one file, a line at
a time), or ``main``: a run without xdist, or the xdist controller (its children are the
workers: its ``children_mb`` is their sum). The suite's peak is where ``peak_mb`` jumps; a
fixture that keeps memory shows as ``rss_mb`` staying up after its tests. ``wall_s`` is the
test's wall time from its setup to its teardown's end, ``cpu_s`` the pytest process's CPU time
(user + system, all its threads) over it and ``child_cpu_s`` that of the child processes it
reaped over it (servers, builds; ``os.times``): a test whose CPU is far below its wall time
waits (on a paced camera, a timeout, a browser) rather than computes.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import TextIO

import pytest

ENV = "FRINGESCOPE_TEST_RSS"


def status_mb(key: str) -> float:
    """A ``VmRSS``/``VmHWM`` line of /proc/self/status, MB (0 where /proc is absent)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def _children_mb() -> float:
    try:
        import psutil
    except ImportError:
        return 0.0
    total = 0
    for child in psutil.Process().children(recursive=True):
        try:
            total += child.memory_info().rss
        except psutil.Error:
            continue
    return total / 1e6


def _clock() -> tuple[float, float, float]:
    """(wall s, this process's CPU s, its reaped children's CPU s) now."""
    t = os.times()
    return time.perf_counter(), t.user + t.system, t.children_user + t.children_system


class RssLog:
    """Writes one line per test after its teardown (fixtures released by then)."""

    def __init__(self, out: TextIO) -> None:
        self.out = out
        self.worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        self.start = _clock()

    @pytest.hookimpl(tryfirst=True)
    def pytest_runtest_logstart(self, nodeid: str) -> None:
        self.start = _clock()

    @pytest.hookimpl(trylast=True)
    def pytest_runtest_logfinish(self, nodeid: str) -> None:
        wall, cpu, child = (b - a for a, b in zip(self.start, _clock(), strict=True))
        self.out.write(f"{nodeid}\t{status_mb('VmRSS'):.0f}\t{status_mb('VmHWM'):.0f}"
                       f"\t{_children_mb():.0f}\t{self.worker}"
                       f"\t{wall:.3f}\t{cpu:.3f}\t{child:.3f}\n")
        self.out.flush()


def pytest_configure(config: pytest.Config) -> None:
    path = os.environ.get(ENV)
    if path:
        out = open(path, "a", encoding="utf-8")  # noqa: SIM115  (closed at unconfigure)
        config.pluginmanager.register(RssLog(out), "fringescope-rss")
        config.add_cleanup(out.close)
