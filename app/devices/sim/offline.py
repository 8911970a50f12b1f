"""Offline rendering: capture sets with ground truth, and calibration folders (not paced)."""

from __future__ import annotations

import io
import json
import os
from pathlib import Path

import numpy as np
import numpy.typing as npt

from app.atomic import atomic_write_text
from app.capture.captureset import CaptureSet, write_capture_set
from app.devices.sim.optics import default_rig
from app.devices.sim.scenes import BoardSpec, Scene, board_poses, board_scene
from app.devices.sim.world import READOUT_MS, SimulatedWorld
from app.recon.patterns import PatternSchedule

F32 = npt.NDArray[np.float32]


def frame_times(n_frames: int, exposure_ms: float, t0_s: float = 0.0,
                frame_period_ms: float | None = None) -> npt.NDArray[np.float64]:
    """Exposure mid-points (s) of consecutive frames from ``t0_s``; period default max(exposure, readout)."""
    period = (frame_period_ms or max(exposure_ms, READOUT_MS)) / 1000.0
    return t0_s + period * np.arange(n_frames) + exposure_ms / 2000.0


def render_capture_set(scene: str | Scene, *, exposure_ms: float = 20.0, led: str = "green", bit_depth: int = 8,
                       seed: int | None = None, t0_s: float = 0.0, distortion: bool = True,
                       schedule: PatternSchedule | None = None, current: float = 0.5,
                       world: SimulatedWorld | None = None, frame_period_ms: float | None = None
                       ) -> tuple[CaptureSet, F32, F32]:
    """One capture set of ``scene``, each frame rendered at its own time, plus ground truth.

    Returns:
        (capture set, truth depth (H, W) float32 mm above the reference plane, NaN off-object,
        truth points (H, W, 3) float32 mm, camera frame). The truth is taken at the middle of
        the set — halfway between the first and last exposure mid-points — recorded in
        ``capture.extra["simulated"]["truth_time_s"]``.
    """
    if bit_depth not in (8, 12):
        raise ValueError(f"bit_depth: must be 8 or 12, got {bit_depth}")
    if not (1.0 <= exposure_ms <= 100.0):
        raise ValueError(f"exposure_ms: must be within 1–100 ms, got {exposure_ms}")
    if world is None:
        world = SimulatedWorld(scene, seed=seed, distortion=distortion, schedule=schedule)
    world.led, world.current = led, current
    sched = world.schedule
    times = frame_times(sched.n_frames, exposure_ms, t0_s, frame_period_ms)
    frames = np.stack([world.render(i, float(t), exposure_ms=exposure_ms, gain=1.0, bits=bit_depth)
                       for i, t in enumerate(times)])
    t_truth = 0.5 * (times[0] + times[-1])
    depth, points = world.truth(float(t_truth))
    meta = {"simulated": {"scene": world.scene.name, "seed": seed, "t0_s": t0_s, "truth_time_s": float(t_truth),
                          "distortion": bool(np.any(world.rig.dist != 0)), "current": current}}
    return (CaptureSet(frames=frames, schedule=sched, exposure_ms=exposure_ms, led=led, extra=meta,
                       bit_depth=bit_depth), depth, points)


def npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def auto_exposure_ms(world: SimulatedWorld, *, target: float = 0.8, bits: int = 8, current: float = 0.5,
                     led: str = "green") -> float:
    """Exposure (ms, 1–100) putting the brightest lit pixels near ``target`` of full scale."""
    r = world.renderer
    world.led, world.current = led, current
    peak = max(float(np.nanpercentile(r.mean_frame(i, 0.0, exposure_ms=10.0, led=led, current=current, bits=bits),
                                      99.9)) for i in (0, world.schedule.steps // 2))
    return float(np.clip(10.0 * target * (2**bits - 1) / max(peak, 1e-6), 1.0, 100.0))


def simulate_calibration_folder(out_dir: str | os.PathLike[str], *, board: str = "checkerboard", poses: int = 8,
                                seed: int | None = None, bit_depth: int = 8, distortion: bool = True,
                                overwrite: bool = False) -> Path:
    """Write ``board.json`` and ``pose_00/`` … capture sets of a board at ``poses`` poses.

    Pose 0 lies in the scenes' default reference plane. Each pose's exposure is set so the
    white paper stays below saturation; its ``capture.json`` records the board pose
    (``simulated.board_origin_mm``, ``simulated.board_axes``: columns e_s, e_t, normal).
    """
    if board not in ("checkerboard", "circles"):
        raise ValueError(f"board: must be 'checkerboard' or 'circles', got {board!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    spec = BoardSpec(type=board)
    rig = default_rig(distortion=distortion)
    atomic_write_text(out / "board.json", json.dumps(spec.to_json(), indent=2) + "\n")
    rng = np.random.default_rng(seed)
    for k, pose in enumerate(board_poses(rig, poses, seed=int(rng.integers(2**31)))):
        world = SimulatedWorld(board_scene(rig, spec, pose), rig=rig, seed=int(rng.integers(2**31)))
        exposure = round(auto_exposure_ms(world, bits=bit_depth), 2)
        cap, depth, _ = render_capture_set(world.scene, exposure_ms=exposure, bit_depth=bit_depth, world=world)
        cap.extra["simulated"].update({"board_origin_mm": pose[0].tolist(), "board_axes": pose[1].tolist(),
                                       "pose": k})
        write_capture_set(out / f"pose_{k:02d}", cap, overwrite=overwrite,
                          extra_files={"truth_depth.npy": npy_bytes(depth)})
    return out
