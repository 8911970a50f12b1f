"""Depth when the camera drops frames: maps against the drop-free stream, and gross errors.

The simulator renders every frame of a scene at its own instant (``--exposure-ms`` apart).
One stream keeps every frame, the other loses each with probability ``--drop-rate`` (seeded),
as a starved CPU or a busy USB bus would. Both go through the service's own set grouping
(``SetAssembler`` by frequency group: a dropped frame costs its group, an earlier cycle's copy
stands in; rolling: ``GroupWindow``, each pattern's newest frame, a coarser group's lost one's
previous frame standing in) and reconstruction step (``Reconstruction.process``: the
engine plus the motion test), with the exact (oracle) calibration of the undistorted rig, and
each map is compared with the true surface at the map's instant.

Figures per mode: maps with and without drops, their ratio (target >= 0.7 at 10 % dropped in
both modes), sets patched from an earlier cycle, groups lost (rolling: groups that ended
without a set), and the gross errors (valid pixels more than 0.5 mm off the truth; target 0)
in the dropping stream.

    python benchmarks/bench_drops.py [--scene breathing] [--seconds 20] [--drop-rate 0.1]
                                     [--schedule paper-16] [--modes set,rolling]
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from app.core.jit import numeric_environment

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

import numpy as np

from app.core.schedule import SCHEDULES
from app.devices.base import Frame
from app.devices.sim import SimulatedWorld
from app.devices.sim.ideal import ideal_calibration
from app.devices.sim.optics import rig_by_name
from app.devices.sim.world import READOUT_MS
from app.recon import Reconstructor
from app.recon.motion import MotionTest
from app.recon.unwrap import LIVE_MAX_MOTION_RAD
from app.recon.validity import DEFAULT_GROSS_ERROR_MM
from app.service.framesets import FrameSet, GroupWindow, SetAssembler, depth_group_of
from app.service.reconstruction import Reconstruction
from app.service.store import NewestQueue

GROSS_MM = 0.5


@dataclass
class Stream:
    """One stream's grouping and what came of it."""

    grouping: SetAssembler | GroupWindow
    maps: int = 0
    gross: int = 0
    valid_px: int = 0
    sq_err: float = 0.0

    def feed(self, frame: Frame) -> FrameSet | None:
        return self.grouping.feed(frame, 0.0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="breathing",
                    help="simulator scene (a moving one tests the stand-in groups)")
    ap.add_argument("--seconds", type=float, default=20.0, help="scene time simulated, s")
    ap.add_argument("--exposure-ms", type=float, default=30.0)
    ap.add_argument("--drop-rate", type=float, default=0.10, help="probability each frame is lost")
    ap.add_argument("--schedule", default="paper-16", help=f"one of {', '.join(SCHEDULES)}")
    ap.add_argument("--modes", default="set,rolling", help="comma-separated of set, rolling")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    if args.schedule not in SCHEDULES:
        known = ", ".join(SCHEDULES)
        print(f"bench_drops: unknown schedule {args.schedule!r}; choose from {known}",
              file=sys.stderr)
        return 2
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if not modes or any(m not in ("set", "rolling") for m in modes):
        print(f"bench_drops: --modes: set and/or rolling, got {args.modes!r}", file=sys.stderr)
        return 2
    if not 0.0 <= args.drop_rate < 1.0:
        print(f"bench_drops: --drop-rate: within [0, 1), got {args.drop_rate}", file=sys.stderr)
        return 2

    schedule = SCHEDULES[args.schedule]
    rig = rig_by_name("default", distortion=False)
    world = SimulatedWorld(args.scene, rig=rig, schedule=schedule, seed=args.seed)
    g, n = len(schedule.frequencies), schedule.steps
    engine = Reconstructor(ideal_calibration(rig, schedule), fast=True,
                           gross_error_mm=DEFAULT_GROSS_ERROR_MM,
                           order_max_motion_rad=LIVE_MAX_MOTION_RAD)
    # the live service's motion test (its defaults, the live gross-error bound)
    motion = MotionTest(gross_error_mm=DEFAULT_GROSS_ERROR_MM)
    # the twin's nominal sensor noise (a fit per set can give a zero read noise, refused)
    recon = Reconstruction(NewestQueue(maxsize=1), lambda: engine, bit_depth=8, motion=motion,
                           noise_estimate_interval_s=0.0)

    def grouping(mode: str) -> SetAssembler | GroupWindow:
        if mode == "set":
            return SetAssembler(schedule.n_frames, n)
        return GroupWindow(g, n, depth_group=depth_group_of(schedule.frequencies))

    streams = {(mode, dropping): Stream(grouping(mode))
               for mode in modes for dropping in (False, True)}
    period_s = max(args.exposure_ms, READOUT_MS) / 1000.0
    n_frames = int(round(args.seconds / period_s))
    rng = np.random.default_rng(args.seed)
    dropped = 0
    print(f"bench_drops: scene {args.scene}, {args.schedule}, {args.seconds:g} s at "
          f"{1 / period_s:.1f} camera fps ({n_frames} frames), {args.drop_rate:.0%} of frames "
          f"dropped at random (seed {args.seed})", flush=True)
    for i in range(n_frames):
        t = i * period_s + args.exposure_ms / 2000.0  # mid-exposure, scene time
        p = i % schedule.n_frames
        data = world.render(p, t, exposure_ms=args.exposure_ms, gain=1.0, bits=8)
        frame = Frame(data, index=i, timestamp=t, pattern_index=p, exposure_ms=args.exposure_ms,
                      led="green")
        lost = bool(rng.random() < args.drop_rate)
        dropped += lost
        for (_, dropping), st in streams.items():
            if dropping and lost:
                continue
            fs = st.feed(frame)
            if fs is None:
                continue
            res = recon.process(engine, fs)
            truth = world.truth(res.map_time_s)[0]
            v = res.valid & np.isfinite(truth)
            err = (res.depth - truth)[v]
            st.maps += 1
            st.valid_px += int(err.size)
            st.gross += int(np.count_nonzero(np.abs(err) > GROSS_MM))
            st.sq_err += float(np.sum(err.astype(np.float64) ** 2))

    print(f"{'mode':<8} {'maps':>5} {'maps@drop':>9} {'ratio':>6} {'patched':>7} "
          f"{'lost grp':>8} {'rms mm':>7} {'gross':>5} {'gross@drop':>10}")
    ok = True
    for mode in modes:
        clean, lossy = streams[(mode, False)], streams[(mode, True)]
        ratio = lossy.maps / clean.maps if clean.maps else float("nan")
        asm = lossy.grouping
        patched = asm.patched
        lost = asm.groups_lost if isinstance(asm, SetAssembler) else asm.incomplete
        rms = (lossy.sq_err / lossy.valid_px) ** 0.5 if lossy.valid_px else float("nan")
        ok &= ratio >= 0.7 and lossy.gross == 0 and clean.gross == 0
        print(f"{mode:<8} {clean.maps:>5} {lossy.maps:>9} {ratio:>6.2f} {patched!s:>7} "
              f"{lost!s:>8} {rms:>7.3f} {clean.gross:>5} {lossy.gross:>10}")
    print(f"frames dropped: {dropped} of {n_frames} ({dropped / max(n_frames, 1):.1%}); "
          "ratio = maps with drops / maps without; gross: valid pixels > 0.5 mm off the truth "
          "at the map's instant")
    print(f"targets (ratio >= 0.7 and gross = 0 in every mode): {'ok' if ok else 'MISSED'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
