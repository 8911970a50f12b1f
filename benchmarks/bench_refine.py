"""The joint (corners + phase) refinement on twin rigs, with and without a projector defect.

    python benchmarks/bench_refine.py [--rig default default-projector-defect] [--poses 8]
                                      [--seed 1] [--accuracy]

Per rig: simulate a calibration folder, calibrate it (``app.calib.calibrate_folder``, as
``fringescope calibrate`` does) and print the refinement's verdict (accepted or rejected, with
its reason), the corner reprojection RMS of the camera the calibration keeps, OpenCV's
camera-only RMS on the same corners (``cv2.calibrateCamera`` with the chosen distortion model)
and their ratio against the target (<= 1.1). ``<preset>-projector-defect`` rigs
(app.devices.sim.optics.projector_defect_rig) have a projector the models lack: radial lens
distortion across the fringes and an uncorrected DMD gamma. ``--accuracy`` then runs
benchmarks/bench_accuracy.py's full acceptance (its ``run_rig``) on each rig, which reports
whether the accuracy targets hold or where the supported region is reduced.
Exit code 1 if a ratio exceeds the target.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from app.core.jit import numeric_environment

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

from app.calib import calibrate_folder  # noqa: E402
from app.devices.sim import simulate_calibration_folder  # noqa: E402

TARGET_RATIO = 1.1


def refinement_figures(rig_name: str, poses: int, seed: int, folder: Path) -> bool:
    """Simulate and calibrate ``rig_name``; print the refinement figures; True if within target."""
    t0 = time.perf_counter()
    simulate_calibration_folder(folder, poses=poses, seed=seed, overwrite=True, rig=rig_name)
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    report = calibrate_folder(folder)
    t_cal = time.perf_counter() - t0
    cal, cam, ref = report.calibration, report.camera, report.refinement
    assert cam is not None
    opencv_rms = cam.rms_px
    print(f"\n=== {rig_name} (seed {seed}, {poses} poses; simulated in {t_sim:.0f} s, "
          f"calibrated in {t_cal:.0f} s) ===")
    print(ref.reason if ref is not None else "phase refinement not tried")
    if ref is not None and not ref.accepted and math.isfinite(ref.joint_rms_px):
        print(f"  the rejected joint fit's corner RMS: {ref.joint_rms_px:.4f} px "
              f"= {ref.joint_rms_px / opencv_rms:.2f} x OpenCV's")
    print(f"distortion model: {cam.model}; active depth model: {cal.model.name}; held-out rms mm: "
          + ", ".join(f"{k} {v.get('rms_mm')}" for k, v in report.held_out.items()))
    print(f"corner reprojection of the kept camera: {report.reprojection_px:.4f} px (per corner)")
    print(f"OpenCV camera-only RMS ({cam.model}):    {opencv_rms:.4f} px")
    ratio = report.reprojection_px / opencv_rms
    ok = ratio <= TARGET_RATIO
    print(f"ratio: {ratio:.3f} (target <= {TARGET_RATIO})  {'PASS' if ok else 'MISS'}")
    return ok


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", nargs="+", default=["default", "default-projector-defect"],
                    help="rig presets or their '-projector-defect' variants")
    ap.add_argument("--poses", type=int, default=8)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--accuracy", action="store_true",
                    help="also run bench_accuracy's acceptance on each rig (minutes per rig)")
    args = ap.parse_args(argv)
    ok = True
    with tempfile.TemporaryDirectory(prefix="bench_refine_") as tmp:
        for name in args.rig:
            ok &= refinement_figures(name, args.poses, args.seed, Path(tmp) / f"calib_{name}")
    if args.accuracy:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_accuracy import run_rig

        acc = argparse.Namespace(poses=args.poses, board="checkerboard", partial_boards=None,
                                 corners_only=False, keep=None, strict=False, seed=args.seed,
                                 exposure="auto")
        for name in args.rig:
            run_rig(name, acc)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
