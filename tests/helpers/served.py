"""``fringescope serve`` as its own process on loopback, its output logged to a file.

The log is a file, never a pipe: a pipe nobody reads fills (64 KiB, ~600 access-log lines
of a fast status poller) and then blocks the server's event loop on its next log line.
"""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (the kernel's pick for port 0)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ServedApp:
    """One ``python -m app serve`` process; stdout and stderr go to ``log_path``."""

    def __init__(self, args: Sequence[str], env: Mapping[str, str], log_path: Path,
                 wrap: Sequence[str] = ()) -> None:
        self.log_path = log_path
        cmd = [sys.executable, "-m", "app", "serve", *args]
        with open(log_path, "w", encoding="utf-8") as log:
            # the child holds its own copy of the descriptor: ours can close at once
            self.proc = subprocess.Popen([*wrap, *cmd], env=dict(env), stdout=log,
                                         stderr=subprocess.STDOUT, text=True)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def running(self) -> bool:
        return self.proc.poll() is None

    def log(self, tail_chars: int = 4000) -> str:
        """The last ``tail_chars`` characters the server wrote."""
        return self.log_path.read_text(encoding="utf-8", errors="replace")[-tail_chars:]

    def stop(self, timeout_s: float = 60.0) -> int:
        """Ctrl-C, then wait; killed if it has not exited after ``timeout_s``. The exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode
