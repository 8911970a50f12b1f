"""Status stays responsive under many streams: the load of issue 25 against a real server.

Runs ``benchmarks/bench_streams.py`` (a real ``fringescope serve`` on loopback, real sockets)
with shortened phases: 20 pollers of /api/status, then 45 MJPEG readers (session cookie) and
5 WebSocket readers, one never reading. Bounded: about 40 s. The absolute p99 depends on
what else this shared machine runs, so the test compares with the baseline of the same run
(a stream holding a worker thread made status 10x slower); the benchmark prints both.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.serial]

ROOT = Path(__file__).resolve().parents[2]


def test_status_and_depth_rate_unchanged_by_50_streams(sim_calibration_file: Path) -> None:
    run = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "bench_streams.py"),
            "--calibration",
            str(sim_calibration_file),
            "--baseline-s",
            "6",
            "--load-s",
            "8",
            "--json",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    print(run.stdout)
    fig = json.loads(run.stdout.strip().splitlines()[-1])
    base, load = fig["baseline"], fig["load"]
    assert base["failures"] == 0 and load["failures"] == 0
    assert load["n"] >= 20 * 8 * 2  # the pollers kept polling (4/s each)
    # every stream delivered images at the depth rate (1 s of slack for the ramp)
    expected = base["results_per_s"] * (fig["load_s"] - 1.0)
    assert fig["mjpeg_images_min"] >= 0.8 * expected, fig
    assert fig["ws_images_min"] >= 0.8 * expected, fig
    # the live depth rate is unchanged, status as quick as without the streams
    assert load["results_per_s"] >= 0.85 * base["results_per_s"], fig
    # p50 is the discriminating figure (streams holding worker threads made it 10x)
    assert load["p50_ms"] <= 2.0 * base["p50_ms"] + 20.0, fig
    # the tail, by the same rule as p50: against the same run without streams (a stream holding
    # a worker thread made it 10x). The absolute target, p99 within 50 ms under the streams
    # (12 ms measured on a quiet 2-core machine), is the benchmark's to print: on this shared
    # VM the tail without any stream ran 39-63 ms in two clean-clone runs and 48.6 ms
    # alone, and under the streams 0.87-1.28x that
    assert load["p99_ms"] <= 2.0 * base["p99_ms"] + 20.0, fig
