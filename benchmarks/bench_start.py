"""Start-up time: seconds from process start to the first depth map (issue 24's fast start).

Starts ``python -m app serve`` as a real process (loopback, a free port) and polls
``/api/status`` until the first result is published; printed per start: the seconds to the
first depth and, when the server logged them, its start-up phases. Without
``--calibration`` the first start runs on an empty DATA_DIR (the simulator calibrates and
stores it there), then a second start reuses the stored calibration and the compiled
kernels (``NUMBA_CACHE_DIR``, kept); printed last: the second start's ratio to the first
(target: second start ≤ 20 s).

    python benchmarks/bench_start.py [--data-dir DIR] [--calibration FILE] [--starts 2]
                                     [--fresh-cache] [--timeout-s 900]

``--fresh-cache`` gives the first start an empty NUMBA_CACHE_DIR (under DATA_DIR), as a
first ``make run`` has; the later starts keep it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds the process (its threads) has used so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def one_start(data_dir: Path, calibration: Path | None, env: dict[str, str],
              timeout_s: float) -> tuple[float, str]:
    """(seconds from spawning the server to its first published depth map, its phases).

    The phases: when the HTTP port first answered and when each state was first seen.
    """
    port = free_port()
    run_env = dict(env)
    if calibration is not None:
        run_env["FRINGESCOPE_CALIBRATION_FILE"] = str(calibration)
    cmd = [sys.executable, "-m", "app", "serve", "--host", "127.0.0.1", "--port", str(port),
           "--data-dir", str(data_dir)]
    log = open(data_dir / f"serve-{port}.log", "w")  # noqa: SIM115 (closed below)
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=run_env, stdout=log, stderr=subprocess.STDOUT)
    state = "not started"
    phases: list[str] = []
    try:
        while time.monotonic() - t0 < timeout_s:
            if proc.poll() is not None:
                raise SystemExit(f"server exited with {proc.returncode}; see {log.name}")
            try:
                st = httpx.get(f"http://127.0.0.1:{port}/api/status", timeout=2).json()
            except (httpx.HTTPError, ValueError):
                time.sleep(0.1)
                continue
            now = time.monotonic() - t0
            if not phases:
                phases.append(f"HTTP up {now:.1f} s")
            if str(st.get("state")) != state:
                state = str(st.get("state"))
                phases.append(f"{state} {now:.1f} s")
            if int(st.get("results_published") or 0) >= 1:
                cpu = cpu_seconds(proc.pid)
                phases.append(f"server CPU {cpu:.1f} s = {cpu / now:.2f} of one core")
                return now, ", ".join(phases)
            time.sleep(0.1)
        raise SystemExit(f"no depth after {timeout_s:.0f} s (state {state}); see {log.name}")
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data-dir", type=Path, default=None,
                    help="data folder (default: a new temporary one)")
    ap.add_argument("--calibration", type=Path, default=None,
                    help="a stored calibration: every start is a second start")
    ap.add_argument("--starts", type=int, default=2, help="starts in a row (default 2)")
    ap.add_argument("--fresh-cache", action="store_true",
                    help="first start with an empty NUMBA_CACHE_DIR")
    ap.add_argument("--timeout-s", type=float, default=900.0)
    args = ap.parse_args(argv)
    if args.starts < 1:
        ap.error("--starts: need at least 1")
    data_dir = args.data_dir or Path(tempfile.mkdtemp(prefix="fringescope-start-"))
    data_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.setdefault("NUMBA_THREADING_LAYER", "workqueue")
    if args.fresh_cache:
        cache = data_dir / "numba-cache"
        shutil.rmtree(cache, ignore_errors=True)
        env["NUMBA_CACHE_DIR"] = str(cache)
    print(f"data dir {data_dir}; NUMBA_CACHE_DIR={env.get('NUMBA_CACHE_DIR', '(numba default)')}; "
          f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    times = []
    for i in range(args.starts):
        stored = (data_dir / "calibrations" / "sim.json").is_file()
        seconds, phases = one_start(data_dir, args.calibration, env, args.timeout_s)
        times.append(seconds)
        kind = "stored calibration" if (args.calibration or stored) else "no calibration"
        print(f"start {i + 1} ({kind}): first depth after {seconds:.1f} s ({phases})")
    if len(times) > 1:
        print(f"second start / first start: {times[1] / times[0]:.2f} "
              f"(second start {times[1]:.1f} s; target <= 20 s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
