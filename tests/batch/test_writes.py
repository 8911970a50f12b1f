"""How a set's outputs reach the disk: the .npy bytes ``np.save`` writes, every file whole
under its name, and the syncs resumption needs (the data synced before the digest that
marks the set done; the digest itself not), seen in the real system calls (strace)."""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import BinaryIO

import numpy as np
import pytest

from app.atomic import write_direct
from app.batch.engine import write_files
from app.batch.setjob import write_npy

ROOT = Path(__file__).resolve().parents[2]
DATA = ("depth.npy", "sigma.npy", "reason.png")


@pytest.mark.parametrize("values", [
    np.random.default_rng(0).random((1032, 1384), dtype=np.float32),
    np.full((3, 4), np.nan, np.float32),
    np.zeros((0, 3), np.float32),
    np.ones((), np.float64),
    np.arange(12, dtype=">i4"),
    np.asfortranarray(np.arange(12, dtype=np.float32).reshape(3, 4)),
    np.arange(24, dtype=np.float32).reshape(4, 6)[:, ::2],
], ids=["camera", "nan", "empty", "0-d", "big-endian", "fortran", "strided"])
def test_write_npy_writes_np_saves_bytes(values, tmp_path):
    expected = io.BytesIO()
    np.save(expected, values, allow_pickle=False)
    in_memory = io.BytesIO()
    write_npy(in_memory, values)
    with open(tmp_path / "buffered.npy", "wb") as fh:
        write_npy(fh, values)
    with open(tmp_path / "raw.npy", "wb", buffering=0) as fh:
        write_npy(fh, values)
    with open(tmp_path / "after.bin", "wb") as fh:  # not a whole file: through the page cache
        fh.write(b"abc")
        write_npy(fh, values)
        fh.write(b"z")
    assert in_memory.getvalue() == expected.getvalue()
    assert (tmp_path / "buffered.npy").read_bytes() == expected.getvalue()
    assert (tmp_path / "raw.npy").read_bytes() == expected.getvalue()
    assert (tmp_path / "after.bin").read_bytes() == b"abc" + expected.getvalue() + b"z"


def test_write_direct_writes_a_whole_new_file_or_nothing(tmp_path):
    data = np.random.default_rng(1).integers(0, 256, 3 * 4096 + 77, dtype=np.uint8).tobytes()
    with open(tmp_path / "new", "wb") as fh:
        assert write_direct(fh.fileno(), (data[:100], memoryview(data)[100:]), len(data))
        assert os.lseek(fh.fileno(), 0, os.SEEK_CUR) == len(data)
        os.write(fh.fileno(), b"!")  # the descriptor writes on, buffered again
    assert (tmp_path / "new").read_bytes() == data + b"!"
    with open(tmp_path / "old", "wb") as fh:  # a file not empty is left to the caller
        fh.write(b"keep")
        fh.flush()
        assert not write_direct(fh.fileno(), (data,), len(data))
    assert (tmp_path / "old").read_bytes() == b"keep"
    with open(tmp_path / "bad", "wb") as fh, pytest.raises(ValueError, match="^size_bytes"):
        write_direct(fh.fileno(), (data,), len(data) + 1)


def _writer(data: bytes):
    def write(fh: BinaryIO) -> None:
        fh.write(data)
    return write


def test_a_failed_write_keeps_every_old_file_and_leaves_no_temporary(tmp_path):
    """The files are renamed only once all of them are written: a writer that fails leaves
    the folder as it was."""
    folder = tmp_path / "set"
    write_files(str(folder), [(n, _writer(b"old " + n.encode())) for n in DATA])

    def broken(fh: BinaryIO) -> None:
        fh.write(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space"):
        write_files(str(folder), [("depth.npy", _writer(b"new")), ("sigma.npy", broken),
                                  ("reason.png", _writer(b"new"))])
    assert sorted(p.name for p in folder.iterdir()) == sorted(DATA)
    for n in DATA:
        assert (folder / n).read_bytes() == b"old " + n.encode()


_JOB = """
import sys
from app.batch.engine import plan, run_set
from app.batch.setjob import ReconOptions
from app.calib import load_calibration
rec, cal, out, modulation = sys.argv[1:5]
calibration = load_calibration(cal)
options = ReconOptions(min_modulation=float(modulation))
task = plan([rec], calibration, out, options)[0].todo[0]
row = run_set(task, calibration, options)
assert row["status"] == "done", row["error"]
"""

_CALL = re.compile(r"^\d+\s+(\w+)\((.*)\)\s+=\s+(-?\d+)")


def _traced_job(tmp: Path, rec: Path, cal: Path, out: Path, modulation: float) -> list[tuple]:
    """The run_set of a child process under strace: its (call, path) events in ``out``, in
    order (``fsync`` named by the path its descriptor was opened with)."""
    log = tmp / f"strace-{modulation:g}.log"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_THREADING_LAYER": "workqueue"}
    env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))
    subprocess.run(["strace", "-f", "-qq", "-o", str(log), "-e",
                    "trace=openat,close,fcntl,fsync,fdatasync,rename,renameat,renameat2,"
                    "unlink,unlinkat", sys.executable, "-c", _JOB, str(rec), str(cal), str(out),
                    str(modulation)], env=env, check=True, timeout=300, capture_output=True)
    opened: dict[str, str] = {}
    events = []
    for line in log.read_text().splitlines():
        m = _CALL.match(line)
        if m is None:
            continue
        call, args, result = m.groups()
        paths = re.findall(r'"([^"]*)"', args)
        if call == "openat" and int(result) >= 0:
            opened[result] = paths[0]
        elif call == "close":
            opened.pop(args.strip(), None)
        elif call in ("fsync", "fdatasync") and args.strip() in opened:
            paths = [opened[args.strip()]]
        elif call == "fcntl" and "F_SETFL" in args and "O_DIRECT" in args:
            fd = args.split(",")[0].strip()
            paths = [opened[fd]] if fd in opened else []
        if paths and all(p.startswith(str(out)) for p in paths) and int(result) >= 0:
            names = tuple(os.path.basename(p) if p != str(out) else "." for p in paths)
            events.append((call, *names))
    return events


@pytest.mark.skipif(shutil.which("strace") is None, reason="needs strace")
def test_the_data_is_synced_before_the_digest_and_the_digest_is_not(tmp_path):
    """Per set: each output written to a temporary, synced, renamed; the folder synced once;
    then ``reprocess.json`` written and renamed without a sync (losing it to a power cut
    means the set is done again). A rerun with other options removes the old digest for
    good (a folder sync) before any output is replaced."""
    from app.calib import save_calibration
    from app.capture import CaptureSet, write_capture_set
    from app.devices.sim.analytic_rig import Rig, bump_surface

    probe = subprocess.run(["strace", "-qq", "-o", os.devnull, "true"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"strace cannot trace here: {probe.stderr.decode().strip()[:200]}")
    rig = Rig()
    rec = tmp_path / "rec"
    write_capture_set(rec / "set_0000", CaptureSet(
        rig.render(bump_surface(rig), noise=0.5, rng=np.random.default_rng(0)), rig.schedule,
        exposure_ms=20.0))
    cal = tmp_path / "calibration.json"
    save_calibration(rig.calibration(), cal)
    out = tmp_path / "out"
    folder = out / "rec" / "set_0000"

    events = _traced_job(tmp_path, rec, cal, folder.parent.parent, 0.0)
    events = [e for e in events if e[0] != "openat" or e[1] != "."]
    kinds = [e[0] for e in events]
    syncs = [e for e in events if e[0] in ("fsync", "fdatasync")]
    renames = [e for e in events if e[0].startswith("rename")]
    temp = {n: next(e[1] for e in events if e[0] == "openat" and e[1].startswith(f".{n}."))
            for n in (*DATA, "reprocess.json")}
    for n in DATA:  # each output synced under its temporary name, then renamed
        assert events.index(("fsync", temp[n])) < events.index((renames[0][0], temp[n], n))
    assert syncs == [("fsync", temp[n]) for n in DATA] + [("fsync", "set_0000")], syncs
    folder_sync = events.index(("fsync", "set_0000"))
    assert all(events.index(r) < folder_sync for r in renames if r[2] in DATA)
    assert folder_sync < events.index(("openat", temp["reprocess.json"]))
    assert renames[-1][1:] == (temp["reprocess.json"], "reprocess.json")
    assert kinds.count("fsync") == 4
    with open(tmp_path / "probe", "wb") as fh:  # where the file system takes direct writes,
        direct = write_direct(fh.fileno(), (b"x",), 1)
    # the arrays go past the page cache
    assert [e[1] for e in events if e[0] == "fcntl"] == (
        [temp["depth.npy"], temp["sigma.npy"]] if direct else [])
    assert json.loads((folder / "reprocess.json").read_text())["row"]["status"] == "done"

    # the same set with other options: the old digest is gone for good before any write
    again = _traced_job(tmp_path, rec, cal, folder.parent.parent, 300.0)
    unlink = next(i for i, e in enumerate(again)
                  if e[0].startswith("unlink") and e[1] == "reprocess.json")
    first_temp = next(i for i, e in enumerate(again)
                      if e[0] == "openat" and e[1].startswith(".depth.npy."))
    assert any(e == ("fsync", "set_0000") for e in again[unlink:first_temp]), again
    assert sum(e[0] == "fsync" for e in again) == 5


def test_the_row_and_the_table_give_the_writes_cpu(tmp_path):
    """``write_cpu_ms``: the task thread's CPU to encode, write, sync and rename the files, a
    part of the set's CPU beside its decoding and reconstruction; a column of the table."""
    import pandas as pd

    from app.batch.engine import plan, run_set, write_table
    from app.batch.setjob import ReconOptions
    from app.calib import load_calibration, save_calibration
    from app.capture import CaptureSet, write_capture_set
    from app.devices.sim.analytic_rig import Rig, bump_surface

    rig = Rig()
    for i in range(2):
        write_capture_set(tmp_path / "rec" / f"set_{i:04d}", CaptureSet(
            rig.render(bump_surface(rig), noise=0.5, rng=np.random.default_rng(i)),
            rig.schedule, exposure_ms=20.0))
    save_calibration(rig.calibration(), tmp_path / "calibration.json")
    calibration = load_calibration(tmp_path / "calibration.json")
    tasks = plan([str(tmp_path / "rec")], calibration, str(tmp_path / "out"), ReconOptions())
    rows = [run_set(t, calibration, ReconOptions()) for t in tasks[0].todo]
    for row in rows:
        assert row["status"] == "done", row["error"]
        assert 0 < row["write_cpu_ms"] < row["cpu_ms"] - row["decode_cpu_ms"] - row["recon_cpu_ms"]
    failed = {**rows[1], "index": 2, "status": "failed", "write_cpu_ms": float("nan")}
    table = pd.read_parquet(write_table(str(tmp_path / "out" / "rec"), [*rows, failed]))
    assert list(table["write_cpu_ms"][:2]) == [r["write_cpu_ms"] for r in rows]
    assert np.isnan(table["write_cpu_ms"][2])
