"""``scripts/start_progress.py`` (make run's progress lines) against the real app on the
simulator."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from app.config import Settings
from tests.helpers.outputs import serve, wait_for

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "start_progress.py"


@pytest.fixture(scope="module")
def stored(tmp_path_factory: pytest.TempPathFactory, request: pytest.FixtureRequest) -> Path:
    """A data folder holding a stored simulator calibration (as after a first start)."""
    given = os.environ.get("FRINGESCOPE_TEST_SIM_CALIBRATION")
    source = (
        Path(given)
        if given and Path(given).is_file()
        else request.getfixturevalue("sim_calibration_file")
    )
    data = tmp_path_factory.mktemp("progress-data")
    (data / "calibrations").mkdir()
    (data / "calibrations" / "sim.json").write_bytes(Path(source).read_bytes())
    return data


@pytest.fixture(scope="module")
def live(stored: Path) -> Iterator[str]:
    from app.main import create_app

    settings = Settings(data_dir=stored, viewer=False, sim_seed=3, exposure_ms=40.0)
    with serve(create_app(settings)) as host:
        yield f"http://{host}"


def run(
    url: str, data_dir: Path, cache_dir: Path, timeout_s: float = 300
) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir))
    return subprocess.run([sys.executable, str(SCRIPT), "--url", url, "--data-dir", str(data_dir),
                           "--timeout-s", str(timeout_s)], capture_output=True, text=True, env=env,
                          timeout=timeout_s + 60)


def test_second_start_estimate_then_phases_until_first_depth(
    live: str, stored: Path, tmp_path: Path
) -> None:
    cache = tmp_path / "cache"
    (cache / "recon").mkdir(parents=True)
    (cache / "recon" / "fast._phase-1.py311.nbi").write_bytes(b"x")  # compiled kernels present
    done = run(live, stored, cache)
    assert done.returncode == 0, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    assert all(line.startswith("[start] ") for line in lines), lines
    assert "first start" not in done.stdout
    assert "first depth expected in about" in lines[0] and "idle machine" in lines[0]
    assert lines[-1] == f"[start] first depth after {lines[-1].split()[4]} s: open {live}/"
    assert httpx.get(live + "/api/status").json()["results_published"] >= 1


def test_first_start_says_what_it_does_and_how_long(live: str, tmp_path: Path) -> None:
    assert wait_for(
        lambda: httpx.get(live + "/api/status").json()["results_published"] >= 1, 300, 0.5
    )
    done = run(live, tmp_path / "empty-data", tmp_path / "empty-cache")
    assert done.returncode == 0, done.stdout + done.stderr
    first, estimate = done.stdout.splitlines()[:2]
    assert "first start" in first and "calibrates" in first and "compiles" in first
    assert "later starts about 10 s" in estimate


def test_gives_up_with_one_line_when_no_server_answers(tmp_path: Path) -> None:
    done = run("http://127.0.0.1:9", tmp_path, tmp_path, timeout_s=3)
    assert done.returncode == 1
    assert done.stdout.splitlines()[-1] == "[start] no depth after 3 s; see the server's log above"
