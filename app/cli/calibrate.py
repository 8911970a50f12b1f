"""``fringescope calibrate CALIB_DIR -o calibration.json [--robust]``."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="fit the phase-to-depth calibration from board poses",
        description=(
            "Calibrate from a folder with board.json and capture sets pose_00/, pose_01/, ... "
            "(pose_00 is the reference plane). Prints per-pose corners, reprojection error and "
            "fit residual, then writes the calibration file atomically."
        ),
    )
    p.add_argument("calib_dir", metavar="CALIB_DIR", help="calibration folder")
    p.add_argument("-o", "--output", required=True, metavar="FILE", help="calibration JSON to write")
    p.add_argument("--robust", action="store_true", help="drop outlier points and poses, and report them")
    p.add_argument("--corners-only", action="store_true",
                   help="fit Eq. (5) on the board corners only, as the paper (default: a dense grid over each board)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.calib import calibrate_folder, save_calibration

    report = calibrate_folder(args.calib_dir, robust=args.robust, dense=not args.corners_only)
    print(report.table())
    dropped = [p.name for p in report.poses if p.dropped]
    if dropped:
        print(f"dropped poses: {', '.join(dropped)}")
    out = save_calibration(report.calibration, Path(args.output))
    print(f"wrote {out}")
    return 0
