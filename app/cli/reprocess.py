"""``fringescope reprocess REC [REC ...] -c calibration.json -o OUT``: whole recordings on Dask.

Per set the files of ``fringescope reconstruct`` (the same bytes), one Parquet table per
recording, a progress bar and one summary line (:mod:`app.batch.engine`).
"""

from __future__ import annotations

import argparse

from app.cli.reconstruct import _range


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "reprocess",
        help="reconstruct every capture set of recordings again (new calibration or options), "
             "on a local Dask cluster or an existing one",
        description="Per set writes OUT/<recording>/<set>/depth.npy, sigma.npy, reason.png "
                    "(as 'reconstruct' does, byte for byte), and per recording "
                    "OUT/<recording>/sets.parquet. A second run skips sets whose outputs exist "
                    "for the same calibration and options.",
    )
    p.add_argument("recordings", nargs="+", metavar="REC",
                   help="recording folder (or any folder whose sub-folders are capture sets); "
                        "a path or an fsspec URL the workers can read")
    p.add_argument("-c", "--calibration", required=True, help="calibration.json")
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="output folder (path or fsspec URL)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=None, metavar="N",
                       help="worker processes of the embedded local cluster (default: the cores)")
    where.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                       help="use an existing Dask scheduler instead of a local cluster")
    p.add_argument("--bracket", type=int, default=1, metavar="K",
                   help="fuse each run of K consecutive sets as an exposure bracket "
                        "(default 1: none)")
    p.add_argument("--ply", action="store_true", help="also write points.ply per set")
    p.add_argument("--depth-png", action="store_true",
                   help="also write depth.png per set (see --range)")
    p.add_argument("--range", type=_range, default=(0.0, 35.0), metavar="MIN,MAX",
                   help="depth.png colormap range in mm (default 0,35)")
    p.add_argument("--max-code", type=int, default=None,
                   help="sensor maximum code, e.g. 4095 for 12-bit data in 16-bit PNGs")
    p.add_argument("--numpy", action="store_true",
                   help="use the numpy reference path instead of numba")
    p.add_argument("--min-modulation", type=float, default=None, metavar="CODES",
                   help="explicit modulation threshold B in sensor codes, replacing the "
                        "noise-aware rule")
    p.add_argument("--phase-error", metavar="FILE", default=None,
                   help="projector-gamma table from `fringescope gamma`, subtracted from every "
                        "wrapped phase before unwrapping (part of the options hash)")
    p.add_argument("--timeout", type=float, default=10.0, metavar="S",
                   help="seconds to wait for the scheduler and its first worker (default 10)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.batch.engine import reprocess, stderr_or_none
    from app.batch.setjob import ALL_FILES, ReconOptions
    from app.calib import load_calibration
    from app.cli.gamma import read_phase_error

    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers: must be >= 1, got {args.workers}")
    if args.timeout <= 0:
        raise ValueError(f"--timeout: must be > 0, got {args.timeout}")
    calibration = load_calibration(args.calibration)
    lut = read_phase_error(args.phase_error) if args.phase_error else None
    if lut is not None:  # refused before any work when learned for another schedule
        sched = calibration.pattern
        lut.check_schedule(sched.steps, tuple(float(k) for k in sched.frequencies))
    options = ReconOptions(max_code=args.max_code, numpy=args.numpy,
                           min_modulation=args.min_modulation, range_mm=args.range,
                           phase_error=lut)
    wanted = {"depth.npy", "sigma.npy", "reason.png"} | ({"points.ply"} if args.ply else set()) \
        | ({"depth.png"} if args.depth_png else set())
    files = tuple(f for f in ALL_FILES if f in wanted)
    summary = reprocess(args.recordings, calibration, args.output, options, files=files,
                        bracket=args.bracket, workers=args.workers, scheduler=args.scheduler,
                        progress=stderr_or_none(args.quiet), timeout_s=args.timeout)
    print(summary.line(args.output))
    return 1 if summary.failed else 0
