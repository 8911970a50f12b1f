"""Frame rate of the simulated camera at 1384×1032 on one core (target ≥ 45 frames/s).

Prints frames/s (wall clock and per CPU second of this process), the ratio to the 45 fps
target and to a plain baseline measured in the same process: generating one uint8 noise
frame of the same size with numpy. Before the frames, the scene's renderer precompute (trace,
shading, fringe tables: what a scene switch, ``World.set_scene``, costs before its first
frame) is timed, CPU and wall, from a fresh renderer that shares nothing with others.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

import numpy as np

TARGET_FPS = 45.0


def bench_precompute(scene: str, rig: str = "default") -> None:
    """CPU and wall seconds of a fresh renderer of ``scene`` up to its first noisy frame."""
    from app.devices.sim import SimulatedWorld
    from app.devices.sim.scenes import build_scene

    world = SimulatedWorld(build_scene(scene, SimulatedWorld(scene, rig=rig).rig), rig=rig,
                           seed=1)  # a Scene, not a name: its own renderer, not a shared one
    t0, c0 = time.perf_counter(), time.process_time()
    world.render(0, 0.0, exposure_ms=20.0, gain=1.0, bits=world.rig.bit_depth)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    print(f"{scene:16s} renderer precompute + first frame: {cpu:5.2f} CPU-s, {wall:5.2f} s wall")


def bench(scene: str, frames: int, rig: str = "default") -> None:
    from app.core.schedule import PatternSchedule
    from app.devices.sim import create_sim_devices

    dev = create_sim_devices(scene=scene, seed=1, realtime=False, rig=rig)
    cam, proj = dev.camera, dev.projector
    cam.open()
    proj.open()
    proj.load_schedule(PatternSchedule(), exposure_ms=20.0)
    proj.start()
    cam.start()
    for _ in range(16):  # warm-up: compile, LED tables
        cam.grab(timeout_s=5.0)
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(frames):
        cam.grab(timeout_s=5.0)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    cam.close()
    proj.close()

    rng = np.random.default_rng(0)
    w, h = dev.world.rig.image_size
    dtype = np.uint8 if cam.settings.bit_depth == 8 else np.uint16
    b0, bc0 = time.perf_counter(), time.process_time()
    for _ in range(frames):
        rng.integers(0, 2**cam.settings.bit_depth, size=(h, w), dtype=dtype)
    bwall, bcpu = time.perf_counter() - b0, time.process_time() - bc0
    fps, fps_cpu = frames / wall, frames / cpu
    print(f"{scene:16s} {fps:7.1f} frames/s wall ({fps / TARGET_FPS:4.2f}x target), "
          f"{fps_cpu:7.1f} per CPU-s ({fps_cpu / TARGET_FPS:4.2f}x target); "
          f"numpy {np.dtype(dtype).name} noise baseline {frames / bwall:7.1f}/s wall, "
          f"{frames / bcpu:7.1f}/CPU-s; "
          f"sim/baseline {fps / (frames / bwall):4.2f} wall, {fps_cpu / (frames / bcpu):4.2f} CPU")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", nargs="*",
                    default=["plane", "dof_target", "intestine_pile", "anastomosis"])
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--rig", default="default", help="simulator rig preset: default or endoscope")
    args = ap.parse_args()
    bench_precompute(args.scenes[0], args.rig)  # compiles the precompute's kernels
    for s in args.scenes:
        bench_precompute(s, args.rig)
    for s in args.scenes:
        bench(s, args.frames, args.rig)


if __name__ == "__main__":
    main()
