"""The dashboard files: ES modules (no build step), offline (no CDN), consistent ids, the
server's colormap, one api-client module with the token helper, limits read from the server."""

from __future__ import annotations

import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np

from app.recon.colormap import depth_colormap

STATIC = Path(__file__).resolve().parents[2] / "static"
MODULES = sorted((STATIC / "js").glob("*.js"))
PANELS = {"depth", "analysis", "texture", "controls", "recording", "wizard", "status", "view3d"}


def _script(name: str) -> str:
    return (STATIC / "js" / name).read_text(encoding="utf-8")


def _all_scripts() -> str:
    return "\n".join(p.read_text(encoding="utf-8") for p in MODULES)


def _code(text: str) -> str:
    return re.sub(r"//[^\n]*", "", re.sub(r"/\*.*?\*/", "", text, flags=re.S))


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
    assert {"js/main.js", "style.css"} <= set(page.refs)
    html = (STATIC / "index.html").read_text(encoding="utf-8")
    assert '<script type="module" src="js/main.js"></script>' in html
    for ref in page.refs:  # nothing from the internet: the OR may have none
        assert not re.match(r"^(https?:)?//", ref), ref
    for path in [STATIC / "style.css", *MODULES]:
        text = path.read_text(encoding="utf-8")
        assert not re.search(r"https?://", text), f"{path.name} refers to a remote URL"
        assert "@import" not in text


def test_one_module_per_panel_and_imports_resolve() -> None:
    names = {p.stem for p in MODULES}
    assert PANELS | {"main", "api"} <= names, sorted(PANELS - names)
    for path in MODULES:
        text = path.read_text(encoding="utf-8")
        for ref in re.findall(r'^import .*? from "([^"]+)";', text, flags=re.M):
            assert ref.startswith("./") and (path.parent / ref).is_file(), f"{path.name}: {ref}"
        # one shared object, one place
        assert "window.fringescope" not in text or path.stem == "state"


def test_every_element_the_script_uses_exists() -> None:
    ids = _page().ids
    used = set(re.findall(r'\$\("([A-Za-z0-9_-]+)"\)', _all_scripts()))
    assert len(used) > 30
    assert used <= ids, sorted(used - ids)


def test_limits_come_from_the_server_not_the_page() -> None:
    """LED names and the exposure range are read from GET /api/limits, not written in static/."""
    html = (STATIC / "index.html").read_text(encoding="utf-8")
    assert "<option value=\"green\"" not in html and 'max="100"' not in html
    code = _code(_all_scripts())
    assert '"/api/limits"' in code
    for fact in ('"red"', '"blue"', 'max = "', 'min = "'):
        assert fact not in code, f"the scripts repeat {fact}"


def test_colour_bar_uses_the_servers_colormap() -> None:
    script = _script("colormap.js")
    block = script.split("const TURBO_HEX =", 1)[1].split(";", 1)[0]
    hex_table = "".join(re.findall(r'"([0-9a-f]+)"', block))
    js_lut = np.frombuffer(bytes.fromhex(hex_table), np.uint8).reshape(256, 3)
    server_lut = depth_colormap(np.arange(256, dtype=np.float32)[None, :], (0.0, 255.0))[0]
    np.testing.assert_array_equal(js_lut, server_lut)
    # Entry i is height min + i/255·(max − min), as the server maps it.
    assert tuple(server_lut[0]) == tuple(depth_colormap(np.zeros((1, 1), np.float32))[0, 0])
    assert tuple(server_lut[255]) == tuple(depth_colormap(np.full((1, 1), 35.0, np.float32))[0, 0])


def test_requests_go_through_the_token_helper() -> None:
    client = _script("api.js")
    everything = _code(_all_scripts())
    assert len(re.findall(r"(?<![\w.])fetch\(", everything)) == 1  # only inside api()
    assert len(re.findall(r"(?<![\w.])fetch\(", _code(client))) == 1
    assert "XMLHttpRequest" not in everything
    assert (
        "localStorage.getItem(TOKEN_KEY)" in client
        and 'const TOKEN_KEY = "fringescope_token"' in client
    )
    assert '"Authorization"] = "Bearer " + token' in client
    # WebSocket and iframe cannot send headers: they carry the token in the query.
    assert "new WebSocket(withToken(" in _script("depth.js") and 'withToken("/viser/")' in _script(
        "view3d.js"
    )
