"""``fringescope change REF_SET SET -c calibration.json -o OUT_DIR``: how the surface moved.

Both capture sets are reconstructed with the calibration; the second is compared with the first
(:func:`app.analysis.change.compare`: pixel by pixel, or after a rigid registration when the
scope moved). Writes ``delta.npy`` (float32 mm, NaN where not compared), ``sigma.npy`` (σ_Δ),
``significance.npy`` (|Δ| / σ_Δ), ``changed.npy`` (bool) and ``delta.png``, and prints one
summary line.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def _rate(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0 < value < 0.5:
        raise argparse.ArgumentTypeError(f"must be in (0, 0.5), got {text!r}")
    return value


def _half_range(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of mm, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0 mm, got {text!r}")
    return value


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "change",
        help="compare a capture set with a reference set: delta.npy, sigma.npy, "
             "significance.npy, changed.npy and delta.png",
        description="Reconstruct REF_SET and SET with one calibration and map how the surface "
                    "rose or sank, with its significance (registering the clouds first when "
                    "the scope moved).",
    )
    p.add_argument("ref_set", metavar="REF_SET", help="the reference capture-set folder")
    p.add_argument("set_dir", metavar="SET", help="the capture-set folder to compare")
    p.add_argument("-c", "--calibration", required=True, help="calibration.json")
    p.add_argument("-o", "--output", required=True, metavar="OUT_DIR", help="output folder")
    p.add_argument("--false-alarm-rate", type=_rate, default=1e-4, metavar="ALPHA",
                   help="false-alarm rate of the changed mask per map: the probability that "
                   "an unchanged surface shows any changed pixel (default 1e-4)")
    p.add_argument("--register", choices=("auto", "never", "always"), default="auto",
                   help="register the clouds rigidly first: auto (when most of the scene "
                        "changed, default), never (fixed scope) or always")
    p.add_argument("--range", type=_half_range, default=1.0, metavar="MM",
                   help="delta.png colours -MM..+MM (default 1)")
    p.set_defaults(func=run)


def summary_line(result: object, area_mm2: object) -> str:
    """One line: changed area, the largest rise and sink ± σ, the registration."""
    from app.analysis.change import ChangeResult
    from app.recon.change import summarize

    assert isinstance(result, ChangeResult)
    cm = result.cmap
    sm = summarize(cm, area_mm2)  # type: ignore[arg-type]

    def extreme(label: str, value: float | None, sigma: float | None) -> str:
        return (f"max {label} none" if value is None
                else f"max {label} {value:+.3f} ± {sigma:.3f} mm")

    reg = result.registration
    if result.mode == "fixed":
        how = "registration none (fixed scope)"
    else:
        assert reg is not None
        how = (f"registration residual {reg.residual_mm:.3f} mm ({reg.rotation_deg:.2f}°, "
               f"{reg.translation_mm:.3f} mm, {reg.elapsed_ms:.0f} ms)")
    share = 100.0 * cm.changed_share
    return (f"changed {sm.changed_area_mm2:.2f} mm² ({share:.3f}% of {cm.compared} px), "
            f"{extreme('rise', sm.rise_mm, sm.rise_sigma_mm)}, "
            f"{extreme('sink', sm.sink_mm, sm.sink_sigma_mm)}, {how}")


def run(args: argparse.Namespace) -> int:
    from app.analysis.change import compare
    from app.atomic import atomic_write_bytes
    from app.batch.setjob import ReconOptions, reconstruct_captures
    from app.calib import load_calibration
    from app.capture import read_capture_set
    from app.core.encoding import npy_bytes
    from app.outputs.change import delta_png
    from app.recon.change import ChangeTest, pixel_area_mm2
    from app.service.schedules import calibration_for_schedule

    dirs = [Path(args.ref_set), Path(args.set_dir)]
    for d in dirs:
        if not d.is_dir():
            raise ValueError(f"{d}: capture-set folder not found")
    ref_cap, cap = (read_capture_set(d) for d in dirs)
    ref_shape, shape = ref_cap.frames.shape[1:], cap.frames.shape[1:]
    if ref_shape != shape:
        raise ValueError(f"{dirs[1]}: frames are {shape[1]}x{shape[0]} px, the reference's "
                         f"{ref_shape[1]}x{ref_shape[0]} px: not comparable")
    calibration = load_calibration(args.calibration)
    results = []
    for d, c in zip(dirs, (ref_cap, cap), strict=True):
        try:  # a set of another schedule with the same finest pattern: it carries over
            cal = calibration_for_schedule(calibration, c.schedule)
        except ValueError as exc:
            raise ValueError(f"{d}: {exc}") from None
        results.append(reconstruct_captures([c], cal, ReconOptions()).result)
    ref, cur = results
    test = ChangeTest(false_alarm_rate=args.false_alarm_rate)
    # the sensor noise only: one pixel's calibration error is the same in both maps and
    # cancels in their difference
    result = compare(cur.depth, cur.sigma_noise, cur.points, ref.depth, ref.sigma_noise,
                     ref.points, camera_matrix=calibration.camera_matrix,
                     dist_coeffs=calibration.dist_coeffs, test=test, register=args.register,
                     sigma_model=cur.sigma_model, ref_sigma_model=ref.sigma_model)
    if result.mode == "failed":
        raise ValueError(f"{dirs[1]}: the scene moved and {result.notes[0]}: no change shown")
    cm = result.cmap
    if cm.compared == 0:
        raise ValueError(f"{dirs[1]}: no pixel is valid in both maps: nothing to compare")
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "delta.npy": npy_bytes(cm.delta),
        "sigma.npy": npy_bytes(cm.sigma),
        "significance.npy": npy_bytes(cm.significance),
        "changed.npy": npy_bytes(cm.changed),
        "delta.png": delta_png(cm.delta, cm.changed, args.range),
    }
    for name, data in files.items():
        atomic_write_bytes(out / name, data)
    print(f"{dirs[1].name} vs {dirs[0].name}: {summary_line(result, pixel_area_mm2(ref.points))}"
          f" -> {out}")
    return 0
