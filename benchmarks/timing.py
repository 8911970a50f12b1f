"""Timing shared by the benchmarks (run as scripts: this folder is on their import path)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable


def median_ms(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """Median wall ms and median process CPU ms (all threads) of ``fn`` after one warm-up call:
    on a shared machine the wall time follows the others' load, the CPU time much less."""
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        wall.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return statistics.median(wall), statistics.median(cpu)
