"""The dashboard files: offline (no CDN), consistent ids, the server's colormap, token helper."""

from __future__ import annotations

import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np

from app.recon.colormap import depth_colormap

STATIC = Path(__file__).resolve().parents[2] / "static"


class _Collect(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.ids: set[str] = set()
        self.refs: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if a.get("id"):
            self.ids.add(str(a["id"]))
        for key in ("src", "href"):
            if a.get(key):
                self.refs.append(str(a[key]))


def _page() -> _Collect:
    parser = _Collect()
    parser.feed((STATIC / "index.html").read_text(encoding="utf-8"))
    return parser


def test_dashboard_is_self_contained() -> None:
    page = _page()
    assert {"app.js", "style.css"} <= set(page.refs)
    for ref in page.refs:  # nothing from the internet: the OR may have none
        assert not re.match(r"^(https?:)?//", ref), ref
    for name in ("app.js", "style.css"):
        text = (STATIC / name).read_text(encoding="utf-8")
        assert not re.search(r"https?://", text), f"{name} refers to a remote URL"
        assert "@import" not in text


def test_every_element_the_script_uses_exists() -> None:
    ids = _page().ids
    script = (STATIC / "app.js").read_text(encoding="utf-8")
    used = set(re.findall(r'\$\("([A-Za-z0-9_-]+)"\)', script))
    assert len(used) > 30
    assert used <= ids, sorted(used - ids)


def test_colour_bar_uses_the_servers_colormap() -> None:
    script = (STATIC / "app.js").read_text(encoding="utf-8")
    block = script.split("const TURBO_HEX =", 1)[1].split(";", 1)[0]
    hex_table = "".join(re.findall(r'"([0-9a-f]+)"', block))
    js_lut = np.frombuffer(bytes.fromhex(hex_table), np.uint8).reshape(256, 3)
    server_lut = depth_colormap(np.arange(256, dtype=np.float32)[None, :], (0.0, 255.0))[0]
    np.testing.assert_array_equal(js_lut, server_lut)
    # Entry i is height min + i/255·(max − min), as the server maps it.
    assert tuple(server_lut[0]) == tuple(depth_colormap(np.zeros((1, 1), np.float32))[0, 0])
    assert tuple(server_lut[255]) == tuple(depth_colormap(np.full((1, 1), 35.0, np.float32))[0, 0])


def test_requests_go_through_the_token_helper() -> None:
    script = (STATIC / "app.js").read_text(encoding="utf-8")
    code = re.sub(r"//[^\n]*", "", re.sub(r"/\*.*?\*/", "", script, flags=re.S))
    assert len(re.findall(r"(?<![\w.])fetch\(", code)) == 1  # only inside api()
    assert "XMLHttpRequest" not in code
    assert 'localStorage.getItem(TOKEN_KEY)' in script and 'const TOKEN_KEY = "fringescope_token"' in script
    assert '"Authorization"] = "Bearer " + token' in script
    # WebSocket and iframe cannot send headers: they carry the token in the query.
    assert "new WebSocket(withToken(" in script and 'withToken("/viser/")' in script
