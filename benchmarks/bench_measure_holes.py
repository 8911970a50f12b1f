"""Live area measurements on a still scene with holes (issue 24 item 2's target).

The live instrument on the simulator (a still tissue scene): a raw set reconstructed
offline with the active calibration (no motion test across sets) gives the squares that
are fully valid; each of ``--squares`` random squares of ``--sizes`` px is then measured
as an area (``POST /api/measure``'s service path) on ``--maps`` successive live depth
maps. Printed per size: the share of (square, map) pairs measured (target >= 0.95 for
100 px), the coverage they had, the live value against the offline one in units of the
live σ (median, 95th percentile), and the MOTION share of the live maps.

    python benchmarks/bench_measure_holes.py [--maps 10] [--squares 100] [--sizes 20,60,100,150]
        [--scene intestine_flap] [--data-dir data]

The first run creates the simulator's calibration in DATA_DIR (a minute or two).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from app.core.jit import numeric_environment

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

import numpy as np

from app.capture.captureset import CaptureSet
from app.config import Settings
from app.core.errors import InvalidRequest
from app.core.reasons import Reason
from app.service.instrument import Instrument
from app.service.measure import calibration_terms, measure_result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--maps", type=int, default=10, help="live depth maps to measure on")
    ap.add_argument("--squares", type=int, default=100, help="random squares per size")
    ap.add_argument("--sizes", default="20,60,100,150", help="square sides, px")
    ap.add_argument("--scene", default="intestine_flap")
    ap.add_argument("--exposure-ms", type=float, default=30.0)
    ap.add_argument("--data-dir", default="data")
    args = ap.parse_args()
    sizes = [int(x) for x in args.sizes.split(",")]

    inst = Instrument(Settings(data_dir=Path(args.data_dir), viewer=False, sim_seed=1,
                               sim_scene=args.scene, exposure_ms=args.exposure_ms))
    inst.start()
    try:
        deadline = time.monotonic() + 900
        while time.monotonic() < deadline:
            if inst.calibration is not None and inst.results.latest()[1] is not None:
                break
            time.sleep(0.5)
        else:
            raise SystemExit(f"no live depth after 900 s: {inst.status().to_dict()['last_error']}")
        acq = inst.acquisition
        assert acq is not None
        _, raw = acq.sets.latest()
        while raw is None:
            time.sleep(0.1)
            _, raw = acq.sets.latest()
        offline = inst.reconstruct_capture(CaptureSet(
            frames=raw.stack(), schedule=inst.schedule, exposure_ms=float(raw.exposure_ms),
            led=raw.led or "green"))
        normal, cal_sigma, cal_length = calibration_terms(inst.calibration)
        rng = np.random.default_rng(0)
        h, w = offline.valid.shape
        squares: dict[int, list[list[list[int]]]] = {}
        ok_int = np.pad(np.cumsum(np.cumsum(offline.valid, 0), 1), ((1, 0), (1, 0)))
        for side in sizes:
            found: list[list[list[int]]] = []
            for _ in range(200 * args.squares):
                if len(found) == args.squares:
                    break
                u, v = int(rng.integers(0, w - side)), int(rng.integers(0, h - side))
                n_ok = (ok_int[v + side, u + side] - ok_int[v, u + side] - ok_int[v + side, u]
                        + ok_int[v, u])
                if n_ok == side * side:  # every pixel of the square valid
                    found.append([[u, v], [u + side - 1, v], [u + side - 1, v + side - 1],
                                  [u, v + side - 1]])
            squares[side] = found
        truth = {side: [measure_result(offline, {"kind": "area", "points": sq}, normal, cal_sigma,
                                       cal_length)["value_mm"] for sq in sqs]
                 for side, sqs in squares.items()}
        n_ok_maps = dict.fromkeys(sizes, 0)
        n_tried = dict.fromkeys(sizes, 0)
        covs: dict[int, list[float]] = {side: [] for side in sizes}
        zs: dict[int, list[float]] = {side: [] for side in sizes}
        motion = []
        seq = -1
        for _ in range(args.maps):
            seq, res = inst.results.wait_newer(seq, 30.0)
            if res is None:
                raise SystemExit("no new live depth map within 30 s")
            motion.append(float((res.reason == int(Reason.MOTION)).mean()))
            for side, sqs in squares.items():
                for sq, ref in zip(sqs, truth[side], strict=True):
                    n_tried[side] += 1
                    try:
                        out = measure_result(res, {"kind": "area", "points": sq}, normal,
                                             cal_sigma, cal_length)
                    except InvalidRequest:
                        continue
                    n_ok_maps[side] += 1
                    covs[side].append(out["coverage"])
                    zs[side].append(abs(out["value_mm"] - ref) / out["sigma_mm"])
    finally:
        inst.close()

    print(f"bench_measure_holes: scene {args.scene}, {args.maps} live maps, MOTION median "
          f"{100 * float(np.median(motion)):.3f} % of pixels (max {100 * max(motion):.3f} %)")
    for side in sizes:
        share = n_ok_maps[side] / n_tried[side] if n_tried[side] else float("nan")
        cov = np.asarray(covs[side]) if covs[side] else np.array([np.nan])
        z = np.asarray(zs[side]) if zs[side] else np.array([np.nan])
        target = f" (target >= 0.95: {'ok' if share >= 0.95 else 'MISSED'})" if side == 100 else ""
        print(f"  {side:4d} px squares ({len(squares[side])} fully valid offline): measured live "
              f"{share:.3f} of {n_tried[side]}{target}; coverage min {cov.min():.3f} median "
              f"{np.median(cov):.3f}; |live - offline| / sigma median {np.median(z):.2f} "
              f"p95 {np.percentile(z, 95):.2f}")
    print(f"  load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
