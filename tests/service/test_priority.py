"""Bulk-work threads yield the CPU to the event loop (app/service/priority.py)."""

from __future__ import annotations

import os
import threading

import pytest

from app.service.priority import BULK_WORK_NICE_STEPS, lower_this_threads_priority


def test_only_the_calling_thread_and_the_threads_it_starts_run_lower() -> None:
    main_nice = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    seen: dict[str, int] = {}

    def child() -> None:
        seen["child"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    def bulk() -> None:
        seen["before"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        seen["lowered"] = int(lower_this_threads_priority())
        seen["after"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        t = threading.Thread(target=child)
        t.start()
        t.join()

    t = threading.Thread(target=bulk)
    t.start()
    t.join()
    assert seen["lowered"] == 1
    assert seen["after"] == min(19, seen["before"] + BULK_WORK_NICE_STEPS)
    assert seen["child"] == seen["after"]  # numba's pool, started from it, inherits it
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == main_nice


def test_raising_a_threads_priority_is_refused() -> None:
    with pytest.raises(ValueError, match="^steps"):
        lower_this_threads_priority(-1)
