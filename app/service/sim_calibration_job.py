"""The simulator's calibration made in a child process, so that closing the service stops it.

A fit cannot be interrupted inside a thread: shutting the service down during the first start
waited for it (up to two minutes). In a process of its own it is terminated instead, and its
half-made work folder removed; the calibration file itself is written atomically, so a
terminated job leaves either the whole file or none.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import shutil
import threading
import time
from collections.abc import Callable
from multiprocessing.queues import SimpleQueue

from app.config import Settings
from app.core.calibration import Calibration
from app.service import calibration_store

log = logging.getLogger("fringescope.service")

#: seconds a terminated child is given to exit before it is killed
_TERMINATE_WAIT_S = 5.0


def _create_in_child(settings: Settings, errors: SimpleQueue[str]) -> None:
    """The child's work: simulate, fit and store the calibration; report a failure's text."""
    try:
        calibration_store.create_sim_calibration(settings)
    except BaseException as exc:  # the parent only sees the exit code and this line
        errors.put(f"{type(exc).__name__}: {exc}")
        raise SystemExit(1) from None


class SimCalibrationJob:
    """Creates the simulator's calibration in a spawned process and hands it to ``on_done``.

    ``on_done`` runs on the job's watcher thread with the loaded calibration; ``on_error`` with
    one line saying why there is none. Neither runs after :meth:`cancel`.
    """

    def __init__(
        self,
        settings: Settings,
        on_done: Callable[[Calibration], None],
        on_error: Callable[[str], None],
    ) -> None:
        self.settings = settings
        self._on_done = on_done
        self._on_error = on_error
        self._cancelled = threading.Event()
        ctx = mp.get_context("spawn")  # fork would copy the service's threads' locks
        self._errors: SimpleQueue[str] = ctx.SimpleQueue()
        self._process = ctx.Process(
            target=_create_in_child, args=(settings, self._errors),
            name="fringescope-calibrate", daemon=True,
        )
        self._thread = threading.Thread(target=self._watch, name="fringescope-calibrate",
                                        daemon=True)
        self._started_at = 0.0

    def start(self) -> None:
        self._started_at = time.time()
        self._process.start()
        self._thread.start()

    @property
    def thread(self) -> threading.Thread:
        return self._thread

    def _watch(self) -> None:
        self._process.join()
        if self._cancelled.is_set():
            return
        if self._process.exitcode != 0:
            why = self._errors.get() if not self._errors.empty() else (
                f"the calibration process ended with code {self._process.exitcode}"
            )
            self._on_error(f"simulator calibration failed: {why}")
            return
        folder = calibration_store.folder(self.settings)
        path = folder / calibration_store.sim_file_name(self.settings)
        try:
            cal = calibration_store.load(path)
        except ValueError as exc:
            self._on_error(f"simulator calibration failed: {exc}")
            return
        self._on_done(cal)

    def cancel(self, timeout_s: float) -> None:
        """Stop the child (terminate, then kill), remove its work folder, join the watcher."""
        self._cancelled.set()
        if self._process.is_alive():
            log.info("stopping the simulator's calibration")
            self._process.terminate()
            self._process.join(_TERMINATE_WAIT_S)
            if self._process.is_alive():
                self._process.kill()
                self._process.join(_TERMINATE_WAIT_S)
            self._remove_work_folders()
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    def _remove_work_folders(self) -> None:
        """The terminated child's ``.sim-calib-*`` folders (made after this job started)."""
        out = calibration_store.folder(self.settings)
        for work in out.glob(calibration_store.WORK_FOLDER_PREFIX + "*"):
            try:
                if work.is_dir() and work.stat().st_mtime >= self._started_at - 1.0:
                    shutil.rmtree(work, ignore_errors=True)
            except OSError:
                pass
