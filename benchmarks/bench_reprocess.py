"""Reprocessing throughput: ``fringescope reprocess``'s engine on Dask against the work itself.

N capture sets of 16 frames at 1384 × 1032 (the Grasshopper3; ``frame_XX.npy.zst`` on disk
as the recorder writes them, or PNG with ``--codec png``), a synthetic rig with a closed-form
Eq. (5). Measured in this process first, on one core as a worker runs
(:func:`app.batch.engine.one_core_per_task`): ``Reconstructor.run`` alone (frames in memory,
tables built, the set's noise fitted inside it as in every run without a given model), its
kernel with the noise given, frame decoding (``read_capture_set``, zstd and PNG), the
encoders, the table statistics, the files written as ``run_set`` writes them (temporaries
synced, renamed, the folder synced), the whole per-set job (``run_set``: decode + run +
encode + writes; printed as the sum of those parts and the rest), and the client's plan and
table. Then sets per second through the engine
with 1 and 2 local worker processes (two embedded LocalClusters, the same batch on each in
turn, ``--rounds`` times: the ratio is the median of the rounds' ratios, so the others' load
on a shared machine falls on both alike) and (not with ``--quick``) with an external
``dask scheduler`` + 2 ``dask worker`` processes on 127.0.0.1; each after one warm-up task
per worker, so cluster start-up (printed apart) and JIT/cache loading are not in the rate.
CPU per set: every process of the run (client, scheduler, the cluster's nannies and
workers; /proc), so the overhead includes Dask's own cost (the idle other cluster's
scheduler, in this process, is counted too). Peak memory per worker: the growth of its resident set
(VmHWM, reset after the warm-up) over a batch. ``/proc/loadavg`` is printed before, per
round and after: on a shared machine the CPU figures hold, the rates follow the load.

Targets (issue 29): ≥ 1.7 × from 1 to 2 workers; overhead per set over
``Reconstructor.run`` ≤ 20 % (decoding reported apart); peak memory per worker ≤ 4 × one
set's frames. Closes with the arithmetic for 50 one-hour recordings (~7,000 sets each).
``python benchmarks/bench_reprocess.py --quick`` (< 3 min) prints the rates, their ratio, the
overhead and the peak memory.
"""

from __future__ import annotations

import argparse
import os

# one BLAS thread, as Dask's nanny gives its workers: the in-process CPU figures are then a
# worker's (two spinning OpenBLAS threads made the noise fit's CPU 60 ms instead of 16)
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

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
from app.core.jit import numeric_environment  # noqa: E402

# before numba is imported: the numeric settings of the CLI (app/core/jit.py)
os.environ.update(numeric_environment(os.environ))

from timing import median_ms  # noqa: E402  (benchmarks/ is the script's folder)

from app.batch.engine import connect, one_core_per_task, plan, run_tasks  # noqa: E402
from app.batch.setjob import (  # noqa: E402
    ReconOptions,
    new_reconstructor,
    output_files,
    reconstruct_captures,
    set_statistics,
)
from app.calib import load_calibration, save_calibration  # noqa: E402
from app.capture import CaptureSet, read_capture_set, write_capture_set  # noqa: E402
from app.devices.sim.analytic_rig import Rig, bump_surface  # noqa: E402
from app.recon.noise import estimate_sensor_noise  # noqa: E402

WIDTH, HEIGHT = 1384, 1032
SETS_PER_HOUR = 7000  # the figure: ~2 sets/s at the paper's schedule
RECORDINGS, MACHINES = 50, 20



def make_sets(folder: Path, n: int, codec: str = "zstd") -> tuple[Path, Path]:
    """``n`` set folders of ``codec`` frames (two rendered scenes, copied), the calibration file."""
    rig = Rig(width=WIDTH, height=HEIGHT, focal_px=200.0 * WIDTH / 160)
    surface = bump_surface(rig)
    rec = folder / "rec"
    for i in range(min(n, 2)):
        frames = rig.render(surface + 0.5 * i, noise=0.8, rng=np.random.default_rng(i))
        write_capture_set(rec / f"set_{i:04d}", CaptureSet(frames, rig.schedule, exposure_ms=20.0),
                          codec=codec)
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


def cpu_s(pids: set[int]) -> float:
    """CPU seconds (user + system) so far of the processes ``pids`` (those still living)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        total += (int(fields[11]) + int(fields[12])) / tick
    return total


def cluster_pids(client: Any, *others: int) -> set[int]:
    """The processes of a run: this one (the client; an embedded cluster's scheduler), each
    worker and its parent (the nanny), and ``others`` (an external scheduler)."""
    workers = client.run(os.getpid)
    parents = client.run(os.getppid)
    return {os.getpid(), *workers.values(), *parents.values(), *others}


def loadavg() -> str:
    return Path("/proc/loadavg").read_text().strip()


def engine_rate(client: Any, rec: Path, cal_path: Path, out: Path,
                n_workers: int, *others: int) -> dict[str, float]:
    """Sets/s of a batch after a warm-up task per worker, the CPU per set of every process
    of the run (:func:`cluster_pids`; ``others``: an external scheduler's pid), and the peak
    RSS growth per worker."""
    calibration = load_calibration(cal_path)
    warm = plan([str(rec)], calibration, str(out / "warm"), ReconOptions())[0].todo[:n_workers]
    for _task, row in run_tasks(client, warm, calibration, ReconOptions(), batch=1):
        assert row["status"] == "done", row["error"]
    base = client.run(_reset_peak)
    tasks = plan([str(rec)], calibration, str(out / "batch"), ReconOptions())[0].todo
    pids = cluster_pids(client, *others)
    cpu0, t0 = cpu_s(pids), time.perf_counter()
    rows = [row for _t, row in run_tasks(client, tasks, calibration, ReconOptions())]
    wall, cpu = time.perf_counter() - t0, cpu_s(pids) - cpu0
    assert all(r["status"] == "done" for r in rows), [r["error"] for r in rows if r["error"]]
    peak = client.run(_peak)
    growth = [peak[w] - base[w] for w in base]
    return {"rate": len(rows) / wall, "wall_s": wall, "peak_growth_mb": max(growth) / 1e6,
            "peak_rss_mb": max(peak.values()) / 1e6,
            "task_ms": statistics.mean(r["task_ms"] for r in rows),
            "cpu_ms": statistics.mean(r["cpu_ms"] for r in rows),
            # every process of the run, per set: workers, nannies, scheduler, client
            "tree_cpu_ms": cpu * 1e3 / len(rows),
            "decode_cpu_ms": statistics.mean(r["decode_cpu_ms"] for r in rows),
            "recon_cpu_ms": statistics.mean(r["recon_cpu_ms"] for r in rows),
            "write_cpu_ms": statistics.mean(r["write_cpu_ms"] for r in rows)}


def _engine_line(r: dict[str, float]) -> str:
    return (f"{r['rate']:.2f} sets/s ({r['wall_s']:.1f} s); CPU per set {r['tree_cpu_ms']:.0f} ms "
            f"all processes (in the task {r['cpu_ms']:.0f} ms: decode {r['decode_cpu_ms']:.0f}, "
            f"noise fit + run {r['recon_cpu_ms']:.0f}, encode + write + sync "
            f"{r['write_cpu_ms']:.0f}); peak RSS growth per worker "
            f"{r['peak_growth_mb']:.0f} MB (RSS {r['peak_rss_mb']:.0f} MB)")


def external_cluster(tmp: Path, n_workers: int) -> tuple[str, list[subprocess.Popen[bytes]]]:
    """``dask scheduler`` + ``n_workers`` ``dask worker`` processes on 127.0.0.1, with the
    embedded cluster's quiet settings as environment variables (as the README says)."""
    from app.batch.engine import WORKER_CONFIG

    dask = Path(sys.executable).parent / "dask"
    spawn = "distributed.nanny.pre-spawn-environ."
    quiet = {("DASK_" + k.upper().replace(".", "__").replace("-", "_")
              if not k.startswith(spawn) else k[len(spawn):]): str(v)
             for k, v in WORKER_CONFIG.items()}
    env = {**os.environ, **quiet, "PYTHONPATH": str(ROOT), "NUMBA_NUM_THREADS": "1"}
    sched_file = tmp / "scheduler.json"
    log = open(tmp / "dask.log", "wb")  # noqa: SIM115 - lives as long as the processes
    procs = [subprocess.Popen([str(dask), "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--no-dashboard", "--scheduler-file", str(sched_file)],
                              env=env, stdout=log, stderr=log)]
    while not sched_file.exists():
        time.sleep(0.1)
    time.sleep(0.2)
    address = json.loads(sched_file.read_text())["address"]
    procs += [subprocess.Popen([str(dask), "worker", address, "--host", "127.0.0.1",
                                "--nthreads", "1", "--no-dashboard"],
                               env=env, stdout=log, stderr=log) for _ in range(n_workers)]
    return address, procs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sets", type=int, default=32, help="capture sets per batch (default 32)")
    parser.add_argument("--repeats", type=int, default=5,
                        help="repeats of the in-process timings (default 5)")
    parser.add_argument("--rounds", type=int, default=3,
                        help="batches on 1 and on 2 local workers, in turn (default 3)")
    parser.add_argument("--codec", choices=("zstd", "png"), default="zstd",
                        help="frame files of the batch (default zstd, as the recorder writes)")
    parser.add_argument("--quick", action="store_true",
                        help="24 sets, 5 repeats, 2 rounds, no external cluster (< 3 min): the "
                             "1 and 2 worker rates, their ratio, the overhead and peak memory")
    args = parser.parse_args()
    if args.quick:
        args.sets, args.repeats, args.rounds = 24, 5, 2
    tmp = Path(tempfile.mkdtemp(prefix="bench-reprocess-"))
    try:
        return _run(tmp, args.sets, args.repeats, args.rounds, args.codec,
                    external=not args.quick)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _run(tmp: Path, n_sets: int, repeats: int, rounds: int, codec: str, *,
         external: bool) -> int:
    t_start = time.perf_counter()
    print(f"bench_reprocess: {n_sets} sets of 16 frames {WIDTH}x{HEIGHT} uint8 ({codec}), "
          f"{os.cpu_count()} CPUs, "
          f"NUMBA_THREADING_LAYER={os.environ.get('NUMBA_THREADING_LAYER')}; "
          f"/proc/loadavg before: {loadavg()}")
    rec, cal_path = make_sets(tmp, n_sets, codec)
    calibration = load_calibration(cal_path)
    options = ReconOptions()
    first = rec / "set_0000"
    capture = read_capture_set(first)
    other = tmp / "other_codec"
    write_capture_set(other, capture, codec="png" if codec == "zstd" else "zstd")
    frames_mb = capture.frames.nbytes / 1e6
    one_core_per_task()  # as on a worker: the CPU figures below are one core's
    base = new_reconstructor(calibration, options)
    noise = estimate_sensor_noise(capture.frames, capture.schedule, max_code=capture.max_code)

    t_run, c_run = median_ms(lambda: base.run(capture.frames, max_code=capture.max_code),
                             repeats)
    t_kernel, c_kernel = median_ms(lambda: base.run(capture.frames, max_code=capture.max_code,
                                                    noise=noise), repeats)
    t_decode, c_decode = median_ms(lambda: read_capture_set(first), repeats)
    t_decode2, c_decode2 = median_ms(lambda: read_capture_set(other), repeats)
    recon = reconstruct_captures([capture], calibration, options, base=base)
    files = ("depth.npy", "sigma.npy", "reason.png")
    t_encode, c_encode = median_ms(lambda: output_files(recon, options, files), repeats)
    t_png, c_png = median_ms(lambda: output_files(recon, options, ("reason.png",)), repeats)
    t_stats, c_stats = median_ms(lambda: set_statistics(recon.result), repeats)
    from app.batch.engine import (
        SetTask,
        calibration_key,
        output_digest,
        run_set,
        write_files,
        write_table,
    )
    from app.batch.setjob import output_writers

    key = calibration_key(calibration)
    digest = output_digest(key, options, files, 1)
    outs = iter(range(10**6))  # a new output folder per job, as in a batch (no overwriting)
    # the files as run_set writes them: encoded, written to temporaries, synced, renamed, the
    # folder synced; less the encoding alone, the writing's own cost
    writers = list(output_writers(recon, options, files).items())
    t_write, c_write = median_ms(
        lambda: write_files(str(tmp / "writes" / f"set_{next(outs)}"), writers), repeats)
    job_rows = []  # each call's own figures: the parts below add up to the same calls' CPU
    t_job, c_job = median_ms(
        lambda: job_rows.append(run_set(
            SetTask("rec", 0, ("set_0000",), (str(first),),
                    str(tmp / "inproc" / f"set_{next(outs)}"), files, digest, key),
            calibration, options)), repeats)
    # the client's work per recording: the plan (lists the sets, reads the first) and the table
    planned = plan([str(rec)], calibration, str(tmp / "planned"), options)
    rows = [run_set(t, calibration, options) for t in planned[0].todo[:2]]
    rows = [{**rows[i % 2], "index": i} for i in range(n_sets)]
    t_plan, c_plan = median_ms(lambda: plan([str(rec)], calibration, str(tmp / "p"), options),
                               repeats)
    t_table, c_table = median_ms(lambda: write_table(str(tmp / "table"), rows), repeats)
    client_ms = (c_plan + c_table) / n_sets
    codec2 = "png" if codec == "zstd" else "zstd"
    print(f"  in-process, one core, median of {repeats}, wall / CPU ms: Reconstructor.run "
          f"{t_run:.1f} / {c_run:.1f} (of which its noise fit {c_run - c_kernel:.1f}, kernel "
          f"{c_kernel:.1f}); decode {codec} {t_decode:.1f} / {c_decode:.1f} ({codec2}: "
          f"{t_decode2:.1f} / {c_decode2:.1f}); encode 3 files {t_encode:.1f} / {c_encode:.1f} "
          f"(reason.png {t_png:.1f} / {c_png:.1f}); statistics {t_stats:.1f} / {c_stats:.1f}; "
          f"encode + write 3 files (synced, renamed) {t_write:.1f} / {c_write:.1f}; "
          f"whole job (run_set, with atomic writes) {t_job:.1f} / {c_job:.1f}; plan + table of "
          f"{n_sets} sets {c_plan:.1f} + {c_table:.1f} CPU ms ({client_ms:.2f} per set)")
    measured = job_rows[1:]  # not the warm-up call

    def job_med(key: str) -> float:
        return statistics.median(r[key] for r in measured)

    rest = statistics.median(r["cpu_ms"] - r["decode_cpu_ms"] - r["recon_cpu_ms"]
                             - r["write_cpu_ms"] for r in measured)
    print(f"  whole job, its own figures (median of {len(measured)}): {job_med('cpu_ms'):.1f} "
          f"CPU ms before its digest file = decode {job_med('decode_cpu_ms'):.1f} + noise fit "
          f"and run {job_med('recon_cpu_ms'):.1f} + encode, write, sync and rename 3 files "
          f"{job_med('write_cpu_ms'):.1f} (of which the writing {c_write - c_encode:.1f} as "
          f"measured apart) + the rest {rest:.1f} (statistics {c_stats:.1f}, the set's "
          f"metadata, the row); wall - CPU {t_job - c_job:.1f} ms (waiting for the syncs, and "
          f"for the CPU others take)")

    results: dict[str, list[dict[str, float]]] = {"local 1": [], "local 2": []}
    t0 = time.perf_counter()
    with connect(None, 1) as c1, connect(None, 2) as c2:
        print(f"  local clusters of 1 and 2 workers started in {time.perf_counter() - t0:.1f} s")
        for i in range(rounds):
            for n, client in ((1, c1), (2, c2)):
                r = engine_rate(client, rec, cal_path, tmp / f"local{n}-{i}", n)
                results[f"local {n}"].append(r)
                print(f"  round {i + 1}, local cluster, {n} worker(s): {_engine_line(r)}; "
                      f"/proc/loadavg {loadavg()}")
    ext: dict[str, float] | None = None
    if external:
        address, procs = external_cluster(tmp, 2)
        try:
            with connect(address, None, timeout_s=60) as client:
                client.wait_for_workers(2, timeout=90)
                ext = engine_rate(client, rec, cal_path, tmp / "external", 2, procs[0].pid)
            print(f"  external scheduler + 2 worker processes: {_engine_line(ext)}")
        finally:
            for p in reversed(procs):
                p.terminate()
            for p in procs:
                p.wait(timeout=30)

    def med(key: str, n: int) -> float:
        return statistics.median(r[key] for r in results[f"local {n}"])

    ratios = [b["rate"] / a["rate"]
              for a, b in zip(results["local 1"], results["local 2"], strict=True)]
    cpu1, cpu2 = med("tree_cpu_ms", 1), med("tree_cpu_ms", 2)
    rate1, rate2 = med("rate", 1), med("rate", 2)
    print(f"ratios: 2 / 1 workers {statistics.median(ratios):.2f} x measured, median of "
          f"{rounds} rounds ({', '.join(f'{x:.2f}' for x in ratios)}; medians {rate1:.2f} and "
          f"{rate2:.2f} sets/s; target >= 1.7); CPU per set (all processes) {cpu1:.0f} ms at "
          f"1 worker, {cpu2:.0f} ms at 2 ({cpu2 / cpu1:.2f} x), so with 2 idle cores "
          f"{2 * cpu1 / cpu2:.2f} x"
          + (f"; external / local 2 {ext['rate'] / rate2:.2f} x" if ext is not None else ""))
    # per set, all processes: everything beyond the decoding and the noise fit +
    # Reconstructor.run of the task thread (both from the same tasks) is the engine's
    # overhead, plus the client's plan and table (measured in-process, per set)
    for n, cpu in ((1, cpu1), (2, cpu2)):
        dec, run, task = med("decode_cpu_ms", n), med("recon_cpu_ms", n), med("cpu_ms", n)
        rest = cpu - dec - run + client_ms
        print(f"ratios: overhead over Reconstructor.run at {n} worker(s): decode excluded "
              f"{100 * rest / run:.0f} % (target <= 20 %), decode included "
              f"{100 * (rest + dec) / run:.0f} %; per set {cpu:.0f} ms CPU = decode {dec:.0f} "
              f"+ noise fit and Reconstructor.run {run:.0f} + rest {rest - client_ms:.0f} "
              f"(in the task {task - dec - run:.0f}: statistics, encoders, writes, the worker's "
              f"other threads; outside it {cpu - task:.0f}: Dask's scheduler, client, nanny and "
              f"worker between tasks) + plan and table {client_ms:.1f}")
    job_rest = c_job - c_run - c_decode
    print(f"ratios: in-process job overhead over Reconstructor.run {100 * job_rest / c_run:.0f} "
          f"% decode excluded, {100 * (job_rest + c_decode) / c_run:.0f} % included; decode "
          f"/ run {codec} {c_decode / c_run:.2f} x, {codec2} {c_decode2 / c_run:.2f} x")
    peak = max(r["peak_growth_mb"] for rs in results.values() for r in rs)
    print(f"ratios: peak RSS growth per worker / one set's frames ({frames_mb:.1f} MB) "
          f"{peak / frames_mb:.1f} x (target <= 4)")
    total = RECORDINGS * SETS_PER_HOUR
    print(f"arithmetic: per-set cost {cpu1 / 1e3:.3f} CPU-s at 1 worker, {cpu2 / 1e3:.3f} at 2 "
          f"({codec} frames, 3 files, all processes); {RECORDINGS} one-hour recordings = "
          f"{RECORDINGS} x {SETS_PER_HOUR} = {total} sets = {total * cpu2 / 1e3 / 3600:.1f} "
          f"CPU-hours")
    cores = os.cpu_count() or 1
    for label, rate in ((f"measured here, 2 workers (load {os.getloadavg()[0]:.1f})", rate2),
                        (f"CPU-bound, {cores} idle cores, one worker each", cores * 1e3 / cpu2)):
        hours = total / rate / 3600
        print(f"arithmetic: {label}: {rate:.2f} sets/s -> {hours:.1f} h on this machine, "
              f"{hours / MACHINES:.2f} h ({60 * hours / MACHINES:.0f} min) on {MACHINES} such "
              f"machines (linear; shared storage must deliver {MACHINES * rate * 14:.0f} MB/s "
              f"at 14 MB per set)")
    print(f"bench_reprocess: done in {time.perf_counter() - t_start:.0f} s; /proc/loadavg "
          f"after: {loadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
