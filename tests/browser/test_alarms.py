"""A recording that stops on a write error raises a dashboard alarm that stays until acknowledged.

Real server on the simulator, real Chromium, a real write error: the recording's folder is
taken away under the running recorder, so its next set cannot be written. The alarm shows,
survives a page reload (it lives on the server), and goes when acknowledged.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.helpers.dashboard import live_server
from tests.helpers.outputs import wait_for

pytestmark = [pytest.mark.browser, pytest.mark.slow]

DATA_NAME = "alarm-data"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory,
           request: pytest.FixtureRequest) -> Iterator[str]:
    with live_server(tmp_path_factory, request, DATA_NAME) as base:
        yield base


def _block(folder: Path) -> None:
    """A write error: a plain file where the recording's folder was, so no set can be written
    there (the atomic writer would recreate a missing folder, not replace a file)."""
    for n in range(20):  # the writer may recreate the folder between the two steps: again
        folder.rename(folder.with_name(f"moved-away-{n}"))
        try:
            os.close(os.open(folder, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            return
        except (FileExistsError, IsADirectoryError):
            continue
    raise AssertionError(f"could not put a file in place of {folder}")


def test_a_write_error_alarm_stays_until_acknowledged(
        page: tuple[Any, list[str]], server: str, tmp_path_factory: pytest.TempPathFactory) -> None:
    pg, errors = page
    assert pg.locator("#alarms").is_hidden()
    r = httpx.post(server + "/api/recording/start", json={"name": "doomed"}, timeout=10)
    assert r.status_code == 200, r.text
    # the server's data folder (pytest also links it as "<name>current")
    base = tmp_path_factory.getbasetemp()
    (folder,) = {p.resolve() for p in base.glob(f"{DATA_NAME}*/recordings/doomed")}
    assert wait_for(lambda: httpx.get(server + "/api/recording", timeout=10).json()["sets"] >= 1,
                    120, 0.2), httpx.get(server + "/api/recording", timeout=10).json()
    _block(folder)

    def stopped() -> bool:
        return httpx.get(server + "/api/status", timeout=10).json()["recording"] is None

    assert wait_for(stopped, 60, 0.2), "the recording did not stop on the write error"
    st = httpx.get(server + "/api/status", timeout=10).json()
    (warning,) = [w for w in st["warnings"] if "recording 'doomed' stopped" in w]
    (alarm,) = st["alarms"]
    assert alarm["source"] == "recorder" and alarm["message"] == warning
    assert alarm["acknowledged_at"] is None

    def shows_alarm() -> None:
        row = pg.locator(f"#alarms .alarm[data-alarm-id='{alarm['id']}']")
        row.wait_for(state="visible", timeout=15_000)
        assert "recording 'doomed' stopped" in row.inner_text()

    shows_alarm()
    pg.reload(wait_until="load")
    pg.wait_for_function("window.fringescope && window.fringescope.status", timeout=60_000)
    shows_alarm()  # still there after the reload: nobody acknowledged it
    pg.wait_for_timeout(1500)  # a few more status polls: it stays
    shows_alarm()

    pg.locator(f"#alarms .alarm[data-alarm-id='{alarm['id']}'] button.alarm-ack").click()
    pg.locator("#alarms").wait_for(state="hidden", timeout=15_000)
    assert httpx.get(server + "/api/status", timeout=10).json()["alarms"] == []
    pg.reload(wait_until="load")
    pg.wait_for_function("window.fringescope && window.fringescope.status", timeout=60_000)
    pg.wait_for_timeout(1500)
    assert pg.locator("#alarms .alarm").count() == 0 and pg.locator("#alarms").is_hidden()
    # the status warning is the present (until a new recording); the alarm was the event
    assert warning in httpx.get(server + "/api/status", timeout=10).json()["warnings"]
    assert not errors, errors
