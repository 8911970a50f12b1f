"""``fringescope gamma REF_SET_DIR -o TABLE.json --steps N``: learn the projector-gamma phase error.

A projector's gamma puts harmonics into the fringes; an N-step decoder turns them into a
phase error periodic in the phase (Zhang & Huang 2007, see :mod:`app.recon.gamma`). Capture
one set of any matte scene with many more shifts than the live schedule (e.g. 12 for a
4-step rig, same frequencies); this command learns the N-step error against it and writes a
table that ``fringescope phase --phase-error`` subtracts.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from app.recon.gamma import PhaseErrorLUT


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "gamma",
        help="learn the projector-gamma phase error of an N-step schedule from a many-step capture",
        description="Decode the N-step subset of a many-step capture set and learn its phase error "
                    "against the phase of all steps (a table per frequency, by wrapped phase).",
    )
    p.add_argument("set_dir", metavar="REF_SET_DIR",
                   help="capture set with more shifts than N (a multiple of N)")
    p.add_argument("-o", "--output", required=True, metavar="FILE", help="table to write (JSON)")
    p.add_argument("--steps", type=int, required=True, metavar="N",
                   help="shifts of the schedule to correct")
    p.add_argument("--min-modulation", type=float, default=10.0, metavar="CODES",
                   help="learn only where the reference modulation reaches this (default 10)")
    p.set_defaults(func=run)


def read_phase_error(path: str | Path) -> PhaseErrorLUT:
    """The table at ``path`` (``ValueError`` with one line when missing or malformed)."""
    from app.atomic import read_json

    table: PhaseErrorLUT = read_json(path, "phase-error table", PhaseErrorLUT.from_dict)
    return table


def run(args: argparse.Namespace) -> int:
    from app.atomic import atomic_write_bytes
    from app.capture import read_capture_set

    set_dir = Path(args.set_dir)
    if not set_dir.is_dir():
        raise ValueError(f"{set_dir}: capture-set folder not found")
    capture = read_capture_set(set_dir)
    s = capture.schedule
    lut = PhaseErrorLUT.learn(capture.frames, s.steps, args.steps,
                              frequencies=tuple(float(k) for k in s.frequencies),
                              max_code=capture.max_code, min_modulation=args.min_modulation)
    atomic_write_bytes(Path(args.output), (json.dumps(lut.to_dict()) + "\n").encode("utf-8"))
    amp = ", ".join(f"{a:.4f}" for a in lut.amplitude_rad())
    worst = float(np.abs(lut.error_rad).max())
    print(f"{set_dir.name}: {args.steps}-step phase error learned against {s.steps} steps, "
          f"RMS per frequency {amp} rad, max {worst:.4f} rad -> {args.output}")
    return 0
