"""Recording every set at the camera's rate (issue 24 item 6): storage, then a live recording.

1. Storage, per codec on one simulated tissue set (``intestine_flap``, 1384 x 1032, 8-bit)
   at the schedule's frame count: MB per set, CPU ms per set (process time, one thread)
   and both as ratios against PNG at zlib level 1 (the previous recorder's format), and the
   read-back CPU. The recorder's choice is ``zstd`` (row differences, zstd level 1).
2. Live: a real server (uvicorn) on the simulator at ``--schedule``; the depth rate over
   ``--baseline-s`` without recording, then a ``--seconds`` recording: sets recorded,
   ``skipped_sets`` (target 0), the writer queue's peak, the depth rate while recording
   against camera fps / frames per map (target >= 0.97) and against the baseline, MB per
   set on disk, and whether every recorded set reads back whole. ``--busy-cores 1`` runs a
   second process spinning on one core for the whole live part (issue 24: ``paper-16`` with
   a second process using one core).

    python benchmarks/bench_recording.py [--schedule geometric-9] [--seconds 60] [--busy-cores 0]
        [--baseline-s 15] [--data-dir data] [--storage-only] [--codec zstd|png]

The first run creates the simulator's calibration in DATA_DIR (a minute or two). The
recording is deleted afterwards.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from app.core.jit import numeric_environment

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

import cv2
import numpy as np
import numpy.typing as npt

from app.capture.captureset import read_zstd_frame, zstd_frame_bytes
from app.core.schedule import schedule_by_name


def storage(
    frames: npt.NDArray[np.uint8], repeats: int = 3
) -> list[tuple[str, float, float, float]]:
    """Per codec: (name, MB/set, encode CPU ms/set, decode CPU ms/set), best of ``repeats``."""
    import tempfile

    def png(level: int, strategy: int) -> Any:
        params = [cv2.IMWRITE_PNG_COMPRESSION, level, cv2.IMWRITE_PNG_STRATEGY, strategy]
        return lambda f: cv2.imencode(".png", f, params)[1].tobytes()

    codecs = [
        ("png level 1 (previous)", png(1, cv2.IMWRITE_PNG_STRATEGY_DEFAULT), "png"),
        ("png level 1 huffman-only", png(1, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY), "png"),
        ("png level 0 (stored)", png(0, cv2.IMWRITE_PNG_STRATEGY_DEFAULT), "png"),
        ("zstd row differences (chosen)", zstd_frame_bytes, "zst"),
    ]
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, encode, kind in codecs:
            enc_s = dec_s = float("inf")
            blobs: list[bytes] = []
            for _ in range(repeats):
                t = time.process_time()
                blobs = [encode(f) for f in frames]
                enc_s = min(enc_s, time.process_time() - t)
            paths = []
            for i, b in enumerate(blobs):
                p = Path(tmp) / f"f{i}.{kind}"
                p.write_bytes(b)
                paths.append(p)
            for _ in range(repeats):
                t = time.process_time()
                back = [
                    read_zstd_frame(p)
                    if kind == "zst"
                    else cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
                    for p in paths
                ]
                dec_s = min(dec_s, time.process_time() - t)
            if not all(
                a is not None and np.array_equal(a, b) for a, b in zip(back, frames, strict=True)
            ):
                raise SystemExit(f"{name}: frames did not read back bit-exact")
            out.append((name, sum(map(len, blobs)) / 1e6, 1e3 * enc_s, 1e3 * dec_s))
    return out


def sim_frames(schedule_name: str) -> npt.NDArray[np.uint8]:
    """One simulated set of ``intestine_flap`` with ``schedule_name``'s patterns, (F, H, W) u8."""
    from app.devices.sim.offline import render_capture_set

    cap, _, _ = render_capture_set(
        "intestine_flap", exposure_ms=30.0, seed=3, schedule=schedule_by_name(schedule_name)
    )
    return np.asarray(cap.frames, np.uint8)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def live(args: argparse.Namespace) -> int:
    import httpx
    import uvicorn

    from app.capture.captureset import read_capture_set
    from app.config import Settings
    from app.main import create_app

    settings = Settings(
        port=free_port(),
        data_dir=Path(args.data_dir),
        exposure_ms=args.exposure_ms,
        sim_scene=args.scene,
        viewer=False,
        schedule=args.schedule,
        sim_seed=1,
    )
    app = create_app(settings)
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=settings.port, log_level="warning")
    )
    thread = threading.Thread(target=server.run, name="bench-uvicorn", daemon=True)
    thread.start()
    busy: list[subprocess.Popen[bytes]] = []
    base = f"http://127.0.0.1:{settings.port}"
    name = f"bench-{int(time.time())}"
    try:
        while not server.started:
            if not thread.is_alive():
                raise SystemExit("server failed to start")
            time.sleep(0.05)
        app.state.recorder.codec = args.codec
        http = httpx.Client(base_url=base, timeout=30)
        deadline = time.monotonic() + 600
        st: dict[str, Any] = {}
        while time.monotonic() < deadline:
            st = http.get("/api/status").json()
            if st["state"] == "running" and st["results_published"] >= 3:
                break
            time.sleep(0.5)
        else:
            raise SystemExit(f"not running after 600 s: {st.get('state')} {st.get('last_error')}")
        for _ in range(args.busy_cores):  # a second process using one core, for the whole live part
            busy.append(subprocess.Popen([sys.executable, "-c", "while True: pass"]))
        time.sleep(3.0)  # let the pipeline settle beside the busy process

        lost: dict[str, int] = {}

        def window(seconds: float) -> tuple[float, float, float, float]:
            """camera fps, depth /s, the span (s) and this process's CPU use (cores) over it"""
            s0, t0, c0 = http.get("/api/status").json(), time.monotonic(), time.process_time()
            time.sleep(seconds)
            s1, t1, c1 = http.get("/api/status").json(), time.monotonic(), time.process_time()
            span = t1 - t0
            for key in ("frames_dropped", "incomplete_sets"):
                lost[key] = s1[key] - s0[key]
            return (
                (s1["frames_received"] - s0["frames_received"]) / span,
                (s1["results_published"] - s0["results_published"]) / span,
                span,
                (c1 - c0) / span,
            )

        per_map = schedule_by_name(args.schedule).n_frames
        cam0, depth0, _, cpu0 = window(args.baseline_s)
        r = http.post("/api/recording/start", json={"name": name})
        r.raise_for_status()
        cam1, depth1, span, cpu1 = window(args.seconds)
        rec_status = http.get("/api/recording").json()
        stopped = http.post("/api/recording/stop").json()["stopped"]
        status = http.get("/api/status").json()
    finally:
        for p in busy:
            p.kill()
            p.wait()
        server.should_exit = True
        thread.join(60)

    root = Path(args.data_dir) / "recordings" / name
    sets = stopped["sets"]
    whole = 0
    for s in sets:
        cap = read_capture_set(root / s["folder"])
        whole += cap.frames.shape[0] == per_map
    frame_bytes = sum(f.stat().st_size for s in sets for f in (root / s["folder"]).glob("frame_*"))
    all_bytes = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
    import shutil

    shutil.rmtree(root, ignore_errors=True)

    def verdict(ok: bool) -> str:
        return "ok" if ok else "MISSED"

    ideal0, ideal1 = cam0 / per_map, cam1 / per_map
    ratio = depth1 / ideal1 if ideal1 else 0.0
    expected = span * ideal1
    n = max(1, len(sets))
    skipped, wr_ms = rec_status["skipped_sets"], rec_status["write_cpu_ms_per_set"]
    print(f"live: schedule {args.schedule} ({per_map} frames/map), scene {args.scene}, "
          f"{args.exposure_ms:g} ms, codec {args.codec}, {args.busy_cores} busy core(s) beside, "
          f"{span:.1f} s recording")
    print(f"  baseline (not recording) camera {cam0:.2f} fps, depth {depth0:.3f} /s = "
          f"{depth0 / ideal0 if ideal0 else 0:.3f} x camera/{per_map}; "
          f"server process {cpu0:.2f} cores")
    print(f"  recording                camera {cam1:.2f} fps, depth {depth1:.3f} /s = "
          f"{ratio:.3f} x camera/{per_map} (target >= 0.97: {verdict(ratio >= 0.97)}); "
          f"depth while recording / baseline {depth1 / depth0 if depth0 else 0:.3f}")
    print(f"  CPU: server process {cpu1:.2f} cores while recording ({cpu1 - cpu0:+.2f} against "
          f"the baseline); the writer {wr_ms:.1f} ms CPU per set = "
          f"{wr_ms * len(sets) / span / 1e3:.2f} cores, {rec_status['write_ms_per_set']:.1f} ms "
          f"elapsed per set (the camera gives one every {1e3 / ideal1 if ideal1 else 0:.0f} ms)")
    print(f"  sets recorded {len(sets)} (camera/{per_map} x {span:.1f} s = {expected:.0f}), "
          f"with depth {rec_status['sets_with_depth']}, skipped_sets {skipped} "
          f"(target 0: {verdict(skipped == 0)}), writer queue peak {rec_status['queue_peak']}, "
          f"errors {rec_status['errors']}")
    print(f"  while recording the camera dropped {lost['frames_dropped']} frames, "
          f"{lost['incomplete_sets']} sets incomplete (never whole, so never recorded)")
    print(f"  on disk: frames {frame_bytes / n / 1e6:.2f} MB/set, all {all_bytes / n / 1e6:.2f} "
          f"MB/set (with depth.npy), {all_bytes / span / 1e6:.1f} MB/s; "
          f"read back whole {whole} of {len(sets)}")
    print(f"  status warnings {status['warnings']}; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    return 0 if rec_status["skipped_sets"] == 0 and ratio >= 0.97 and whole == len(sets) else 1


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--schedule", default="geometric-9", help="pattern schedule by name")
    ap.add_argument("--seconds", type=float, default=60.0, help="recording length, s")
    ap.add_argument(
        "--baseline-s", type=float, default=15.0, help="depth rate without recording first, s"
    )
    ap.add_argument(
        "--busy-cores", type=int, default=0, help="processes spinning one core each, beside"
    )
    ap.add_argument("--exposure-ms", type=float, default=30.0)
    ap.add_argument("--scene", default="intestine_flap")
    ap.add_argument(
        "--codec", choices=("zstd", "png"), default="zstd", help="the recorder's frame storage"
    )
    ap.add_argument("--data-dir", default="data")
    ap.add_argument("--storage-only", action="store_true", help="only the codec comparison")
    args = ap.parse_args()

    frames = sim_frames(args.schedule)
    rows = storage(frames)
    ref_mb, ref_ms = rows[0][1], rows[0][2]
    shape = " x ".join(str(x) for x in frames.shape)
    print(f"storage: one {args.schedule} set of intestine_flap, {shape} {frames.dtype} "
          f"({frames.nbytes / 1e6:.1f} MB raw); ratios against png level 1")
    for name, mb, enc_ms, dec_ms in rows:
        print(f"  {name:30s} {mb:6.2f} MB/set ({mb / ref_mb:4.2f})  encode {enc_ms:6.1f} ms "
              f"CPU/set ({enc_ms / ref_ms:4.2f})  read {dec_ms:6.1f} ms CPU/set")
    sets_per_s = 30.0 / frames.shape[0]  # at 30 frames/s
    chosen = rows[-1]
    print(f"  at {sets_per_s:.2f} sets/s (30 frames/s) the chosen codec needs "
          f"{chosen[2] * sets_per_s / 1e3:.2f} of a core and {chosen[1] * sets_per_s:.1f} MB/s "
          f"of disk for the frames; png level 1 {ref_ms * sets_per_s / 1e3:.2f} of a core")
    if args.storage_only:
        return 0
    return live(args)


if __name__ == "__main__":
    sys.exit(main())
