"""The motion test on real still scenes: how much of each it flags, with and without the
light correction (:func:`app.recon.motion.group_light`).

The CFPE captures (``../shared/data/cfpe``, MIT licence; ``FRINGESCOPE_CFPE_DIR`` to move
them) are four still scenes, 12 steps on each of three fringe periods, 640 × 480 8-bit. A
still scene should flag nothing: the test is built so that a still map has any flagged pixel
with probability ≤ 1e-4. Per scene and step count (12, and the 6-, 4- and 3-step subsets,
every 2nd, 3rd and 4th step) it prints each group's light relative to the set's mean, and the
flagged share of the pixels with the light correction and without it (the baseline, the same
frames in the same process), with the set's own fitted noise (N > 3; nominal for N = 3).

``python benchmarks/bench_motion_real.py``
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from app.core.jit import numeric_environment  # noqa: E402

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

from app.core.schedule import PatternSchedule  # noqa: E402
from app.recon.motion import group_light, motion_mask  # noqa: E402
from app.recon.noise import resolve_set_noise  # noqa: E402

CFPE = Path(os.environ.get("FRINGESCOPE_CFPE_DIR", ROOT / ".." / "shared" / "data" / "cfpe"))
PERIODS_PX = (48, 45, 42)  # ascending fringe count; the files' period index is 2, 1, 0
SCENES = (1, 4, 6, 8)


def load(scene: int, steps: int) -> npt.NDArray[np.uint8]:
    """(3·steps, 480, 640) uint8 in capture-set order: every (12 / steps)-th step."""
    import cv2

    out = []
    for period in PERIODS_PX:
        index = {42: 0, 45: 1, 48: 2}[period]
        for s in range(0, 12, 12 // steps):
            img = cv2.imread(str(CFPE / "recordings" / f"{scene:02d}{12 * index + s:02d}.png"),
                             cv2.IMREAD_UNCHANGED)
            if img is None:
                raise SystemExit(f"CFPE frame missing under {CFPE}")
            out.append(img)
    return np.asarray(out, np.uint8)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, nargs="+", default=[12, 6, 4, 3],
                    choices=[12, 6, 4, 3], help="step counts: 12, or every 2nd/3rd/4th step")
    args = ap.parse_args()
    print(f"bench_motion_real: CFPE still scenes from {CFPE}; flagged = share of pixels the "
          "motion test flags (before growth), default settings")
    for steps in args.steps:
        sched = PatternSchedule(frequencies=tuple(1920 / p for p in PERIODS_PX), steps=steps,
                                width=1920, height=1080, unwrap="heterodyne")
        for scene in SCENES:
            frames = load(scene, steps)
            est = resolve_set_noise(frames, sched, 255)
            light = group_light(frames, 3)
            on = float(motion_mask(frames, 3, noise=est.noise).mean())
            off = float(motion_mask(frames, 3, noise=est.noise, light_correction=False).mean())
            print(f"{steps:2d} steps scene {scene}: noise {est.source:7s} light "
                  f"{' '.join(f'{x:.4f}' for x in light)}  flagged {100 * on:6.2f} % "
                  f"(without the light correction {100 * off:6.2f} %)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
