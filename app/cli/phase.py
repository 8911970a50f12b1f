"""``fringescope phase SET_DIR -o OUT_DIR``: calibration-free unwrapped phase of any capture set."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "phase",
        help="decode one capture set without a calibration: phase.npy, modulation.npy, "
             "reason.npy, phase.png",
        description="Unwrapped phase of the finest frequency (rad, NaN invalid), its modulation "
                    "(codes) and per-pixel reason codes, honouring the set's bit_depth, channel "
                    "and pattern keys.",
    )
    p.add_argument("set_dir", metavar="SET_DIR", help="capture-set folder (capture.json + frames)")
    p.add_argument("-o", "--output", required=True, metavar="OUT_DIR", help="output folder")
    p.add_argument("--phase-error", metavar="FILE", default=None,
                   help="projector-gamma table from `fringescope gamma`, subtracted before "
                        "unwrapping")
    p.add_argument("--min-modulation", type=float, default=None, metavar="CODES",
                   help="explicit modulation threshold B in sensor codes, replacing the default "
                        "noise-aware rule")
    p.set_defaults(func=run)


def phase_files(res: Any) -> dict[str, bytes]:
    """The output files of ``fringescope phase`` (name → bytes) for a :class:`PhaseResult`."""
    from app.core.encoding import npy_bytes
    from app.recon import render_depth_png

    out: dict[str, bytes] = {}
    for name, arr in (("phase.npy", res.phase.astype(np.float32)),
                      ("modulation.npy", res.modulation),
                      ("reason.npy", res.reason.astype(np.uint8))):
        out[name] = npy_bytes(arr)
    out["phase.png"] = render_depth_png(res.phase, phase_range(res.phase), unit="rad")
    return out


def phase_range(phase: Any) -> tuple[float, float]:
    """Colormap range of a phase map: 0.1 to 99.9 percentile of its finite values (0..2π when
    none)."""
    finite = phase[np.isfinite(phase)]
    if finite.size == 0:
        return 0.0, 2 * math.pi
    lo, hi = (float(q) for q in np.percentile(finite, [0.1, 99.9]))
    return (lo, hi) if hi > lo else (lo, lo + 1.0)


def summary(name: str, capture: Any, res: Any) -> str:
    """One line: size, schedule, bit depth, valid fraction, phase range, recovered pixels."""
    h, w = res.phase.shape
    s = capture.schedule
    valid = float(np.isfinite(res.phase).mean())
    lo, hi = phase_range(res.phase) if valid > 0 else (math.nan, math.nan)
    freqs = ",".join(f"{k:g}" for k in s.frequencies)
    bits = capture.bit_depth or (8 if capture.frames.dtype == np.uint8 else 16)
    return (f"{name}: {w}x{h} px, {s.unwrap} [{freqs}]x{s.steps} {s.orientation}, {bits}-bit, "
            f"valid {100 * valid:.1f}%, phase {lo:.2f}..{hi:.2f} rad, "
            f"{res.recovered} px recovered from clipping")


def run(args: argparse.Namespace) -> int:
    from app.atomic import atomic_write_bytes
    from app.capture import read_capture_set
    from app.cli.gamma import read_phase_error
    from app.service.phase import decode_capture

    set_dir = Path(args.set_dir)
    if not set_dir.is_dir():
        raise ValueError(f"{set_dir}: capture-set folder not found")
    lut = read_phase_error(args.phase_error) if args.phase_error else None
    capture = read_capture_set(set_dir)
    res = decode_capture(capture, lut, min_modulation=args.min_modulation)
    files = phase_files(res)  # everything computed before anything is written
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():
        atomic_write_bytes(out / name, data)
    print(f"{summary(set_dir.name, capture, res)} -> {out}")
    return 0
