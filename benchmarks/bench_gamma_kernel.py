"""What applying a projector-gamma phase-error table costs the fused kernel.

Sets of the twin whose projector has γ 1.5 (the default rig's 8-bit 1384 × 1032, 4 × 4
schedule): tissue (``intestine_flap`` at 15 ms) and the 45° DOF target at 40 ms (its bright
half clips and is refitted), and tissue again with the frequencies combined
(``combine_frequencies``: the kernel's general row-by-row path, which heterodyne schedules
take too; a table of N ≠ 4 has no series in the kernel's form and is looked up). Each set is
reconstructed with the table its own 2nd harmonic gives (:mod:`app.recon.gamma_model`, the
table a run without a learned one applies) passed to the run, three ways, in one process
with the same noise model and called in turn: no table; the table looked up per sample
(``phase_error_series=False``, the path before the series); the table as its Fourier series
(:attr:`PhaseErrorLUT.series`, the default where a table has one). Prints the median CPU ms
per call (all numba threads), the ratios table / no table, series / no table and series /
table; then a run given neither noise nor table (the set's noise, table and series made per
run: Python, REST, CLI) with the look-ups and with the series; and how far the series'
outputs are from the table's (depth, phase, σ, reason codes). The load average is printed
beside the timings: CPU time follows the others' load far less than wall time, but not
wholly.

``python benchmarks/bench_gamma_kernel.py [--repeats N]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.jit import numeric_environment

# before numba is imported: numba runs the kernel as under the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

import numpy as np
import numpy.typing as npt
from timing import median_ms

from app.devices.sim.ideal import ideal_calibration
from app.devices.sim.offline import render_capture_set
from app.devices.sim.optics import rig_by_name
from app.devices.sim.world import SimulatedWorld
from app.recon import Reconstructor, SensorNoise
from app.recon.gamma import PhaseErrorLUT
from app.recon.noise import resolve_set_noise

GAMMA = 1.5  # the twin projector's response exponent
#: (scene, exposure ms, seed, combine frequencies: the kernel's general row-by-row path)
SETS = (("intestine_flap", 15.0, 2, False), ("dof_target", 40.0, 3, False),
        ("intestine_flap", 15.0, 2, True))


def time_paths(frames: npt.NDArray[np.uint8], max_code: int, noise: SensorNoise,
               lut: PhaseErrorLUT, rec: Reconstructor, table_only: Reconstructor,
               repeats: int) -> None:
    """Print the median CPU ms of the three paths, called in turn (no table, table, series)
    ``repeats`` times so that a change of load falls on all three, and the medians of the
    per-turn ratios with their quartiles."""
    paths: dict[str, Callable[[], object]] = {
        "no table": lambda: rec.run(frames, max_code=max_code, noise=noise),
        "table": lambda: table_only.run(frames, max_code=max_code, noise=noise, phase_error=lut),
        "series": lambda: rec.run(frames, max_code=max_code, noise=noise, phase_error=lut),
    }
    cpu_ms: dict[str, list[float]] = {name: [] for name in paths}
    for fn in paths.values():
        fn()  # warm-up
    for _ in range(repeats):
        for name, fn in paths.items():
            c0 = time.process_time()
            fn()
            cpu_ms[name].append((time.process_time() - c0) * 1e3)
    print("  " + "  ".join(f"{name} cpu {statistics.median(v):6.2f} ms"
                           for name, v in cpu_ms.items()) + f"  load {os.getloadavg()[0]:.1f}")
    for num, den in (("table", "no table"), ("series", "no table"), ("series", "table")):
        ratio = np.asarray(cpu_ms[num]) / np.asarray(cpu_ms[den])
        q1, med, q3 = np.percentile(ratio, [25, 50, 75])
        print(f"  {num} / {den}: {med:.2f} (quartiles {q1:.2f}–{q3:.2f}; CPU, per turn)")


def time_own_estimate(frames: npt.NDArray[np.uint8], max_code: int, rec: Reconstructor,
                      table_only: Reconstructor, repeats: int) -> None:
    """Print the CPU ms of a run given neither noise nor table (Python, REST, CLI): the set's
    noise and its table are estimated per run, and the series fitted per run."""
    cpu_ms = {}
    for name, r in (("table", table_only), ("series", rec)):
        wall, cpu = median_ms(lambda r=r: r.run(frames, max_code=max_code), repeats)
        cpu_ms[name] = cpu
        print(f"  own noise and table, {name:6s}: cpu {cpu:6.2f} ms  wall {wall:6.2f} ms  "
              f"load {os.getloadavg()[0]:.1f}")
    print(f"  own noise and table: series / table {cpu_ms['series'] / cpu_ms['table']:.2f} (CPU)")


def compare_outputs(frames: npt.NDArray[np.uint8], max_code: int, noise: SensorNoise,
                    lut: PhaseErrorLUT, rec: Reconstructor, table_only: Reconstructor) -> None:
    """Print how far the series' outputs are from the table's."""
    a = table_only.run(frames, max_code=max_code, noise=noise, phase_error=lut)
    b = rec.run(frames, max_code=max_code, noise=noise, phase_error=lut)
    assert a.phase is not None and b.phase is not None
    ok = a.valid & b.valid
    print(f"  series vs table: reasons differ at {int(np.sum(a.reason != b.reason))} px, "
          f"valid {a.valid.mean():.4f} / {b.valid.mean():.4f}, "
          f"max |Δdepth| {np.abs(a.depth[ok] - b.depth[ok]).max():.2e} mm, "
          f"max |Δphase| {np.abs(a.phase[ok] - b.phase[ok]).max():.2e} rad, "
          f"max |Δσ|/σ {np.abs(a.sigma[ok] / b.sigma[ok] - 1).max():.2e}")


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=31, help="timed calls per path (median)")
    args = ap.parse_args()
    rig = rig_by_name("default", distortion=False)
    cal = ideal_calibration(rig)
    print(f"bench_gamma_kernel: γ {GAMMA} twin, {os.cpu_count()} CPUs, "
          f"NUMBA_THREADING_LAYER={os.environ.get('NUMBA_THREADING_LAYER')}, "
          f"{args.repeats} calls per path")
    for scene, exposure_ms, seed, combine in SETS:
        rec = Reconstructor(cal, with_phase=True, combine_frequencies=combine)
        table_only = Reconstructor(cal, with_phase=True, combine_frequencies=combine,
                                   phase_error_series=False)
        world = SimulatedWorld(scene, seed=seed, projector_gamma=GAMMA, rig=rig)
        cs = render_capture_set(scene, exposure_ms=exposure_ms, world=world)[0]
        est = resolve_set_noise(cs.frames, cal.pattern, cs.max_code)
        lut = est.phase_error
        if lut is None or est.noise is None:
            print(f"{scene}: the set gives no table")
            continue
        series = lut.series
        fit = ("none (table path)" if series is None else
               f"{series.harmonics} harmonics of {series.period}φ, "
               f"max |series − table| {series.max_dev_rad:.1e} rad")
        path = "general path (frequencies combined)" if combine else "4 × 4 path"
        print(f"{scene} {exposure_ms:g} ms, {path}: table RMS {lut.amplitude_rad().max():.4f} rad, "
              f"series: {fit}")
        time_paths(cs.frames, cs.max_code, est.noise, lut, rec, table_only, args.repeats)
        time_own_estimate(cs.frames, cs.max_code, rec, table_only, args.repeats)
        compare_outputs(cs.frames, cs.max_code, est.noise, lut, rec, table_only)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
