"""What applying a projector-gamma phase-error table costs the fused kernel.

Sets of the twin whose projector has γ 1.5 (the default rig's 8-bit 1384 × 1032, 4 × 4
schedule): tissue (``intestine_flap`` at 15 ms) and the 45° DOF target at 40 ms (its
bright half clips and is refitted). Each set is reconstructed with the table its own 2nd
harmonic gives (:mod:`app.recon.gamma_model`, the table a run without a learned one
applies) passed to the run, three ways, back to back in one process with the same noise
model: no table; the table looked up per sample (``phase_error_series=False``, the path
before the series); the table as its Fourier series (:attr:`PhaseErrorLUT.series`, the
default where a table has one). Prints the median CPU ms per call (all numba threads) and
wall ms, the ratios table / no table and series / no table, series / table, and how far the
series' outputs are from the table's (depth, phase, σ, reason codes). The load average is
printed beside every row: CPU time follows the others' load far less than wall time, but
not wholly.

``python benchmarks/bench_gamma_kernel.py [--repeats N]``
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.jit import numba_environment

# before numba is imported: numba runs the kernel as under the CLI (app/core/jit.py)
os.environ.update(numba_environment(os.environ))

import numpy as np
from timing import median_ms

from app.devices.sim.ideal import ideal_calibration
from app.devices.sim.offline import render_capture_set
from app.devices.sim.optics import rig_by_name
from app.devices.sim.world import SimulatedWorld
from app.recon import Reconstructor
from app.recon.noise import resolve_set_noise

GAMMA = 1.5  # the twin projector's response exponent
#: (scene, exposure ms, seed)
SETS = (("intestine_flap", 15.0, 2), ("dof_target", 40.0, 3))


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=21, help="timed calls per path (median)")
    args = ap.parse_args()
    rig = rig_by_name("default", distortion=False)
    cal = ideal_calibration(rig)
    with_table = Reconstructor(cal, with_phase=True)
    table_only = Reconstructor(cal, with_phase=True, phase_error_series=False)
    print(f"bench_gamma_kernel: γ {GAMMA} twin, {os.cpu_count()} CPUs, "
          f"NUMBA_THREADING_LAYER={os.environ.get('NUMBA_THREADING_LAYER')}, "
          f"{args.repeats} calls per path")
    for scene, exposure_ms, seed in SETS:
        world = SimulatedWorld(scene, seed=seed, projector_gamma=GAMMA, rig=rig)
        cs = render_capture_set(scene, exposure_ms=exposure_ms, world=world)[0]
        est = resolve_set_noise(cs.frames, cal.pattern, cs.max_code)
        lut = est.phase_error
        if lut is None:
            print(f"{scene}: the set gives no table")
            continue
        series = lut.series
        fit = ("none (table path)" if series is None else
               f"{series.harmonics} harmonics of {series.period}φ, "
               f"max |series − table| {series.max_dev_rad:.1e} rad")
        print(f"{scene} {exposure_ms:g} ms: table RMS {lut.amplitude_rad().max():.4f} rad, "
              f"series: {fit}")

        def run(rec: Reconstructor, table: object = lut) -> object:
            return rec.run(cs.frames, max_code=cs.max_code, noise=est.noise,
                           phase_error=table)  # type: ignore[arg-type]

        rows = {}
        # back to back, twice, so that a change of load shows as a change between the rounds
        for rnd in range(2):
            for name, fn in (("no table", lambda: run(with_table, None)),
                             ("table", lambda: run(table_only)),
                             ("series", lambda: run(with_table))):
                wall, cpu = median_ms(fn, args.repeats)
                rows[name] = cpu
                print(f"  round {rnd}: {name:8s} cpu {cpu:6.2f} ms  wall {wall:6.2f} ms  "
                      f"load {os.getloadavg()[0]:.1f}")
            print(f"  round {rnd}: table / no table {rows['table'] / rows['no table']:.2f}  "
                  f"series / no table {rows['series'] / rows['no table']:.2f}  "
                  f"series / table {rows['series'] / rows['table']:.2f} (CPU)")
        a = table_only.run(cs.frames, max_code=cs.max_code, noise=est.noise, phase_error=lut)
        b = with_table.run(cs.frames, max_code=cs.max_code, noise=est.noise, phase_error=lut)
        ok = a.valid & b.valid
        assert a.phase is not None and b.phase is not None
        print(f"  series vs table: reasons differ at {int(np.sum(a.reason != b.reason))} px, "
              f"valid {a.valid.mean():.4f} / {b.valid.mean():.4f}, "
              f"max |Δdepth| {np.abs(a.depth[ok] - b.depth[ok]).max():.2e} mm, "
              f"max |Δphase| {np.abs(a.phase[ok] - b.phase[ok]).max():.2e} rad, "
              f"max |Δσ|/σ {np.abs(a.sigma[ok] / b.sigma[ok] - 1).max():.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
