"""Every benchmark script starts: its imports and arguments still match the code it measures.

The scripts' ``--help`` runs share one interpreter (:data:`_USAGE_DRIVER`): each script runs
as ``__main__`` from its own folder, as ``python bench_x.py --help`` runs it, but numpy, numba
and the app are imported once for all of them, not once per script (~1-1.5 s of CPU each).
One script also runs alone in its own interpreter, the way a user starts it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p for p in (ROOT / "benchmarks").glob("bench_*.py"))

#: Runs each script given on the command line as ``__main__`` with ``--help`` (sys.path[0] its
#: folder, as for ``python script.py``); prints one JSON object: per script path its exit code
#: and what it wrote to stdout and stderr (an exception: exit code 1 and the traceback).
_USAGE_DRIVER = r"""
import contextlib, io, json, runpy, sys, traceback
from pathlib import Path

results = {}
scripts = sys.argv[1:]
for path in scripts:
    sys.path[0] = str(Path(path).parent)
    sys.argv = [path, "--help"]
    out, err = io.StringIO(), io.StringIO()
    code = 0
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            runpy.run_path(path, run_name="__main__")
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except BaseException:
            traceback.print_exc()
            code = 1
    results[path] = {"returncode": code, "stdout": out.getvalue(), "stderr": err.getvalue()}
print(json.dumps(results))
"""


@pytest.fixture(scope="module")
def usage_runs() -> dict[str, dict[str, int | str]]:
    """Every script's ``--help`` run, from one interpreter started at the repository root."""
    run = subprocess.run([sys.executable, "-c", _USAGE_DRIVER, *map(str, SCRIPTS)], cwd=ROOT,
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    results: dict[str, dict[str, int | str]] = json.loads(run.stdout.strip().splitlines()[-1])
    return results


def test_the_benchmarks_are_found():
    assert len(SCRIPTS) >= 5


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.stem)
def test_benchmark_prints_its_usage(script: Path, usage_runs: dict[str, dict[str, int | str]]):
    run = usage_runs[str(script)]
    assert run["returncode"] == 0, str(run["stderr"])[-2000:]
    assert "usage" in str(run["stdout"]).lower()


def test_a_benchmark_starts_alone_in_its_own_interpreter():
    """The way a user starts one: ``python benchmarks/bench_recon.py --help`` (it imports the
    reconstruction engine and its kernels' module)."""
    script = ROOT / "benchmarks" / "bench_recon.py"
    run = subprocess.run([sys.executable, str(script), "--help"], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "usage" in run.stdout.lower()
