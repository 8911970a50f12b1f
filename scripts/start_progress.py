"""Start-up progress on the console for ``make run``: how long it will take, then each phase.

Started beside ``fringescope serve`` (see the Makefile): says up front whether this is a
first start (no stored calibration or no compiled kernels: the simulator calibrates and
numba compiles, minutes) or a second one (seconds), scaled by the machine's current load;
then prints each state the server reports (``GET /api/status``) with the elapsed time, and
the address of the dashboard once the first depth map is there. Leaves when the server
has shown its first depth, when it goes away, or after ``--timeout-s``.

    python scripts/start_progress.py [--url http://127.0.0.1:8000] [--data-dir data]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

# CPU seconds to the first depth, measured with benchmarks/bench_start.py on a 2-core
# machine under load: a second start (stored calibration, cached kernels and simulator scene
# geometry) about 5 s, a first start (simulator calibration, kernel compilation) about 100 s
SECOND_START_CPU_S = 5.0
FIRST_START_EXTRA_CPU_S = 95.0


def first_start_reasons(data_dir: Path, cache_dir: str | None) -> list[str]:
    """What a first start still has to do (empty: this is a second start)."""
    reasons = []
    if not any((data_dir / "calibrations").glob("*.json")):
        reasons.append("the simulator calibrates itself (board poses, then the fit)")
    if cache_dir and not any(Path(cache_dir).rglob("*.nbi")):
        reasons.append("numba compiles the reconstruction kernels (cached for later starts)")
    return reasons


def estimate_s(cpu_s: float) -> float:
    """Wall seconds for ``cpu_s`` of mostly single-threaded work at the current load."""
    cores = os.cpu_count() or 1
    load = os.getloadavg()[0]
    share = min(1.0, cores / max(load + 1.0, 1.0))
    return cpu_s / share


def status(url: str) -> dict[str, object] | None:
    try:
        with urllib.request.urlopen(url + "/api/status", timeout=3) as resp:
            data: dict[str, object] = json.load(resp)
            return data
    except urllib.error.HTTPError as exc:
        if exc.code == 401:
            return {"state": "up (status needs the API token)", "results_published": 1}
        return None
    except (OSError, ValueError):
        return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    port = os.environ.get("FRINGESCOPE_PORT", "8000")
    ap.add_argument("--url", default=f"http://127.0.0.1:{port}", help="the server's address")
    ap.add_argument("--data-dir", type=Path,
                    default=Path(os.environ.get("FRINGESCOPE_DATA_DIR", "data")))
    ap.add_argument("--timeout-s", type=float, default=1800.0)
    args = ap.parse_args(argv)
    say = lambda text: print(f"[start] {text}", flush=True)  # noqa: E731
    reasons = first_start_reasons(args.data_dir, os.environ.get("NUMBA_CACHE_DIR"))
    cpu_s = SECOND_START_CPU_S + (FIRST_START_EXTRA_CPU_S if reasons else 0.0)
    load = f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    if reasons:
        say("first start: " + "; ".join(reasons) + ".")
    say(f"first depth expected in about {estimate_s(cpu_s):.0f} s ({load}; "
        f"about {cpu_s:.0f} s on an idle machine)"
        + (", later starts about 10 s" if reasons else ""))
    parent = os.getppid()
    t0 = time.monotonic()
    last_state, last_note = "", t0
    while time.monotonic() - t0 < args.timeout_s:
        if os.getppid() != parent:  # the server (our parent) has gone
            return 1
        st = status(args.url)
        now = time.monotonic()
        state = "starting the web server" if st is None else str(st.get("state"))
        phase = "" if st is None else str(st.get("phase") or st.get("progress") or "")
        shown = state + (f": {phase}" if phase else "")
        if shown != last_state or now - last_note >= 15:
            say(f"{shown} … {now - t0:.0f} s")
            last_state, last_note = shown, now
        if st is not None and int(str(st.get("results_published") or 0)) >= 1:
            say(f"first depth after {now - t0:.0f} s: open {args.url}/")
            return 0
        time.sleep(1.0)
    say(f"no depth after {args.timeout_s:.0f} s; see the server's log above")
    return 1


if __name__ == "__main__":
    sys.exit(main())
