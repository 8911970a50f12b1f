"""Reconstruction speed: fused numba kernel vs numpy oracle vs one memory pass.

16 frames of 1384 × 1032 (the Grasshopper3), uint8 and uint16, a synthetic rig with a
closed-form Eq. (5), and the same rig with the geometric depth model (``geometric``
rows). Every run computes σ. Prints the median ms per set of each path and the ratios
fast / memory pass and numpy / fast (with the noise model given, as live), and what
fitting the noise to each set adds (a run without a given noise: Python, REST, CLI). Target: fast (with points and σ) ≤ 5 ms and ≤ 3×
the memory pass (``frames.sum()``).
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from timing import median_ms

from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon import Reconstructor

WIDTH, HEIGHT = 1384, 1032



def main() -> int:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()  # --help; no options
    rig = Rig(width=WIDTH, height=HEIGHT, focal_px=200.0 * WIDTH / 160)
    height_mm = bump_surface(rig)
    print(f"bench_recon: 16 frames {WIDTH}x{HEIGHT}, {os.cpu_count()} CPUs, "
          f"NUMBA_THREADING_LAYER={os.environ.get('NUMBA_THREADING_LAYER')}, "
          f"load average {os.getloadavg()[0]:.1f} (wall times inflate when other work shares the CPUs)")
    geo = rig.geometric_calibration()
    for model, dtype, scale in (("eq5", np.uint8, 1.0), ("eq5", np.uint16, 16.0),
                                ("geometric", np.uint8, 1.0), ("geometric", np.uint16, 16.0)):
        frames = rig.render(height_mm, background=110 * scale, amplitude=90 * scale,
                            noise=1.0 * scale, dtype=dtype, max_code=4095 if dtype == np.uint16 else None)
        cal = rig.calibration() if model == "eq5" else geo
        rec16 = Reconstructor(cal, max_code=4095 if dtype == np.uint16 else None)
        res = rec16.run(frames)  # no noise given: fitted to the set (res.noise_source == "set")
        known = res.noise  # the kernel rows pass it, as the live path passes its measured model
        mem, mem_cpu = median_ms(lambda f=frames: f.sum(), 15)
        fast, fast_cpu = median_ms(lambda r=rec16, f=frames, n=known: r.run(f, noise=n), 30)
        numpy_ms, _ = median_ms(lambda r=rec16, f=frames, n=known: r.run(f, fast=False, noise=n), 3)
        own, own_cpu = median_ms(lambda r=rec16, f=frames: r.run(f), 10)
        name = f"{np.dtype(dtype).name:6s} {model:9s}"
        print(f"{name} fast {fast:7.2f} ms (cpu {fast_cpu:6.1f})  numpy {numpy_ms:7.1f} ms  "
              f"memory pass {mem:6.2f} ms (cpu {mem_cpu:5.1f})  fast/memory {fast / mem:4.2f}  "
              f"numpy/fast {numpy_ms / fast:5.1f}  valid {res.valid.mean():.3f}")
        print(f"{name} noise from the set ({res.noise_source}): fast {own:7.2f} ms (cpu {own_cpu:6.1f}), "
              f"the estimate adds {own - fast:6.2f} ms per run = {own / fast:4.2f} x the kernel "
              f"(Python/REST/CLI without a given noise; the live path passes its measured model)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
