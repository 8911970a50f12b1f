"""CPU time of calibrating a twin calibration folder, per stage, against an in-process baseline.

    python benchmarks/bench_calibrate.py [--rig default] [--poses 8] [--seed 1] [--repeats 3]
                                         [--folder DIR] [--save FILE.npz] [--compare FILE.npz]

Simulates one calibration folder (``app.devices.sim.simulate_calibration_folder``; its time is
printed apart, it is not the calibration's) — or uses ``--folder`` as it is — then calibrates it
``--repeats`` times with ``app.calib.calibrate_folder`` (as ``fringescope calibrate`` does) and
prints the median process CPU seconds of each stage and of the whole:

    read        reading the poses' PNG frames (``read_capture_set``)
    observe     phase and board corners of every set (``observe_set``)
    camera      the corner calibration with the lens model's choice (``calibrate_camera``)
    refine      the joint corners + phase refinement (``_refine_with_phase``)
    jackknife   the whole calibration refitted with each pose left out (``_pipeline_jackknife``)
    held_out    the depth models' leave-one-pose-out errors (``_held_out_errors``)
    other       the rest (dense samples, the models' fits, the verified region, ...)

The baseline, run in the same process just before (the project's rule: ratios against a
baseline measured in the same conditions): one pass of ``frames.sum(axis=0, dtype=np.uint16)``
over every set already in memory. Each figure is also printed as a multiple of it.

``--save`` writes the calibration's numbers (camera, distortion, poses' reprojection, reference
plane, the geometric model, the pipeline jackknife's refits, a σ_model table and the held-out
errors) to an ``.npz``; ``--compare`` prints, per number, the largest absolute and relative
difference from such a file: how far a change moved the calibration.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from app.core.jit import numeric_environment

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

import app.calib.fitting as fitting  # noqa: E402
from app.calib import CalibrationReport, calibrate_folder  # noqa: E402
from app.calib.model import undistort_points  # noqa: E402
from app.capture.captureset import read_capture_set  # noqa: E402
from app.core.geometric import GeometricModel  # noqa: E402
from app.devices.sim import simulate_calibration_folder  # noqa: E402

F64 = npt.NDArray[np.float64]
#: the stages timed, in order: (label, name of the function in app.calib.fitting)
STAGES = (("read", "read_capture_set"), ("observe", "observe_set"),
          ("camera", "calibrate_camera"), ("refine", "_refine_with_phase"),
          ("jackknife", "_pipeline_jackknife"), ("held_out", "_held_out_errors"))


def _timed(fn: Callable[..., Any], label: str, cpu_s: dict[str, float]) -> Callable[..., Any]:
    """``fn`` adding its process CPU seconds to ``cpu_s[label]`` on every call."""
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        c0 = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            cpu_s[label] += time.process_time() - c0
    return wrapper


def calibrate_timed(folder: Path) -> tuple[CalibrationReport, dict[str, float]]:
    """Calibrate ``folder`` once; (the report, CPU seconds per stage and ``total``)."""
    cpu_s: dict[str, float] = defaultdict(float)
    saved = {name: getattr(fitting, name) for _, name in STAGES}
    for label, name in STAGES:  # instrumentation only: the same functions are called
        setattr(fitting, name, _timed(saved[name], label, cpu_s))
    try:
        c0 = time.process_time()
        report = calibrate_folder(folder)
        cpu_s["total"] = time.process_time() - c0
    finally:
        for name, fn in saved.items():
            setattr(fitting, name, fn)
    cpu_s["other"] = cpu_s["total"] - sum(cpu_s[label] for label, _ in STAGES)
    return report, dict(cpu_s)


def baseline_cpu_s(folder: Path) -> float:
    """CPU seconds of one ``frames.sum(axis=0, dtype=np.uint16)`` pass over every pose's set
    (the sets read beforehand, not timed): the in-process yardstick."""
    sets = [read_capture_set(p) for p in sorted(folder.glob("pose_*"))]
    c0 = time.process_time()
    for cs in sets:
        cs.frames.sum(axis=0, dtype=np.uint16)
    return time.process_time() - c0


def fingerprint(report: CalibrationReport) -> dict[str, F64]:
    """The calibration's numbers by name, float64 arrays (the rounding of files left out)."""
    cal = report.calibration
    out: dict[str, F64] = {
        "camera_matrix": cal.camera_matrix, "dist_coeffs": cal.dist_coeffs,
        "plane_normal": np.asarray(cal.plane_normal), "plane_offset_mm": np.array([
            cal.plane_offset_mm]),
        "reprojection_px": np.array([report.reprojection_px]),
        "pose_reprojection_px": np.array([p.reprojection_px for p in report.poses]),
        "pose_rms_mm": np.array([p.rms_mm for p in report.poses]),
    }
    if report.refinement is not None:
        r = report.refinement
        out["refinement_chi2_rms"] = np.array([r.chi2, r.joint_rms_px, r.corners_rms_px])
    for model, h in report.held_out.items():
        for key in ("rms_mm", "max_mm", "noise_mm", "systematic_mm", "correlation_mm"):
            val = h.get(key)
            out[f"held_out.{model}.{key}"] = np.array(
                [float(val) if isinstance(val, int | float) else math.nan])
    geo = report.geometric
    if isinstance(geo, GeometricModel):
        out["geometric"] = _projector(geo)
        for i, p in enumerate(geo.pipeline):
            out[f"jackknife[{i}].camera"] = np.concatenate([np.ravel(p.camera_matrix),
                                                            np.ravel(p.dist_coeffs)])
            out[f"jackknife[{i}].plane"] = np.append(np.ravel(p.plane.normal), p.plane.offset_mm)
            out[f"jackknife[{i}].projector"] = _projector(p.projector)
        out["sigma_model_mm"] = sigma_model_table(report)
    return out


def _projector(g: GeometricModel) -> F64:
    return np.concatenate([g.rvec, g.t_mm, [g.focal_px, g.principal_px, g.k1]])


def sigma_model_table(report: CalibrationReport) -> F64:
    """σ_model (mm) of the geometric model on a 9 × 7 pixel grid at 5 heights over the
    calibrated range: (5, 63) float64."""
    cal, geo = report.calibration, report.geometric
    assert geo is not None
    w, h = cal.image_size
    uu, vv = np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 7))
    u, v = uu.ravel(), vv.ravel()
    rays = undistort_points(np.stack([u, v], axis=1), cal.camera_matrix, cal.dist_coeffs)
    lo, hi = cal.height_range_mm
    return np.stack([geo.height_sigma(u, v, rays, np.full(u.size, z), cal.reference_plane)
                     for z in np.linspace(lo, hi, 5)])


def compare(now: dict[str, F64], path: Path) -> None:
    """Print per number the largest |difference| and |difference| / |value| against ``path``."""
    ref = dict(np.load(path))
    print(f"\ndifferences from {path} (largest |after - before|, and relative to |before|):")
    for key in sorted(set(ref) | set(now)):
        if key not in ref or key not in now or ref[key].shape != now[key].shape:
            print(f"  {key:<34} only in one of them or of another shape")
            continue
        a, b = np.asarray(ref[key], np.float64), np.asarray(now[key], np.float64)
        same_nan = np.isnan(a) & np.isnan(b)
        d = np.where(same_nan, 0.0, np.abs(b - a))
        rel = np.where(same_nan, 0.0, d / np.maximum(np.abs(a), 1e-300))
        print(f"  {key:<34} {float(np.max(d)):.3e}  rel {float(np.max(rel)):.3e}"
              + _in_standard_errors(key, d, ref))


def _in_standard_errors(key: str, diff: F64, ref: dict[str, F64]) -> str:
    """For the projector and the camera: the largest difference in units of the parameter's
    jackknife standard error in ``ref`` (√((g − 1)/g Σ (θ_i − θ̄)²) over its g refits): how
    far within the fit's own noise it is; "" for other numbers or without a jackknife."""
    part = {"geometric": "projector", "camera_matrix": "camera", "dist_coeffs": "camera"}.get(key)
    refits = [ref[k] for k in sorted(ref) if k.startswith("jackknife[") and k.endswith(
        f".{part}")]
    if part is None or len(refits) < 3:
        return ""
    stack = np.stack(refits)
    if part == "camera":  # the refits' (camera matrix (9), dist (5)), as the calibration's
        stack = stack[:, :9] if key == "camera_matrix" else stack[:, 9:9 + diff.size]
    g = len(stack)
    se = np.sqrt((g - 1) / g * np.sum((stack - stack.mean(axis=0)) ** 2, axis=0)).ravel()
    ok = se > 0
    if not ok.any():
        return ""
    return f"  = {float(np.max(diff.ravel()[ok] / se[ok])):.1e} jackknife SE"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default="default")
    ap.add_argument("--poses", type=int, default=8)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--folder", type=Path, help="an existing calibration folder (no simulation)")
    ap.add_argument("--save", type=Path, help="write the calibration's numbers to this .npz")
    ap.add_argument("--compare", type=Path, help="compare the calibration with this .npz")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_calibrate_") as tmp:
        folder = args.folder
        if folder is None:
            folder = Path(tmp) / "calib"
            c0, t0 = time.process_time(), time.perf_counter()
            simulate_calibration_folder(folder, poses=args.poses, seed=args.seed, rig=args.rig)
            print(f"simulated {args.rig} rig, {args.poses} poses, seed {args.seed}: "
                  f"{time.process_time() - c0:.1f} s CPU, {time.perf_counter() - t0:.1f} s wall "
                  "(not part of the figures below)")
        base = statistics.median(baseline_cpu_s(folder) for _ in range(5))
        runs, report = [], None
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            report, cpu_s = calibrate_timed(folder)
            cpu_s["wall"] = time.perf_counter() - t0
            runs.append(cpu_s)
        assert report is not None
        print(f"baseline (one uint16 sum over every set's frames): {base * 1e3:.1f} ms CPU")
        print(f"calibrate_folder, median of {args.repeats}:")
        for label in [s for s, _ in STAGES] + ["other", "total", "wall"]:
            med = statistics.median(r[label] for r in runs)
            kind = "s wall" if label == "wall" else "s CPU "
            print(f"  {label:<10} {med:7.2f} {kind} = {med / base:8.1f} x baseline")
        numbers = fingerprint(report)
        if args.save:
            save: Any = np.savez  # its **arrays collide with allow_pickle in numpy's stubs
            save(args.save, **numbers)
            print(f"numbers saved to {args.save}")
        if args.compare:
            compare(numbers, args.compare)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
