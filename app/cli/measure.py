"""``fringescope measure SET_DIR -c calibration.json --length u1,v1,u2,v2 | …``: one 3-D
measurement, one JSON line."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

KINDS = {"length": "length", "point_line": "point_to_line", "depth": "depth",
         "profile": "profile", "area": "area"}


def _pixels(text: str) -> list[list[float]]:
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected u1,v1,u2,v2,… pixel coordinates, got {text!r}") from None
    if len(vals) % 2 or not vals:
        raise argparse.ArgumentTypeError(
            f"expected pairs u,v of pixel coordinates, got {len(vals)} numbers")
    return [[vals[i], vals[i + 1]] for i in range(0, len(vals), 2)]


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "measure",
        help="measure in 3-D on one capture set: length, point-to-line, depth, profile or area, "
             "± 1σ",
        description="Reconstruct one capture set and measure between pixels (u = column, v = row). "
                    "Prints one JSON line: value_mm (area: mm²), sigma_mm (1-σ from the per-pixel "
                    "noise), the points used (snapped to the nearest valid pixel within --snap-px "
                    "if a click is invalid).",
    )
    p.add_argument("set_dir", metavar="SET_DIR", help="capture-set folder (capture.json + frames)")
    p.add_argument("-c", "--calibration", required=True, help="calibration.json")
    kind = p.add_mutually_exclusive_group(required=True)
    kind.add_argument("--length", type=_pixels, metavar="U1,V1,U2,V2",
                      help="distance between two points")
    kind.add_argument("--point-line", dest="point_line", type=_pixels, metavar="U,V,U1,V1,U2,V2",
                      help="distance of a point from the line through two others")
    kind.add_argument("--depth", type=_pixels, metavar="U,V,U1,V1,U2,V2,U3,V3",
                      help="signed distance of a point from the plane through three others "
                           "(+ toward the scope)")
    kind.add_argument("--profile", type=_pixels, metavar="U1,V1,U2,V2[,…]",
                      help="heights along a polyline, every pixel, against its chord "
                           "(or --reference)")
    kind.add_argument("--area", type=_pixels, metavar="U1,V1,U2,V2,U3,V3[,…]",
                      help="polygon area on the surface, mm²")
    p.add_argument("--reference", type=_pixels, metavar="U1,V1,U2,V2,U3,V3",
                   help="--profile only: heights against the plane through these three points")
    p.add_argument("--noise-only", action="store_true",
                   help="σ from the pixels' noise alone (default: plus the calibration's "
                        "systematic error)")
    p.add_argument("--snap-px", type=float, default=3.0,
                   help="snap invalid clicks within this radius (default 3)")
    p.add_argument("--max-code", type=int, default=None,
                   help="sensor maximum code, e.g. 4095 for 12-bit data in 16-bit PNGs")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.analysis.measure import measure
    from app.calib import load_calibration
    from app.capture import read_capture_set
    from app.core.schedule import check_pattern
    from app.recon import Reconstructor
    from app.service.measure import calibration_terms

    kind = next(k for k in KINDS if getattr(args, k) is not None)
    if args.reference is not None and kind != "profile":
        raise ValueError("--reference: only with --profile")
    set_dir = Path(args.set_dir)
    if not set_dir.is_dir():
        raise ValueError(f"{set_dir}: capture-set folder not found")
    capture = read_capture_set(set_dir)
    calibration = load_calibration(args.calibration)
    check_pattern(calibration.pattern, capture.schedule, str(set_dir))
    max_code = args.max_code or capture.max_code
    # σ from the camera noise this set shows (N > 3), as `reconstruct` and `validate`
    res = Reconstructor(calibration, max_code=args.max_code).run(capture.frames, max_code=max_code)
    normal, cal_sigma, cal_length = calibration_terms(calibration)
    # the noise part is independent between pixels; the calibration's enters through its covariance
    m = measure(KINDS[kind], res.points, res.valid, res.sigma_noise, getattr(args, kind),
                reference=args.reference, snap_px=args.snap_px, plane_normal=normal,
                reason=res.reason, calibration_sigma_mm=0.0 if args.noise_only else cal_sigma,
                calibration_length_mm=cal_length,
                calibration=None if args.noise_only else calibration)
    out = {"set": set_dir.name, **m.to_dict(), "noise_source": res.noise_source}
    print(json.dumps(out, separators=(",", ":")))
    return 0
