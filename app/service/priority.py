"""The CPU priority of the service's bulk-work threads.

Reconstruction (with numba's pool, which it starts) and the 3-D viewer's updates keep both
cores of a small machine busy; the event loop that answers ``/api/status`` and the controls
then waited for a core behind them. Under 50 streams on a 2-core machine, status p99 was 30–69 ms
over five runs at the process's priority and 17–27 ms over three with these threads 5 nice steps
lower, the depth rate unchanged (``benchmarks/bench_streams.py``). Control must stay responsive;
bulk work yields to it. Acquisition keeps the process's priority: a camera's frames must not
wait.
"""

from __future__ import annotations

import logging
import os
import threading

log = logging.getLogger(__name__)

#: how much lower than the process a bulk-work thread runs (Unix nice steps; raising the nice
#: value needs no privilege, lowering it would)
BULK_WORK_NICE_STEPS = 5


def lower_this_threads_priority(steps: int = BULK_WORK_NICE_STEPS) -> bool:
    """Raise the calling thread's nice value by ``steps`` (Linux: per thread); threads it starts
    afterwards (numba's pool, when this thread starts it) inherit it. False where the platform
    has no per-thread priority or refuses; the thread then runs as before."""
    if steps < 0:
        raise ValueError(f"steps: must be >= 0 (lowering a thread's priority), got {steps}")
    if not hasattr(os, "setpriority") or not hasattr(threading, "get_native_id"):
        return False
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + steps))
    except OSError as exc:  # e.g. a sandbox that forbids it: not a fault, only slower controls
        log.info("thread %s keeps its CPU priority: %s", threading.current_thread().name, exc)
        return False
    return True
