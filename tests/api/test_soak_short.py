"""A short run of ``scripts/soak.py``: real uvicorn, 4 WebSocket clients, drops and unplugs.

The full soak (10 minutes, an unplug a minute) is ``python scripts/soak.py``; here the
same script runs for 45 s with an unplug every 15 s, so several fault/recovery cycles
fit. (It lives beside the live-app tests to share their simulator calibration.)
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]


def test_short_soak_survives_faults(sim_calibration_file: Path) -> None:
    proc = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "soak.py"), "--minutes", "0.75",
         "--disconnect-every-s", "15", "--clients", "4", "--drop-rate", "0.05",
         "--exposure-ms", "40", "--calibration", str(sim_calibration_file),
         "--startup-timeout-s", "300"],
        cwd=REPO, capture_output=True, text=True, timeout=900,
        env={**os.environ, "NUMBA_THREADING_LAYER": "workqueue"},
    )
    out = proc.stdout + proc.stderr
    print(out)
    assert proc.returncode == 0, out
    assert out.rstrip().endswith("PASS")
    # the figures the script promises are all there
    for label in (
        "memory (RSS)",
        "threads",
        "device faults",
        "frames dropped",
        "client 3",
        "server exit",
    ):
        assert label in out, label
    episodes = int(re.search(r"(\d+) episodes", out).group(1))  # type: ignore[union-attr]
    assert episodes >= 2  # 45 s with an unplug every 15 s
