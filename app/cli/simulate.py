"""``fringescope simulate``: capture sets with ground truth, or calibration folders, from the
twin."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from app.core.limits import EXPOSURE_RANGE_MS, LEDS

if TYPE_CHECKING:
    from app.devices.sim.scenes import Scene


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "simulate",
        help="render capture sets (with truth_depth.npy/truth_points.npy) or a calibration "
             "folder",
        description="SCENE -o DIR writes set_0000/, set_0001/ … (capture.json, frames, "
                    "truth_depth.npy, truth_points.npy); 'calibration -o DIR' writes board.json "
                    "and pose_00/ …",
    )
    p.add_argument("scene", nargs="?", help="scene name, or 'calibration' (see --list)")
    p.add_argument("-o", "--output", type=Path, help="output folder")
    p.add_argument("--list", action="store_true", help="list the scenes and exit")
    p.add_argument("--exposure-ms", type=float, default=20.0,
                   help="camera exposure per frame (default 20)")
    p.add_argument("--led", choices=LEDS, default="green", help="projector LED (default green)")
    p.add_argument("--rig", default="default",
                   help="rig preset: default (the paper's rig) or endoscope (1280x1024, wide "
                        "angle, barrel k1 = -0.25, 12-bit, partial boards); default 'default'")
    p.add_argument("--bits", type=int, choices=(8, 12), default=None,
                   help="ADC bit depth (default: the rig's sensor, 8 for default, 12 for "
                        "endoscope)")
    p.add_argument("--seed", type=int, default=None,
                   help="random seed (noise, faults) for reproducible output")
    p.add_argument("--frames-per-second", type=float, default=None,
                   help="camera frame rate (default: as fast as the exposure and readout allow)")
    p.add_argument("--duration-s", type=float, default=None,
                   help="simulated time to cover; one capture set per 16 frames (default: one set)")
    p.add_argument("--board", choices=("checkerboard", "circles"), default="checkerboard",
                   help="calibration board type (calibration only)")
    p.add_argument("--poses", type=int, default=8,
                   help="number of board poses (calibration only, default 8)")
    p.add_argument("--no-distortion", action="store_true",
                   help="ideal pinhole camera (no lens distortion)")
    boards = p.add_mutually_exclusive_group()
    boards.add_argument("--partial-boards", dest="partial_boards", action="store_true",
                        default=None,
                        help="boards cover only the central half of the field (calibration "
                             "only; the endoscope rig's default)")
    boards.add_argument("--full-boards", dest="partial_boards", action="store_false",
                        help="boards as large as the default rig's (calibration only)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from app.devices.sim import list_scenes
    from app.devices.sim.optics import RIG_NAMES

    if args.rig not in RIG_NAMES:
        raise ValueError(f"--rig: unknown {args.rig!r}; choose from {', '.join(RIG_NAMES)}")
    if args.list:
        from app.devices.sim.optics import rig_by_name
        from app.devices.sim.scenes import build_scene

        rig = rig_by_name(args.rig)
        for name in list_scenes():
            print(f"{name}: {scene_summary(build_scene(name, rig))}")
        print("calibration: a calibration board in a sequence of poses (see --help)")
        return 0
    if not args.scene:
        raise ValueError("scene: give a scene name (see --list) or 'calibration'")
    if args.output is None:
        raise ValueError("-o/--output: an output folder is required")
    if args.scene == "calibration":
        return _calibration(args)
    if args.scene not in list_scenes():
        raise ValueError(f"scene: unknown {args.scene!r}; choose from "
                         f"{', '.join(list_scenes())} or calibration")
    return _scene(args)


def _calibration(args: argparse.Namespace) -> int:
    from app.devices.sim import simulate_calibration_folder

    if args.poses < 2:
        raise ValueError(f"--poses: need at least 2, got {args.poses}")
    out = simulate_calibration_folder(args.output, board=args.board, poses=args.poses,
                                      seed=args.seed, bit_depth=args.bits,
                                      distortion=not args.no_distortion, rig=args.rig,
                                      partial_boards=args.partial_boards)
    print(f"wrote {out}/board.json and {args.poses} poses")
    return 0


def _scene(args: argparse.Namespace) -> int:
    from app.capture.captureset import write_capture_set
    from app.core.encoding import npy_bytes
    from app.devices.sim.offline import render_capture_set
    from app.devices.sim.world import READOUT_MS, SimulatedWorld

    if not (EXPOSURE_RANGE_MS[0] <= args.exposure_ms <= EXPOSURE_RANGE_MS[1]):
        lo, hi = EXPOSURE_RANGE_MS
        raise ValueError(f"--exposure-ms: must be within {lo:g}–{hi:g} ms, "
                         f"got {args.exposure_ms}")
    min_period_ms = max(args.exposure_ms, READOUT_MS)
    if args.frames_per_second is None:
        period_ms = min_period_ms
    else:
        if not (args.frames_per_second > 0 and math.isfinite(args.frames_per_second)):
            raise ValueError(f"--frames-per-second: must be positive, got {args.frames_per_second}")
        period_ms = 1000.0 / args.frames_per_second
        if period_ms < min_period_ms - 1e-9:
            raise ValueError(f"--frames-per-second: at most {1000.0 / min_period_ms:.1f} "
                             "at this exposure")
    world = SimulatedWorld(args.scene, seed=args.seed, distortion=not args.no_distortion,
                           rig=args.rig)
    n_frames = world.schedule.n_frames
    set_s = n_frames * period_ms / 1000.0
    if args.duration_s is not None and not (args.duration_s > 0):
        raise ValueError(f"--duration-s: must be positive, got {args.duration_s}")
    n_sets = 1 if args.duration_s is None else max(1, int(args.duration_s / set_s))
    args.output.mkdir(parents=True, exist_ok=True)
    for k in range(n_sets):
        cap, depth, points = render_capture_set(world.scene, exposure_ms=args.exposure_ms,
                                                led=args.led, bit_depth=args.bits, seed=args.seed,
                                                t0_s=k * set_s, world=world,
                                                frame_period_ms=period_ms)
        truth = {"truth_depth.npy": npy_bytes(depth), "truth_points.npy": npy_bytes(points)}
        write_capture_set(args.output / f"set_{k:04d}", cap, extra_files=truth)
    print(f"wrote {n_sets} capture set(s) of {args.scene} to {args.output}")
    return 0


def scene_summary(scene: Scene) -> str:
    """``description; surface 80.0 x 60.0 mm, relief 0.00..12.34 mm[, spheres Ø …][, moving]``
    ``[, with a tool]``.

    The true dimensions from the scene's own geometry: the height field's extent (mm along
    its two axes), its heights above its base plane (mm) and any sphere's diameter (mm).
    """
    hf = scene.surface
    ny, nx = hf.heights.shape
    parts = [scene.description or scene.name,
             f"surface {nx * hf.ds:.1f} x {ny * hf.ds:.1f} mm, "
             f"relief {float(hf.heights.min()):.2f}..{float(hf.heights.max()):.2f} mm"]
    if scene.spheres:
        diameters = ", ".join(f"{2 * s.radius_mm:.3f}" for s in scene.spheres)
        parts.append(f"spheres Ø {diameters} mm")
        if len(scene.spheres) == 2:
            gap = float(np.linalg.norm(scene.spheres[0].centre - scene.spheres[1].centre))
            parts.append(f"centre distance {gap:.3f} mm")
    if scene.motion is not None:
        parts.append("moving")
    if scene.tool is not None:
        parts.append("with a tool")
    return "; ".join(parts)
