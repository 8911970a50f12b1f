"""CPU time of the twin's calibration-folder simulation (what the calibration tests render).

Prints, for ``simulate_calibration_folder(poses=P, seed=1, rig=R)``: the CPU seconds of this
process (numba kernels compiled in a warm-up run first), wall seconds, per pose, the folder's
size, and a baseline measured in the same process: making and PNG-encoding as many numpy noise
frames of the same size and depth, the floor of writing the folder's frames without any
rendering. ``--profile N`` prints the N functions of largest own time.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import tempfile
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

import numpy as np


def folder_bytes(folder: Path) -> int:
    """Total size (bytes) of the files under ``folder``."""
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())


def bench(poses: int, rig: str, profile: int) -> None:
    from app.core.encoding import png_bytes
    from app.devices.sim import rig_by_name, simulate_calibration_folder

    with tempfile.TemporaryDirectory() as tmp:
        simulate_calibration_folder(Path(tmp) / "warm", poses=2, seed=1, rig=rig)  # compile
        prof = cProfile.Profile() if profile else None
        t0, c0 = time.perf_counter(), time.process_time()
        if prof is not None:
            prof.enable()
        folder = simulate_calibration_folder(Path(tmp) / "f", poses=poses, seed=1, rig=rig)
        if prof is not None:
            prof.disable()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        size_mb = folder_bytes(folder) / 1e6
        n_frames = len(list(folder.rglob("frame_*.png")))
    sim_rig = rig_by_name(rig)
    w, h = sim_rig.image_size
    dtype = np.uint8 if sim_rig.bit_depth == 8 else np.uint16
    rng = np.random.default_rng(0)
    b0, bc0 = time.perf_counter(), time.process_time()
    for _ in range(n_frames):
        png_bytes(rng.integers(0, 2**sim_rig.bit_depth, size=(h, w), dtype=dtype))
    bwall, bcpu = time.perf_counter() - b0, time.process_time() - bc0
    print(f"folder {rig} {poses} poses ({n_frames} frames, {size_mb:.1f} MB): "
          f"{cpu:6.2f} CPU-s ({cpu / poses:5.2f}/pose), {wall:6.2f} s wall; "
          f"baseline (numpy noise frames -> PNG) {bcpu:5.2f} CPU-s, {bwall:5.2f} s wall; "
          f"folder/baseline {cpu / bcpu:4.2f} CPU")
    if prof is not None:
        pstats.Stats(prof).sort_stats("tottime").print_stats(profile)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--poses", type=int, default=8)
    ap.add_argument("--rigs", nargs="*", default=["default"],
                    help="simulator rig presets, e.g. default endoscope")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="print the N functions of largest own time")
    args = ap.parse_args()
    for rig in args.rigs:
        bench(args.poses, rig, args.profile)


if __name__ == "__main__":
    main()
