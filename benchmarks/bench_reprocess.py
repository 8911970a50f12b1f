"""Reprocessing throughput: ``fringescope reprocess``'s engine on Dask against the work itself.

N capture sets of 16 frames at 1384 × 1032 (the Grasshopper3, PNG on disk, as the recorder
writes them), a synthetic rig with a closed-form Eq. (5). Measured in this process first:
``Reconstructor.run`` alone (frames in memory, tables built), frame decoding
(``read_capture_set``), and the whole per-set job in-process (decode + noise estimate +
run + encode + atomic writes). Then sets per second through the engine with 1 and 2 local
worker processes (embedded LocalCluster) and with an external ``dask scheduler`` + 2
``dask worker`` processes on 127.0.0.1; each after one warm-up task per worker, so cluster
start-up (printed apart) and JIT/cache loading are not in the rate. Peak memory per worker:
the growth of its resident set (VmHWM, reset after the warm-up) over a batch.

Targets (issue 29): ≥ 1.7 × from 1 to 2 workers; engine overhead per set over
``Reconstructor.run`` ≤ 20 % (decoding reported apart); peak memory per worker ≤ 4 × one
set's frames. Closes with the arithmetic for 50 one-hour recordings (~7,000 sets each).
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from timing import median_ms  # noqa: E402  (benchmarks/ is the script's folder)

from app.batch.engine import connect, plan, run_tasks  # noqa: E402
from app.batch.setjob import ReconOptions, new_reconstructor, output_files, reconstruct_captures  # noqa: E402
from app.calib import load_calibration, save_calibration  # noqa: E402
from app.capture import CaptureSet, read_capture_set, write_capture_set  # noqa: E402
from app.devices.sim.analytic_rig import Rig, bump_surface  # noqa: E402
from app.recon.noise import estimate_sensor_noise  # noqa: E402

WIDTH, HEIGHT = 1384, 1032
SETS_PER_HOUR = 7000  # the figure: ~2 sets/s at the paper's schedule
RECORDINGS, MACHINES = 50, 20



def make_sets(folder: Path, n: int) -> tuple[Path, Path]:
    """``n`` set folders (two rendered scenes, copied) and the calibration file."""
    rig = Rig(width=WIDTH, height=HEIGHT, focal_px=200.0 * WIDTH / 160)
    surface = bump_surface(rig)
    rec = folder / "rec"
    for i in range(min(n, 2)):
        frames = rig.render(surface + 0.5 * i, noise=0.8, rng=np.random.default_rng(i))
        write_capture_set(rec / f"set_{i:04d}", CaptureSet(frames, rig.schedule, exposure_ms=20.0))
    for i in range(2, n):
        shutil.copytree(rec / f"set_{i % 2:04d}", rec / f"set_{i:04d}")
    cal = folder / "calibration.json"
    save_calibration(rig.calibration(), cal)
    return rec, cal


def _reset_peak() -> int:
    """On a worker: reset VmHWM to the current RSS (Linux clear_refs 5); return RSS in bytes."""
    Path("/proc/self/clear_refs").write_text("5")
    return _status_kb("VmRSS") * 1024


def _peak() -> int:
    return _status_kb("VmHWM") * 1024


def _status_kb(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"{key} not in /proc/self/status")


def engine_rate(client: Any, rec: Path, cal_path: Path, out: Path, n_workers: int) -> dict[str, float]:
    """Sets/s of a batch after a warm-up task per worker, and the peak RSS growth per worker."""
    calibration = load_calibration(cal_path)
    warm = plan([str(rec)], calibration, str(out / "warm"), ReconOptions())[0].todo[:n_workers]
    for _task, row in run_tasks(client, warm, calibration, ReconOptions()):
        assert row["status"] == "done", row["error"]
    base = client.run(_reset_peak)
    tasks = plan([str(rec)], calibration, str(out / "batch"), ReconOptions())[0].todo
    t0 = time.perf_counter()
    rows = [row for _t, row in run_tasks(client, tasks, calibration, ReconOptions())]
    wall = time.perf_counter() - t0
    assert all(r["status"] == "done" for r in rows), [r["error"] for r in rows if r["error"]]
    peak = client.run(_peak)
    growth = [peak[w] - base[w] for w in base]
    return {"rate": len(rows) / wall, "wall_s": wall, "peak_growth_mb": max(growth) / 1e6,
            "peak_rss_mb": max(peak.values()) / 1e6,
            "task_ms": statistics.mean(r["task_ms"] for r in rows),
            "cpu_ms": statistics.mean(r["cpu_ms"] for r in rows)}


def external_cluster(tmp: Path, n_workers: int) -> tuple[str, list[subprocess.Popen[bytes]]]:
    dask = Path(sys.executable).parent / "dask"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_NUM_THREADS": "1"}
    sched_file = tmp / "scheduler.json"
    log = open(tmp / "dask.log", "wb")  # noqa: SIM115 - lives as long as the processes
    procs = [subprocess.Popen([str(dask), "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(sched_file)], env=env, stdout=log, stderr=log)]
    while not sched_file.exists():
        time.sleep(0.1)
    time.sleep(0.2)
    address = json.loads(sched_file.read_text())["address"]
    procs += [subprocess.Popen([str(dask), "worker", address, "--host", "127.0.0.1", "--nthreads", "1",
                                "--no-dashboard"], env=env, stdout=log, stderr=log) for _ in range(n_workers)]
    return address, procs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sets", type=int, default=12, help="capture sets per batch (default 12)")
    parser.add_argument("--repeats", type=int, default=5, help="repeats of the in-process timings (default 5)")
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-reprocess-"))
    try:
        return _run(tmp, args.sets, args.repeats)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _run(tmp: Path, n_sets: int, repeats: int) -> int:
    print(f"bench_reprocess: {n_sets} sets of 16 frames {WIDTH}x{HEIGHT} uint8 (PNG), {os.cpu_count()} CPUs, "
          f"NUMBA_THREADING_LAYER={os.environ.get('NUMBA_THREADING_LAYER')}")
    rec, cal_path = make_sets(tmp, n_sets)
    calibration = load_calibration(cal_path)
    options = ReconOptions()
    first = rec / "set_0000"
    capture = read_capture_set(first)
    frames_mb = capture.frames.nbytes / 1e6
    base = new_reconstructor(calibration, options)

    t_run, c_run = median_ms(lambda: base.run(capture.frames, max_code=capture.max_code), repeats)
    t_decode, c_decode = median_ms(lambda: read_capture_set(first), repeats)
    t_noise, c_noise = median_ms(lambda: estimate_sensor_noise(capture.frames, capture.schedule,
                                                               max_code=capture.max_code), repeats)
    recon = reconstruct_captures([capture], calibration, options, base=base)
    files = ("depth.npy", "sigma.npy", "reason.png")
    t_encode, c_encode = median_ms(lambda: output_files(recon, options, files), repeats)
    from app.batch.engine import SetTask, calibration_key, output_digest, run_set

    key = calibration_key(calibration)
    task = SetTask("rec", 0, ("set_0000",), (str(first),), str(tmp / "inproc" / "set_0000"), files,
                   output_digest(key, options, files, 1), key)
    t_job, c_job = median_ms(lambda: run_set(task, calibration, options), repeats)
    print(f"  in-process, median of {repeats}, wall / CPU ms: Reconstructor.run {t_run:.1f} / {c_run:.1f}; "
          f"decode (read_capture_set) {t_decode:.1f} / {c_decode:.1f}; noise estimate {t_noise:.1f} / "
          f"{c_noise:.1f}; encode 3 files {t_encode:.1f} / {c_encode:.1f}; whole job (run_set, with "
          f"atomic writes) {t_job:.1f} / {c_job:.1f}")

    results: dict[str, dict[str, float]] = {}
    for n in (1, 2):
        t0 = time.perf_counter()
        with connect(None, n) as client:
            startup = time.perf_counter() - t0
            results[f"local {n}"] = r = engine_rate(client, rec, cal_path, tmp / f"local{n}", n)
        print(f"  local cluster, {n} worker(s): {r['rate']:.2f} sets/s ({r['wall_s']:.1f} s for {n_sets}), "
              f"task mean {r['task_ms']:.0f} ms wall / {r['cpu_ms']:.0f} ms CPU, start-up {startup:.1f} s, peak RSS growth per worker "
              f"{r['peak_growth_mb']:.0f} MB (RSS {r['peak_rss_mb']:.0f} MB)")
    address, procs = external_cluster(tmp, 2)
    try:
        with connect(address, None, timeout_s=60) as client:
            client.wait_for_workers(2, timeout=90)
            results["external 2"] = r = engine_rate(client, rec, cal_path, tmp / "external", 2)
        print(f"  external scheduler + 2 worker processes: {r['rate']:.2f} sets/s ({r['wall_s']:.1f} s), "
              f"task mean {r['task_ms']:.0f} ms wall / {r['cpu_ms']:.0f} ms CPU, peak RSS growth per worker {r['peak_growth_mb']:.0f} MB "
              f"(RSS {r['peak_rss_mb']:.0f} MB)")
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            p.wait(timeout=30)

    one, two = results["local 1"], results["local 2"]
    per_set_ms = 1e3 / one["rate"]
    dask_overhead = per_set_ms / one["task_ms"] - 1.0  # time between tasks: scheduling, result transfer
    # CPU per set on the worker beyond decoding and Reconstructor.run, over Reconstructor.run
    cpu_rest = one["cpu_ms"] - c_decode - c_run
    overhead = cpu_rest / c_run
    peak = max(r["peak_growth_mb"] for r in results.values())
    print(f"ratios: 2 / 1 workers {two['rate'] / one['rate']:.2f} x measured (target >= 1.7); CPU per set "
          f"2 / 1 workers {two['cpu_ms'] / one['cpu_ms']:.2f} x; external / local 2 "
          f"{results['external 2']['rate'] / two['rate']:.2f} x")
    print(f"ratios: CPU per set at 1 worker {one['cpu_ms']:.0f} ms = decode {c_decode:.0f} + run {c_run:.0f} "
          f"+ rest {cpu_rest:.0f} (noise estimate {c_noise:.0f}, encode {c_encode:.0f}, writes and Dask "
          f"{cpu_rest - c_noise - c_encode:.0f}); overhead over Reconstructor.run, decode excluded "
          f"{100 * overhead:.0f} % (target <= 20 %); decode / run {c_decode / c_run:.1f} x; worker CPU / "
          f"in-process job CPU {one['cpu_ms'] / c_job:.2f} x; wall between tasks {100 * dask_overhead:+.0f} % "
          f"of a task's wall")
    print(f"ratios: peak RSS growth per worker / one set's frames ({frames_mb:.1f} MB) "
          f"{peak / frames_mb:.1f} x (target <= 4)")
    total = RECORDINGS * SETS_PER_HOUR
    cpu_s = two["cpu_ms"] / 1e3
    load = os.getloadavg()[0]
    for label, rate in ((f"measured here (load average {load:.1f})", two["rate"]),
                        (f"CPU-bound, 2 idle cores ({cpu_s:.2f} CPU-s per set)", 2 / cpu_s)):
        hours = total / rate / 3600
        print(f"arithmetic: {RECORDINGS} one-hour recordings = {RECORDINGS} x {SETS_PER_HOUR} = {total} sets; "
              f"{label}: {rate:.2f} sets/s -> {hours:.1f} h on this machine, {hours / MACHINES:.1f} h "
              f"({60 * hours / MACHINES:.0f} min) on {MACHINES} such machines (linear; shared storage must "
              f"deliver {MACHINES * rate * 14:.0f} MB/s at 14 MB per set)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
