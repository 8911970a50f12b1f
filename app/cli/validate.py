"""``fringescope validate SET_DIR -c calibration.json (--plane | --feature | --sphere D)``."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "validate",
        help="measure accuracy figures on a capture set of a known target",
        description=(
            "Reconstruct a capture set and report plane accuracy/precision/flatness (--plane), "
            "feature (suture) height (--feature) or VDI/VDE 2634-2 sphere figures (--sphere D)."
        ),
    )
    p.add_argument("set_dir", metavar="SET_DIR", help="capture-set folder")
    p.add_argument("-c", "--calibration", required=True, metavar="FILE", help="calibration JSON")
    mode = p.add_mutually_exclusive_group(required=True)
    mode.add_argument("--plane", action="store_true", help="plane target (e.g. the 45° DOF target)")
    mode.add_argument("--feature", action="store_true", help="raised feature (suture) height")
    mode.add_argument("--sphere", type=float, metavar="DIAMETER_MM",
                      help="sphere of calibrated diameter")
    p.add_argument("--roi", metavar="x0,y0,x1,y1", help="pixel box to analyse (x1, y1 exclusive)")
    p.add_argument("--threshold", type=float, help="feature: intensity threshold (default Otsu)")
    p.add_argument("--polarity", choices=("auto", "bright", "dark"), default="auto",
                   help="feature: brighter or darker than its surroundings (default auto: the "
                        "side that stands up)")
    p.add_argument("--json", metavar="OUT", help="write the figures as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.analysis import feature_height, parse_roi, plane_accuracy, roi_mask, sphere_figures
    from app.analysis.feature import plane_coordinates
    from app.atomic import atomic_write_text
    from app.calib import load_calibration
    from app.capture.captureset import read_capture_set
    from app.core.schedule import check_pattern
    from app.recon import Reconstructor
    from app.recon.exposure import low_signal

    if args.feature and not args.roi:
        raise ValueError("--feature: needs --roi x0,y0,x1,y1 around the feature and its baseline")
    roi = parse_roi(args.roi) if args.roi else None
    capture = read_capture_set(args.set_dir)
    calibration = load_calibration(args.calibration)
    check_pattern(calibration.pattern, capture.schedule, str(args.set_dir))
    # the set's own noise (N > 3), as reconstruct, measure and the service: one validity rule
    result = Reconstructor(calibration).run(capture.frames, max_code=capture.max_code)
    area = roi_mask(result.valid.shape, roi)
    figures: dict[str, Any] = {
        "set": str(args.set_dir),
        "roi": list(roi) if roi else None,
        "valid_fraction": float(result.valid[area].mean()),
        "noise_source": result.noise_source,
    }
    dark = low_signal(result.reason, area, result.texture, result.modulation, capture.exposure_ms,
                      float(capture.max_code))
    if dark is not None:
        figures.update(low_signal_fraction=dark.share,
                       suggested_exposure_ms=dark.suggested_exposure_ms, warning=dark.message())
    if args.plane:
        pa = plane_accuracy(result.points, result.valid, roi=roi)
        figures.update(
            mode="plane", accuracy_mm=pa.accuracy_mm, precision_mm=pa.precision_mm,
            flatness_mm=pa.flatness_mm, mean_distance_mm=pa.mean_distance_mm,
            std_distance_mm=pa.std_distance_mm, n_points=pa.n_points,
            inlier_fraction=pa.inlier_fraction,
            bins=[{"center_mm": b.center_mm, "count": b.count, "accuracy_mm": b.accuracy_mm,
                   "precision_mm": b.precision_mm} for b in pa.bins],
        )
    elif args.feature:
        fh = feature_height(result.depth, result.texture, result.valid, roi=roi,
                            threshold=args.threshold,
                            polarity=None if args.polarity == "auto" else args.polarity,
                            coords_mm=plane_coordinates(result.points, calibration.plane_normal))
        figures.update(mode="feature", height_mm=fh.height_mm, height_se_mm=fh.height_se_mm,
                       polarity=fh.polarity, height_std_mm=fh.height_std_mm,
                       count=fh.count, baseline_rms_mm=fh.baseline_rms_mm,
                       feature_pixels=int(fh.mask.sum()))
    else:
        sf = sphere_figures(result.points, args.sphere, result.valid, roi=roi)
        figures.update(mode="sphere", nominal_diameter_mm=args.sphere, diameter_mm=sf.diameter_mm,
                       pf_mm=sf.pf_mm, ps_mm=sf.ps_mm, rms_mm=sf.rms_mm, n_points=sf.n_points)
    print(format_table(figures))
    if args.json:
        out = atomic_write_text(Path(args.json), json.dumps(_clean(figures), indent=2) + "\n")
        print(f"wrote {out}")
    return 0


def format_table(figures: dict[str, Any]) -> str:
    """Two-column table of the scalar figures (bins summarised by their count)."""
    rows = []
    for key, val in figures.items():
        if key == "bins":
            rows.append(("bins", f"{len(val)} along the incline"))
        elif isinstance(val, float):
            rows.append((key, f"{val:.4f}" if key.endswith("_mm") else f"{val:.4g}"))
        elif val is not None:
            rows.append((key, str(val)))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def _clean(obj: Any) -> Any:
    """JSON-safe: non-finite floats become null."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_clean(v) for v in obj]
    return obj
