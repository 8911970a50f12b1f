"""The calibration manager: the store, creation (the simulator's), activation,
the REST wizard's session.

Activating a calibration installs a fresh reconstruction engine in the live pipeline;
uploaded sets are reconstructed with an engine of their own.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import numpy as np

from app.calib.fitting import CalibrationReport
from app.capture.captureset import CaptureSet
from app.config import Settings
from app.core.board import BoardSpec
from app.core.calibration import Calibration
from app.core.errors import Conflict, InvalidRequest
from app.core.limits import full_scale
from app.core.records import CalibrationSummary
from app.core.schedule import PatternSchedule, calibration_mismatch
from app.recon import ReconResult, Reconstructor
from app.recon.unwrap import LIVE_MAX_MOTION_RAD
from app.service import calibration_store
from app.service.calibration_checks import ValidFractionWatch, check_physical, dry_run_problem
from app.service.calibration_session import CalibrationSession
from app.service.pipeline import LivePipeline
from app.service.schedules import calibration_for_schedule
from app.service.sim_calibration_job import SimCalibrationJob

log = logging.getLogger("fringescope.service")


class CalibrationManager:
    """The active calibration of ``pipeline``, where it is kept, and how a new one is made."""

    def __init__(self, settings: Settings, pipeline: LivePipeline) -> None:
        self.settings = settings
        self.pipeline = pipeline
        self.calibration: Calibration | None = None
        self.name: str | None = None
        self.session: CalibrationSession | None = None
        self.warnings: list[str] = []
        self.last_error: str | None = None
        self._upload_engine: Reconstructor | None = None
        self._upload_engine_cal: Calibration | None = None
        self._upload_lock = threading.Lock()
        self._lock = threading.Lock()
        self._activate_lock = threading.Lock()  # one activation at a time: its dry run compares
        self.watch = ValidFractionWatch()
        self._creating: SimCalibrationJob | None = None

    @property
    def schedule(self) -> PatternSchedule:
        """The schedule the live pipeline runs now."""
        return self.pipeline.schedule

    # -- loading and creation ----------------------------------------------------------------
    def load_initial(self, *, is_sim: bool) -> None:
        """Load the configured / active / simulator calibration, or begin
        creating the simulator's."""
        s = self.settings
        try:
            path = calibration_store.initial_path(s)
        except ValueError as exc:
            self._error(str(exc))
            return
        if path is not None:
            try:
                cal = calibration_store.load(path)
                self.activate(cal, name=str(cal.extra.get(calibration_store.NAME_KEY, path.stem)),
                              persist=False)
                return
            except ValueError as exc:
                self._error(str(exc))
                if s.calibration_file is not None:
                    return
        if is_sim:
            self._creating = SimCalibrationJob(self.settings, self._sim_created, self._error)
            self._creating.start()
        else:
            self.warnings.append("no calibration: "
                                 "load one (PUT /api/calibration/file) or calibrate")

    def _sim_created(self, cal: Calibration) -> None:
        if self.pipeline.closed:
            return
        try:
            self.activate(cal, name="sim", persist=False)
        except ValueError as exc:
            self._error(f"simulator calibration refused: {exc}")

    @property
    def creating(self) -> bool:
        return self._creating is not None and self._creating.thread.is_alive()

    def thread(self) -> threading.Thread | None:
        return None if self._creating is None else self._creating.thread

    def join(self, timeout_s: float) -> None:
        """Stop a simulator calibration still being made (its process is terminated)."""
        if self._creating is not None:
            self._creating.cancel(timeout_s)

    # -- activation --------------------------------------------------------------------------
    def activate(self, cal: Calibration, *, name: str, persist: bool = True,
                 force: bool = False) -> None:
        """Check ``cal``, then make it active for live and uploaded sets.

        The physical checks (:func:`check_physical`) always apply; then, unless ``force``, a
        dry run on the newest frames must leave at least half the active calibration's valid
        fraction. Only then is it saved as the active one (if ``persist``) and installed.

        Raises:
            ValueError: naming the field or the dry run's figures; nothing has changed.
        """
        with self._activate_lock:
            size = self.pipeline.image_size()
            if size is not None and tuple(cal.image_size) != size:
                raise ValueError(
                    f"calibration: image size {cal.image_size[0]}x{cal.image_size[1]} does not "
                    f"match the camera's {size[0]}x{size[1]}"
                )
            check_physical(cal, self.schedule)
            engine = self._engine(cal, self.schedule)
            if not force:
                self._dry_run(engine)
            if persist:
                calibration_store.save_active(self.settings, cal, name)
            self.observe_live()
            with self._lock:
                self.calibration, self.name = cal, name
                self._upload_engine = None
                self.warnings = [w for w in self.warnings if not w.startswith("no calibration")]
                self.watch.changed(f"activating calibration {name!r}")
            self.pipeline.use_engine(engine)

    def _dry_run(self, candidate: Reconstructor) -> None:
        """``ValueError`` if ``candidate`` leaves far fewer valid pixels of the newest whole set
        than the active calibration; nothing to compare (no active one, no set yet) passes."""
        active, acq = self.calibration, self.pipeline.acquisition
        if active is None or acq is None:
            return
        _, fs = acq.sets.latest()
        if fs is None or len(fs.frame_indices) != self.schedule.n_frames:
            return
        frames = fs.stack()
        noise = self.pipeline.reconstruction.noise.current
        fractions = []
        for engine in (candidate, self._engine(active, self.schedule)):
            # the live reconstruction's noise model, passed with the call (the engine is shared)
            fractions.append(float(engine.run(frames, noise=noise).valid.mean()))
        reason = dry_run_problem(fractions[0], fractions[1], self.name)
        if reason is not None:
            log.warning("calibration refused: %s", reason)
            raise ValueError(f"calibration: {reason}")

    def observe_live(self) -> None:
        """Feed the newest live result's valid fraction to :attr:`watch`."""
        seq, res = self.pipeline.results.latest()
        # once per result: the status calls this on every poll, and a 1.4 MP mean is ~ms
        if res is not None and seq != self.watch.last_seq:
            valid = res.valid
            self.watch.observe(seq, np.count_nonzero(valid) / valid.size if valid.size else 0.0)

    def collapse_warning(self) -> str | None:
        """The status warning while the live valid fraction has collapsed after a change."""
        self.observe_live()
        return self.watch.warning()

    def _engine(self, cal: Calibration, schedule: PatternSchedule) -> Reconstructor:
        bits = self.settings.bit_depth
        # live scenes move: heterodyne orders are guarded against motion between the groups
        return Reconstructor(calibration_for_schedule(cal, schedule), fast=True,
                             max_code=None if bits == 8 else full_scale(bits),
                             max_sigma_mm=self.settings.max_sigma_mm,
                             min_modulation=self.settings.min_modulation,
                             gross_error_mm=self.settings.gross_error_mm or None,
                             order_max_motion_rad=LIVE_MAX_MOTION_RAD)

    def engine_for(self, schedule: PatternSchedule) -> tuple[Reconstructor | None, str | None]:
        """The live engine for ``schedule`` with the active calibration, or None and
        why it does not apply."""
        cal, name = self.calibration, self.name
        if cal is None:
            return None, None
        reason = calibration_mismatch(cal.pattern, schedule)
        if reason is not None:
            return None, f"calibration {name!r} does not apply to this schedule: {reason}"
        return self._engine(cal, schedule), None

    def summary(self) -> CalibrationSummary | None:
        cal = self.calibration
        if cal is None:
            return None
        w, h = cal.image_size
        lo, hi = cal.height_range_mm
        return CalibrationSummary(
            name=self.name, created=cal.created, height_range_mm=(float(lo), float(hi)),
            image_size=(int(w), int(h)), software_version=cal.software_version,
            poses=len(cal.pose_residuals), model=cal.model.name, held_out=cal.held_out,
        )

    # -- uploaded sets -----------------------------------------------------------------------
    def reconstruct(self, capture: CaptureSet) -> ReconResult:
        """Reconstruct an uploaded set with the active calibration (its own engine instance)."""
        active = self.calibration
        if active is None:
            raise Conflict("no calibration is active: load or create one first")
        try:  # a set of another schedule with the same finest pattern: the carry-over rule
            cal = calibration_for_schedule(active, capture.schedule)
            cal.check_frames(capture.frames.shape)
        except ValueError as exc:
            raise InvalidRequest(str(exc)) from None
        with self._upload_lock:
            engine = self._upload_engine
            if (engine is None or self._upload_engine_cal is not active
                    or engine.calibration.pattern != cal.pattern):
                engine = self._upload_engine = Reconstructor(cal, fast=True)
                self._upload_engine_cal = active
            return engine.run(capture.frames, max_code=capture.max_code)

    # -- the session (the REST wizard) -------------------------------------------------------
    def start_session(self, board: dict[str, Any]) -> CalibrationSession:
        try:
            spec = BoardSpec.from_dict(board)
        except (ValueError, TypeError, KeyError) as exc:
            raise InvalidRequest(f"board: {exc}") from None
        self.session = CalibrationSession(spec)
        return self.session

    def cancel_session(self) -> CalibrationSession | None:
        """End the session without a calibration; the one it ended (None if there was none)."""
        with self._lock:
            session, self.session = self.session, None
        return session

    def require_session(self) -> CalibrationSession:
        if self.session is None:
            raise Conflict("no calibration session: POST /api/calibration/session first")
        return self.session

    def capture_pose(self, timeout_s: float) -> dict[str, Any]:
        """Grab the next whole set of the current view and add it to the session."""
        session = self.require_session()
        index, pose = session.add(self.pipeline.next_capture(timeout_s))
        return {**pose.summary(index), "corner_points": pose.detection.image_points.tolist(),
                "coverage": session.coverage_dict()}

    def solve_session(self, *, robust: bool = False) -> CalibrationReport:
        """Fit the session's poses; too few or unusable poses are a Conflict with the reason."""
        session = self.require_session()
        try:
            return session.solve(robust=robust)
        except ValueError as exc:
            raise Conflict(f"calibration solve: {exc}") from None

    def activate_session(self, name: str, *, force: bool = False) -> CalibrationSummary:
        session = self.require_session()
        if session.report is None:
            raise Conflict("calibration session not solved: POST "
                           "/api/calibration/session/solve first")
        try:
            self.activate(session.report.calibration, name=name, persist=True, force=force)
        except ValueError as exc:
            raise InvalidRequest(str(exc)) from None
        with self._lock:  # done: the session ends (unless a new one replaced it meanwhile)
            if self.session is session:
                self.session = None
        summary = self.summary()
        assert summary is not None
        return summary

    def _error(self, msg: str) -> None:
        log.warning("%s", msg)
        self.last_error = msg
        self.warnings.append(msg)
