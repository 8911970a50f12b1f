"""``fringescope bench``: run the timing scripts in ``benchmarks/`` and print their output."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parents[2] / "benchmarks"


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser("bench", help="run the benchmarks (benchmarks/bench_*.py)")
    p.add_argument("names", nargs="*", metavar="NAME", help="only these benchmarks, e.g. recon")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not BENCH_DIR.is_dir():
        raise ValueError(f"{BENCH_DIR}: benchmarks folder not found (a source checkout is needed)")
    scripts = sorted(BENCH_DIR.glob("bench_*.py"))
    if args.names:
        wanted = {n.removeprefix("bench_").removesuffix(".py") for n in args.names}
        unknown = wanted - {s.stem.removeprefix("bench_") for s in scripts}
        if unknown:
            raise ValueError(f"names: no benchmark {sorted(unknown)} in {BENCH_DIR}")
        scripts = [s for s in scripts if s.stem.removeprefix("bench_") in wanted]
    layer = os.environ.get("NUMBA_THREADING_LAYER", "workqueue")
    env = {**os.environ, "NUMBA_THREADING_LAYER": layer}
    failed = 0
    for script in scripts:
        print(f"== {script.name}", flush=True)
        rc = subprocess.run([sys.executable, str(script)], env=env, cwd=BENCH_DIR.parent).returncode
        if rc:
            print(f"{script.name}: exit code {rc}", file=sys.stderr)
            failed += 1
    return 1 if failed else 0
