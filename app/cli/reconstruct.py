"""``fringescope reconstruct SET_DIR [SET_DIR ...] -c calibration.json -o OUT_DIR``: capture sets → depth files.

One set gives its depth. Several sets of one scene at different exposures (an exposure
bracket) are fused: each pixel from the set that measures it with the smallest σ
(:mod:`app.recon.fusion`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


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
        help="turn a capture set (or an exposure bracket of sets) into depth.npy, sigma.npy, points.ply, "
             "depth.png and reason.png",
        description="Reconstruct one capture-set folder with a calibration file; several folders of one scene "
                    "at different exposures are fused (each pixel from the set that measures it best).",
    )
    p.add_argument("set_dirs", nargs="+", metavar="SET_DIR",
                   help="capture-set folder (capture.json + frames); more than one: an exposure bracket")
    p.add_argument("-c", "--calibration", required=True, help="calibration.json")
    p.add_argument("-o", "--output", required=True, metavar="OUT_DIR", help="output folder")
    p.add_argument("--range", type=_range, default=(0.0, 35.0), metavar="MIN,MAX",
                   help="depth colormap range in mm (default 0,35)")
    p.add_argument("--max-code", type=int, default=None,
                   help="sensor maximum code, e.g. 4095 for 12-bit data in 16-bit PNGs")
    p.add_argument("--numpy", action="store_true", help="use the numpy reference path instead of numba")
    p.add_argument("--min-modulation", type=float, default=None, metavar="CODES",
                   help="explicit modulation threshold B in sensor codes, replacing the default noise-aware rule (the schedule's order-error bound under the camera noise, and its depth-σ bound)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.atomic import atomic_write_bytes
    from app.calib import load_calibration
    from app.capture import read_capture_set
    from app.capture.ply import write_ply
    from app.core.encoding import npy_bytes
    from app.recon import Reconstructor, reason_png, render_depth_png

    dirs = [Path(d) for d in args.set_dirs]
    for d in dirs:
        if not d.is_dir():
            raise ValueError(f"{d}: capture-set folder not found")
    captures = [read_capture_set(d) for d in dirs]
    calibration = load_calibration(args.calibration)
    from app.service.schedules import calibration_for_schedule

    try:  # a set of another schedule with the same finest pattern: the calibration carries over
        calibration = calibration_for_schedule(calibration, captures[0].schedule)
    except ValueError as exc:
        raise ValueError(f"{dirs[0]}: {exc}") from None
    for d, c in zip(dirs[1:], captures[1:], strict=True):
        if c.schedule != captures[0].schedule:
            raise ValueError(f"{d}: a bracket's sets need one schedule; {dirs[0].name} has another")
        if c.frames.shape != captures[0].frames.shape:
            raise ValueError(f"{d}: frames {c.frames.shape[1:]} differ from {dirs[0].name}'s "
                             f"{captures[0].frames.shape[1:]}")
    from app.recon.noise import estimate_sensor_noise

    # σ from the camera noise the sets show (the N-step residual, N > 3): the first set that has it
    noise = None
    for c in captures:
        try:
            noise = estimate_sensor_noise(c.frames, c.schedule, max_code=args.max_code or c.max_code)
            break
        except ValueError:
            continue  # N = 3 or too few usable pixels; none: the typical sensor
    rec = Reconstructor(calibration, max_code=args.max_code, fast=not args.numpy, noise=noise,
                        min_modulation=args.min_modulation)
    # each set at its own bit_depth unless told
    members = [rec.run(c.frames, max_code=args.max_code or c.max_code) for c in captures]
    if len(members) == 1:
        res, bracket = members[0], ""
    else:
        from app.recon.fusion import fuse_exposures

        fused = fuse_exposures(members, [c.exposure_ms for c in captures])
        res = fused.result
        shares = (f"{c.exposure_ms:g} ms ({100 * fused.valid_from(i) / res.valid.size:.1f}%)"
                  for i, c in enumerate(captures))
        bracket = " fused from " + ", ".join(shares) + ";"
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out / "depth.npy", npy_bytes(res.depth))
    atomic_write_bytes(out / "sigma.npy", npy_bytes(res.sigma))
    write_ply(out / "points.ply", res.points, res.valid, res.texture, res.sigma)
    atomic_write_bytes(out / "depth.png", render_depth_png(res.depth, args.range))
    atomic_write_bytes(out / "reason.png", reason_png(res.reason))
    h, w = res.depth.shape
    frac = float(res.valid.mean())
    if frac > 0:
        span = f"height {np.nanmin(res.depth):.3f}..{np.nanmax(res.depth):.3f} mm"
    else:
        span = "height n/a"
    path = "numpy" if args.numpy or not rec.fast else "fast"
    print(f"{dirs[0].name}: valid {100 * frac:.1f}% of {w}x{h} px,{bracket} {span}, {res.elapsed_ms:.1f} ms ({path}) "
          f"-> {out}")
    return 0
