"""Reconstruction speed: fused numba kernel vs numpy oracle vs one memory pass.

16 frames of 1384 × 1032 (the Grasshopper3), uint8 and uint16, a synthetic rig with a
closed-form Eq. (5), and the same rig with the geometric depth model (``geometric``
rows). Every run computes σ. Prints the median ms per set of each path and the ratios
fast / memory pass and numpy / fast (with the noise model given, as live), and what
fitting the noise to each set adds (a run without a given noise: Python, REST, CLI).
Target: fast (with σ) ≤ 3× the memory pass: ``frames.sum(axis=0,
dtype=np.uint16)``, one read of the frames and one (H, W) write (``frames.sum()``
accumulates in uint64 and is slower than a memory pass, which flattered the ratio).

Then the twin's scenes (the default rig's 8-bit 1384 × 1032): the held-out 45° DOF target
at 40 ms, where its bright half clips and is refitted from the unclipped samples, and
tissue (``intestine_flap``) at 20 ms, reconstructed with ``--calibration FILE`` (a
calibration of the twin, e.g. from ``fringescope calibrate`` on ``fringescope simulate
--calibration``: the geometric model with its σ_model table) or, without it, the twin's
ideal Eq. (5) calibration. σ is the total (noise ⊕ calibration) in every row. These rows
also give the CPU time of one call on one numba thread (as the live service and
reprocess run it) against the memory pass's CPU time: on a shared machine CPU time
follows the others' load much less than wall time. The fast path makes the 3-D points
only when they are read (``ReconResult.points``): the scene rows add what making them once
costs (CPU, one thread). ``--scenes-only`` prints these rows alone.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.jit import WIDE_VECTORS, numeric_environment

# before numba is imported: numba runs the kernel as under the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

import numpy as np
from timing import median_ms

from app.devices.sim.analytic_rig import Rig, bump_surface
from app.recon import Reconstructor

WIDTH, HEIGHT = 1384, 1032



def memory_pass(frames: np.ndarray) -> np.ndarray:
    """One read of the frames and one (H, W) write: the floor any per-pixel kernel pays."""
    return frames.sum(axis=0, dtype=np.uint16)


def vector_width() -> str:
    """Which vectors numba was told to prefer (:mod:`app.core.jit`)."""
    wide = os.environ.get("NUMBA_CPU_FEATURES", "").endswith(WIDE_VECTORS)
    return "512-bit vectors preferred" if wide else "LLVM's default vector width"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calibration", metavar="FILE",
                    help="a calibration of the twin's default rig for the scene rows "
                         "(default: the twin's ideal Eq. (5) calibration)")
    ap.add_argument("--scenes-only", action="store_true", help="only the twin's scene rows")
    args = ap.parse_args()
    if args.scenes_only:
        twin_scenes(args.calibration)
        return 0
    rig = Rig(width=WIDTH, height=HEIGHT, focal_px=200.0 * WIDTH / 160)
    height_mm = bump_surface(rig)
    print(f"bench_recon: 16 frames {WIDTH}x{HEIGHT}, {os.cpu_count()} CPUs, "
          f"NUMBA_THREADING_LAYER={os.environ.get('NUMBA_THREADING_LAYER')}, "
          f"load average {os.getloadavg()[0]:.1f} "
          "(wall times inflate when other work shares the CPUs)")
    geo = rig.geometric_calibration()
    for model, dtype, scale in (("eq5", np.uint8, 1.0), ("eq5", np.uint16, 16.0),
                                ("geometric", np.uint8, 1.0), ("geometric", np.uint16, 16.0)):
        top = 4095 if dtype == np.uint16 else None
        frames = rig.render(height_mm, background=110 * scale, amplitude=90 * scale,
                            noise=1.0 * scale, dtype=dtype, max_code=top)
        cal = rig.calibration() if model == "eq5" else geo
        rec16 = Reconstructor(cal, max_code=top)
        res = rec16.run(frames)  # no noise given: fitted to the set (res.noise_source == "set")
        known = res.noise  # the kernel rows pass it, as the live path passes its measured model
        mem, mem_cpu = median_ms(lambda f=frames: memory_pass(f), 15)
        fast, fast_cpu = median_ms(lambda r=rec16, f=frames, n=known: r.run(f, noise=n), 30)
        numpy_ms, _ = median_ms(lambda r=rec16, f=frames, n=known: r.run(f, fast=False, noise=n), 3)
        own, own_cpu = median_ms(lambda r=rec16, f=frames: r.run(f), 10)
        name = f"{np.dtype(dtype).name:6s} {model:9s}"
        print(f"{name} fast {fast:7.2f} ms (cpu {fast_cpu:6.1f})  numpy {numpy_ms:7.1f} ms  "
              f"memory pass {mem:6.2f} ms (cpu {mem_cpu:5.1f})  fast/memory {fast / mem:4.2f}  "
              f"numpy/fast {numpy_ms / fast:5.1f}  valid {res.valid.mean():.3f}")
        print(f"{name} noise from the set ({res.noise_source}): fast {own:7.2f} ms "
              f"(cpu {own_cpu:6.1f}), "
              f"the estimate adds {own - fast:6.2f} ms per run = {own / fast:4.2f} x the kernel "
              f"(Python/REST/CLI without a given noise; the live path passes its measured model)")
    twin_scenes(args.calibration)
    return 0


def twin_scenes(calibration_file: str | None) -> None:
    """Fast / memory pass on the twin's clipped 45° plate and tissue (module docstring)."""
    import numba

    from app.calib import load_calibration
    from app.devices.sim.ideal import ideal_calibration
    from app.devices.sim.offline import render_capture_set
    from app.devices.sim.optics import rig_by_name

    if calibration_file:
        cal = load_calibration(calibration_file)
    else:
        cal = ideal_calibration(rig_by_name("default"))
    rec = Reconstructor(cal)
    known = ("with its sigma_model table" if rec.model_sigma is not None
             else "sigma_model 0 (no jackknife)")
    print(f"twin scenes, calibration {calibration_file or 'ideal (eq5)'}: model {cal.model.name}, "
          f"{known}; {numba.get_num_threads()} numba threads, then 1; {vector_width()}")
    threads = numba.get_num_threads()
    for label, scene, exposure_ms in (("45 deg plate, bright half clipped", "dof_target", 40.0),
                                      ("tissue (intestine_flap)", "intestine_flap", 20.0)):
        cs, _, _ = render_capture_set(scene, seed=3, exposure_ms=exposure_ms)
        frames = cs.frames
        res = rec.run(frames)
        known_noise = res.noise
        mem, mem_cpu = median_ms(lambda f=frames: memory_pass(f), 15)
        fast, fast_cpu = median_ms(lambda f=frames, n=known_noise: rec.run(f, noise=n), 30)
        numba.set_num_threads(1)
        try:
            _, one_cpu = median_ms(lambda f=frames, n=known_noise: rec.run(f, noise=n), 30)
        finally:
            numba.set_num_threads(threads)
        rays = res.point_rays
        buf = np.empty((*frames.shape[1:], 3), np.float32)
        _, pts_cpu = (median_ms(lambda q=rays, r=res, b=buf: q.points(r.depth, b), 15)
                      if rays is not None else (0.0, float("nan")))
        clipped = float((frames.max(axis=0) >= 255).mean())
        print(f"{label:34s} fast {fast:7.2f} ms (cpu {fast_cpu:5.1f})  memory pass {mem:5.2f} ms "
              f"(cpu {mem_cpu:4.2f})  fast/memory {fast / mem:4.2f}  "
              f"1 thread: cpu {one_cpu:5.2f} ms "
              f"= {one_cpu / mem_cpu:4.2f} x the memory pass's cpu  clipped {clipped:.1%}  "
              f"refitted {res.recovered} px  valid {res.valid.mean():.3f}  "
              f"points when read: cpu {pts_cpu:4.2f} ms  load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    raise SystemExit(main())
