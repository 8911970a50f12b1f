"""Live pipeline on the simulator behind a real uvicorn server (issue 5's speed targets).

At 30 ms exposure: camera fps, depth rate and its ratio to camera fps / 16 (target
≥ 0.97), median latency last frame → result (target ≤ 20 ms), p99 of GET /api/status
while 4 WebSocket clients stream the depth colormap (target < 50 ms), and the rate each
stream client receives compared with the depth rate (target ≥ 0.97). Then, per mode
(whole set; rolling: a map after every frequency group), the depth rate against its ideal
(camera fps / frames per map) and the latency of every result (median, p95; target median
≤ 20 ms in every mode).

    python benchmarks/bench_live.py [--seconds 20] [--mode-seconds 10] [--exposure-ms 30]
        [--data-dir data]

The first run creates the simulator's calibration in DATA_DIR (a minute or two).
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from app.core.jit import numeric_environment

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

import httpx
import numpy as np
import uvicorn
from websockets.sync.client import connect

from app.config import Settings
from app.main import create_app


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_server(settings: Settings) -> tuple[uvicorn.Server, threading.Thread]:
    server = uvicorn.Server(uvicorn.Config(create_app(settings), host="127.0.0.1",
                                           port=settings.port, log_level="warning"))
    thread = threading.Thread(target=server.run, name="bench-uvicorn", daemon=True)
    thread.start()
    while not server.started:
        if not thread.is_alive():
            raise SystemExit("server failed to start")
        time.sleep(0.05)
    return server, thread


def wait_running(base: str, timeout_s: float) -> dict:
    deadline = time.monotonic() + timeout_s
    st: dict = {}
    while time.monotonic() < deadline:
        st = httpx.get(base + "/api/status", timeout=5).json()
        if st["state"] == "running" and st["results_published"] >= 2:
            return st
        time.sleep(0.5)
    raise SystemExit(f"instrument not running after {timeout_s:.0f} s: {st.get('state')} "
                     f"{st.get('last_error')}")


def stream_client(url: str, stop: threading.Event, arrivals: list[float], sizes: list[int]) -> None:
    with connect(url, max_size=None, open_timeout=10) as ws:
        while not stop.is_set():
            try:
                msg = ws.recv(timeout=1.0)
            except TimeoutError:
                continue
            arrivals.append(time.monotonic())
            sizes.append(len(msg))


def measure_modes(base: str,
                  seconds: float) -> list[tuple[str, float, int, list[float], list[float]]]:
    """Per mode: depth rate (/s), frames per map, the latency of every result seen and of it
    the motion test's time (ms)."""
    out = []
    with httpx.Client(base_url=base, timeout=5) as http:
        st = http.get("/api/status").json()
        start_mode = st["mode"]
        sched = st.get("schedule") or {}
        n_freq = len(sched.get("frequencies", [1, 4, 12, 36]))
        steps = int(sched.get("steps", 4))
        for mode in ("set", "rolling"):
            http.put("/api/mode", json={"rolling": mode == "rolling"}).raise_for_status()
            time.sleep(3.0)  # the window refills; older results drain
            s0 = http.get("/api/status").json()
            t0 = time.monotonic()
            lat: dict[int, float] = {}
            mot: dict[int, float] = {}
            while time.monotonic() - t0 < seconds:
                r = http.get("/api/result/latest")
                if r.status_code == 200:
                    m = r.json()
                    if m["mode"] == mode:
                        lat[m["seq"]] = m["latency_ms"]
                        mot[m["seq"]] = m.get("motion_ms", 0.0)
                time.sleep(0.01)
            span = time.monotonic() - t0
            s1 = http.get("/api/status").json()
            rate = (s1["results_published"] - s0["results_published"]) / span
            out.append((mode, rate, steps if mode == "rolling" else n_freq * steps,
                        list(lat.values()), list(mot.values())))
        http.put("/api/mode", json={"rolling": start_mode == "rolling"})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--exposure-ms", type=float, default=30.0)
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--mode-seconds", type=float, default=10.0,
                    help="per-mode latency measurement, s (0: skip)")
    ap.add_argument("--data-dir", default="data")
    ap.add_argument("--scene", default="intestine_flap", help="simulator scene (the serve default)")
    ap.add_argument("--viewer", action="store_true", help="also run the viser 3-D viewer")
    ap.add_argument("--rig", choices=("default", "endoscope"), default="default",
                    help="simulator rig preset (endoscope: 12-bit sensor)")
    ap.add_argument("--schedule", default=None,
                    help="pattern schedule by name (app/core/schedule.py; default the paper's)")
    args = ap.parse_args()

    settings = Settings(port=free_port(), data_dir=Path(args.data_dir),
                        exposure_ms=args.exposure_ms, viewer=args.viewer, sim_seed=1,
                        sim_scene=args.scene, sim_rig=args.rig,
                        bit_depth=12 if args.rig == "endoscope" else 8,
                        **({"schedule": args.schedule} if args.schedule else {}))
    base = f"http://127.0.0.1:{settings.port}"
    server, thread = start_server(settings)
    try:
        wait_running(base, timeout_s=600)
        time.sleep(2.0)  # warm-up: JIT, first encodings
        stop = threading.Event()
        arrivals: list[list[float]] = [[] for _ in range(args.clients)]
        sizes: list[int] = []
        ws_url = f"ws://127.0.0.1:{settings.port}/api/stream/depth"
        clients = [threading.Thread(target=stream_client, args=(ws_url, stop, arrivals[i], sizes),
                                    daemon=True)
                   for i in range(args.clients)]
        for c in clients:
            c.start()
        time.sleep(1.0)
        status_ms: list[float] = []
        with httpx.Client(base_url=base, timeout=5) as http:
            s0 = http.get("/api/status").json()
            t0 = time.monotonic()
            arr_start = [len(a) for a in arrivals]
            while time.monotonic() - t0 < args.seconds:
                t = time.perf_counter()
                r = http.get("/api/status")
                status_ms.append(1000 * (time.perf_counter() - t))
                r.raise_for_status()
                time.sleep(0.02)
            t1 = time.monotonic()
            s1 = http.get("/api/status").json()
        stop.set()
        for c in clients:
            c.join(5)
        per_mode = measure_modes(base, args.mode_seconds) if args.mode_seconds > 0 else []
    finally:
        server.should_exit = True
        thread.join(30)

    span = t1 - t0
    camera_fps = (s1["frames_received"] - s0["frames_received"]) / span
    depth_fps = (s1["results_published"] - s0["results_published"]) / span
    frames_per_map = int((s1.get("schedule") or {}).get("frames_per_depth") or 16)
    ideal = camera_fps / frames_per_map
    ratio = depth_fps / ideal if ideal else 0.0
    latency = s1["latency_ms"]
    p50, p99 = np.percentile(status_ms, [50, 99])
    stream_rates = [sum(1 for x in a[n0:] if t0 <= x <= t1) / span
                    for a, n0 in zip(arrivals, arr_start, strict=True)]
    stream_ratio = min(stream_rates) / depth_fps if depth_fps else 0.0

    def verdict(ok: bool) -> str:
        return "ok" if ok else "MISSED"

    print(f"bench_live: {span:.1f} s, scene {args.scene}, {args.exposure_ms:g} ms exposure, "
          f"{args.clients} WebSocket clients{' + viewer' if args.viewer else ''}")
    print(f"  camera fps            {camera_fps:8.2f}")
    print(f"  depth rate            {depth_fps:8.3f} /s   ideal camera/{frames_per_map} = "
          f"{ideal:.3f} /s   ratio {ratio:.3f} (target >= 0.97: {verdict(ratio >= 0.97)})")
    print(f"  latency median        {latency if latency is not None else float('nan'):8.2f} ms  "
          f"(last frame -> result; target <= 20: {verdict(latency is not None and latency <= 20)}; "
          f"of it reconstruction {s1['recon_ms']} ms)")
    print(f"  GET /api/status       p50 {p50:.2f} ms  p99 {p99:.2f} ms  n={len(status_ms)} "
          f"(target p99 < 50: {verdict(p99 < 50)})")
    print(f"  stream rate / client  {', '.join(f'{r:.3f}' for r in stream_rates)} /s   "
          f"min/depth ratio {stream_ratio:.3f} (target >= 0.97: {verdict(stream_ratio >= 0.97)})  "
          f"mean JPEG {np.mean(sizes) / 1024 if sizes else 0:.0f} KiB")
    print(f"  load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs (other work on the "
          "machine skews every figure)")
    for mode, rate, per_map, lat, mot in per_mode:
        ideal_m = camera_fps / per_map if per_map else 0.0
        med, p95 = (np.percentile(lat, [50, 95]) if lat else (float("nan"), float("nan")))
        print(f"  mode {mode:<8} depth rate {rate:7.3f} /s  ideal camera/{per_map} = {ideal_m:.3f} "
              f"/s  ratio {rate / ideal_m if ideal_m else 0.0:.3f};  latency median {med:6.2f} ms  "
              f"p95 {p95:6.2f} ms  (motion test {np.median(mot) if mot else float('nan'):.2f}) "
              f"n={len(lat)} (target median <= 20: {verdict(bool(lat) and med <= 20)})")
    print(f"  sets dropped (newest wins) {s1['dropped_sets'] - s0['dropped_sets']}, incomplete "
          f"{s1['incomplete_sets'] - s0['incomplete_sets']}, frames dropped "
          f"{s1['frames_dropped'] - s0['frames_dropped']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
