#!/usr/bin/env python3
"""Run a command and print the peak memory of its whole process tree.

    python scripts/peak_tree_rss.py [--interval-s 0.5] [--log FILE] -- COMMAND [ARG ...]

Every ``--interval-s`` it sums, over the command and every process descended from it (pytest
workers, servers, browsers, builds), the resident set (``VmRSS``) and the proportional set
size (``Pss`` of ``/proc/PID/smaps_rollup``: a page shared by k processes counts 1/k, so
forked workers and browser processes are not counted twice). At the end it prints the
peaks, the processes at the PSS peak, the wall time and the 1-minute load average seen
(what else the machine ran). A process once seen in the tree stays counted after its
parent exits (a daemon reparented to init); one that detaches before the first sample that
would see it is missed. Exit code: the command's. Linux only (/proc).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO


@dataclass
class Sample:
    """One look at the tree: summed sizes in kB and the sizes of each process."""

    t_s: float
    rss_kb: int = 0
    pss_kb: int = 0
    procs: list[tuple[int, int, int, str]] = field(default_factory=list)  # pid, rss, pss, cmd


def _parents() -> dict[int, int]:
    """pid -> parent pid of every process now (from /proc/PID/stat)."""
    out: dict[int, int] = {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            stat = Path(entry.path, "stat").read_text()
        except OSError:
            continue
        # the command name (field 2) may hold spaces and parentheses: split after its last ')'
        out[int(entry.name)] = int(stat[stat.rindex(")") + 2 :].split()[1])
    return out


def _kb(path: str, key: str) -> int:
    """The ``key:  N kB`` value of a /proc status-like file, 0 if absent or gone."""
    try:
        with open(path, encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith(key):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


def _cmd(pid: int) -> str:
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return "?"
    return raw.replace(b"\0", b" ").decode(errors="replace").strip()[:120]


def sample(root: int, known: set[int], t_s: float) -> Sample:
    """Sum the sizes of ``root``'s tree; ``known`` (updated) holds every pid seen in it."""
    parents = _parents()
    known.intersection_update(parents)  # forget processes that ended
    known.add(root)
    grew = True
    while grew:  # a process whose parent is in the tree is in the tree
        new = {pid for pid, ppid in parents.items() if ppid in known and pid not in known}
        known.update(new)
        grew = bool(new)
    s = Sample(t_s)
    for pid in sorted(known):
        rss = _kb(f"/proc/{pid}/status", "VmRSS:")
        pss = _kb(f"/proc/{pid}/smaps_rollup", "Pss:")
        if rss or pss:
            s.rss_kb += rss
            s.pss_kb += pss
            s.procs.append((pid, rss, pss, _cmd(pid)))
    return s


def _load1() -> float:
    try:
        return float(Path("/proc/loadavg").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return float("nan")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--interval-s", type=float, default=0.5)
    parser.add_argument("--log", type=Path, help="write one line a sample: t_s rss_mb pss_mb n")
    parser.add_argument("command", nargs=argparse.REMAINDER)
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("no command given (put it after --)")
    if not args.interval_s > 0:
        parser.error("--interval-s must be > 0")
    log: TextIO | None = open(args.log, "w", encoding="utf-8") if args.log else None  # noqa: SIM115
    t0 = time.monotonic()
    proc = subprocess.Popen(command)
    known: set[int] = set()
    peak_rss = Sample(0.0)
    peak_pss = Sample(0.0)
    loads: list[float] = []
    try:
        while True:
            done = proc.poll() is not None
            s = sample(proc.pid, known, time.monotonic() - t0) if not done else None
            if s is not None:
                peak_rss = s if s.rss_kb > peak_rss.rss_kb else peak_rss
                peak_pss = s if s.pss_kb > peak_pss.pss_kb else peak_pss
                loads.append(_load1())
                if log is not None:
                    log.write(f"{s.t_s:.1f}\t{s.rss_kb / 1024:.0f}\t{s.pss_kb / 1024:.0f}"
                              f"\t{len(s.procs)}\n")
                    log.flush()
            if done:
                break
            time.sleep(args.interval_s)
    except KeyboardInterrupt:
        proc.wait()
    finally:
        if log is not None:
            log.close()
    wall_s = time.monotonic() - t0
    mean_load = sum(loads) / len(loads) if loads else float("nan")
    print(f"peak_tree_rss: wall {wall_s:.0f} s ({wall_s / 60:.1f} min), exit {proc.returncode}",
          file=sys.stderr)
    print(f"peak_tree_rss: peak summed RSS {peak_rss.rss_kb / 1024:.0f} MB at {peak_rss.t_s:.0f} s"
          f"; peak summed PSS {peak_pss.pss_kb / 1024:.0f} MB at {peak_pss.t_s:.0f} s"
          f" ({len(peak_pss.procs)} processes)", file=sys.stderr)
    max_load = max(loads, default=float("nan"))
    print(f"peak_tree_rss: load average (1 min) mean {mean_load:.2f}, max {max_load:.2f}"
          f" over {len(loads)} samples", file=sys.stderr)
    for pid, rss, pss, cmd in sorted(peak_pss.procs, key=lambda p: -p[2])[:8]:
        print(f"peak_tree_rss:   {pid:>7} rss {rss / 1024:6.0f} MB pss {pss / 1024:6.0f} MB  {cmd}",
              file=sys.stderr)
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
