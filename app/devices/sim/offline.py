"""Offline rendering: capture sets with ground truth, and calibration folders (not paced)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from app.atomic import atomic_write_text
from app.capture.captureset import CaptureSet, write_capture_set
from app.core.board import BoardSpec
from app.core.encoding import npy_bytes, png_bytes
from app.core.limits import (
    DEFAULT_EXPOSURE_MS,
    DEFAULT_LED,
    EXPOSURE_RANGE_MS,
    LIVE_BIT_DEPTHS,
    check_exposure_ms,
    full_scale,
)
from app.core.schedule import PatternSchedule
from app.devices.sim.optics import SimRig, rig_by_name
from app.devices.sim.scenes import Scene, board_poses, board_scene, sim_board
from app.devices.sim.world import READOUT_MS, SimulatedWorld
from app.recon.exposure import (
    DEFAULT_SATURATION_LIMIT,
    AutoExposureResult,
    choose_exposure,
    set_statistics,
)

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


def frame_times(n_frames: int, exposure_ms: float, t0_s: float = 0.0,
                frame_period_ms: float | None = None) -> npt.NDArray[np.float64]:
    """Exposure mid-points (s) of consecutive frames from ``t0_s``; period default
    max(exposure, readout)."""
    period = (frame_period_ms or max(exposure_ms, READOUT_MS)) / 1000.0
    return t0_s + period * np.arange(n_frames, dtype=np.float64) + exposure_ms / 2000.0


def render_capture_set(scene: str | Scene, *, exposure_ms: float = DEFAULT_EXPOSURE_MS,
                       led: str = DEFAULT_LED, bit_depth: int | None = None,
                       seed: int | None = None, t0_s: float = 0.0, distortion: bool = True,
                       schedule: PatternSchedule | None = None, current: float = 0.5,
                       world: SimulatedWorld | None = None, frame_period_ms: float | None = None,
                       rig: str | SimRig = "default") -> tuple[CaptureSet, F32, F32]:
    """One capture set of ``scene``, each frame rendered at its own time, plus ground truth.

    ``rig``: the rig preset (optics.RIG_NAMES) or a :class:`SimRig` (e.g. a random one) when no
    ``world`` is given; ``bit_depth`` None: the rig sensor's native depth (8 for ``default``, 12
    for ``endoscope``).

    Returns:
        (capture set, truth depth (H, W) float32 mm above the reference plane, NaN off-object,
        truth points (H, W, 3) float32 mm, camera frame). The truth is taken at the middle of
        the set — halfway between the first and last exposure mid-points — recorded in
        ``capture.extra["simulated"]["truth_time_s"]``.
    """
    if bit_depth is not None and bit_depth not in LIVE_BIT_DEPTHS:
        raise ValueError(f"bit_depth: must be one of {LIVE_BIT_DEPTHS}, got {bit_depth}")
    check_exposure_ms(exposure_ms)
    if world is None:
        world = SimulatedWorld(scene, seed=seed, distortion=distortion, schedule=schedule, rig=rig)
    if bit_depth is None:
        bit_depth = world.rig.bit_depth
    world.led, world.current = led, current
    sched = world.schedule
    times = frame_times(sched.n_frames, exposure_ms, t0_s, frame_period_ms)
    frames: npt.NDArray[Any] = np.stack([world.render(i, float(t), exposure_ms=exposure_ms,
                                                      gain=1.0, bits=bit_depth)
                       for i, t in enumerate(times)])
    t_truth = 0.5 * (times[0] + times[-1])
    depth, points = world.truth(float(t_truth))
    meta: dict[str, object] = {
        "simulated": {"scene": world.scene.name, "seed": seed, "t0_s": t0_s,
                      "truth_time_s": float(t_truth),
                      "distortion": bool(np.any(world.rig.dist != 0)), "current": current}}
    sim_meta: dict[str, object] = meta["simulated"]  # type: ignore[assignment]
    if world.rig.name != "default":  # the default rig's capture.json stays as it was
        sim_meta["rig"] = world.rig.name
    # bit_depth: the capture set's own key (DESIGN.md: 12-bit codes in 16-bit PNGs)
    return (CaptureSet(frames=frames, schedule=sched, exposure_ms=exposure_ms, led=led, extra=meta,
                       bit_depth=bit_depth), depth, points)


def instrument_exposure(scene: str | Scene, *, seed: int | None = None,
                        rig: str | SimRig = "default",
                        saturation_limit: float = DEFAULT_SATURATION_LIMIT, current: float = 0.5,
                        led: str = DEFAULT_LED, t0_s: float = 0.0) -> AutoExposureResult:
    """The exposure the instrument's own auto-exposure picks for ``scene``.

    The search is :func:`app.recon.exposure.choose_exposure`, the one ``POST /api/exposure/auto``
    runs on grabbed sets. Each trial here is a capture set rendered at that exposure. The
    search uses a world of its own, so a later :func:`render_capture_set` with the same seed
    renders the same noise as without the search.

    Args:
        scene: a scene name or :class:`~app.devices.sim.scenes.Scene`; ``seed``, ``rig``,
            ``current``, ``led`` and ``t0_s`` as in :func:`render_capture_set`.
        saturation_limit: allowed fraction of saturated pixels, [0, 1).

    Returns:
        The search's :class:`~app.recon.exposure.AutoExposureResult` (``exposure_ms``, trials).
    """
    world = SimulatedWorld(scene, seed=seed, rig=rig)

    def measure(exposure_ms: float) -> tuple[float, float]:
        cs, _, _ = render_capture_set(world.scene, exposure_ms=exposure_ms, seed=seed, t0_s=t0_s,
                                      current=current, led=led, world=world)
        return set_statistics(cs.frames, cs.schedule, cs.max_code)

    return choose_exposure(measure, saturation_limit=saturation_limit)


def auto_exposure_ms(world: SimulatedWorld, *, target: float = 0.8, bits: int = 8,
                     current: float = 0.5, led: str = DEFAULT_LED) -> float:
    """Exposure (ms, 1–100) putting the brightest lit pixels near ``target`` of full scale."""
    r = world.renderer
    world.led, world.current = led, current
    peak = max(float(np.nanpercentile(r.mean_frame(i, 0.0, exposure_ms=10.0, led=led,
                                                   current=current, bits=bits),
                                      99.9)) for i in (0, world.schedule.steps // 2))
    return float(np.clip(10.0 * target * full_scale(bits) / max(peak, 1e-6), *EXPOSURE_RANGE_MS))


def central_fraction(rig: SimRig, pitch_mm: float, spec: BoardSpec,
                     poses: list[tuple[F64, F64]]) -> float:
    """How far the printed grid of ``spec`` (at ``pitch_mm``) reaches from the image centre
    over ``poses``: max over poses and grid corners of max(|u − cx|/(W/2), |v −
    cy|/(H/2)) (1 = the image edge)."""
    cols, rows = spec.cols, spec.rows
    hs, ht = (cols + 1) * pitch_mm / 2, (rows + 1) * pitch_mm / 2
    edge = np.linspace(-1.0, 1.0, 9)
    outline = np.concatenate([np.stack([edge * hs, np.full(9, ht)], 1),
                              np.stack([edge * hs, np.full(9, -ht)], 1),
                              np.stack([np.full(9, hs), edge * ht], 1),
                              np.stack([np.full(9, -hs), edge * ht], 1)])
    w, h = rig.image_size
    worst = 0.0
    for origin, axes in poses:
        pts = origin + outline[:, :1] * axes[:, 0] + outline[:, 1:] * axes[:, 1]
        uv = rig.camera.project(pts)
        worst = max(worst, float(np.max(np.abs(uv[:, 0] - (w - 1) / 2) / (w / 2))),
                    float(np.max(np.abs(uv[:, 1] - (h - 1) / 2) / (h / 2))))
    return worst


def partial_board_spec(rig: SimRig, spec: BoardSpec, poses: list[tuple[F64, F64]],
                       fraction: float = 0.5
                       ) -> BoardSpec:
    """``spec`` with its pitch shrunk (to 0.001 mm) so that at every pose its printed grid stays in
    the central ``fraction`` of the image width and height, as a bench board that
    covers only the centre."""
    if not 0.05 <= fraction <= 1.0:
        raise ValueError(f"fraction: must be within 0.05–1, got {fraction}")
    pitch = spec.pitch_mm
    for _ in range(50):
        reach = central_fraction(rig, pitch, spec, poses)
        if reach <= fraction:
            return BoardSpec(spec.type, spec.cols, spec.rows, pitch)
        pitch = math.floor(1000.0 * pitch * min(0.999, 0.995 * fraction / reach)) / 1000.0
    raise ValueError(f"fraction: the board cannot be made to fit the central {fraction:.2f} "
                     "of the field")


def simulate_calibration_folder(out_dir: str | os.PathLike[str], *, board: str = "checkerboard",
                                poses: int = 8, seed: int | None = None,
                                bit_depth: int | None = None, distortion: bool = True,
                                overwrite: bool = False, rig: str = "default",
                                partial_boards: bool | None = None) -> Path:
    """Write ``board.json`` and ``pose_00/`` … capture sets of a board at ``poses`` poses.

    Pose 0 lies in the scenes' default reference plane. Each pose's exposure is set so the
    white paper stays below saturation; its ``capture.json`` records the board pose
    (``simulated.board_origin_mm``, ``simulated.board_axes``: columns e_s, e_t, normal).

    Args:
        rig: the rig preset (optics.RIG_NAMES).
        bit_depth: 8 or 12; None: the rig sensor's native depth.
        partial_boards: True: the board (its pitch scaled down, its paper cut to a margin around
            the print) covers only the central half of the image width and height at every pose,
            as on a real bench, so the outer field is never calibrated; None: the rig's default
            (off for ``default``, on for ``endoscope``).
    """
    spec = sim_board(board)
    sim_rig = rig_by_name(rig, distortion=distortion)
    if bit_depth is None:
        bit_depth = sim_rig.bit_depth
    if bit_depth not in LIVE_BIT_DEPTHS:
        raise ValueError(f"bit_depth: must be one of {LIVE_BIT_DEPTHS}, got {bit_depth}")
    partial = sim_rig.partial_boards if partial_boards is None else bool(partial_boards)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    pose_list = board_poses(sim_rig, poses, seed=int(rng.integers(2**31)))
    paper_half_mm = 11.0
    if partial:
        spec = partial_board_spec(sim_rig, spec, pose_list)
        cols, rows = spec.cols, spec.rows
        paper_half_mm = (max(cols, rows) + 1) * spec.pitch_mm / 2 + 1.5 * spec.pitch_mm
    atomic_write_text(out / "board.json", json.dumps(spec.to_dict(), indent=2) + "\n")
    for k, pose in enumerate(pose_list):
        scene = board_scene(sim_rig, spec, pose, paper_half_mm=paper_half_mm)
        world = SimulatedWorld(scene, rig=sim_rig, seed=int(rng.integers(2**31)))
        exposure = round(auto_exposure_ms(world, bits=bit_depth), 2)
        cap, depth, _ = render_capture_set(world.scene, exposure_ms=exposure, bit_depth=bit_depth,
                                           world=world)
        sim_meta = cap.extra["simulated"]
        sim_meta.update({"board_origin_mm": pose[0].tolist(), "board_axes": pose[1].tolist(),
                         "pose": k})
        if partial:
            sim_meta["partial_board"] = True
        # PNG level 1 without the per-row prediction filter: lossless as the default, a quarter
        # less encoding CPU (8-bit 1384 x 1032: 21 -> 16 ms a frame) for files 10-16 % larger
        # (0.50 -> 0.58 MB; 12-bit 1280 x 1024: 38 -> 28 ms, 1.20 -> 1.32 MB)
        encoded = [png_bytes(frame, compression=1, filter_none=True) for frame in cap.frames]
        write_capture_set(out / f"pose_{k:02d}", cap, overwrite=overwrite, encoded=encoded,
                          extra_files={"truth_depth.npy": npy_bytes(depth)})
    return out
