"""``fringescope reprocess`` with the real engine: a ``dask scheduler`` and two ``dask worker``
processes started here on 127.0.0.1 (or the embedded LocalCluster), recordings written by the
recorder's :class:`~app.capture.recording.Recording`, outputs compared byte for byte with
``fringescope reconstruct`` of each set."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from app.calib import load_calibration, save_calibration
from app.capture import CaptureSet, write_capture_set
from app.capture.recording import Recording
from app.cli import main
from app.core.schedule import PatternSchedule
from app.devices.sim.analytic_rig import Rig, bump_surface

ROOT = Path(__file__).resolve().parents[2]
DASK = Path(sys.executable).parent / "dask"
FILES = ("depth.npy", "sigma.npy", "reason.png")


def _record(root: Path, name: str, rig: Rig, n_sets: int, *, t0: float = 1.7e9) -> Path:
    """A recording as the recorder writes it: ``n_sets`` sets of a slowly rising surface."""
    rec = Recording(root, name, settings={"exposure_ms": 20.0})
    surface = bump_surface(rig)
    for i in range(n_sets):
        frames = rig.render(surface + 0.2 * i, noise=0.5, rng=np.random.default_rng(i))
        rec.add_set(CaptureSet(frames, rig.schedule, exposure_ms=10.0 + i), timestamp=t0 + 0.5 * i)
    rec.close()
    return rec.path


def _reconstruct(set_dirs: list[Path], cal: Path, out: Path, *extra: str) -> Path:
    assert main(["reconstruct", *map(str, set_dirs), "-c", str(cal), "-o", str(out), *extra]) == 0
    return out


def _same_files(a: Path, b: Path, names=FILES) -> None:
    for name in names:
        assert (a / name).read_bytes() == (b / name).read_bytes(), f"{a / name} != {b / name}"


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.update(PYTHONPATH=str(ROOT), NUMBA_THREADING_LAYER="workqueue", NUMBA_NUM_THREADS="1")
    env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))
    return env


class DaskCluster:
    """``dask scheduler`` + ``dask worker`` processes on 127.0.0.1, ports chosen free."""

    def __init__(self, tmp: Path, n_workers: int = 2) -> None:
        self.procs: list[subprocess.Popen[bytes]] = []
        sched_file = tmp / "scheduler.json"
        log = open(tmp / "dask.log", "wb")  # noqa: SIM115 - closed in stop()
        self.log = log
        self.procs.append(subprocess.Popen(
            [str(DASK), "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
             "--scheduler-file", str(sched_file)], env=_env(), stdout=log, stderr=log))
        deadline = time.monotonic() + 60
        while not sched_file.exists():
            assert time.monotonic() < deadline, (tmp / "dask.log").read_text()
            time.sleep(0.1)
        time.sleep(0.2)  # the file is written whole, but give the listener a moment
        self.address = json.loads(sched_file.read_text())["address"]
        self.workers = [subprocess.Popen(
            [str(DASK), "worker", self.address, "--host", "127.0.0.1", "--nthreads", "1",
             "--no-nanny", "--no-dashboard", "--name", f"w{i}"],
            env=_env(), stdout=log, stderr=log)
            for i in range(n_workers)]
        self.procs += self.workers
        from distributed import Client

        with Client(self.address, timeout="30s") as c:
            c.wait_for_workers(n_workers, timeout=90)

    def stop(self) -> None:
        """The workers first, then the scheduler: a worker sent SIGTERM while the scheduler
        closes too could hang in its close until killed (15 s of every teardown); with the
        scheduler still up each worker leaves in about a second."""
        scheduler = self.procs[0]
        self._terminate(self.workers)
        self._terminate([scheduler])
        self.log.close()

    @staticmethod
    def _terminate(procs: list[subprocess.Popen[bytes]]) -> None:
        """SIGTERM to every process still running, then wait for each (SIGKILL after 15 s)."""
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


@pytest.fixture
def cluster(tmp_path):
    c = DaskCluster(tmp_path)
    yield c
    c.stop()


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A 6-set 160×120 recording and its calibration."""
    tmp = tmp_path_factory.mktemp("small")
    rig = Rig()
    rec = _record(tmp / "recordings", "rec_small", rig, 6)
    cal = tmp / "calibration.json"
    save_calibration(rig.calibration(), cal)
    return rec, cal


def _table(out: Path, name: str) -> pd.DataFrame:
    return pd.read_parquet(out / name / "sets.parquet")


@pytest.mark.slow
def test_external_scheduler_matches_reconstruct_and_resumes(small, cluster, tmp_path, capsys,
                                                           monkeypatch):
    rec, cal = small
    out = tmp_path / "out"
    args = ["reprocess", str(rec), "-c", str(cal), "-o", str(out), "--scheduler", cluster.address,
            "--ply"]
    assert main(args) == 0
    summary = capsys.readouterr()
    assert summary.out.strip().splitlines()[-1].startswith(
        "reprocess: 1 recording(s), 6 set(s): 6 done, 0 reused")
    assert "6/6 sets" in summary.err and "sets/s" in summary.err and "ETA" in summary.err
    session = json.loads((rec / "session.json").read_text())
    table = _table(out, rec.name)
    assert (list(table["folder"]) == [s["folder"] for s in session["sets"]]
            and set(table["status"]) == {"done"})
    for i, s in enumerate(session["sets"]):
        got = out / rec.name / s["folder"]
        ref = _reconstruct([rec / s["folder"]], cal, tmp_path / "ref" / s["folder"])
        _same_files(got, ref, (*FILES, "points.ply"))
        depth = np.load(got / "depth.npy")
        row = table.iloc[i]
        assert row["index"] == i and row["exposure_ms"] == 10.0 + i
        assert row["valid_fraction"] == pytest.approx(np.isfinite(depth).mean())
        assert row["median_sigma_mm"] == pytest.approx(np.nanmedian(np.load(got / "sigma.npy")))
        assert row["timestamp"] == pd.Timestamp(s["timestamp"]).tz_convert(None)  # UTC
        assert row["motion_share"] == 0.0 and row["recon_ms"] > 0
        # the task thread's decoding and reconstruction CPU, parts of its process's CPU
        assert row["decode_cpu_ms"] > 0 and row["recon_cpu_ms"] > 0
        assert row["decode_cpu_ms"] + row["recon_cpu_ms"] < row["cpu_ms"]
        assert 0 < row["write_cpu_ms"] < row["cpu_ms"] - row["decode_cpu_ms"] - row["recon_cpu_ms"]
    # the second run skips every set: same digest, nothing rewritten
    stamps = {p: p.stat().st_mtime_ns for p in (out / rec.name).rglob("*")
              if p.is_file() and p.suffix != ".parquet"}
    assert main(args) == 0
    assert "0 done, 6 reused" in capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert set(_table(out, rec.name)["status"]) == {"reused"}
    # another build is another digest: its outputs are not kept (the numbers may differ)
    import app.batch.engine as engine

    monkeypatch.setattr(engine, "software_key", lambda: "a build with other numerics")
    assert main([*args, "--quiet"]) == 0
    assert set(_table(out, rec.name)["status"]) == {"done"}
    monkeypatch.undo()
    # another option is another digest: everything is redone
    assert main([*args, "--min-modulation", "200", "--quiet"]) == 0
    assert capsys.readouterr().err == ""
    assert set(_table(out, rec.name)["status"]) == {"done"}
    assert np.isnan(np.load(out / rec.name / "set_0000" / "depth.npy")).all()  # B = 90 < 200


@pytest.mark.slow
def test_a_worker_killed_mid_run_changes_nothing(cluster, tmp_path):
    """SIGKILL one of the two workers while it runs a set: the scheduler reruns its tasks on the
    other worker; the table is complete and every set equals ``reconstruct``'s."""
    from distributed import Client

    from app.batch.engine import reprocess
    from app.batch.setjob import ReconOptions

    rig = Rig(width=640, height=480, focal_px=800.0)
    rec = _record(tmp_path / "recordings", "rec_kill", rig, 16)
    cal_path = tmp_path / "calibration.json"
    save_calibration(rig.calibration(), cal_path)
    out = tmp_path / "out"
    with Client(cluster.address, timeout="30s") as watcher:
        pids = watcher.run(os.getpid)
    victim = cluster.workers[0]
    victim_addr = next(a for a, pid in pids.items() if pid == victim.pid)
    killed_while: list[str] = []

    def kill_when_busy() -> None:
        with Client(cluster.address, timeout="30s") as watcher:
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                done = (list((out / rec.name).glob("set_*/reprocess.json"))
                        if (out / rec.name).exists() else [])
                busy = watcher.processing().get(victim_addr, [])
                if done and busy:
                    victim.send_signal(signal.SIGKILL)
                    killed_while.extend(str(k) for k in busy)
                    return
                time.sleep(0.01)

    killer = threading.Thread(target=kill_when_busy)
    summary = reprocess([str(rec)], load_calibration(cal_path), str(out), ReconOptions(),
                        scheduler=cluster.address, on_submitted=lambda _c: killer.start())
    killer.join(timeout=130)
    assert killed_while, "the victim never ran a set while others were done"
    assert victim.wait(timeout=10) == -signal.SIGKILL
    assert (summary.done, summary.failed, summary.sets) == (16, 0, 16)
    table = _table(out, rec.name)
    assert list(table["index"]) == list(range(16)) and set(table["status"]) == {"done"}
    for s in sorted(p.name for p in rec.glob("set_*")):
        _same_files(out / rec.name / s, _reconstruct([rec / s], cal_path, tmp_path / "ref" / s))
    assert not [p for p in out.rglob(".*") if p.is_file()], "a temporary was left behind"


@pytest.mark.slow
def test_local_cluster_fuses_brackets_and_reports_a_failed_set(tmp_path, capsys):
    """``--workers 2`` (embedded LocalCluster, worker processes), a plain folder of sets (no
    session.json) in brackets of two; a set with a corrupt frame is a failed row, not a crash."""
    rig = Rig()
    surface = bump_surface(rig)
    folder = tmp_path / "sets"
    for i, (name, exposure) in enumerate((("a0", 5.0), ("a1", 40.0), ("b0", 5.0), ("b1", 40.0))):
        frames = rig.render(surface, amplitude=90.0 * exposure / 40.0,
                            background=110.0 * exposure / 40.0,
                            noise=0.5, rng=np.random.default_rng(i))
        write_capture_set(folder / name, CaptureSet(frames, rig.schedule, exposure_ms=exposure))
    (folder / "b1" / "frame_03.png").write_bytes(b"not a png")
    cal = tmp_path / "calibration.json"
    save_calibration(rig.calibration(), cal)
    out = tmp_path / "out"
    rc = main(["reprocess", str(folder), "-c", str(cal), "-o", str(out), "--workers", "2",
               "--bracket", "2", "--quiet"])
    assert rc == 1  # a set failed; the others are done
    assert "1 done, 0 reused, 1 failed" in capsys.readouterr().out
    table = _table(out, "sets")
    assert list(table["folder"]) == ["a0", "b0"] and list(table["status"]) == ["done", "failed"]
    assert "frame_03.png" in table.iloc[1]["error"] and np.isnan(table.iloc[1]["valid_fraction"])
    _same_files(out / "sets" / "a0",
                _reconstruct([folder / "a0", folder / "a1"], cal, tmp_path / "ref"))
    assert not (out / "sets" / "b0").exists()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.parametrize(
    "case", ["not-a-recording", "image-size", "schedule", "scheduler", "workers"])
def test_bad_input_is_one_line_and_exit_2_before_any_work(small, tmp_path, capsys, case):
    rec, cal = small
    extra: list[str] = []
    if case == "not-a-recording":
        rec = tmp_path / "empty"
        rec.mkdir()
    elif case == "image-size":
        cal = tmp_path / "cal80.json"
        save_calibration(Rig(width=80, height=60).calibration(), cal)
    elif case == "schedule":
        cal = tmp_path / "cal12.json"
        save_calibration(Rig(schedule=PatternSchedule((1, 4, 12), 4)).calibration(), cal)
    elif case == "scheduler":
        extra = ["--scheduler", f"tcp://127.0.0.1:{_free_port()}", "--timeout", "2"]
    else:
        extra = ["--workers", "0"]
    out = tmp_path / "out"
    t0 = time.monotonic()
    rc = main(["reprocess", str(rec), "-c", str(cal), "-o", str(out), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    expected = {"not-a-recording": "not a recording", "image-size": "160",
                "schedule": "finest pattern", "scheduler": "cannot connect",
                "workers": "--workers"}[case]
    assert expected in err[0]
    assert not out.exists()
    assert time.monotonic() - t0 < 30


def test_remote_storage_through_fsspec(small, tmp_path):
    """A set on an fsspec file system that is not local (``memory://``) is copied, read by the
    public reader, and its outputs are put there: the same bytes as ``reconstruct``."""
    import fsspec

    from app.batch.engine import SetTask, calibration_key, list_sets, output_digest, run_set
    from app.batch.setjob import ReconOptions

    rec, cal_path = small
    fs = fsspec.filesystem("memory")
    fs.put(str(rec / "set_0002"), "/rec/set_0002", recursive=True)
    assert list_sets("memory://rec") == ["set_0002"]
    calibration = load_calibration(cal_path)
    key = calibration_key(calibration)
    task = SetTask("rec", 0, ("set_0002",), ("memory://rec/set_0002",),
                   "memory://out/rec/set_0002", FILES,
                   output_digest(key, ReconOptions(), FILES, 1), key)
    row = run_set(task, calibration, ReconOptions())
    assert row["status"] == "done", row["error"]
    ref = _reconstruct([rec / "set_0002"], cal_path, tmp_path / "ref")
    for name in FILES:
        assert fs.cat_file(f"/out/rec/set_0002/{name}") == (ref / name).read_bytes()
    assert json.loads(fs.cat_file("/out/rec/set_0002/reprocess.json"))["digest"] == task.digest
    fs.rm("/rec", recursive=True)
    fs.rm("/out", recursive=True)


@pytest.mark.slow
def test_ctrl_c_leaves_whole_files_and_the_next_run_finishes(tmp_path):
    """SIGINT to the command's process group (a terminal's Ctrl-C) mid-run: exit 130, the table
    of the sets finished so far, no visible file half written; the next run reuses those sets
    and does the rest, every set equal to ``reconstruct``'s."""
    rig = Rig(width=640, height=480, focal_px=800.0)
    rec = _record(tmp_path / "recordings", "rec_int", rig, 24)
    cal = tmp_path / "calibration.json"
    save_calibration(rig.calibration(), cal)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "app", "reprocess", str(rec), "-c", str(cal), "-o", str(out),
           "--workers", "2", "--quiet"]
    # a terminal's command has SIGINT's default action; a suite started in the background (`make
    # test &`, nohup) passes SIGINT ignored to its children, and the command would run to the end
    proc = subprocess.Popen(cmd, cwd=ROOT, env=_env(), start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=_default_sigint)
    deadline = time.monotonic() + 120
    while not list(out.glob(f"{rec.name}/set_*/reprocess.json")):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err.decode()[-2000:]
    table = _table(out, rec.name)
    # the results the client had received
    assert len(table) < 24 and set(table["status"]) <= {"done"}
    # a worker finishes the set in its hands; such a set is whole, just not in the table
    finished = {p.parent.name for p in out.glob(f"{rec.name}/set_*/reprocess.json")}
    assert set(table["folder"]) <= finished and len(finished) < 24
    for p in out.rglob("*"):  # whatever is visible is whole: the bytes reconstruct writes
        if p.is_file() and not p.name.startswith(".") and p.suffix in (".npy", ".png"):
            ref = tmp_path / "ref" / p.parent.name
            if not ref.exists():
                _reconstruct([rec / p.parent.name], cal, ref)
            assert p.read_bytes() == (ref / p.name).read_bytes(), p
    rc = main(["reprocess", str(rec), "-c", str(cal), "-o", str(out), "--workers", "2", "--quiet"])
    assert rc == 0
    table2 = _table(out, rec.name)
    assert len(table2) == 24 and set(table2[table2["status"] == "reused"]["folder"]) == finished
    for s in sorted(p.name for p in rec.glob("set_*")):
        ref = tmp_path / "ref" / s
        if not ref.exists():
            _reconstruct([rec / s], cal, ref)
        _same_files(out / rec.name / s, ref)
    assert not [p for p in out.rglob(".*") if p.is_file()], "a temporary was left behind"


def test_a_rerun_stopped_among_the_writes_is_not_taken_as_finished(small, tmp_path):
    """Redoing a set with other options drops its digest before the first write: a run that
    stops among the writes (here a folder stands where sigma.npy goes) leaves a set that the
    next run does again, for either options, never one with mixed files marked done."""
    from app.batch.engine import plan, run_set
    from app.batch.setjob import ReconOptions

    rec, cal_path = small
    calibration = load_calibration(cal_path)
    out = tmp_path / "out"
    first, other = ReconOptions(), ReconOptions(min_modulation=200.0)
    task = plan([str(rec)], calibration, str(out), first)[0].todo[0]
    assert run_set(task, calibration, first)["status"] == "done"
    again = plan([str(rec)], calibration, str(out), first)[0]
    assert [r["folder"] for r in again.reused] == [task.folders[0]]
    folder = out / rec.name / task.folders[0]
    (folder / "sigma.npy").unlink()
    (folder / "sigma.npy").mkdir()
    row = run_set(plan([str(rec)], calibration, str(out), other)[0].todo[0], calibration, other)
    assert row["status"] == "failed" and "sigma.npy" in row["error"]
    assert np.isnan(np.load(folder / "depth.npy")).all()  # the other options' depth is written
    for options in (first, other):
        redo = plan([str(rec)], calibration, str(out), options)[0]
        assert task.folders[0] in [t.folders[0] for t in redo.todo] and not redo.reused


_FAULTS = """
import resource, sys
import numpy as np
from app.batch.engine import one_core_per_task
import numba
if sys.argv[1] == "worker":
    one_core_per_task()
    assert numba.get_num_threads() == 1, numba.get_num_threads()
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(2):  # as one set after another: a 20 MB array made, filled and freed
    a = np.ones(20 * 2**20, np.uint8); del a
f0 = faults()
for _ in range(5):
    a = np.ones(20 * 2**20, np.uint8); del a
print(faults() - f0)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux")
                    or os.confstr("CS_GNU_LIBC_VERSION") is None, reason="glibc's mallopt")
def test_a_worker_reuses_freed_memory_under_dasks_trim_threshold():
    # Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536: without the task's set-up
    # every large array is mapped and faulted in afresh (per 20 MB 5120 faults, or 10 in huge
    # pages); with it the heap keeps and reuses them
    env = {**_env(), "MALLOC_TRIM_THRESHOLD_": "65536", "NUMBA_NUM_THREADS": "2"}
    faults = {}
    for mode in ("plain", "worker"):
        out = subprocess.run([sys.executable, "-c", _FAULTS, mode], env=env, capture_output=True,
                             text=True, timeout=120, check=True)
        faults[mode] = int(out.stdout.split()[-1])
    assert faults["plain"] >= 5 * 10, faults
    assert faults["worker"] * 20 < faults["plain"], faults


def test_the_software_key_follows_the_code_that_makes_outputs(tmp_path):
    """The digest's software part changes with any source file of the listed parts, and
    only with those (a change to the web API does not redo a recording)."""
    from app.batch.engine import source_digest

    (tmp_path / "recon").mkdir()
    (tmp_path / "api").mkdir()
    (tmp_path / "recon" / "phase.py").write_text("STEPS = 4\n")
    (tmp_path / "atomic.py").write_text("pass\n")
    (tmp_path / "api" / "routes.py").write_text("pass\n")
    parts = ("atomic.py", "recon")
    before = source_digest(tmp_path, parts)
    (tmp_path / "api" / "routes.py").write_text("ROUTES = 2\n")
    assert source_digest(tmp_path, parts) == before
    (tmp_path / "recon" / "phase.py").write_text("STEPS = 5\n")
    changed = source_digest(tmp_path, parts)
    assert changed != before
    (tmp_path / "recon" / "phase.py").rename(tmp_path / "recon" / "wrap.py")
    assert source_digest(tmp_path, parts) not in (before, changed)  # a path is part of it
