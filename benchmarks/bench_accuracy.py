"""Accuracy on the simulator, beside the paper's figures (Le et al. 2018).

simulate a calibration → calibrate → simulate the 45° DOF target, planes, spheres and a dark
and a bright 0.72 mm suture → reconstruct → validate against the simulator's ground truth.

    python benchmarks/bench_accuracy.py [--rig default endoscope] [--poses 8]
                                        [--board checkerboard]
                                        [--partial-boards | --full-boards] [--keep DIR]
                                        [--strict] [--seed S]
                                        [--exposure auto|MS]
    python benchmarks/bench_accuracy.py --random-rigs N [--seed S] [--lengths 40] [--keep DIR]
                                        [--projector-k1 MAX] [--oracle] [--strict]

Each target scene (DOF target, planes, spheres) is captured at the exposure the instrument's own
auto-exposure picks for it (``--exposure auto``, the default: app.recon.exposure.choose_exposure,
as ``POST /api/exposure/auto`` runs it, each trial a rendered set), or at a fixed exposure
(``--exposure 20``: the twin's default, as runs before the auto-exposure did). The spheres on
their white plate span more light than one exposure holds: with ``auto`` they are also taken as an
exposure bracket (the auto-exposure and two stops more, app.recon.exposure.bracket_exposures) and
fused (app.recon.fusion); the table gives the single set's figures beside the bracket's. The
sutures keep their explicit 30 ms at full LED current, centred on a breathing extremum.

Per rig preset: one table (figure, measured, paper, acceptance target, PASS/MISS), then the
acceptance in every ninth of the image (3 × 3 grid) for the DOF target, the tilted plane and
the far plane: |mean error| against its limit (the issue's: 0.005 mm, or 2 σ_model where the
ninth's RMS σ_model exceeds 2.5 µm; app.analysis.acceptance.bias_limit_mm, as for the random
rigs), RMS, RMS / predicted noise floor, gross errors (> 0.5 mm) on valid pixels, valid
fraction of lit unsaturated pixels; "in" = inside the calibrated volume and
inside the calibration's supported region at the pixel's TRUE height and TRUE phase (the phase
from the twin's projector geometry), reported apart from the pixels outside the volume ("out")
and those in the volume but outside the supported region ("off": valid count, gross count, max
error — no gross error is allowed anywhere). The predicted floor is ``ReconResult.sigma`` when
the reconstruction has it, else the noise-floor prediction of app/analysis/noise.py. Exit code 0
(with ``--strict``: 1 if any acceptance target is missed).

``--random-rigs N``: N rigs drawn by app/devices/sim/random_rig.py from seeds S … S + N − 1
(sensor, focal length, principal point, k1/k2, bit depth 8/10/12, triangulation angle and
baseline, board size and coverage from the central third to the full field, 6–16 poses), each
calibrated by the calibration path (calibrate_folder) from its rendered board poses; the DOF
target and tissue (intestine_flap) rendered with it at the instrument's auto-exposure. Per rig
the issue's targets: valid share of the lit, unsaturated pixels inside the calibrated volume
(DOF black print excluded; and the share refused only as ``outside the calibrated field``),
every ninth's RMS(error/σ) in 0.85–1.15 and |mean error| ≤ 0.005 mm (≤ 2 σ_model where the
result carries a σ_model above 2.5 µm), RMS(error/σ) of random lengths (``--lengths`` per scene)
in 0.8–1.25, zero gross errors (> 0.5 mm) on valid pixels; then the share of rigs meeting
each. ``--projector-k1 MAX`` gives each rig's projector a radial lens distortion drawn in
±MAX (app.devices.sim.random_rig: a defect the depth models lack, as real projection optics
have). ``--oracle`` adds, per scene, the same figures with the
twin's true geometry as the calibration (app.devices.sim.ideal.true_geometric_calibration).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from app.core.jit import numeric_environment

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

from app.analysis import feature_height, sphere_figures  # noqa: E402
from app.analysis.acceptance import (  # noqa: E402
    BIAS_MM,
    background_codes,
    bias_limit_mm,
    ninths_report,
    noise_floor_mm,
    plane_target_report,
    sphere_target_report,
    supported_mask,
    true_phase_rad,
)
from app.analysis.feature import plane_coordinates  # noqa: E402
from app.analysis.measure import measure  # noqa: E402
from app.calib import calibrate_folder  # noqa: E402
from app.core.reasons import Reason  # noqa: E402
from app.devices.sim import (  # noqa: E402
    RIG_NAMES,
    instrument_exposure,
    render_capture_set,
    rig_by_name,
    simulate_calibration_folder,
)
from app.devices.sim.ideal import true_geometric_calibration  # noqa: E402
from app.devices.sim.random_rig import RandomRig, random_rig, simulate_random_calibration  # noqa: E402
from app.devices.sim.scenes import build_scene  # noqa: E402
from app.devices.sim.scenes.base import frame_from_normal  # noqa: E402
from app.devices.sim.scenes.targets import dof_target_field, ruler_printer  # noqa: E402
from app.devices.sim.world import READOUT_MS, SimulatedWorld  # noqa: E402
from app.recon import Reconstructor  # noqa: E402
from app.recon.exposure import bracket_exposures  # noqa: E402
from app.recon.fusion import fuse_exposures  # noqa: E402
from app.service.measure import calibration_terms  # noqa: E402

SUTURE_TRUTH_MM = 0.72
GROSS_MM = 0.5


def _capture(scene, seed, rig, **kw):  # noqa: ANN001, ANN003, ANN202
    world = SimulatedWorld(scene, seed=seed, rig=rig)
    cs, depth, points = render_capture_set(world.scene, seed=seed, world=world, **kw)
    return world, cs, depth, points


def exposure_for(scene, seed, rig_name, exposure):  # noqa: ANN001, ANN201
    """(exposure ms, how it was chosen) for one target scene: the instrument's auto-exposure
    ("auto") or the fixed value given."""
    if exposure != "auto":
        return float(exposure), "fixed"
    ae = instrument_exposure(scene, seed=seed, rig=rig_name)
    return ae.exposure_ms, f"auto-exposure, {ae.saturated_fraction:.2%} saturated"


def _exposure_arg(text: str) -> str:
    if text == "auto":
        return text
    try:
        float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'auto' or milliseconds, got {text!r}") from None
    return text


def predicted_sigma_mm(cal, res, world, bits):  # noqa: ANN001, ANN201
    """Per-pixel predicted 1-σ depth noise, mm: the reconstruction's own ``sigma`` when it has one,
    else |∂z/∂φ|·σ_φ from the intensity noise the simulator's sensor model predicts."""
    sigma = getattr(res, "sigma", None)
    if sigma is not None:
        return np.asarray(sigma, np.float64)
    return noise_floor_mm(cal, res, world.noise_sigma(background_codes(res), bits=bits))


def lit_mask(world, points):  # noqa: ANN001, ANN201
    """Pixels whose true surface point the projector lights (inside its DMD, in front of it)."""
    p = points.astype(np.float64)
    proj = world.rig.projector
    with np.errstate(invalid="ignore", divide="ignore"):
        q = proj.to_projector(p)
        xp, yp = proj.column(p), proj.row(p)
        w, h = proj.size
        return (
            np.isfinite(p).all(-1)
            & (q[..., 2] > 0)
            & (xp >= -0.5)
            & (xp <= w - 0.5)
            & (yp >= -0.5)
            & (yp <= h - 0.5)
        )


def supported(cal, world, truth, points):  # noqa: ANN001, ANN201
    """Pixels whose TRUE (height, phase) lie inside the calibration's supported region; the true
    phase from the twin's projector geometry (its projector coordinate of each true surface
    point)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        xp = world.rig.projector.fringe_coordinate(
            points.astype(np.float64), cal.pattern.orientation
        )
    return supported_mask(cal.model.region, truth, true_phase_rad(xp, cal.pattern))


def print_ninths(title, cells):  # noqa: ANN001, ANN201
    """The per-ninth table; returns how many acceptance checks it missed."""
    print(
        f"\n{title}: every ninth of the image (row, col); lit pixels inside the calibrated "
        "volume and the "
        "supported region (in), outside the volume (out), in the volume but outside the "
        "supported region (off)"
    )
    head = (
        f"{'cell':<6}{'px in':>8}{'valid':>8}{'mean mm':>9}{'limit':>7}{'RMS mm':>8}{'floor':>8}"
        f"{'RMS/fl':>7}{'std/fl':>7}"
        f"{'gross':>6}{'px out':>8}{'valid':>7}{'gross':>6}{'max mm':>8}"
        f"{'px off':>8}{'valid':>7}{'gross':>6}{'max mm':>8}  result"
    )
    print(head)
    print("-" * len(head))
    missed = 0
    for c in cells:
        fails = []
        if c["pixels"] > 0:
            if not abs(c["mean_error_mm"]) <= c["bias_limit_mm"]:
                fails.append("bias")
            if not c["rms_ratio"] <= 1.15:
                fails.append("rms")
            if not c["valid_fraction"] >= 0.99:
                fails.append("valid")
        if c["gross"] or c["outside_gross"] or c["off_region_gross"]:
            fails.append("gross")
        missed += len(fails)
        seen = c["pixels"] or c["outside_pixels"] or c["off_region_pixels"]
        verdict = ("MISS " + ",".join(fails)) if fails else ("PASS" if seen else "")
        omax, fmax = c["outside_max_abs_error_mm"], c["off_region_max_abs_error_mm"]
        print(
            f"({c['row']},{c['col']}) {c['pixels']:>8}{c['valid_fraction']:>8.4f}"
            f"{c['mean_error_mm']:>+9.4f}{c['bias_limit_mm']:>7.4f}"
            f"{c['rms_mm']:>8.4f}{c['floor_mm']:>8.4f}{c['rms_ratio']:>7.2f}"
            f"{c['std_ratio']:>7.2f}{c['gross']:>6}"
            f"{c['outside_pixels']:>8}{c['outside_valid']:>7}{c['outside_gross']:>6}{omax:>8.3f}"
            f"{c['off_region_pixels']:>8}{c['off_region_valid']:>7}{c['off_region_gross']:>6}"
            f"{fmax:>8.3f}  {verdict}"
        )
    return missed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--rig",
        nargs="+",
        choices=RIG_NAMES,
        default=list(RIG_NAMES),
        help="rig presets to run (default: all)",
    )
    ap.add_argument("--poses", type=int, default=8)
    ap.add_argument("--board", choices=("checkerboard", "circles"), default="checkerboard")
    boards = ap.add_mutually_exclusive_group()
    boards.add_argument(
        "--partial-boards",
        dest="partial_boards",
        action="store_true",
        default=None,
        help="boards cover only the central half of the field (the endoscope rig's default)",
    )
    boards.add_argument(
        "--full-boards",
        dest="partial_boards",
        action="store_false",
        help="boards as large as the default rig's (the default rig's default)",
    )
    ap.add_argument(
        "--corners-only", action="store_true", help="fit Eq. (5) on corners only (the paper)"
    )
    ap.add_argument("--keep", metavar="DIR", help="keep the simulated calibration folders here")
    ap.add_argument(
        "--strict", action="store_true", help="exit 1 if an acceptance target is missed"
    )
    ap.add_argument(
        "--seed",
        type=int,
        default=1,
        help="simulator seed of the calibration; the scenes' seeds move with it (default 1)",
    )
    ap.add_argument(
        "--exposure",
        type=_exposure_arg,
        default="auto",
        help="'auto' (the instrument's auto-exposure per target scene, the default) or a fixed "
        "exposure in ms for the target scenes (20: the twin's default)",
    )
    ap.add_argument(
        "--random-rigs",
        type=int,
        default=0,
        metavar="N",
        help="instead of the presets: N random rigs (app/devices/sim/random_rig.py), "
        "rig i drawn from seed S + i; per rig the issue's targets, then the share "
        "of rigs meeting each",
    )
    ap.add_argument(
        "--lengths", type=int, default=40, help="random lengths per scene (--random-rigs)"
    )
    ap.add_argument(
        "--projector-k1",
        type=float,
        default=0.0,
        metavar="MAX",
        help="--random-rigs: each rig's projector lens with a radial distortion k1 drawn in "
        "+-MAX (a defect the depth models lack; every other parameter as without it)",
    )
    ap.add_argument(
        "--oracle",
        action="store_true",
        help="--random-rigs: also reconstruct each scene with the twin's true geometry "
        "as the calibration (what rendering and reconstruction do without a fit)",
    )
    args = ap.parse_args(argv)
    if args.random_rigs:
        if args.random_rigs < 0:
            ap.error(f"--random-rigs: need N >= 1, got {args.random_rigs}")
        return run_random_rigs(args)
    missed = 0
    for rig_name in args.rig:
        missed += run_rig(rig_name, args)
    print(f"\nacceptance targets missed, all rigs: {missed}")
    return 1 if (args.strict and missed) else 0


def run_rig(rig_name: str, args: argparse.Namespace) -> int:
    rig = rig_by_name(rig_name)
    bits = rig.bit_depth
    partial = rig.partial_boards if args.partial_boards is None else args.partial_boards
    print(
        f"\n=== rig {rig_name} (seed {args.seed}): {rig.image_size[0]}x{rig.image_size[1]}, "
        f"f = {rig.K[0, 0]:.0f} px, "
        f"k1 = {rig.dist[0]:+.2f}, {bits}-bit, {'partial' if partial else 'full'} boards ==="
    )
    tmp = tempfile.TemporaryDirectory(prefix="bench_accuracy_")
    base = Path(args.keep) if args.keep else Path(tmp.name)
    t0 = time.perf_counter()
    seed0 = 10 * (
        args.seed - 1
    )  # scene seeds: 3, 4, 9, 5, 7 at --seed 1 (the figures the issue quotes)
    folder = simulate_calibration_folder(
        base / f"calib_{rig_name}",
        board=args.board,
        poses=args.poses,
        seed=args.seed,
        overwrite=True,
        rig=rig_name,
        partial_boards=partial,
    )
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    report = calibrate_folder(folder, dense=not args.corners_only)
    t_cal = time.perf_counter() - t0
    cal = report.calibration
    print(report.table())
    print(f"simulated {args.poses} poses in {t_sim:.0f} s, calibrated in {t_cal:.0f} s\n")
    rec = Reconstructor(cal, with_phase=True, max_code=2**bits - 1)
    ninths = []
    exposures = {}

    def capture(scene, seed):  # noqa: ANN001, ANN202
        exposures[scene] = exposure_for(scene, seed, rig_name, args.exposure)
        return _capture(scene, seed, rig_name, exposure_ms=exposures[scene][0])

    world, cs, truth, points = capture("dof_target", seed0 + 3)
    res = rec.run(cs.frames)
    origin, axes = dof_target_field(world.rig)
    st = (points.astype(np.float64) - origin) @ axes
    black = ruler_printer()(st[..., 0], st[..., 1]) < 0.5
    sup = supported(cal, world, truth, points)
    dof = _plane_report(
        cal,
        res,
        truth,
        world.noise_sigma(background_codes(res), bits=bits),
        "DOF target",
        exclude=black,
        supported=sup,
    )
    ninths.append(
        (
            "DOF target, black print excluded",
            ninths_report(
                res,
                truth,
                cal.height_range_mm,
                predicted_sigma_mm(cal, res, world, bits),
                lit=lit_mask(world, points) & ~black,
                gross_mm=GROSS_MM,
                supported=sup,
                sigma_model_mm=res.sigma_model,
            ),
        )
    )

    world, cs, truth, points = capture("plane", seed0 + 4)  # fills the field, inside the volume
    res = rec.run(cs.frames)
    ninths.append(
        (
            "tilted plane (10 mm, 15 deg)",
            ninths_report(
                res,
                truth,
                cal.height_range_mm,
                predicted_sigma_mm(cal, res, world, bits),
                lit=lit_mask(world, points),
                gross_mm=GROSS_MM,
                supported=supported(cal, world, truth, points),
                sigma_model_mm=res.sigma_model,
            ),
        )
    )

    world, cs, truth, points = capture(
        "far_plane", seed0 + 9
    )  # crosses the calibrated volume's far end
    res = rec.run(cs.frames)
    far = _plane_report(
        cal,
        res,
        truth,
        world.noise_sigma(background_codes(res), bits=bits),
        "far plane",
        supported=supported(cal, world, truth, points),
    )
    ninths.append(
        (
            "far plane (-6 mm, 30 deg)",
            ninths_report(
                res,
                truth,
                cal.height_range_mm,
                predicted_sigma_mm(cal, res, world, bits),
                lit=lit_mask(world, points),
                gross_mm=GROSS_MM,
                supported=supported(cal, world, truth, points),
                sigma_model_mm=res.sigma_model,
            ),
        )
    )

    world, cs, truth, points = capture("sphere", seed0 + 5)
    res_one = rec.run(cs.frames)
    spheres = world.scene.spheres
    sphere_sup = supported(cal, world, truth, points)

    def sphere_report(result):  # noqa: ANN001, ANN202
        return sphere_target_report(
            cal,
            result,
            truth,
            points,
            [s.centre for s in spheres],
            spheres[0].radius_mm,
            projector_centre_mm=world.rig.projector.centre,
            incidence_limits_deg=(80.0, 87.0, 90.0),
            supported=sphere_sup,
        )

    sph_one = sphere_report(res_one)
    bracket = (
        bracket_exposures(exposures["sphere"][0])
        if args.exposure == "auto"
        else (exposures["sphere"][0],)
    )
    members = [res_one]
    for i, e in enumerate(bracket[1:], start=1):  # a later set: noise of its own
        members.append(
            rec.run(_capture("sphere", seed0 + 5 + 1000 * i, rig_name, exposure_ms=e)[1].frames)
        )
    fused = fuse_exposures(members, bracket)
    res = fused.result
    sph = sphere_report(res)
    seg = sphere_figures(res.points, 2 * spheres[0].radius_mm, res.valid)
    bracket_text = " + ".join(f"{e:g}" for e in bracket) + " ms"

    sutures = {}
    for scene_name, current in (("anastomosis", 1.0), ("anastomosis_bright", 0.5)):
        scene = build_scene(scene_name, rig)
        # The dark suture needs more light than the default (30 ms, full LED current); the set is
        # centred on a breathing extremum so the tissue is nearly still.
        t_start = 1.0 - 7.5 * max(30.0, READOUT_MS) / 1000.0 - 0.015
        world, cs, truth, points = _capture(
            scene, seed0 + 7, rig, t0_s=t_start, exposure_ms=30.0, current=current
        )
        res = rec.run(cs.frames)
        origin, axes = frame_from_normal(rig.reference_point_mm, rig.reference.normal)
        st = (points.astype(np.float64) - origin) @ axes
        ys, xs = np.nonzero((st[..., 0] > -15.0) & (st[..., 0] < -9.0) & (np.abs(st[..., 1]) < 1.5))
        roi = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)
        box = (slice(roi[1], roi[3]), slice(roi[0], roi[2]))
        saturated = float((res.reason[box] == Reason.SATURATED).mean())
        # cross-sections in the surface's own (reference-plane) coordinates; the same estimator on
        # the TRUE depth map shows what the scene itself (the tissue under the thread) gives
        try:
            measured = feature_height(
                res.depth,
                res.texture,
                res.valid,
                roi=roi,
                coords_mm=plane_coordinates(res.points, cal.plane_normal),
            )
        except ValueError as exc:  # e.g. no valid depth in the ROI (outside the supported region)
            measured = None
            print(
                f"suture height, {scene_name}: not measured ({exc}); "
                "ROI pixels outside the supported region: "
                f"{float((res.reason[box] == Reason.OUTSIDE_FIELD).mean()):.2f}"
            )
        on_truth = feature_height(
            truth,
            res.texture,
            np.isfinite(truth),
            roi=roi,
            coords_mm=plane_coordinates(points, cal.plane_normal),
        )
        sutures[scene_name] = (measured, saturated, on_truth)

    ps_worst = max(abs(s["ps_mm"]) for s in sph["spheres"])
    rows = _plane_rows(dof, far) + _sphere_rows(
        sph, sph_one, seg, bracket_text, exposures["sphere"][0], ps_worst
    )
    for scene_name, (fh, saturated, ft) in sutures.items():
        if fh is None:
            rows.append(
                (
                    f"suture height, {scene_name} (mm)",
                    "no depth",
                    "0.726 ± 0.0075",
                    f"{SUTURE_TRUTH_MM} ± 0.01",
                    False,
                )
            )
            continue
        rows += [
            (
                f"suture height, {scene_name} (mm)",
                f"{fh.height_mm:.4f} ± {fh.height_se_mm:.4f}",
                "0.726 ± 0.0075",
                f"{SUTURE_TRUTH_MM} ± 0.01",
                abs(fh.height_mm - SUTURE_TRUTH_MM) <= 0.01,
            ),
            (
                "  polarity found / spread along (mm)",
                f"{fh.polarity} / {fh.height_std_mm:.4f}",
                "",
                "",
                None,
            ),
            ("  cross-sections / ROI saturated", f"{fh.count} / {saturated:.4f}", "", "", None),
            (
                "  same estimator on the true depth map (mm)",
                f"{ft.height_mm:.4f} ± {ft.height_se_mm:.4f}",
                "",
                "",
                None,
            ),
        ]
    print(
        "exposures: "
        + "; ".join(f"{name} {ms:g} ms ({how})" for name, (ms, how) in exposures.items())
    )
    w = max(len(r[0]) for r in rows)
    print(f"{'figure':<{w}}  {'measured':>18}  {'paper':>14}  {'target':>13}  result")
    missed = 0
    for name, val, paper, target, ok in rows:
        verdict = "" if ok is None else ("PASS" if ok else "MISS")
        missed += ok is False
        print(f"{name:<{w}}  {val:>18}  {paper:>14}  {target:>13}  {verdict}")
    for title, cells in ninths:
        missed += print_ninths(f"{rig_name}: {title}", cells)
    print(f"\nacceptance targets missed, rig {rig_name}: {missed}")
    tmp.cleanup()
    return missed


def _plane_report(cal, res, truth, noise, what, **kw):  # noqa: ANN001, ANN003, ANN202
    """:func:`plane_target_report`, or None (printed) when the plane has too few valid pixels to
    fit: the miss is reported, the run goes on."""
    try:
        return plane_target_report(cal, res, truth, noise, **kw)
    except ValueError as exc:
        print(
            f"{what}: no plane fit ({exc}); valid pixels {int(np.count_nonzero(res.valid))}",
            flush=True,
        )
        return None


def _plane_rows(dof, far):  # noqa: ANN001, ANN202
    """The DOF target's and far plane's rows (a plane without a fit: 'no depth', a miss)."""
    if dof is None:
        rows = [("DOF target (plane fit)", "no depth", "", "valid px", False)]
    else:
        rows = [
            # figure, measured, paper, target text, pass
            ("DOF plane accuracy (mm)", f"{dof['accuracy_mm']:.4f}", "0.008", "", None),
            ("DOF plane precision (mm)", f"{dof['precision_mm']:.4f}", "0.25", "", None),
            ("  noise floor predicted (mm)", f"{dof['noise_floor_mm']:.4f}", "", "", None),
            (
                "  precision / noise floor",
                f"{dof['precision_ratio']:.3f}",
                "",
                "<= 1.15",
                dof["precision_ratio"] <= 1.15,
            ),
            ("DOF flatness F (mm)", f"{dof['flatness_mm']:.4f}", "", "", None),
            (
                "DOF valid, in volume and region, excl. black print",
                f"{dof['valid_fraction']:.4f}",
                "",
                ">= 0.99",
                dof["valid_fraction"] >= 0.99,
            ),
            ("DOF valid, in volume, all pixels", f"{dof['valid_fraction_all']:.4f}", "", "", None),
            (
                "DOF mean error vs truth (mm)",
                f"{dof['mean_error_mm']:+.4f}",
                "",
                "|.| <= 0.005",
                abs(dof["mean_error_mm"]) <= 0.005,
            ),
            (
                "DOF max |error| (mm)",
                f"{dof['max_abs_error_mm']:.4f}",
                "",
                "<= 0.5",
                dof["max_abs_error_mm"] <= 0.5,
            ),
            ("DOF depth precision / floor", f"{dof['depth_precision_ratio']:.3f}", "", "", None),
        ]
    if far is None:
        return [*rows, ("outside volume (far plane)", "no depth", "", "valid px", False)]
    return [
        *rows,
        (
            "outside volume (far plane): valid px / max |error| (mm)",
            f"{far['outside_valid']} / {far['outside_max_abs_error_mm']:.4f}",
            "",
            "<= 0.5",
            far["outside_pixels"] > 0
            and (far["outside_valid"] == 0 or far["outside_max_abs_error_mm"] <= 0.5),
        ),
    ]


def _sphere_rows(sph, sph_one, seg, bracket_text, exposure_ms, ps_worst):  # noqa: ANN001, ANN202
    """The sphere target's rows."""
    return [
        (
            f"sphere valid, lit and unsaturated (in volume and region), {bracket_text}",
            f"{sph['lit_valid_fraction']:.4f}",
            "",
            ">= 0.99",
            sph["lit_valid_fraction"] >= 0.99,
        ),
        (
            f"  the same, one set at {exposure_ms:g} ms",
            f"{sph_one['lit_valid_fraction']:.4f}",
            "",
            "",
            None,
        ),
        (
            "  sphere valid, all pixels in volume and region (its shadow too)",
            f"{sph['valid_fraction']:.4f}",
            "",
            "",
            None,
        ),
        (
            "  sphere px off the supported region: count / valid",
            f"{sph['off_region_pixels']} / {sph['off_region_valid']}",
            "",
            "",
            None,
        ),
        (
            "  sphere px unlit / lit beyond 87 deg (projector)",
            f"{sph['unlit_fraction']:.4f} / {1 - sph['incidence'][87.0]['pixels_fraction']:.4f}",
            "",
            "",
            None,
        ),
        (
            "  sphere valid where lit at <= 80 deg",
            f"{sph['incidence'][80.0]['valid_fraction']:.4f}",
            "",
            "",
            None,
        ),
        (
            "sphere mean error (mm)",
            f"{sph['mean_error_mm']:+.4f}",
            "",
            "|.| <= 0.005",
            abs(sph["mean_error_mm"]) <= 0.005,
        ),
        (
            "sphere max |error| (mm)",
            f"{sph['max_abs_error_mm']:.4f}",
            "",
            "<= 0.5",
            sph["max_abs_error_mm"] <= 0.5,
        ),
        (
            f"  the same, one set at {exposure_ms:g} ms",
            f"{sph_one['max_abs_error_mm']:.4f}",
            "",
            "<= 0.5",
            sph_one["max_abs_error_mm"] <= 0.5,
        ),
        ("sphere PS worst (mm)", f"{ps_worst:.4f}", "", "<= 0.02", ps_worst <= 0.02),
        ("sphere PF (mm)", " / ".join(f"{s['pf_mm']:.3f}" for s in sph["spheres"]), "", "", None),
        ("sphere PS, RANSAC-segmented (mm)", f"{seg.ps_mm:+.4f}", "", "", None),
    ]


NINTH_RMS_Z = (0.85, 1.15)
LENGTH_RMS_Z = (0.8, 1.25)
COVERAGE_TARGET = 0.97
#: the coverage target's condition: boards reaching at least half the field from its centre (the
#: generator also draws smaller boards, down to the central third)
CONDITION_REACH = 0.5


def ninth_z_figures(res, truth, sigma, mask, sigma_model=None):  # noqa: ANN001, ANN201
    """Per ninth (row-major) over ``mask & valid``: (pixels, RMS(error/σ), mean error mm, bias
    limit mm, model share): the limit is :func:`bias_limit_mm` of the ninth's RMS(σ_model);
    the model share is the mean of σ_model²/σ² (0 without σ_model)."""
    err = np.asarray(res.depth, np.float64) - truth
    ok = mask & res.valid & np.isfinite(err) & np.isfinite(sigma) & (sigma > 0)
    h, w = err.shape
    ys, xs = np.linspace(0, h, 4).round().astype(int), np.linspace(0, w, 4).round().astype(int)
    out = []
    for r in range(3):
        for c in range(3):
            win = (slice(ys[r], ys[r + 1]), slice(xs[c], xs[c + 1]))
            sel = ok[win]
            e, s = err[win][sel], sigma[win][sel]
            if e.size < 50:
                out.append((int(e.size), float("nan"), float("nan"), BIAS_MM, 0.0))
                continue
            limit, share = BIAS_MM, 0.0
            if sigma_model is not None:
                sm_px = np.asarray(sigma_model, np.float64)[win][sel]
                limit = bias_limit_mm(float(np.sqrt(np.mean(np.square(sm_px)))))
                share = float(np.mean(np.square(sm_px / s)))
            out.append(
                (int(e.size), float(np.sqrt(np.mean((e / s) ** 2))), float(e.mean()), limit, share)
            )
    return out


def model_dominated_summary(rows: list[dict]) -> str:
    """The ninths whose σ is mostly the calibration's own (σ_model² > σ_noise²), pooled over the
    rigs: their model error is one draw per ninth (spatially coherent, shared by its pixels), so
    even an honest σ_model gives a ninth RMS(error/σ) like √(f·ζ² + 1 − f), ζ ~ N(0, 1), f the
    model share — inside 0.85–1.15 for only a minority of such ninths. The pooled RMS over many
    rigs is what can say whether σ_model is honest: ~1 honest, < 1 too large, > 1 too small."""
    cells = [
        c
        for r in rows
        if "error" not in r
        for sc in r["scenes"].values()
        for c in sc["cells"]
        if c[0] >= 50 and c[4] > 0.5
    ]
    if not cells:
        return "ninths where sigma_model dominates sigma: none"
    z = np.array([c[1] for c in cells])
    f = np.array([c[4] for c in cells])
    # the share an honest sigma_model would put in the band, by Monte Carlo over ζ at each f
    zeta = np.random.default_rng(0).standard_normal(20000)
    honest = np.mean([
        np.mean(np.abs(np.sqrt(fk * zeta**2 + 1 - fk) - 1.0) <= 0.15) for fk in f
    ])
    pooled = float(np.sqrt(np.mean(z**2)))
    return (
        f"ninths where sigma_model dominates sigma (sigma_model^2 > sigma_noise^2): {len(cells)} "
        f"(model share {f.min():.2f}-{f.max():.2f}); pooled RMS(error/sigma) {pooled:.2f}"
        f" (1 = honest), each {z.min():.2f}-{z.max():.2f}; in {NINTH_RMS_Z[0]}-{NINTH_RMS_Z[1]}: "
        f"{np.mean((z >= NINTH_RMS_Z[0]) & (z <= NINTH_RMS_Z[1])):.0%} (an honest sigma_model: "
        f"~{honest:.0%}); too small (> {NINTH_RMS_Z[1]}): {int(np.sum(z > NINTH_RMS_Z[1]))}"
    )


def calibration_vs_truth(cal, rr: RandomRig) -> str:  # noqa: ANN001
    """One line: the calibrated camera and reference plane against the twin's: principal point
    error (px), the plane's tilt error (deg) and its height error at the reference point and over
    the image corners (mm, the calibrated plane's height of true reference-plane points)."""
    rig = rr.rig
    k = np.asarray(cal.camera_matrix, np.float64)
    dpp = k[:2, 2] - rig.K[:2, 2]
    n_t, n_c = rig.reference.normal, np.asarray(cal.plane_normal, np.float64)
    tilt = np.degrees(np.arccos(min(1.0, float(n_t @ n_c))))
    w, h = rig.image_size
    u, v = (
        np.array([(w - 1) / 2, 0.0, w - 1.0, 0.0, w - 1.0]),
        np.array([(h - 1) / 2, 0.0, 0.0, h - 1.0, h - 1.0]),
    )
    rays = rig.camera.rays(u, v)
    pts = ((0.0 - rig.reference.offset_mm) / (rays @ n_t))[:, None] * rays
    dh = pts @ n_c + cal.plane_offset_mm
    return (
        f"calibration vs truth: principal point {dpp[0]:+.2f}, {dpp[1]:+.2f} px; reference plane "
        f"tilt {tilt:.3f} deg, height of the true plane at the centre {dh[0]:+.4f} mm, at the "
        "image corners "
        + ", ".join(f"{x:+.4f}" for x in dh[1:])
        + " mm"
    )


def lens_field_mask(cal):  # noqa: ANN001, ANN201
    """(H, W) True inside the camera lens model's supported field ellipse (the whole image when the
    calibration records none): outside it the calibration refuses depth whatever the depth model."""
    w, h = cal.image_size
    radius = (cal.extra.get("camera_model") or {}).get("field_radius")
    if radius is None:
        return np.ones((h, w), bool)
    k = np.asarray(cal.camera_matrix, np.float64)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return ((u - k[0, 2]) / (radius * k[0, 0])) ** 2 + (
        (v - k[1, 2]) / (radius * k[1, 1])
    ) ** 2 <= 1.0


def random_lengths(res, truth_pts, cal, n, rng):  # noqa: ANN001, ANN201
    """(error mm, σ mm) of ``n`` random lengths between two valid pixels (σ as ``POST
    /api/measure`` reports it, app.service.measure.measure_result: the pixels' noise part and the
    calibration's own 3-D covariance, shared between the two points), each against the same
    length on the true points."""
    normal, cal_sigma, cal_length = calibration_terms(cal)
    noise_sigma = res.sigma_noise  # the calibration part enters through its own covariance
    ok = res.valid & np.all(np.isfinite(truth_pts), -1)
    vv, uu = np.nonzero(ok)
    errs, sigmas = [], []
    for _ in range(20 * n):
        if len(errs) >= n or len(uu) < 2:
            break
        i, j = rng.choice(len(uu), 2, replace=False)
        pix = [[int(uu[i]), int(vv[i])], [int(uu[j]), int(vv[j])]]
        try:
            m = measure(
                "length",
                res.points,
                res.valid,
                noise_sigma,
                pix,
                snap_px=0.0,
                plane_normal=normal,
                reason=res.reason,
                calibration_sigma_mm=cal_sigma,
                calibration_length_mm=cal_length,
                calibration=cal,
            )
            t = measure("length", truth_pts, ok, None, pix, snap_px=0.0, plane_normal=normal)
        except ValueError:
            continue
        if m.sigma_mm > 0 and np.isfinite(m.sigma_mm):
            errs.append(m.value_mm - t.value_mm)
            sigmas.append(m.sigma_mm)
    return np.asarray(errs), np.asarray(sigmas)


def run_one_random_rig(rr: RandomRig, args: argparse.Namespace, base: Path) -> dict:
    """Simulate, calibrate and measure one random rig; the figures of the issue's targets."""
    rig = rr.rig
    bits = rig.bit_depth
    print(f"\n=== {rig.name}: {rr.describe()} ===", flush=True)
    t0 = time.perf_counter()
    folder = simulate_random_calibration(
        base / f"calib_{rig.name}", rr, seed=rr.seed, overwrite=True
    )
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    try:
        report = calibrate_folder(folder)
    except ValueError as exc:
        print(f"calibration refused: {exc}", flush=True)
        return {"rig": rig.name, "error": str(exc)}
    cal = report.calibration
    k_err = np.abs(cal.camera_matrix[0, 0] / rig.K[0, 0] - 1)
    held = cal.held_out.get(cal.model.name, {})
    print(
        f"simulated {rr.poses} poses in {t_sim:.0f} s, calibrated in "
        f"{time.perf_counter() - t0:.0f} s: model {cal.model.name}, reprojection "
        f"{report.reprojection_px:.3f} px, fit RMS {report.rms_mm:.4f} mm, held-out RMS "
        f"{held.get('rms_mm')}, lens {report.camera.model if report.camera else '-'}, "
        f"|f/f_true - 1| {k_err:.1e}, heights {cal.height_range_mm[0]:.2f}.."
        f"{cal.height_range_mm[1]:.2f} mm",
        flush=True,
    )
    print(calibration_vs_truth(cal, rr), flush=True)
    rec = Reconstructor(cal, with_phase=True, max_code=2**bits - 1)
    rng = np.random.default_rng(rr.seed)
    out: dict = {"rig": rig.name, "scenes": {}, "gross": 0}
    errs_all, sig_all = [], []
    for scene_name, seed in (("dof_target", 3), ("intestine_flap", 4)):
        ae = instrument_exposure(scene_name, seed=seed, rig=rig)
        world = SimulatedWorld(scene_name, seed=seed, rig=rig)
        cs, truth32, points = render_capture_set(
            world.scene, seed=seed, world=world, exposure_ms=ae.exposure_ms
        )
        res = rec.run(cs.frames)
        truth = truth32.astype(np.float64)
        lit = lit_mask(world, points)
        if scene_name == "dof_target":
            origin, axes = dof_target_field(world.rig)
            st = (points.astype(np.float64) - origin) @ axes
            lit &= ~(ruler_printer()(st[..., 0], st[..., 1]) < 0.5)
        lo, hi = cal.height_range_mm
        with np.errstate(invalid="ignore"):
            in_vol = lit & (truth >= lo) & (truth <= hi) & (res.reason != Reason.SATURATED)
        n_in = int(in_vol.sum())
        valid = float((in_vol & res.valid).sum() / max(n_in, 1))
        outside_field = float((in_vol & (res.reason == Reason.OUTSIDE_FIELD)).sum() / max(n_in, 1))
        outside_lens = float((in_vol & ~lens_field_mask(cal)).sum() / max(n_in, 1))
        err = np.asarray(res.depth, np.float64) - truth
        with np.errstate(invalid="ignore"):
            gross = int((res.valid & (np.abs(np.nan_to_num(err, nan=np.inf)) > GROSS_MM)).sum())
        sigma = np.asarray(res.sigma, np.float64)
        cells = ninth_z_figures(res, truth, sigma, in_vol, getattr(res, "sigma_model", None))
        e_len, s_len = random_lengths(res, points.astype(np.float64), cal, args.lengths, rng)
        errs_all.append(e_len)
        sig_all.append(s_len)
        len_z = float(np.sqrt(np.mean((e_len / s_len) ** 2))) if e_len.size else float("nan")
        len_rms = float(np.sqrt(np.mean(e_len**2))) if e_len.size else float("nan")
        with np.errstate(invalid="ignore"):
            whole_bias = (
                float(np.nanmean(err[in_vol & res.valid]))
                if (in_vol & res.valid).any()
                else float("nan")
            )
        print(
            f"{scene_name}: {ae.exposure_ms:.1f} ms, noise {res.noise_source}; lit unsaturated px "
            f"in volume {n_in}, valid {valid:.4f}, refused as outside the field "
            f"{outside_field:.4f} (beyond the lens model's field {outside_lens:.4f}); mean error "
            f"{whole_bias:+.4f} mm; gross {gross}; lengths {e_len.size}: RMS error "
            f"{len_rms:.4f} mm, RMS(err/sigma) {len_z:.2f}",
            flush=True,
        )
        print("  ninth   px      RMS(e/s)  mean mm   limit  model share")
        for k, (n_px, z, mean, limit, share) in enumerate(cells):
            print(
                f"  ({k // 3},{k % 3}) {n_px:>8} {z:>9.2f} {mean:>+9.4f} {limit:>7.4f}"
                f" {share:>6.2f}"
            )
        if args.oracle:
            true_cal = true_geometric_calibration(rig, cal.pattern, cal.height_range_mm)
            res_t = Reconstructor(true_cal, max_code=2**bits - 1).run(cs.frames)
            cells_t = [
                c
                for c in ninth_z_figures(res_t, truth, np.asarray(res_t.sigma, np.float64), in_vol)
                if c[0] >= 50
            ]
            print(
                f"  with the twin's true geometry as the calibration: valid "
                f"{float((in_vol & res_t.valid).sum() / max(n_in, 1)):.4f}, ninth RMS(e/sigma) "
                f"{min(c[1] for c in cells_t):.2f}..{max(c[1] for c in cells_t):.2f}, max |mean| "
                f"{max(abs(c[2]) for c in cells_t):.4f} mm",
                flush=True,
            )
        out["scenes"][scene_name] = {
            "valid": valid,
            "outside_field": outside_field,
            "outside_lens": outside_lens,
            "cells": cells,
            "gross": gross,
            "bias_mm": whole_bias,
        }
        out["gross"] += gross
    e, s = np.concatenate(errs_all), np.concatenate(sig_all)
    out["lengths"] = int(e.size)
    out["length_rms_z"] = float(np.sqrt(np.mean((e / s) ** 2))) if e.size else float("nan")
    out["length_rms_mm"] = float(np.sqrt(np.mean(e**2))) if e.size else float("nan")
    return out


def random_rig_verdicts(r: dict) -> dict[str, bool]:
    """Which of the issue's targets rig ``r`` meets."""
    if "error" in r:
        return {
            k: False for k in ("coverage", "ninth_rms_z", "ninth_bias", "lengths", "zero_gross")
        }
    cells = [c for sc in r["scenes"].values() for c in sc["cells"] if c[0] >= 50]
    return {
        "coverage": all(sc["valid"] >= COVERAGE_TARGET for sc in r["scenes"].values()),
        "ninth_rms_z": all(NINTH_RMS_Z[0] <= c[1] <= NINTH_RMS_Z[1] for c in cells),
        "ninth_bias": all(abs(c[2]) <= c[3] for c in cells),
        "lengths": r["lengths"] >= 40 and LENGTH_RMS_Z[0] <= r["length_rms_z"] <= LENGTH_RMS_Z[1],
        "zero_gross": r["gross"] == 0,
    }


def run_random_rigs(args: argparse.Namespace) -> int:
    """``--random-rigs N``: per rig the targets, then the share of rigs meeting each."""
    tmp = tempfile.TemporaryDirectory(prefix="bench_accuracy_rigs_")
    base = Path(args.keep) if args.keep else Path(tmp.name)
    rows = []
    t_all = time.perf_counter()
    for i in range(args.random_rigs):
        rr = random_rig(args.seed + i, projector_k1_max=args.projector_k1)
        r = run_one_random_rig(rr, args, base)
        r["describe"] = rr.describe()
        r["coverage"] = rr.coverage
        rows.append(r)
    print(
        f"\n=== {len(rows)} random rigs (seeds {args.seed}..{args.seed + len(rows) - 1}), "
        f"{time.perf_counter() - t_all:.0f} s ==="
    )
    head = (
        f"{'rig':<11}{'board':>6}{'cond':>5}{'bits':>5}{'valid DOF':>10}{'tissue':>8}"
        f"{'out-field':>10}"
        f"{'lens':>7}{'ninth z':>14}{'max|mean|':>10}{'len z':>7}{'gross':>6}  missed"
    )
    print(head)
    print("-" * len(head))
    verdicts = []
    for r in rows:
        v = random_rig_verdicts(r)
        verdicts.append(v)
        if "error" in r:
            cond = "yes" if r["coverage"] >= CONDITION_REACH else "no"
            print(f"{r['rig']:<11}{r['coverage']:>6.2f}{cond:>5}  calibration refused: "
                  f"{r['error']}")
            continue
        sc = r["scenes"]
        zs = [c[1] for s in sc.values() for c in s["cells"] if c[0] >= 50]
        means = [abs(c[2]) for s in sc.values() for c in s["cells"] if c[0] >= 50]
        bits = r["describe"].split("-bit")[0].rsplit(" ", 1)[-1]
        print(
            f"{r['rig']:<11}{r['coverage']:>6.2f}"
            f"{'yes' if r['coverage'] >= CONDITION_REACH else 'no':>5}{bits:>5}"
            f"{sc['dof_target']['valid']:>10.4f}"
            f"{sc['intestine_flap']['valid']:>8.4f}"
            f"{max(s['outside_field'] for s in sc.values()):>10.4f}"
            f"{max(s['outside_lens'] for s in sc.values()):>7.4f}"
            f"{min(zs):>7.2f}-{max(zs):<6.2f}{max(means):>10.4f}{r['length_rms_z']:>7.2f}"
            f"{r['gross']:>6}  "
            + (",".join(k for k, ok in v.items() if not ok) or "-")
        )
    inside = [r["coverage"] >= CONDITION_REACH for r in rows]
    print(
        "\nshare of rigs meeting each target (issue 26: >= 90 %; zero gross on every rig): all "
        f"rigs, then the {sum(inside)} whose boards reach >= {CONDITION_REACH:.0%} of the field "
        "(the targets' condition)"
    )
    missed = 0
    for key, text in (
        ("coverage", f"valid >= {COVERAGE_TARGET:.0%} of lit unsaturated px in the volume"),
        ("ninth_rms_z", f"every ninth RMS(error/sigma) in {NINTH_RMS_Z[0]}-{NINTH_RMS_Z[1]}"),
        ("ninth_bias", "every ninth |mean error| <= 0.005 mm (2 sigma_model where larger)"),
        ("lengths", f">= 40 lengths, RMS(error/sigma) in {LENGTH_RMS_Z[0]}-{LENGTH_RMS_Z[1]}"),
        ("zero_gross", "zero gross errors (> 0.5 mm) on valid pixels"),
    ):
        share = float(np.mean([v[key] for v in verdicts]))
        cond = [v[key] for v, ok in zip(verdicts, inside, strict=True) if ok]
        share_in = float(np.mean(cond)) if cond else float("nan")
        need = 1.0 if key == "zero_gross" else 0.9
        missed += share < need
        print(
            f"  {text:<66} {share:>6.0%}  {'PASS' if share >= need else 'MISS'}"
            f"   in condition {share_in:>6.0%}  {'PASS' if share_in >= need else 'MISS'}"
        )
    print(model_dominated_summary(rows))
    tmp.cleanup()
    return 1 if (args.strict and missed) else 0


if __name__ == "__main__":
    sys.exit(main())
