"""``fringescope reconstruct SET_DIR [SET_DIR ...] -c calibration.json -o OUT_DIR``: capture sets
→ depth files.

One set gives its depth. Several sets of one scene at different exposures (an exposure
bracket) are fused: each pixel from the set that measures it with the smallest σ
(:mod:`app.recon.fusion`).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def _range(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MIN,MAX in mm, got {text!r}") from None
    if not lo < hi:
        raise argparse.ArgumentTypeError(f"need MIN < MAX, got {text!r}")
    return lo, hi


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "reconstruct",
        help="turn a capture set (or an exposure bracket of sets) into depth.npy, sigma.npy, "
             "points.ply, depth.png and reason.png",
        description="Reconstruct one capture-set folder with a calibration file; several "
                    "folders of one scene at different exposures are fused (each pixel from the "
                    "set that measures it best).",
    )
    p.add_argument("set_dirs", nargs="+", metavar="SET_DIR",
                   help="capture-set folder (capture.json + frames); more than one: an exposure "
                        "bracket")
    p.add_argument("-c", "--calibration", required=True, help="calibration.json")
    p.add_argument("-o", "--output", required=True, metavar="OUT_DIR", help="output folder")
    p.add_argument("--range", type=_range, default=(0.0, 35.0), metavar="MIN,MAX",
                   help="depth colormap range in mm (default 0,35)")
    p.add_argument("--max-code", type=int, default=None,
                   help="sensor maximum code, e.g. 4095 for 12-bit data in 16-bit PNGs")
    p.add_argument("--numpy", action="store_true",
                   help="use the numpy reference path instead of numba")
    p.add_argument("--min-modulation", type=float, default=None, metavar="CODES",
                   help="explicit modulation threshold B in sensor codes, replacing the default "
                        "noise-aware rule (the schedule's order-error bound under the camera "
                        "noise, and its depth-σ bound)")
    p.add_argument("--phase-error", metavar="FILE", default=None,
                   help="projector-gamma table from `fringescope gamma`, subtracted from every "
                        "wrapped phase before unwrapping")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.atomic import atomic_write_bytes
    from app.batch.setjob import (
        ReconOptions,
        check_bracket,
        output_files,
        reconstruct_captures,
        summary_line,
    )
    from app.calib import load_calibration
    from app.capture import read_capture_set
    from app.cli.gamma import read_phase_error

    dirs = [Path(d) for d in args.set_dirs]
    for d in dirs:
        if not d.is_dir():
            raise ValueError(f"{d}: capture-set folder not found")
    lut = read_phase_error(args.phase_error) if args.phase_error else None
    captures = [read_capture_set(d) for d in dirs]
    calibration = load_calibration(args.calibration)
    from app.service.schedules import calibration_for_schedule

    try:  # a set of another schedule with the same finest pattern: the calibration carries over
        calibration = calibration_for_schedule(calibration, captures[0].schedule)
    except ValueError as exc:
        raise ValueError(f"{dirs[0]}: {exc}") from None
    check_bracket(captures, [str(d) for d in dirs])
    options = ReconOptions(max_code=args.max_code, numpy=args.numpy,
                           min_modulation=args.min_modulation, range_mm=args.range,
                           phase_error=lut)
    recon = reconstruct_captures(captures, calibration, options)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    for name, data in output_files(recon, options).items():
        atomic_write_bytes(out / name, data)
    print(f"{dirs[0].name}: {summary_line(recon)} -> {out}")
    return 0
