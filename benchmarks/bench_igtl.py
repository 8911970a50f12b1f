"""OpenIGTLink streaming on the simulator behind a real uvicorn server (issue 16's targets).

One pyigtl client (``pyigtl.OpenIGTLinkClient``) receives for ``--seconds`` while a second
client connects and never reads. Printed: the depth rate (from /api/status), the rate of
IMAGE (``FringescopeDepth``) and POLYDATA (``FringescopeCloud``) messages the reading
client received and their ratios to the depth rate (target ≥ 0.97 each), the time from
connecting to the first IMAGE (target ≤ 1 s), and the server's queued bytes and the
process's RSS over the run with the never-reading client connected (target: flat).

    python benchmarks/bench_igtl.py [--seconds 20] [--exposure-ms 30] [--data-dir data]
                                    [--calibration FILE]

Without ``--calibration`` the first run creates the simulator's calibration in DATA_DIR.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from app.core.jit import numeric_environment

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

import httpx  # noqa: E402
import pyigtl  # noqa: E402

from app.config import Settings  # noqa: E402
from app.outputs.igtl import CLOUD_DEVICE, DEPTH_DEVICE, STATUS_DEVICE, register_codecs  # noqa: E402
from benchmarks.bench_live import free_port, start_server, wait_running  # noqa: E402


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


class Arrivals(dict):  # type: ignore[type-arg]
    """pyigtl's per-device "incoming" dict, noting each message's result (by its timestamp).

    The four messages of one result share a timestamp; the STATUS message names the
    result's sequence number.
    """

    def __init__(self) -> None:
        super().__init__()
        self.stamps: dict[str, set[float]] = {}
        self.seq_of: dict[float, int] = {}
        self.lock = threading.Lock()

    def __setitem__(self, key: str, value: Any) -> None:
        with self.lock:
            self.stamps.setdefault(key, set()).add(value.timestamp)
            if key == STATUS_DEVICE:
                self.seq_of[value.timestamp] = int(json.loads(value.string)["seq"])
        super().__setitem__(key, value)

    def results(self, device: str, after_seq: int, upto_seq: int) -> int:
        """How many results ``after_seq < seq <= upto_seq`` arrived as ``device`` messages."""
        with self.lock:
            seqs = {self.seq_of.get(t) for t in self.stamps.get(device, set())}
        return sum(1 for q in seqs if q is not None and after_seq < q <= upto_seq)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--exposure-ms", type=float, default=30.0)
    ap.add_argument("--data-dir", default="data")
    ap.add_argument("--calibration", default=None,
                    help="calibration file (default: the data dir's)")
    ap.add_argument("--scene", default="intestine_flap")
    ap.add_argument("--max-points", type=int, default=100_000)
    args = ap.parse_args()
    register_codecs()

    settings = Settings(port=free_port(), igtl_port=free_port(), data_dir=Path(args.data_dir),
                        calibration_file=args.calibration, exposure_ms=args.exposure_ms,
                        viewer=False, sim_seed=1, sim_scene=args.scene,
                        igtl_max_points=args.max_points)
    server, thread = start_server(settings)
    base = f"http://127.0.0.1:{settings.port}"
    try:
        wait_running(base, timeout_s=600)
        time.sleep(2.0)  # warm-up
        igtl = server.config.app.state.igtl

        lazy = socket.create_connection(("127.0.0.1", settings.igtl_port))  # never reads
        lazy.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)

        t_connect = time.monotonic()
        client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=settings.igtl_port,
                                          start_now=False)
        arrivals = Arrivals()
        client.incoming_messages = arrivals
        client.start()
        first = client.wait_for_message(DEPTH_DEVICE, timeout=10)
        first_s = time.monotonic() - t_connect if first is not None else float("nan")

        rss: list[float] = []
        pending: list[int] = []
        with httpx.Client(base_url=base, timeout=5) as http:
            s0 = http.get("/api/status").json()
            t0 = time.monotonic()
            while time.monotonic() - t0 < args.seconds:
                rss.append(rss_mb())
                pending.append(igtl.pending_bytes())
                time.sleep(0.5)
                with arrivals.lock:  # what the client does not take is replaced; keep it small
                    dict.clear(arrivals)
            t1 = time.monotonic()
            s1 = http.get("/api/status").json()
        time.sleep(1.5)  # messages of results published before t1 still in flight
        client.stop()
        lazy.close()
    finally:
        server.should_exit = True
        thread.join(30)

    span = t1 - t0
    depth_rate = (s1["results_published"] - s0["results_published"]) / span
    q0, q1 = s0["results_published"], s1["results_published"]  # = the results' sequence numbers
    n_img = arrivals.results(DEPTH_DEVICE, q0, q1)
    n_cloud = arrivals.results(CLOUD_DEVICE, q0, q1)
    n_results = q1 - q0
    img_rate, cloud_rate = n_img / span, n_cloud / span
    half = len(rss) // 2
    print(f"window {span:.1f} s, depth maps published {n_results}, depth rate {depth_rate:.3f} /s")
    print(f"results {q0 + 1}..{q1}: of each, was an IMAGE / a POLYDATA message received?")
    print(f"IMAGE    {n_img} received, {img_rate:.3f} /s, ratio to depth rate "
          f"{n_img / max(n_results, 1):.3f} (target >= 0.97)")
    print(f"POLYDATA {n_cloud} received, {cloud_rate:.3f} /s, ratio to depth rate "
          f"{n_cloud / max(n_results, 1):.3f} (target >= 0.97)")
    print(f"first IMAGE {first_s:.3f} s after connecting (target <= 1 s)")
    print(f"server queued bytes with a never-reading client: max {max(pending) / 1e6:.2f} MB, "
          f"first half max {max(pending[:half]) / 1e6:.2f} MB, second half max "
          f"{max(pending[half:]) / 1e6:.2f} MB")
    print(f"process RSS: start {rss[0]:.1f} MB, first-half mean {sum(rss[:half]) / half:.1f} MB, "
          f"second-half mean {sum(rss[half:]) / (len(rss) - half):.1f} MB, end {rss[-1]:.1f} MB "
          "(ratio second/first half "
          f"{sum(rss[half:]) / (len(rss) - half) / (sum(rss[:half]) / half):.3f})")
    ok = (n_img >= 0.97 * n_results and n_cloud >= 0.97 * n_results and first_s <= 1.0)
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
