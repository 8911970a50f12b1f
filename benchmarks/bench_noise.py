"""The set's camera-noise fit: its CPU time against the previous fit's and a memory pass, and
its estimate before and after on the same sets, with its standard error.

Timing (in this process, one core: one BLAS thread, as a reprocessing worker runs): on the
1384 × 1032 16-frame set of ``bench_reprocess.py`` and on the twin's 8-bit tissue set, the
median CPU ms of :func:`app.recon.noise.estimate_sensor_noise`, of the previous fit (its
code kept below as :func:`previous_fit`, the baseline), of ``Reconstructor.run`` with the
noise given (the kernel the fit serves) and of one memory pass (``frames.sum(axis=0,
dtype=uint16)``); the ratios of each to the memory pass and the previous / new ratio.

Estimates: the twin's presets (default rig 8-bit, endoscope rig 12-bit; tissue and the DOF
target), each with the projector's gamma 1.0 and 1.5, and the real CFPE captures (N = 12 and
their 4-step subsets) where ``FRINGESCOPE_CFPE_DIR`` (default ``../shared/data/cfpe``) holds
them: gain and read noise before and after, σ_I² at the set's median lit level before and
after, the new fit's standard error there, their difference in those standard errors, and
(twin) the sensor's own σ_I². ``--quick``: the timing and the default rig's sets only.
``python benchmarks/bench_noise.py``.
"""

from __future__ import annotations

import argparse
import math
import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import sys
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from app.core.jit import numeric_environment  # noqa: E402

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

from timing import median_ms  # noqa: E402  (benchmarks/ is the script's folder)

from app.core.schedule import PatternSchedule  # noqa: E402
from app.recon import Reconstructor  # noqa: E402
from app.recon.noise import QUANTISATION_NOISE_DN, fit_sensor_noise  # noqa: E402
from app.recon.phase import check_stack  # noqa: E402
from app.recon.sensor import SensorNoise  # noqa: E402

CFPE = Path(os.environ.get("FRINGESCOPE_CFPE_DIR", ROOT / ".." / "shared" / "data" / "cfpe"))


def previous_fit(frames: Any, schedule: PatternSchedule, max_code: int | None = None
                 ) -> SensorNoise:
    """The fit as it was (the baseline): float64 copy of a 100 000-pixel subsample, the N-step
    projector by tensordot, per-pixel harmonics 2 … H for N ≥ 8, the trimmed line fit with
    ``np.linalg.lstsq``, gain and read noise clipped."""
    from scipy.stats import chi2

    stack = check_stack(frames)
    n = schedule.steps
    top = int(max_code) if max_code is not None else int(np.iinfo(stack.dtype).max)
    h, w = stack.shape[1:]
    step = max(1, math.isqrt(max(1, h * w // 100_000)))
    sub = stack[:, ::step, ::step].astype(np.float64)
    delta = 2.0 * np.pi * np.arange(n) / n
    harmonics = max(1, (n - 4) // 2)
    cos_sin = [f(hh * delta) for hh in range(1, harmonics + 1) for f in (np.cos, np.sin)]
    basis = np.stack([np.ones(n)] + cos_sin, 1)
    residual = np.eye(n) - basis @ np.linalg.pinv(basis)
    dof = n - basis.shape[1]
    var_sum = np.zeros(sub.shape[1:])
    k = len(schedule.frequencies)
    for fi in range(k):
        block = sub[fi * n:(fi + 1) * n]
        var_sum += (np.tensordot(residual, block, axes=1) ** 2).sum(axis=0) / dof
    var = var_sum / k
    intensity = sub.mean(axis=0)
    usable = (sub.max(axis=0) < top) & (sub.min(axis=0) > 0)
    fit = max(1, int(usable.sum()) // 50_000)
    x, y, nu = intensity[usable][::fit], var[usable][::fit], dof * k
    limit = float(chi2.ppf(0.999, nu)) / nu
    design = np.stack([np.ones(x.size), x], axis=1)
    bins = np.array_split(np.argsort(x, kind="stable"), max(2, min(32, x.size // 50)))
    med = np.array([np.median(y[b]) for b in bins]) / (float(chi2.median(nu)) / nu)
    start = np.stack([np.ones(len(bins)), [x[b].mean() for b in bins]], axis=1)
    coef, *_ = np.linalg.lstsq(start, med, rcond=None)
    keep = np.zeros(x.size, bool)
    for _ in range(20):
        new = y <= limit * np.maximum(design @ coef, 1e-3)
        if new.sum() < 100 or np.array_equal(new, keep):
            break
        keep = new
        coef, *_ = np.linalg.lstsq(design[keep], y[keep], rcond=None)
    read_dn = max(math.sqrt(max(float(coef[0]), 0.0)), QUANTISATION_NOISE_DN)
    return SensorNoise(gain_dn_per_e=max(float(coef[1]), 0.0), read_noise_dn=read_dn)


def timing(name: str, frames: npt.NDArray[Any], schedule: PatternSchedule, max_code: int,
           rec: Reconstructor, repeats: int) -> None:
    """Print the CPU ms of the fits, the kernel and a memory pass, and their ratios."""
    _, mem = median_ms(lambda: frames.sum(axis=0, dtype=np.uint16), repeats)
    _, old = median_ms(lambda: previous_fit(frames, schedule, max_code), repeats)
    _, new = median_ms(lambda: fit_sensor_noise(frames, schedule, max_code=max_code), repeats)
    noise = fit_sensor_noise(frames, schedule, max_code=max_code).noise
    _, kernel = median_ms(lambda: rec.run(frames, max_code=max_code, noise=noise), repeats)
    print(f"{name}: CPU ms (median of {repeats}, one core): memory pass {mem:.2f}, previous fit "
          f"{old:.2f} ({old / mem:.1f} x the pass), new fit {new:.2f} ({new / mem:.1f} x), "
          f"kernel with the noise given {kernel:.2f} ({kernel / mem:.1f} x); ratios: previous / "
          f"new {old / new:.2f}, new fit / kernel {new / kernel:.2f} (previous {old / kernel:.2f})")


def compare(name: str, frames: npt.NDArray[Any], schedule: PatternSchedule, max_code: int,
            truth: tuple[float, float] | None = None) -> None:
    """Print the estimates before and after, at the set's median lit level, with the SE."""
    old = previous_fit(frames, schedule, max_code)
    fit = fit_sensor_noise(frames, schedule, max_code=max_code)
    mean = frames.mean(axis=0)
    level = float(np.median(mean[mean > 0.05 * max_code]))
    se = fit.variance_se_dn2(level)
    new_v, old_v = fit.noise.variance_dn2(level), float(old.variance_dn2(level))
    line = (f"{name}: gain {old.gain_dn_per_e:.4f} -> {fit.gain_dn_per_e:.4f} ± {fit.gain_se:.4f}"
            f" DN/e-, read {old.read_noise_dn:.3f} -> {fit.noise.read_noise_dn:.3f} DN; σ_I² at "
            f"{level:.0f} DN {old_v:.3f} -> {new_v:.3f} ± {se:.3f} DN² (SE {100 * se / new_v:.2f} "
            f"%, σ_I {50 * se / new_v:.2f} %; {fit.pixels} px, ν {fit.dof}); after − before "
            f"{(new_v - old_v) / se:+.1f} SE")
    if truth is not None:
        true_v = truth[0] + truth[1] * level
        line += (f"; sensor {true_v:.3f} (gain {truth[1]:.4f}): after − sensor "
                 f"{(new_v - true_v) / se:+.1f} SE ({100 * (new_v / true_v - 1):+.1f} %)")
    print(line)


def twin_sets(quick: bool) -> None:
    from app.devices.sim.offline import render_capture_set
    from app.devices.sim.optics import rig_by_name
    from app.devices.sim.world import SimulatedWorld

    rigs = ("default",) if quick else ("default", "endoscope")
    for rig_name in rigs:
        rig = rig_by_name(rig_name)
        for scene, exposure in (("intestine_flap", 15.0), ("dof_target", 10.0)):
            for gamma in (1.0, 1.5):
                world = SimulatedWorld(scene, seed=2, projector_gamma=gamma, rig=rig)
                cs, _, _ = render_capture_set(scene, exposure_ms=exposure, world=world)
                sensor = world.renderer.sensor
                g = sensor.dn_per_electron(cs.bit_depth, 1.0)
                compare(f"twin {rig_name} {cs.bit_depth}-bit {scene} {exposure:g} ms gamma "
                        f"{gamma:g}", cs.frames, cs.schedule, cs.max_code,
                        ((g * sensor.read_noise_e) ** 2 + 1 / 12, g))


def cfpe_sets() -> None:
    import cv2

    if not (CFPE / "recordings").is_dir():
        print(f"CFPE: not found at {CFPE}")
        return
    periods = (48, 45, 42)
    for scene in (1, 4, 6, 8):
        for steps in (12, 4):
            out = []
            for period in periods:
                index = {42: 0, 45: 1, 48: 2}[period]
                for s in range(0, 12, 12 // steps):
                    path = CFPE / "recordings" / f"{scene:02d}{12 * index + s:02d}.png"
                    out.append(cv2.imread(str(path), cv2.IMREAD_UNCHANGED))
            sched = PatternSchedule(frequencies=tuple(1920 / p for p in periods), steps=steps,
                                    width=1920, height=1080, unwrap="heterodyne")
            compare(f"CFPE scene {scene:02d} N = {steps}", np.stack(out), sched, 255)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="timing and the default rig only")
    parser.add_argument("--repeats", type=int, default=15, help="timed calls per row")
    args = parser.parse_args()
    from app.devices.sim.analytic_rig import Rig, bump_surface
    from app.devices.sim.ideal import ideal_calibration
    from app.devices.sim.offline import render_capture_set
    from app.devices.sim.optics import rig_by_name

    rig = Rig(width=1384, height=1032, focal_px=200.0 * 1384 / 160)
    frames = rig.render(bump_surface(rig), noise=0.8, rng=np.random.default_rng(0))
    timing("bench_reprocess set (analytic rig, 8-bit)", frames, rig.schedule, 255,
           Reconstructor(rig.calibration()), args.repeats)
    cs, _, _ = render_capture_set("intestine_flap", exposure_ms=15.0, seed=2)
    timing("twin default rig intestine_flap 15 ms (8-bit)", cs.frames, cs.schedule, cs.max_code,
           Reconstructor(ideal_calibration(rig_by_name("default"))), args.repeats)
    compare("bench_reprocess set (constant level: the split of read and shot is free)",
            frames, rig.schedule, 255, (0.8**2 + 1 / 12, 0.0))
    twin_sets(args.quick)
    if not args.quick:
        cfpe_sets()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
