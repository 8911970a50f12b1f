from __future__ import annotations

import threading
import time

import pytest

from app.service.store import LatestSlot, NewestQueue, RateMeter, RecentValues


def test_newest_queue_drops_oldest_and_counts():
    q: NewestQueue[int] = NewestQueue(maxsize=1)
    for i in range(5):
        q.put(i)
    assert q.dropped == 4 and q.get(0.01) == 4 and q.get(0.01) is None


def test_newest_queue_wakes_a_waiting_consumer():
    q: NewestQueue[str] = NewestQueue()
    got: list[str | None] = []
    t = threading.Thread(target=lambda: got.append(q.get(2.0)))
    t.start()
    time.sleep(0.05)
    q.put("x")
    t.join(2.0)
    assert got == ["x"]


def test_latest_slot_wait_newer_and_close():
    slot: LatestSlot[str] = LatestSlot()
    assert slot.wait_newer(0, 0.01) == (0, None)
    assert slot.publish("a") == 1
    assert slot.wait_newer(0, 0.01) == (1, "a")
    assert slot.wait_newer(1, 0.01) == (1, None)
    result: list[tuple[int, str | None]] = []
    t = threading.Thread(target=lambda: result.append(slot.wait_newer(1, 5.0)))
    t.start()
    time.sleep(0.05)
    slot.close()
    t.join(1.0)
    assert not t.is_alive() and result == [(1, None)]


def test_rate_meter_measures_a_regular_stream():
    m = RateMeter(window_s=10.0)
    now = time.monotonic()
    for i in range(21):
        m.tick(now - 2.0 + 0.1 * i)
    assert m.rate() == pytest.approx(10.0, rel=0.05)
    assert RateMeter().rate() == 0.0


def test_rate_meter_decays_when_the_stream_stalls():
    m = RateMeter(window_s=10.0)
    now = time.monotonic()
    for i in range(11):
        m.tick(now - 5.0 + 0.1 * i)  # 10 events/s, then 4 s of silence
    assert m.rate() < 3.0


def test_recent_values_median():
    r = RecentValues(3)
    assert r.median() is None
    for v in (1, 100, 2, 3):
        r.add(v)
    assert r.median() == 3.0
