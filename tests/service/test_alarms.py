"""The alarm board: raised, listed, acknowledged (once), bounded."""

from __future__ import annotations

import threading

import pytest

from app.core.errors import NotFound
from app.service.alarms import AlarmBoard


def test_an_alarm_stays_active_until_acknowledged() -> None:
    board = AlarmBoard()
    first = board.raise_alarm("recorder", "recording 'a' stopped: disk full")
    second = board.raise_alarm("recorder", "recording 'b' stopped: write error")
    assert [a.id for a in board.active()] == [first.id, second.id] and first.id != second.id
    assert first.acknowledged_at is None and first.raised_at.endswith("+00:00")
    acked = board.acknowledge(first.id)
    assert acked.acknowledged_at is not None and acked.message == first.message
    assert [a.id for a in board.active()] == [second.id]
    assert board.acknowledge(first.id) == acked  # twice: unchanged
    assert [a.id for a in board.all()] == [first.id, second.id]


def test_an_unknown_alarm_is_not_found_by_its_id() -> None:
    board = AlarmBoard()
    with pytest.raises(NotFound, match="alarm_id: no alarm 7"):
        board.acknowledge(7)


def test_the_board_drops_acknowledged_alarms_first_when_full() -> None:
    board = AlarmBoard(keep=3)
    a, b, c = (board.raise_alarm("recorder", f"m{i}") for i in range(3))
    board.acknowledge(b.id)
    d = board.raise_alarm("recorder", "m3")
    assert [x.id for x in board.all()] == [a.id, c.id, d.id]
    e = board.raise_alarm("recorder", "m4")  # none acknowledged: the oldest goes
    assert [x.id for x in board.all()] == [c.id, d.id, e.id]
    with pytest.raises(ValueError, match="keep"):
        AlarmBoard(keep=0)


def test_alarms_raised_from_many_threads_get_distinct_ids() -> None:
    board = AlarmBoard(keep=1000)
    threads = [threading.Thread(target=lambda: [board.raise_alarm("t", "x") for _ in range(50)])
               for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    ids = [a.id for a in board.active()]
    assert len(ids) == len(set(ids)) == 200
