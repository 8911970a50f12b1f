"""``fringescope calibrate CALIB_DIR -o calibration.json [--robust] [--model eq5|geometric]``."""

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
            "(pose_00 is the reference plane). Fits both depth models (Eq. (5) and the geometric "
            "projector model), prints per-pose corners, reprojection error and fit residual and "
            "both models' held-out-pose errors, keeps the better model (or --model), then writes "
            "the calibration file atomically."
        ),
    )
    p.add_argument("calib_dir", metavar="CALIB_DIR", help="calibration folder")
    p.add_argument("-o", "--output", required=True, metavar="FILE",
                   help="calibration JSON to write")
    p.add_argument("--robust", action="store_true",
                   help="drop outlier points and poses, and report them")
    p.add_argument("--corners-only", action="store_true",
                   help="fit Eq. (5) on the board corners only, as the paper (default: a dense "
                        "grid over each board)")
    p.add_argument("--model", choices=("eq5", "geometric"), default=None,
                   help="force the depth model (default: the one with the smaller held-out error)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.calib import calibrate_folder, save_calibration

    report = calibrate_folder(args.calib_dir, robust=args.robust, dense=not args.corners_only,
                              model=args.model)
    print(report.table())
    dropped = [p.name for p in report.poses if p.dropped]
    if dropped:
        print(f"dropped poses: {', '.join(dropped)}")
    print(f"active model: {report.calibration.model.name}")
    _print_coverage(report)
    out = save_calibration(report.calibration, Path(args.output))
    print(f"wrote {out}")
    return 0


def _print_coverage(report: Any) -> None:
    """The image x height cells the poses cover, sigma_model per cell, and the pose to add."""
    from app.calib.coverage import report_coverage
    from app.calib.model import undistort_points

    if report.samples is None:
        return
    cal = report.calibration
    cov, advice = report_coverage(
        report.samples, cal.reference_plane,
        lambda uv: undistort_points(uv, cal.camera_matrix, cal.dist_coeffs), report.geometric)
    print(cov.table())
    if report.geometric is None:
        print("sigma_model: no geometric model fitted; cells count by board points only")
    print(("next pose (optional): " if cov.reached else "next pose: ") + advice.text)
