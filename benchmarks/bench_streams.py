"""Control stays responsive while many clients stream (issue 25, item 5).

A real ``fringescope serve`` process on loopback (the simulator, a token set). First a
baseline: N pollers GET /api/status (bearer token) every POLL ms. Then, in the same run,
the load: the same pollers plus M MJPEG readers (session cookie only) and K WebSocket
readers of the depth colormap, one of which never reads. Printed: /api/status p50 and p99
in both phases and their ratio (target: p99 <= 50 ms under load), the depth rate in both
phases and its ratio (target: unchanged), and the images each stream received. The stream
readers run in a process of their own, as they would on other machines: in the pollers'
event loop, parsing 50 streams' images would delay the pollers' own reads and show up as
status latency the server never had.

    python benchmarks/bench_streams.py --calibration sim.json [--pollers 20] [--mjpeg 45]
        [--ws 5] [--baseline-s 8] [--load-s 15] [--poll-ms 250] [--json]

Without --calibration the simulator's calibration is created first (a minute or two).
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import multiprocessing
import os
import secrets
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

BOUNDARY = b"Content-Type: image/jpeg"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def percentile(values: list[float], q: float) -> float:
    """The ``q`` quantile (0-1) of ``values`` (nearest rank); NaN if empty."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q * len(ordered) + 0.5) - 1))]


async def _request(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, path: str,
                   headers: dict[str, str],
                   method: str = "GET") -> tuple[int, dict[str, str], bytes]:
    """One HTTP/1.1 request on a kept-alive connection: (status, headers, body)."""
    lines = [f"{method} {path} HTTP/1.1", "Host: 127.0.0.1", "Content-Length: 0",
             *(f"{k}: {v}" for k, v in headers.items())]
    writer.write(("\r\n".join(lines) + "\r\n\r\n").encode())
    await writer.drain()
    status = int((await reader.readline()).split()[1])
    got: dict[str, str] = {}
    while (line := await reader.readline()) not in (b"\r\n", b""):
        k, _, v = line.decode("latin-1").partition(":")
        got[k.strip().lower()] = v.strip()
    body = await reader.readexactly(int(got.get("content-length", "0")))
    return status, got, body


class Load:
    """The clients of one run and what they measured."""

    def __init__(self, port: int, token: str) -> None:
        self.port, self.token = port, token
        self.auth = {"Authorization": f"Bearer {token}"}
        self.cookie: dict[str, str] = {}
        self.latencies_ms: list[float] = []
        self.failures = 0
        self.mjpeg_images: list[int] = []
        self.ws_images: list[int] = []
        self.stop = asyncio.Event()

    async def login(self) -> None:
        reader, writer = await asyncio.open_connection("127.0.0.1", self.port)
        status, headers, _ = await _request(reader, writer, "/api/login", self.auth, "POST")
        writer.close()
        assert status == 200, status
        self.cookie = {"Cookie": headers["set-cookie"].split(";")[0]}

    async def status(self) -> dict[str, Any]:
        reader, writer = await asyncio.open_connection("127.0.0.1", self.port)
        try:
            _, _, body = await _request(reader, writer, "/api/status", self.auth)
            return dict(json.loads(body))
        finally:
            writer.close()

    async def poller(self, poll_s: float, record: asyncio.Event) -> None:
        reader, writer = await asyncio.open_connection("127.0.0.1", self.port)
        try:
            while not self.stop.is_set():
                t0 = time.perf_counter()
                status, _, _ = await _request(reader, writer, "/api/status", self.auth)
                dt_ms = 1000.0 * (time.perf_counter() - t0)
                if record.is_set():
                    self.latencies_ms.append(dt_ms)
                    self.failures += status != 200
                await asyncio.sleep(max(0.0, poll_s - dt_ms / 1000.0))
        finally:
            writer.close()

    async def mjpeg(self, index: int) -> None:
        self.mjpeg_images.append(0)
        reader, writer = await asyncio.open_connection("127.0.0.1", self.port)
        head = ["GET /api/stream/depth.mjpeg HTTP/1.1", "Host: 127.0.0.1",
                *(f"{k}: {v}" for k, v in self.cookie.items())]
        writer.write(("\r\n".join(head) + "\r\n\r\n").encode())
        await writer.drain()
        tail = b""
        try:
            while not self.stop.is_set():
                chunk = await reader.read(1 << 16)
                if not chunk:
                    break
                data = tail + chunk
                self.mjpeg_images[index] += data.count(BOUNDARY)
                tail = data[-len(BOUNDARY) + 1:]
        finally:
            writer.close()

    async def websocket(self, index: int, *, reads: bool) -> None:
        """A WebSocket reader of the colormap; ``reads=False`` completes the handshake, then
        never reads a byte (its socket buffers fill up)."""
        self.ws_images.append(0)
        reader, writer = await asyncio.open_connection("127.0.0.1", self.port)
        key = base64.b64encode(secrets.token_bytes(16)).decode()
        head = ["GET /api/stream/depth HTTP/1.1", "Host: 127.0.0.1", "Upgrade: websocket",
                "Connection: Upgrade", f"Sec-WebSocket-Key: {key}", "Sec-WebSocket-Version: 13",
                *(f"{k}: {v}" for k, v in self.cookie.items())]
        writer.write(("\r\n".join(head) + "\r\n\r\n").encode())
        await writer.drain()
        try:
            if not reads:
                await self.stop.wait()
                return
            status = await reader.readline()
            assert b" 101 " in status, status
            while (await reader.readline()) not in (b"\r\n", b""):
                pass
            while not self.stop.is_set():
                b0, b1 = await reader.readexactly(2)
                n = b1 & 0x7F
                if n == 126:
                    n = int.from_bytes(await reader.readexactly(2), "big")
                elif n == 127:
                    n = int.from_bytes(await reader.readexactly(8), "big")
                await reader.readexactly(n)
                if b0 & 0x0F == 0x2:
                    self.ws_images[index] += 1
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()


async def measure(port: int, token: str, args: argparse.Namespace) -> dict[str, Any]:
    load = Load(port, token)
    await load.login()
    record = asyncio.Event()
    tasks = [asyncio.create_task(load.poller(args.poll_ms / 1000.0, record))
             for _ in range(args.pollers)]
    await asyncio.sleep(1.0)
    base0 = (await load.status())["results_published"]
    tb = time.monotonic()
    record.set()
    await asyncio.sleep(args.baseline_s)
    record.clear()
    base = load.latencies_ms[:]
    base_fail = load.failures
    base_status = await load.status()
    base_rate = (base_status["results_published"] - base0) / (time.monotonic() - tb)
    load.latencies_ms.clear()
    load.failures = 0

    ctx = multiprocessing.get_context("spawn")
    images: Any = ctx.Queue()
    streams = ctx.Process(target=stream_readers, name="bench-stream-readers",
                          args=(port, load.cookie, args.mjpeg, args.ws, args.load_s, images))
    streams.start()
    loop = asyncio.get_running_loop()
    ready = await loop.run_in_executor(None, images.get, True, 60.0)  # every stream connected
    assert ready == "connected", ready
    await asyncio.sleep(2.0)  # every stream running
    results0 = (await load.status())["results_published"]
    t0 = time.monotonic()
    record.set()
    await asyncio.sleep(args.load_s)
    record.clear()
    load_status = await load.status()
    elapsed = time.monotonic() - t0
    load.stop.set()
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    counts = await loop.run_in_executor(None, images.get, True, 60.0)
    streams.join(10.0)
    load.mjpeg_images, load.ws_images = counts["mjpeg"], counts["ws"]
    readers = [n for i, n in enumerate(load.ws_images) if i != 0]
    return {
        "pollers": args.pollers, "mjpeg": args.mjpeg, "ws": args.ws,
        "baseline": {"n": len(base), "failures": base_fail, "p50_ms": percentile(base, 0.5),
                     "p99_ms": percentile(base, 0.99), "depth_fps": base_status["depth_fps"],
                     "results_per_s": base_rate},
        "load": {"n": len(load.latencies_ms), "failures": load.failures,
                 "p50_ms": percentile(load.latencies_ms, 0.5),
                 "p99_ms": percentile(load.latencies_ms, 0.99),
                 "depth_fps": load_status["depth_fps"],
                 "results_per_s": (load_status["results_published"] - results0) / elapsed},
        "mjpeg_images_min": min(load.mjpeg_images, default=0),
        "mjpeg_images_median": statistics.median(load.mjpeg_images) if load.mjpeg_images else 0,
        "ws_images_min": min(readers, default=0),
        "load_s": elapsed,
    }


def stream_readers(port: int, cookie: dict[str, str], n_mjpeg: int, n_ws: int, load_s: float,
                   out: Any) -> None:
    """The stream clients, in a process of their own: ``"connected"`` once every stream is
    open, then the images each received over ``load_s`` seconds, starting 2 s after that."""

    async def run() -> dict[str, list[int]]:
        load = Load(port, "")
        load.cookie = cookie
        tasks = [asyncio.create_task(load.mjpeg(i)) for i in range(n_mjpeg)]
        tasks += [asyncio.create_task(load.websocket(i, reads=i != 0)) for i in range(n_ws)]
        await asyncio.sleep(0.5)
        out.put("connected")
        await asyncio.sleep(2.0)
        load.mjpeg_images = [0] * len(load.mjpeg_images)
        load.ws_images = [0] * len(load.ws_images)
        await asyncio.sleep(load_s)
        counts = {"mjpeg": list(load.mjpeg_images), "ws": list(load.ws_images)}
        load.stop.set()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        return counts

    out.put(asyncio.run(run()))


def start_server(calibration: Path, data_dir: Path, port: int, token: str,
                 streams: int) -> subprocess.Popen[str]:
    env = dict(os.environ, FRINGESCOPE_CALIBRATION_FILE=str(calibration),
               FRINGESCOPE_VIEWER="false", FRINGESCOPE_API_TOKEN=token,
               FRINGESCOPE_SIM_SCENE="dof_target", FRINGESCOPE_EXPOSURE_MS="30",
               FRINGESCOPE_SIM_SEED="1", FRINGESCOPE_MAX_STREAMS_PER_CLIENT=str(streams),
               NUMBA_THREADING_LAYER="workqueue")
    return subprocess.Popen([sys.executable, "-m", "app", "serve", "--port", str(port),
                             "--data-dir", str(data_dir)],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)


def wait_ready(port: int, token: str, proc: subprocess.Popen[str], timeout_s: float) -> None:
    import httpx

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited: {proc.stderr.read() if proc.stderr else ''}")
        try:
            st = httpx.get(f"http://127.0.0.1:{port}/api/status",
                           headers={"Authorization": f"Bearer {token}"}, timeout=5).json()
            if st.get("results_published", 0) >= 2:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    raise RuntimeError(f"no live results within {timeout_s:.0f} s")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--calibration", type=Path, default=None,
                   help="calibration file (default: create the sim's)")
    p.add_argument("--pollers", type=int, default=20)
    p.add_argument("--mjpeg", type=int, default=45)
    p.add_argument("--ws", type=int, default=5, help="WebSocket readers, the first never reading")
    p.add_argument("--baseline-s", type=float, default=8.0)
    p.add_argument("--load-s", type=float, default=15.0)
    p.add_argument("--poll-ms", type=float, default=250.0, help="each poller's period")
    p.add_argument("--json", action="store_true", help="also print the figures as one JSON line")
    args = p.parse_args(argv)
    token = secrets.token_urlsafe(24)
    with tempfile.TemporaryDirectory(prefix="bench-streams-") as tmp:
        calibration = args.calibration
        if calibration is None:
            from app.calib.calibration import save_calibration
            from app.config import Settings
            from app.service.calibration_store import create_sim_calibration

            calibration = Path(tmp) / "sim.json"
            sim_settings = Settings(data_dir=Path(tmp) / "cal", sim_seed=0)
            save_calibration(create_sim_calibration(sim_settings), calibration)
        port = free_port()
        proc = start_server(calibration, Path(tmp) / "data", port, token, args.mjpeg + args.ws + 2)
        try:
            wait_ready(port, token, proc, 300)
            fig = asyncio.run(measure(port, token, args))
        finally:
            proc.terminate()
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
    b, lo = fig["baseline"], fig["load"]
    print(f"/api/status, {args.pollers} pollers every {args.poll_ms:.0f} ms")
    print(f"  baseline:   p50 {b['p50_ms']:7.1f} ms  p99 {b['p99_ms']:7.1f} ms  "
          f"({b['n']} requests, {b['failures']} failed)  depth maps {b['results_per_s']:.2f}/s")
    print(f"  + {args.mjpeg} MJPEG, {args.ws} WebSocket (1 never reading):")
    print(f"              p50 {lo['p50_ms']:7.1f} ms  p99 {lo['p99_ms']:7.1f} ms  ({lo['n']} "
          f"requests, {lo['failures']} failed)  depth maps {lo['results_per_s']:.2f}/s")
    print(f"  ratio load/baseline: p50 {lo['p50_ms'] / b['p50_ms']:.2f}  p99 "
          f"{lo['p99_ms'] / b['p99_ms']:.2f}  depth rate "
          f"{lo['results_per_s'] / b['results_per_s']:.2f}" if b["results_per_s"] else "")
    print(f"  images per MJPEG reader in {fig['load_s']:.1f} s: min {fig['mjpeg_images_min']}, "
          f"median {fig['mjpeg_images_median']}; per reading WebSocket: min {fig['ws_images_min']}")
    print(f"  target p99 <= 50 ms under load: {'met' if lo['p99_ms'] <= 50.0 else 'NOT met'}")
    if args.json:
        print(json.dumps(fig))
    return 0


if __name__ == "__main__":
    sys.exit(main())
