"""The Instrument: what cuts across the live pipeline and the calibration manager.

The schedule-change rules (no change while recording or calibrating), the changes the
valid-fraction watch must know of, the state and the status record live here; routers use
the parts themselves for the rest (``app.api.deps``). The live pipeline
(:mod:`app.service.pipeline`) owns the devices, the acquisition and reconstruction threads
and the latest result; the calibration manager (:mod:`app.service.calibrations`) owns the active
calibration, its store, its creation and the REST wizard's session. Threads stop on events and are
joined in :meth:`Instrument.close`.
"""

from __future__ import annotations

import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.config import Settings
from app.core.calibration import Calibration
from app.core.errors import Conflict, DeviceUnavailable, InvalidRequest
from app.core.limits import full_scale
from app.core.records import Bracket, State, Status
from app.core.schedule import PatternSchedule, schedule_by_name, schedule_name_of
from app.recon.reconstructor import SensorNoise
from app.service import calibration_store
from app.service.alarms import AlarmBoard
from app.service.calibrations import CalibrationManager
from app.service.change import ChangeService
from app.service.devices import DeviceBundle, create_devices
from app.service.pipeline import LivePipeline, PipelineConfig
from app.service.poses import TrackerPoses
from app.service.reconstruction import LiveResult
from app.service.recorder import Recorder
from app.service.schedules import rig_pixels, schedule_table, sensor_noise_of
from app.service.wizard import CalibrationWizard, sim_calibration_poses

if TYPE_CHECKING:
    from app.service.acquisition import Acquisition
    from app.service.store import LatestSlot

__all__ = ["Instrument"]


class Instrument:
    """The live instrument built from ``settings``; ``start()`` then ``close()``.

    ``poses``: the tracker's poses (written by the OpenIGTLink server), stored with each
    recorded set; None: no tracker.
    """

    def __init__(self, settings: Settings, *, devices: DeviceBundle | None = None,
                 poses: TrackerPoses | None = None) -> None:
        self.settings = settings
        config = PipelineConfig(exposure_ms=settings.exposure_ms, led=settings.led,
                                bit_depth=settings.bit_depth, rolling=settings.rolling,
                                autostart=settings.autostart,
                                motion_false_alarm_rate=settings.motion_false_alarm_rate,
                                motion_grow_px=settings.motion_grow_px,
                                gross_error_mm=settings.gross_error_mm or None,
                                noise_estimate_interval_s=settings.noise_estimate_interval_s)
        self.pipeline = LivePipeline(config, schedule_by_name(settings.schedule), devices)
        self.calibrations = CalibrationManager(settings, self.pipeline)
        self.alarms = AlarmBoard()  # faults shown until acknowledged (the recorder raises them)
        self._closed = False
        self._started = False
        self._schedule_lock = threading.Lock()
        self._noise: tuple[int, SensorNoise | None] = (-1, None)  # (raw set seq, its fitted noise)
        self._last_map_s: float | None = None  # time.monotonic() of the newest depth map
        self._warmup: dict[str, int] | None = None  # the counters at the first depth map
        # errors their part keeps without a time: (message, first seen monotonic, ISO time)
        self._seen_errors: dict[str, tuple[str, float, str | None]] = {}
        self.results.subscribe(self._on_map)
        # the change map against a reference kept in the data folder (its own thread)
        self.change = ChangeService(Path(settings.data_dir) / "reference",
                                    lambda: self.calibration)
        self.results.subscribe(self.change.on_map)
        # the status shows the recording and a schedule change waits for its end
        self.recorder = Recorder(self, min_free_mb=settings.recording_min_free_mb,
                                 pose_source=None if poses is None else poses.latest,
                                 alarms=self.alarms, changes=self.change)
        # the REST wizard's steps on the live view (the twin's board, its exposure)
        self.wizard = CalibrationWizard(settings, self.pipeline, self.calibrations,
                                        self.set_exposure)

    # -- the parts, by the names the routers, the viewer and the recorder use ----------------
    @property
    def schedule(self) -> PatternSchedule:
        """The fringe pattern schedule the instrument runs now."""
        return self.pipeline.schedule

    @property
    def acquisition(self) -> Acquisition | None:
        return self.pipeline.acquisition

    @property
    def results(self) -> LatestSlot[LiveResult]:
        return self.pipeline.results

    store = results  # the viewer's name for the latest-result slot

    @property
    def calibration(self) -> Calibration | None:
        return self.calibrations.calibration

    # -- lifecycle -----------------------------------------------------------------------
    def start(self) -> None:
        """Create the devices, start both threads, and load (or begin creating) a calibration."""
        if self._started:
            return
        self._started = True
        self.pipeline.start(self.pipeline.devices or create_devices(self.settings))
        assert self.pipeline.devices is not None
        self.calibrations.load_initial(is_sim=self.pipeline.devices.is_sim)
        self.change.start()
        self.pipeline.run()

    def close(self, timeout_s: float = 15.0) -> None:
        """Stop and join every thread, close the devices (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.recorder.stop()  # finish a running recording before the devices stop
        self.pipeline.close(timeout_s)
        self.change.close(timeout_s)
        self.calibrations.join(timeout_s)

    def threads(self) -> list[threading.Thread]:
        """The instrument's own threads (for shutdown checks)."""
        out = self.pipeline.threads() + self.change.threads()
        if (creating := self.calibrations.thread()) is not None:
            out.append(creating)
        return out

    # -- control ---------------------------------------------------------------------------
    def set_exposure(self, exposure_ms: float) -> float:
        self._changing(f"the exposure change to {exposure_ms:g} ms")
        return self.pipeline.set_exposure(exposure_ms)

    def set_led(self, led: str) -> str:
        self._changing(f"the LED change to {led}")
        return self.pipeline.set_led(led)

    def set_rolling(self, rolling: bool) -> None:
        self._changing("the mode change")
        self.pipeline.set_rolling(rolling)

    def set_bracket(self, on: bool) -> None:
        """Exposure bracketing on or off (``Conflict`` in rolling mode)."""
        self._changing(f"exposure bracketing {'on' if on else 'off'}")
        self.pipeline.set_bracket(on)

    def _bracket_status(self) -> Bracket | None:
        """The status's ``bracket`` record: exposures, who switched it on, the rate note."""
        acq, note = self.acquisition, self.pipeline.bracket_note()
        if acq is None or note is None:
            return None
        return Bracket(on=True, auto=self.pipeline.bracket_auto,
                       exposures_ms=(acq.exposure_ms, acq.bracket_long_ms), note=note)

    def _changing(self, what: str) -> None:
        """Mark a change for the valid-fraction watch (a collapse after it is a status warning)."""
        self.calibrations.observe_live()
        self.calibrations.watch.changed(what)

    # -- schedules ---------------------------------------------------------------------------
    def set_schedule(self, name: str) -> str:
        """Run the registered schedule ``name`` from the next set boundary.

        The projector and the controller get its patterns and sequence length; the active
        calibration carries over when its finest pattern is the same (else no depth, and
        the status says why).

        Raises:
            InvalidRequest: no schedule of that name.
            Conflict: a recording runs or a calibration is being made (their sets
            must share one schedule).
        """
        try:
            schedule = schedule_by_name(name)
        except ValueError as exc:
            raise InvalidRequest(str(exc)) from None
        with self._schedule_lock:
            if self.recorder.active_name is not None:
                raise Conflict(f"schedule: recording {self.recorder.active_name!r} runs; "
                               "stop it first")
            if self.calibrations.creating:
                raise Conflict("schedule: the simulator's calibration is being made with the "
                               "current schedule; wait until it is active")
            if (session := self.calibrations.session) is not None:
                raise Conflict(f"schedule: a calibration session ({len(session.poses)} poses) uses "
                               "the current schedule; cancel it (DELETE /api/calibration/session, "
                               "the wizard's Cancel) or activate its calibration first")
            self._changing(f"the schedule change to {name}")
            self.pipeline.set_schedule(schedule, self.calibrations.engine_for)
        return name

    def schedules(self) -> list[dict[str, Any]]:
        """Every registered schedule with its predicted depth σ and order-error
        rate at the rig's noise."""
        schedule = self.schedule
        top = full_scale(self.settings.bit_depth)
        _, res = self.results.latest()
        return schedule_table(rig_pixels(res, schedule, top, self._sensor_noise(schedule, top)),
                              schedule, self.calibration)

    def _sensor_noise(self, schedule: PatternSchedule, top: int) -> SensorNoise | None:
        measured = self.pipeline.reconstruction.noise.current  # what the live engine uses
        if measured is not None:
            return measured
        acq = self.acquisition
        if acq is None:
            return None
        seq, fs = acq.sets.latest()
        if fs is None or len(fs.frame_indices) != schedule.n_frames:
            return None
        if self._noise[0] != seq:
            self._noise = (seq, sensor_noise_of(fs.stack(), schedule, top))
        return self._noise[1]

    # -- results -----------------------------------------------------------------------------
    def latest_result(self) -> LiveResult:
        _, res = self.results.latest()
        if res is None:
            if self.calibrations.creating:
                raise DeviceUnavailable("no depth result yet: the calibration is being created")
            raise self.pipeline.why_no_result() or DeviceUnavailable("no depth result yet")
        return res

    # -- status ----------------------------------------------------------------------------------
    def _on_map(self, _seq: int, result: LiveResult) -> None:
        """Each published depth map (reconstruction thread): its time; the first ends warm-up."""
        self._last_map_s = result.published_s
        if self._warmup is None:
            self._warmup = self._counters()

    def _counters(self) -> dict[str, int]:
        acq = self.acquisition
        asm = acq.assembler if acq is not None else None
        return {
            "sets_completed": asm.completed if asm else 0,
            "dropped_sets": self.pipeline.queue.dropped,
            "incomplete_sets": asm.incomplete if asm else 0,
            "mixed_sets": asm.mixed if asm else 0,
            "groups_lost": asm.groups_lost if asm else 0,
            "patched_sets": asm.patched if asm else 0,
            "frames_received": acq.frames_received if acq else 0,
            "frames_dropped": acq.frames_dropped if acq else 0,
            "faults": acq.faults if acq else 0,
        }

    def _set_period_s(self) -> float:
        """One whole fringe set at the camera's frame period (measured while it runs), s."""
        acq = self.acquisition
        if acq is not None:
            frame_s = acq.frame_period_s
        else:
            frame_s = max(self.settings.exposure_ms, 1.0) / 1000.0
        return self.schedule.n_frames * frame_s

    def _depth_age_s(self, now: float) -> float | None:
        return None if self._last_map_s is None else max(0.0, now - self._last_map_s)

    def state(self) -> State:
        """starting | calibrating | running | stalled | stopped | fault (fault outranks all)."""
        return self._state_reason(time.monotonic())[0]

    def _state_reason(self, now: float) -> tuple[State, str | None]:
        """The state and, unless running, why: running only while depth maps arrive."""
        acq = self.acquisition
        if self._closed:
            return "stopped", "the instrument is shut down"
        if acq is None:
            return "starting", "opening the devices"
        devices = self.pipeline.devices
        if acq.acquiring and (acq.fault or (devices is not None and devices.faulted())):
            bad = [f"{d.name}: {d.error}" for d in (devices.describe() if devices else ())
                   if d.state == "fault"]
            return "fault", acq.fault or "; ".join(bad) or "device fault"
        if self.calibrations.creating:
            return "calibrating", self._calibration_phase()[0]
        if not acq.acquiring:
            return "stopped", "acquisition stopped (POST /api/acquisition/start)"
        period = self._set_period_s()
        if self.pipeline.bracketing:  # a map per pair: a set at each exposure (frame time ∝ it)
            period *= 1.0 + acq.bracket_long_ms / acq.exposure_ms
        age = self._depth_age_s(now)
        # a fault after the newest map: that map is from before it, so not yet running again
        faulted_since_map = acq.last_error_s is not None and (
            self._last_map_s is None or self._last_map_s <= acq.last_error_s)
        if age is not None and age <= 2 * period and not faulted_since_map:
            return "running", self.pipeline.bracket_note()  # None unless bracketing: say why slower
        if self.calibration is None:
            return "stalled", "no calibration: load one (PUT /api/calibration/file) or calibrate"
        if self.pipeline.engine_note:
            return "stalled", self.pipeline.engine_note
        if self._warmup is None and (phase := self._startup_phase()) is not None:
            return "starting", phase
        if acq.last_error_s is not None and now - acq.last_error_s <= 2 * period + 1.0:
            return "stalled", f"recovering from: {acq.last_error}"
        if acq.last_frame_s is None or now - acq.last_frame_s > 2 * period:
            return "stalled", "no frames from the camera"
        if acq.frames_since_set > acq.schedule.n_frames:
            dropped, frames = acq.dropped_since_set, acq.frames_since_set
            return "stalled", (f"no complete fringe set: the camera dropped {dropped} of the last "
                               f"{frames} frames")
        rec = self.pipeline.reconstruction
        if rec.last_error:
            return "stalled", rec.last_error
        recon_ms = rec.recon_times.median()
        if recon_ms is not None and recon_ms / 1000.0 > period:
            return "stalled", (f"depth maps are late: reconstruction takes {recon_ms:.0f} ms a "
                               "set, longer than the camera takes for one")
        return "stalled", (f"waiting for a complete fringe set: {acq.frames_since_set} frames "
                           f"since the last, {acq.dropped_since_set} of them dropped")

    def _startup_phase(self) -> str | None:
        """Before the first depth map: what the instrument is waiting for."""
        acq = self.acquisition
        if acq is None:
            return "opening the devices"
        if acq.frames_received == 0:
            return "waiting for the camera's first frame"
        if self.pipeline.reconstruction.completed == 0 and acq.assembler.completed > 0:
            # the first set is in the engine: numba compiles (or loads cached) kernels first
            return "compiling kernels for the first depth map (cached for the next start)"
        if acq.frames_since_set > 3 * acq.schedule.n_frames:
            return None  # frames come but no set does: not start-up any more, a stall
        return "waiting for the first complete fringe set"

    def _calibration_phase(self) -> tuple[str, float | None]:
        """The simulator's calibration: poses simulated so far (its work folder's), then the fit."""
        work = calibration_store.folder(self.settings)
        try:
            poses = sum(1 for _ in work.glob(".sim-calib-*/poses/pose_*"))
        except OSError:
            poses = 0
        n = sim_calibration_poses()
        if poses == 0 and (work / calibration_store.sim_file_name(self.settings)).is_file():
            return "calibrating: activating the new calibration", 0.95  # fitted, work folder gone
        if poses == 0:
            return "calibrating: simulating board poses", 0.0
        if poses < n:  # the newest folder is the one being written; the fit takes about a fifth
            return f"calibrating pose {poses} of {n}", round(0.8 * (poses - 1) / n, 3)
        return f"calibrating: fitting the depth model to {n} poses", 0.8

    def _last_error(self) -> tuple[str | None, float | None, str | None]:
        """The newest error of any part: (message, time.monotonic(), ISO time)."""
        acq, rec = self.acquisition, self.pipeline.reconstruction
        now, at = time.monotonic(), datetime.now(UTC).isoformat(timespec="milliseconds")
        sources = [("calibrations", self.calibrations.last_error),
                   ("reconstruction", rec.last_error)]
        if (devs := self.pipeline.devices) is not None:
            # a device's own fault state comes before the acquisition thread records it: the
            # status that says "fault" names it at once
            sources += [(f"device {d.name}", d.error) for d in devs.describe()
                        if d.state == "fault"]
        for source, msg in sources:
            if msg and self._seen_errors.get(source, (None,))[0] != msg:
                self._seen_errors[source] = (msg, now, at)  # first seen now (these keep no time)
        errors = list(self._seen_errors.values())
        if acq is not None and acq.last_error and acq.last_error_s is not None:
            errors.append((acq.last_error, acq.last_error_s, acq.last_error_at))
        if not errors:
            return None, None, None
        return max(errors, key=lambda e: e[1] or 0.0)

    def _phase_error_in_use(self) -> str | None:
        """Which projector-gamma table corrected the newest map, in the status's words."""
        _, newest = self.results.latest()
        if newest is None:
            return None
        # the live thread passes the table it measured from the live sets to the engine
        return {"given": "measured"}.get(newest.phase_error_source, newest.phase_error_source)

    def status(self) -> Status:
        """The status record (``GET /api/status`` is its :meth:`~Status.to_dict`)."""
        acq, rec, s = self.acquisition, self.pipeline.reconstruction, self.settings
        now = time.monotonic()
        latency, recon = rec.latencies.median(), rec.recon_times.median()
        # the error before the state: a fault between them then reads as a fault, not as a
        # running instrument with an unresolved error
        last_error, error_s, error_at = self._last_error()
        state, reason = self._state_reason(now)
        warnings = list(self.calibrations.warnings)
        n_frames = self.schedule.n_frames
        if acq is not None and acq.acquiring and acq.frames_since_set > 3 * n_frames:
            # no depth rather than depth from frames that are not gap-free groups: say why
            g = len(self.schedule.frequencies)
            warnings.append(
                f"no complete fringe set in the last {acq.frames_since_set} frames: the camera "
                f"dropped {acq.dropped_since_set} of them and each of the {g} frequency groups "
                f"needs {self.schedule.steps} consecutive frames (within 3 projector cycles)"
                if acq.dropped_since_set else
                f"no complete fringe set in the last {acq.frames_since_set} frames (pattern "
                "indices missing or out of order, or the exposure/LED changing)")
        if self.pipeline.engine_note:
            warnings.append(self.pipeline.engine_note)
        if (collapse := self.calibrations.collapse_warning()) is not None:
            warnings.append(collapse)
        if self.recorder.warning:
            warnings.append(self.recorder.warning)
        phase, progress = None, None
        if state == "calibrating":
            phase, progress = self._calibration_phase()
        elif state == "starting":
            phase = reason
        counters = self._counters()
        warmup = self._warmup or {}
        since = {k: v - warmup[k] for k, v in counters.items()} if warmup else {}
        session = self.calibrations.session
        age = self._depth_age_s(now)
        return Status(
            state=state,
            camera_fps=round(acq.camera_rate.rate(), 3) if acq else 0.0,
            depth_fps=round(rec.depth_rate.rate(), 3),
            latency_ms=None if latency is None else round(latency, 3),
            recon_ms=None if recon is None else round(recon, 3),
            exposure_ms=acq.exposure_ms if acq else s.exposure_ms,
            led=acq.led if acq else s.led,
            mode="rolling" if (acq.rolling if acq else s.rolling) else "set",
            acquiring=bool(acq and acq.acquiring),
            calibration=self.calibrations.summary(),
            devices=() if (devs := self.pipeline.devices) is None else devs.describe(),
            last_error=last_error,
            sets_completed=counters["sets_completed"],
            results_published=rec.completed,
            dropped_sets=counters["dropped_sets"],
            incomplete_sets=counters["incomplete_sets"],
            mixed_sets=counters["mixed_sets"],
            frames_received=counters["frames_received"],
            frames_dropped=counters["frames_dropped"],
            # a device fault the acquisition thread has not recorded yet counts already
            faults=counters["faults"] + int(state == "fault" and acq is not None
                                            and acq.fault is None),
            recording=self.recorder.active_name,
            bit_depth=s.bit_depth,
            schedule={"name": schedule_name_of(self.schedule), **self.schedule.to_dict(),
                      "frames_per_depth": self.schedule.n_frames,
                      "calibration_applies": (None if self.calibration is None
                                              else self.pipeline.engine_note is None)},
            warnings=tuple(warnings),
            sensor_noise={**rec.noise.describe(), "phase_error": self._phase_error_in_use()},
            state_reason=reason,
            phase=phase,
            progress=progress,
            set_period_s=round(self._set_period_s(), 4),
            last_depth_age_s=None if age is None else round(age, 3),
            last_error_at=error_at,
            last_error_resolved=None if error_s is None else bool(
                self._last_map_s is not None and self._last_map_s > error_s),
            groups_lost=counters["groups_lost"],
            patched_sets=counters["patched_sets"],
            warmup=dict(warmup),
            since_warmup=since,
            bracket=self._bracket_status(),
            calibration_session=None if session is None else {
                "board": session.board.to_dict(), "created": session.created,
                "poses": len(session.poses), "solved": session.report is not None},
            alarms=self.alarms.active(),
        )
