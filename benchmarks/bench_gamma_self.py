"""The projector gamma the set itself shows, on the real CFPE captures: does it predict the
4-step phase error?

Each CFPE scene has 12 phase steps per fringe period; its 12-step phase is blind to the
harmonics below the 11th and is the reference. Its three 4-step subsets (steps o, o + 3,
o + 6, o + 9 for o = 0, 1, 2) are decoded as a 4-step set would be, and for each scene,
subset and period this prints:

* γ: the power-law exponent the subset's own noise fit reads from its 2nd harmonic
  (:func:`app.recon.noise.resolve_set_noise`, :mod:`app.recon.gamma_model`);
* the 4-step phase error against the 12-step phase (rad RMS over the usable pixels),
  without and with the table made from γ (route a), and its systematic part (the RMS of
  the error's mean in 64 bins of the reference phase: the part a table can remove), and the
  same with the table's Fourier series (:attr:`app.recon.gamma.PhaseErrorLUT.series`, what
  the fused kernel evaluates for a 4 × 4 schedule) in its place;
* the noise fits: gain (DN/e⁻) and read noise (DN) of the subset's own fit and of the
  12-step fit of the same scene, and the ratio of their σ_I at the scene's median usable
  mean intensity (σ_φ ∝ σ_I: the factor by which the subset's σ differs from the 12-step's);
* RMS(error / σ_φ) with σ_φ predicted from the noise as the run would (the subset's own
  noise fit; the 12-step fit's, whose per-pixel harmonics leave the cleaner noise, beside
  it), for the error without a table, with the table, and without a table but σ_φ widened
  in quadrature by the table's RMS (route b). The error against the 12-step phase has
  variance (2/3)·σ_φ² from the noise (the reference shares a third of the subset's
  samples' weight), which the ratio includes.

``python benchmarks/bench_gamma_self.py`` (``FRINGESCOPE_CFPE_DIR`` for the data).
"""

from __future__ import annotations

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
from app.recon.gamma_model import (  # noqa: E402
    gamma_from_measured_second_harmonic,
    second_harmonic_ratios,
)
from app.recon.noise import fit_sensor_noise, resolve_set_noise  # noqa: E402
from app.recon.phase import wrapped_phase  # noqa: E402

CFPE = Path(os.environ.get("FRINGESCOPE_CFPE_DIR", ROOT / ".." / "shared" / "data" / "cfpe"))
PERIODS_PX = (48, 45, 42)
SCENES = (1, 4, 6, 8)
#: bins of the reference phase the systematic error is averaged in
SYSTEMATIC_BINS = 64
F64 = npt.NDArray[np.float64]


def schedule(steps: int) -> PatternSchedule:
    """The CFPE schedule with ``steps`` shifts per period."""
    return PatternSchedule(frequencies=tuple(1920 / p for p in PERIODS_PX), steps=steps,
                           width=1920, height=1080, unwrap="heterodyne")


def load(scene: int) -> npt.NDArray[np.uint8]:
    """(3, 12, 480, 640) uint8: period (ascending fringe count) × step."""
    import cv2

    out = []
    for period in PERIODS_PX:
        index = {42: 0, 45: 1, 48: 2}[period]
        out.append([cv2.imread(str(CFPE / "recordings" / f"{scene:02d}{12 * index + s:02d}.png"),
                               cv2.IMREAD_UNCHANGED) for s in range(12)])
    return np.asarray(out, np.uint8)


def wrap(x: F64) -> F64:
    """Angles to (−π, π], rad."""
    return np.asarray(np.angle(np.exp(1j * x)), np.float64)


def systematic_rms(err: F64, reference: F64) -> float:
    """RMS over the pixels of the error's mean in :data:`SYSTEMATIC_BINS` bins of the
    reference phase, rad."""
    idx = np.floor(np.mod(reference, 2 * np.pi) * (SYSTEMATIC_BINS / (2 * np.pi))).astype(int)
    idx = np.minimum(idx, SYSTEMATIC_BINS - 1)
    mean = np.bincount(idx, err, SYSTEMATIC_BINS) / np.maximum(np.bincount(idx, None,
                                                                           SYSTEMATIC_BINS), 1)
    return float(np.sqrt(np.mean(mean[idx] ** 2)))


def rms(x: F64) -> float:
    return float(np.sqrt(np.mean(x**2)))


def main() -> int:
    import argparse

    argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0]).parse_args()
    if not (CFPE / "recordings").is_dir():
        print(f"CFPE: not found at {CFPE}")
        return 1
    totals: dict[str, list[float]] = {}
    for scene in SCENES:
        per = load(scene)
        full = per.reshape(36, *per.shape[2:])
        ref = wrapped_phase(full, 12, max_code=255)
        usable = (ref.modulation.min(axis=0) >= 10.0) & ~(full >= 255).any(axis=0)
        noise12 = fit_sensor_noise(full, schedule(12), max_code=255).noise
        median_dn = float(np.median(full.mean(axis=0)[usable]))
        print(f"scene {scene:02d} 12-step fit: gain {noise12.gain_dn_per_e:.4f} DN/e-, read "
              f"{noise12.read_noise_dn:.3f} DN; σ_I at the median usable level {median_dn:.0f} DN "
              f"{np.sqrt(noise12.variance_dn2(median_dn)):.3f} DN", flush=True)
        for offset in range(3):
            sub = np.ascontiguousarray(per[:, offset::3].reshape(12, *per.shape[2:]))
            few = wrapped_phase(sub, 4, max_code=255)
            est = resolve_set_noise(sub, schedule(4), 255)
            fit4 = fit_sensor_noise(sub, schedule(4), max_code=255)
            ratios = second_harmonic_ratios(fit4.mean_harmonics, fit4.sources, fit4.steps)
            assert est.phase_error is not None and ratios is not None
            corrected = est.phase_error.apply(few.phase)
            # the same table as the fused kernel's Fourier series (PhaseErrorLUT.series), if any
            series = est.phase_error.series
            by_series = (None if series is None else
                         np.mod(few.phase - series.error_at(few.phase), 2 * np.pi))
            sigma_ratio = float(np.sqrt(fit4.noise.variance_dn2(median_dn)
                                        / noise12.variance_dn2(median_dn)))
            print(f"scene {scene:02d} subset {offset} 4-step fit: gain "
                  f"{fit4.noise.gain_dn_per_e:.4f} DN/e-, read {fit4.noise.read_noise_dn:.3f} DN;"
                  f" σ_I / 12-step σ_I at {median_dn:.0f} DN {sigma_ratio:.3f}", flush=True)
            totals.setdefault(f"{scene:02d} sigma_I_ratio", []).append(sigma_ratio)
            shift = 2 * np.pi * offset / 12  # the subset's first step
            ok = usable & ~few.saturated
            for k in range(3):
                r = ref.phase[k][ok]
                before = wrap(few.phase[k][ok] - r - shift)
                after = wrap(corrected[k][ok] - r - shift)
                sys_rms = float(est.phase_error.amplitude_rad()[k])
                gamma = gamma_from_measured_second_harmonic(float(ratios[k]))
                line = [f"scene {scene:02d} subset {offset} period {PERIODS_PX[k]}: "
                        f"γ {gamma:.3f} table RMS {sys_rms:.4f} | error RMS {rms(before):.4f} → "
                        f"{rms(after):.4f}, systematic {systematic_rms(before, r):.4f} → "
                        f"{systematic_rms(after, r):.4f}"]
                vals = {"error": rms(before), "error_a": rms(after),
                        "sys": systematic_rms(before, r), "sys_a": systematic_rms(after, r)}
                if by_series is None:
                    line.append("  series: none (the table path)")
                else:
                    after_s = wrap(by_series[k][ok] - r - shift)
                    vals |= {"error_s": rms(after_s), "sys_s": systematic_rms(after_s, r)}
                    line.append(f"  series ({series.harmonics} harmonics of "
                                f"{series.period}φ): error RMS {rms(after_s):.4f}, "
                                f"systematic {systematic_rms(after_s, r):.4f}")
                for name, noise in (("set", est.noise), ("12-step", noise12)):
                    var_i = noise.variance_dn2(few.background[ok])
                    sigma = np.sqrt(var_i * 2.0 / (4.0 * few.modulation[k][ok] ** 2) * (2 / 3))
                    z0, za = rms(before / sigma), rms(after / sigma)
                    zb = rms(before / np.hypot(sigma, sys_rms))
                    line.append(f"  RMS(e/σ) {name} noise: none {z0:.3f} (a) {za:.3f} "
                                f"(b) {zb:.3f}")
                    vals |= {f"z_{name}": z0, f"za_{name}": za, f"zb_{name}": zb}
                print("\n".join(line), flush=True)
                for key, v in vals.items():
                    totals.setdefault(f"{scene:02d} {key}", []).append(v)
    print("\nmeans over subsets and periods:")
    for scene in SCENES:
        keys = [k for k in totals if k.startswith(f"{scene:02d} ")]
        print(f"scene {scene:02d}: " + ", ".join(
            f"{k.split(' ', 1)[1]} {np.mean(totals[k]):.4f}" for k in keys))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
