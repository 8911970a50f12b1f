"""Hostile input against a served app: how fast and how cheaply it is refused.

    python benchmarks/bench_hostile.py [--repeat 5] [--json-mb 10]

The app is served by uvicorn on loopback (a free port) in this process, its lifespan off (no
instrument needs to run to refuse input); requests go over TCP with httpx. Each hostile
request is timed beside a baseline of the same route with a small valid body, in the same
process, and printed as a ratio:

- a ``--json-mb`` MB JSON body to ``PUT /api/measure/tool`` (announced by Content-Length, and
  streamed chunked) against one kept measurement;
- a PNG decompression bomb (a zip of 16 all-zero 8000 × 8000 PNGs, ~1 MB) to ``POST /api/phase``
  against a whole 16-frame 64 × 64 set, with the process's peak RSS growth during the bomb
  (peak reset through ``/proc/self/clear_refs``);
- ``/api/limits`` latency while the large bodies are sent, against it alone.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from app.core.jit import numeric_environment

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

MB = 1024 * 1024


def _median_ms(fn: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000)
    return statistics.median(times)


def _peak_growth_mb(fn: Callable[[], object]) -> float:
    def kb(key: str) -> int:
        with open("/proc/self/status", encoding="ascii") as fh:
            return next(int(line.split()[1]) for line in fh if line.startswith(key + ":"))

    before = kb("VmRSS")
    with open("/proc/self/clear_refs", "w", encoding="ascii") as fh:
        fh.write("5")  # VmHWM := VmRSS
    fn()
    return (kb("VmHWM") - before) / 1024


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=5, help="timed requests per figure (median)")
    parser.add_argument(
        "--json-mb", type=float, default=10.0, help="size of the large JSON body, MB"
    )
    args = parser.parse_args(argv)

    import httpx
    import uvicorn

    from app.config import Settings
    from app.main import create_app
    from tests.helpers.hostile import capture_json, png_bomb_zip, zero_png

    app = create_app(Settings(data_dir=Path(tempfile.mkdtemp()), viewer=False, autostart=False))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, lifespan="off", log_level="warning")
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    base = f"http://127.0.0.1:{port}"
    small = b'{"measurements": [{"kind": "length", "points": [[1.5, 2.5], [3.5, 4.5]]}]}'
    item = b'{"kind": "length", "points": [[1.5, 2.5], [3.5, 4.5]]}, '
    big = b'{"measurements": [' + item * int(args.json_mb * MB / len(item)) + b"{}]}"
    valid_set = [("files", ("capture.json", capture_json(), "application/json"))] + [
        ("files", (f"frame_{i:02d}.png", zero_png(64, 64), "image/png")) for i in range(16)
    ]
    bomb = png_bomb_zip()
    json_headers = {"content-type": "application/json"}
    rows: list[tuple[str, float, str, float]] = []
    try:
        with httpx.Client(base_url=base, timeout=60) as c:

            def put(body: bytes | Iterator[bytes], expect: int) -> None:
                r = c.put("/api/measure/tool", content=body, headers=json_headers)
                assert r.status_code == expect, r.text

            def chunked() -> Iterator[bytes]:
                for start in range(0, len(big), 64 * 1024):
                    yield big[start : start + 64 * 1024]

            base_ms = _median_ms(lambda: put(small, 200), args.repeat)
            rows.append(
                (
                    f"{args.json_mb:g} MB JSON, Content-Length -> 413",
                    _median_ms(lambda: put(big, 413), args.repeat),
                    "1 kept measurement",
                    base_ms,
                )
            )
            rows.append(
                (
                    f"{args.json_mb:g} MB JSON, chunked -> 413",
                    _median_ms(lambda: put(chunked(), 413), args.repeat),
                    "1 kept measurement",
                    base_ms,
                )
            )

            def phase(files: object, content: bytes | None, expect: int) -> None:
                r = (
                    c.post("/api/phase", files=files)
                    if content is None
                    # type: ignore[arg-type]
                    else c.post(
                        "/api/phase", content=content, headers={"content-type": "application/zip"}
                    )
                )
                assert r.status_code == expect, r.text

            set_ms = _median_ms(lambda: phase(valid_set, None, 200), args.repeat)
            rows.append(
                (
                    "PNG bomb zip (16 x 8000x8000) -> 422",
                    _median_ms(lambda: phase(None, bomb, 422), args.repeat),
                    "16-frame 64x64 set",
                    set_ms,
                )
            )
            growth_mb = _peak_growth_mb(lambda: phase(None, bomb, 422))

            alone_ms = _median_ms(lambda: c.get("/api/limits"), 20)
            stop = threading.Event()

            def flood() -> None:
                with httpx.Client(base_url=base, timeout=60) as other:
                    while not stop.is_set():
                        other.put("/api/measure/tool", content=big, headers=json_headers)

            flooder = threading.Thread(target=flood)
            flooder.start()
            try:
                busy_ms = _median_ms(lambda: c.get("/api/limits"), 20)
            finally:
                stop.set()
                flooder.join()
            rows.append(
                ("GET /api/limits during 10 MB bodies", busy_ms, "GET /api/limits alone", alone_ms)
            )
    finally:
        server.should_exit = True
        thread.join(timeout=10)

    print(f"{'request':44s} {'ms':>8s}   {'baseline':24s} {'ms':>8s} {'ratio':>7s}")
    for name, ms, base_name, b_ms in rows:
        print(f"{name:44s} {ms:8.1f}   {base_name:24s} {b_ms:8.1f} {ms / b_ms:7.2f}")
    print(
        f"PNG bomb: peak RSS growth of the serving process {growth_mb:.1f} MB "
        f"(bomb {len(bomb) / MB:.2f} MB, {16 * 64} MB if decoded)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
