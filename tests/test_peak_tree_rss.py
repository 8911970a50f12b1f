"""scripts/peak_tree_rss.py: the peak memory of a command's whole process tree, children too."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TOOL = ROOT / "scripts" / "peak_tree_rss.py"

# a parent holding 80 MB that starts a child holding 80 MB; both stay alive about 1.5 s
CHILD = "import time; b = b'\\1' * (80 << 20); time.sleep(1.5)"
PARENT = (
    "import subprocess, sys, time; b = b'\\1' * (80 << 20); "
    f"p = subprocess.Popen([sys.executable, '-c', {CHILD!r}]); time.sleep(0.2); p.wait(); "
    "sys.exit(3)"
)


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(TOOL), *args], capture_output=True, text=True,
                          timeout=60)


def _peak_mb(stderr: str, what: str) -> float:
    line = next(ln for ln in stderr.splitlines() if f"peak summed {what}" in ln)
    return float(line.split(f"peak summed {what} ")[1].split(" MB")[0])


def test_the_peak_sums_the_command_and_its_children(tmp_path: Path) -> None:
    log = tmp_path / "samples.tsv"
    run = _run("--interval-s", "0.1", "--log", str(log), "--", sys.executable, "-c", PARENT)
    assert run.returncode == 3, run.stderr  # the command's exit code
    # two processes of 80 MB each (plus their interpreters): one of them alone is < 120 MB
    assert _peak_mb(run.stderr, "RSS") >= 170, run.stderr
    assert _peak_mb(run.stderr, "PSS") >= 170, run.stderr
    rows = [ln.split("\t") for ln in log.read_text().splitlines()]
    assert len(rows) >= 5 and max(int(r[3]) for r in rows) == 2
    assert "load average (1 min) mean" in run.stderr


def test_no_command_or_a_bad_interval_is_exit_2() -> None:
    run = _run()
    assert run.returncode == 2 and "no command given" in run.stderr
    run = _run("--interval-s", "0", "--", "true")
    assert run.returncode == 2 and "--interval-s must be > 0" in run.stderr
