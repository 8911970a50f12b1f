"""The dashboard says when exposure bracketing halves the depth rate (headless Chromium)."""

from __future__ import annotations

from typing import Any

import httpx
import pytest

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def test_the_status_bar_names_bracketing_and_why_the_rate_fell(page: tuple[Any, list[str]],
                                                               server: str) -> None:
    pg, errors = page
    r = httpx.put(f"{server}/api/mode", json={"bracket": True}, timeout=30)
    assert r.status_code == 200 and r.json()["bracket"] is True
    try:
        pg.wait_for_function("document.querySelector('#m-mode').textContent === 'bracket'",
                             timeout=30_000)
        pg.wait_for_function(
            "document.querySelector('#warnings').textContent.includes('depth rate halves')",
            timeout=30_000)
        note = httpx.get(f"{server}/api/status", timeout=30).json()["bracket"]["note"]
        assert pg.get_attribute("#m-mode", "title") == note
        assert note in (pg.text_content("#warnings") or "")
    finally:
        httpx.put(f"{server}/api/mode", json={"bracket": False}, timeout=30)
    pg.wait_for_function("document.querySelector('#m-mode').textContent === 'set'", timeout=30_000)
    assert "depth rate halves" not in (pg.text_content("#warnings") or "")
    assert [e for e in errors if "/viser/" not in e] == [], "\n".join(errors)
