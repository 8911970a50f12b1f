"""tests/helpers/rss.py: each test's resident set, wall time and CPU time, in a real pytest run."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# one test that waits, one that computes, one whose child process computes (0.4 s each)
TESTS = '''
import subprocess, sys, time

BURN = "import time\\nt = time.process_time()\\nwhile time.process_time() - t < 0.4: pass"


def test_waits():
    time.sleep(0.4)


def test_computes():
    exec(BURN)


def test_child_computes():
    subprocess.run([sys.executable, "-c", BURN], check=True)
'''


def test_each_line_says_wall_and_cpu_time_of_the_test_and_its_children(tmp_path: Path) -> None:
    (tmp_path / "test_three.py").write_text(TESTS)
    (tmp_path / "pytest.ini").write_text("[pytest]\n")
    log = tmp_path / "rss.tsv"
    env = {**os.environ, "FRINGESCOPE_TEST_RSS": str(log), "PYTHONPATH": str(ROOT)}
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "tests.helpers.rss", "-p", "no:cacheprovider",
         "-p", "no:randomly", "-c", str(tmp_path / "pytest.ini"), str(tmp_path)],
        capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    assert run.returncode == 0, run.stdout + run.stderr
    rows = {r[0].split("::")[1]: r for r in (ln.split("\t") for ln in log.read_text().splitlines())}
    assert set(rows) == {"test_waits", "test_computes", "test_child_computes"}
    for r in rows.values():
        assert len(r) == 8 and r[4] == "main"
        assert float(r[1]) > 0 and float(r[2]) >= float(r[1])
    wall, cpu, child = ({k: float(r[i]) for k, r in rows.items()} for i in (5, 6, 7))
    assert wall["test_waits"] >= 0.4 and cpu["test_waits"] < 0.2
    assert cpu["test_computes"] >= 0.4 and child["test_computes"] < 0.1
    assert child["test_child_computes"] >= 0.4 and cpu["test_child_computes"] < 0.3
    assert all(wall[k] >= cpu[k] + child[k] - 0.05 for k in wall)
