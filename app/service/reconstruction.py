"""The reconstruction thread: sets from a newest-wins queue → depth results in a slot.

Pipelined with acquisition: while the camera exposes the next set, the last one is
reconstructed, so the depth rate is bounded by the camera as long as one
reconstruction takes less than one set's acquisition.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import numpy as np
import numpy.typing as npt

from app.recon import ReconResult, Reconstructor
from app.recon.fusion import fuse_exposures
from app.recon.model_sigma import ModelSigmaTable
from app.recon.motion import MotionTest, map_time
from app.recon.points import LazyPoints, PointRays
from app.recon.reconstructor import PhaseErrorSource, split_noise
from app.recon.sensor import NoiseSource, SensorNoise
from app.service.framesets import FrameSet
from app.service.priority import lower_this_threads_priority
from app.service.sensor_noise import LiveNoise
from app.service.store import LatestSlot, NewestQueue, RateMeter, RecentValues

log = logging.getLogger("fringescope.service.reconstruction")

@dataclass
class LiveResult:
    """One published depth map with its provenance.

    Arrays as ``ReconResult``: depth (H, W) f32 mm NaN-invalid, points (H, W, 3) f32 mm,
    valid (H, W) bool, reason (H, W) uint8, texture/modulation (H, W) f32 in sensor units.
    ``sigma`` (H, W) f32 total 1-σ depth uncertainty (noise ⊕ calibration), mm, NaN invalid
    (None when not computed); its parts :attr:`sigma_noise` and :attr:`sigma_model` (from
    ``model_sigma``, the calibration's σ table, on access).
    ``motion`` (H, W) bool: pixels whose frequency groups disagree beyond the sensor noise
    (:mod:`app.recon.motion`; invalid with reason MOTION unless saturated), in both modes.
    ``noise``: the camera noise model the engine used (the measured one once there is one).
    Times: ``received_s`` is when the newest frame arrived, ``published_s`` when the result
    was ready (``time.monotonic``); ``latency_ms`` their difference. ``map_time_s`` is the
    instant the depth stands for, on the frames' timestamp clock: the mid time of the finest
    frequency's group (see :func:`app.recon.motion.map_time`).
    """

    depth: npt.NDArray[np.float32]
    valid: npt.NDArray[np.bool_]
    reason: npt.NDArray[np.uint8]
    texture: npt.NDArray[np.float32]
    modulation: npt.NDArray[np.float32]
    motion: npt.NDArray[np.bool_] | None
    mode: str
    frame_indices: list[int]
    timestamps: list[float]
    exposure_ms: float
    led: str
    full_scale: float
    received_s: float
    published_s: float
    recon_ms: float
    #: given, or made from ``depth`` and ``point_rays`` on the first read (as ReconResult's)
    points: LazyPoints = LazyPoints()
    point_rays: PointRays | None = None
    created: str = field(
        default_factory=lambda: datetime.now(UTC).isoformat(timespec="milliseconds"))
    seq: int = 0
    sigma: npt.NDArray[np.float32] | None = None
    map_time_s: float = float("nan")
    moved_pixels: int = 0
    motion_ms: float = 0.0
    scene_moved: bool = False
    uncertain_moving_pixels: int = 0
    noise: SensorNoise | None = None
    noise_source: NoiseSource = "given"  # or "set"/"nominal": the engine's own until measured
    #: the projector-gamma table the set was corrected with (``given``: the live sets' own,
    #: :meth:`LiveNoise.phase_error`)
    phase_error_source: PhaseErrorSource = "none"
    #: exposure bracketing: the two sets' exposures (ms) this map fuses (None: one set)
    bracket_exposures_ms: tuple[float, float] | None = None
    model_sigma: ModelSigmaTable | None = None
    _cache: dict[Any, bytes] = field(default_factory=dict, repr=False)
    _cache_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    # (the objects they were computed from, {"model"/"noise": the part}): see _sigma_part
    _sigma_cache: tuple[tuple[Any, ...], dict[str, npt.NDArray[np.float32] | None]] | None = (
        field(default=None, repr=False))
    _sigma_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def sigma_model(self) -> npt.NDArray[np.float32] | None:
        """The calibration's part of ``sigma``, mm, NaN invalid (0 where it carries none);
        read-only, computed once per result (see :meth:`_sigma_part`)."""
        return self._sigma_part("model")

    @property
    def sigma_noise(self) -> npt.NDArray[np.float32] | None:
        """The sensor-noise part of ``sigma``, mm, NaN invalid; read-only, computed once."""
        return self._sigma_part("noise")

    def _sigma_part(self, part: str) -> npt.NDArray[np.float32] | None:
        """σ_model (``part`` "model") or σ_noise ("noise"), evaluated on the first access and
        kept: the change thread, the recorder and REST each ask for them per map. The cache is
        keyed on the very objects ``depth``, ``sigma`` and ``model_sigma`` it was computed
        from, so a result whose field is replaced afterwards (a fused or edited result) is
        evaluated afresh; the parts are read-only, so no reader changes what the next gets.
        Without a σ table σ_noise is ``sigma`` itself (a read-only view: nothing to split)."""
        key = (self.depth, self.sigma, self.model_sigma)
        with self._sigma_lock:
            got = self._sigma_cache
            if got is None or not all(a is b for a, b in zip(got[0], key, strict=True)):
                got = self._sigma_cache = (key, {})
            parts = got[1]
            if part in parts:
                return parts[part]
            out: npt.NDArray[np.float32] | None = None
            table = self.model_sigma
            if self.sigma is not None:
                if table is None:
                    out = self.sigma.view() if part == "noise" else np.where(
                        np.isfinite(self.sigma), np.float32(0.0), np.float32(np.nan)
                    ).astype(np.float32)
                elif part == "noise":
                    model = parts.get("model")
                    if model is None:
                        model = parts["model"] = table.sigma_mm(self.depth)
                        model.setflags(write=False)
                    out = split_noise(self.sigma, model)
                else:
                    out = table.sigma_mm(self.depth)
                out.setflags(write=False)
            parts[part] = out
            return out

    @property
    def latency_ms(self) -> float:
        return 1000.0 * (self.published_s - self.received_s)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.depth.shape[0]), int(self.depth.shape[1]))

    def cached(self, key: Any, make: Callable[[], bytes]) -> bytes:
        """Encode once per result and key, however many clients ask (streams share it)."""
        with self._cache_lock:
            hit = self._cache.get(key)
            if hit is None:
                hit = make()
                self._cache[key] = hit
            return hit

    def metadata(self) -> dict[str, Any]:
        return {
            "seq": self.seq, "mode": self.mode, "created": self.created,
            "exposure_ms": self.exposure_ms, "led": self.led,
            "frame_indices": self.frame_indices, "timestamps": self.timestamps,
            "latency_ms": round(self.latency_ms, 3), "recon_ms": round(self.recon_ms, 3),
            "valid_fraction": float(self.valid.mean()) if self.valid.size else 0.0,
            "map_time": self.map_time_s if np.isfinite(self.map_time_s) else None,
            "moved_pixels": self.moved_pixels, "motion_ms": round(self.motion_ms, 3),
            "scene_moved": self.scene_moved,
            "uncertain_moving_pixels": self.uncertain_moving_pixels,
            "shape": list(self.shape),
            "bracket_exposures_ms": None if self.bracket_exposures_ms is None
            else list(self.bracket_exposures_ms),
        }


class Reconstruction:
    """The reconstruction thread: takes the newest set from ``queue``, runs the engine that
    ``reconstructor()`` returns now (None: none; the set is dropped) with the measured camera
    noise and the motion test, and publishes the result in ``results``.

    Args:
        motion: the motion test run on every set (None: none).
        noise_estimate_interval_s: how often the camera's noise is measured from a set
            (:class:`~app.service.sensor_noise.LiveNoise`; 0: the engine's own model).
    """

    def __init__(
        self,
        queue: NewestQueue[FrameSet],
        reconstructor: Callable[[], Reconstructor | None],
        *,
        bit_depth: int = 8,
        motion: MotionTest | None = None,
        noise_estimate_interval_s: float = 30.0,
    ) -> None:
        if motion is not None and not isinstance(motion, MotionTest):
            raise ValueError("motion: expected a MotionTest")
        self.queue = queue
        self.reconstructor = reconstructor
        self.bit_depth = bit_depth
        self.motion = motion
        self.noise = LiveNoise(noise_estimate_interval_s)  # the camera's, measured from the sets
        self.results: LatestSlot[LiveResult] = LatestSlot()
        self.depth_rate = RateMeter()
        self.latencies = RecentValues(100)
        self.recon_times = RecentValues(100)
        self.completed = 0
        self.last_error: str | None = None
        #: exposure bracketing (set mode): a map only from two consecutive sets of different
        #: exposures, fused per pixel (app.recon.fusion); the first of a pair waits here
        self.bracket = False
        self._bracket_first: tuple[FrameSet, ReconResult, float] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fringescope-reconstruction",
                                        daemon=True)

    def start_thread(self) -> None:
        self._thread.start()

    def set_bracket(self, on: bool) -> None:
        """Pair sets of two exposures from now on (or not); a waiting first of a pair is dropped."""
        self.bracket = bool(on)
        self._bracket_first = None

    def shutdown(self, timeout_s: float = 10.0) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        self.results.close()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        lower_this_threads_priority()  # bulk work: the event loop answers first
        while not self._stop.is_set():
            fs = self.queue.get(timeout_s=0.1)
            if fs is None:
                continue
            engine = self.reconstructor()
            if engine is None:
                continue
            try:
                result = self.process_bracket(engine, fs) if self.bracket and fs.mode == "set" \
                    else self.process(engine, fs)
            except Exception as exc:  # a bad set must not kill the thread
                self.last_error = f"reconstruction: {exc}"
                log.warning("reconstruction failed: %s", exc, exc_info=True)
                continue
            if result is None:  # the first set of a bracket: its partner comes next
                continue
            result.seq = self.results.publish(result)
            self.completed += 1
            self.depth_rate.tick(result.published_s)
            self.latencies.add(result.latency_ms)
            self.recon_times.add(result.recon_ms)
            schedule = engine.calibration.pattern
            if self.noise.due(time.monotonic(), schedule):  # after publishing: no map waits for it
                self.noise.update(fs.stack(), schedule, int(result.full_scale), time.monotonic())

    def live_noise(self, engine: Reconstructor, full_scale: float) -> SensorNoise | None:
        """The camera noise model live sets are reconstructed with: the measured one; None until
        measured (the engine fits it to each set); with measuring off the engine's or nominal."""
        noise = self.noise.current
        if noise is None and self.noise.interval_s == 0.0:
            noise = engine.noise or SensorNoise.typical(int(full_scale))
        return noise

    def _run_engine(self, engine: Reconstructor, fs: FrameSet) -> tuple[ReconResult, float, float]:
        """(result, full scale, milliseconds) of one set with the live noise and motion test."""
        t0 = time.perf_counter()
        frames = fs.stack()
        full_scale = 255.0 if frames.dtype == np.uint8 else float(2**self.bit_depth - 1)
        res = engine.run(frames, noise=self.live_noise(engine, full_scale), motion=self.motion,
                         phase_error=self.noise.phase_error(engine.calibration.pattern))
        return res, full_scale, 1000.0 * (time.perf_counter() - t0)

    def process(self, engine: Reconstructor, fs: FrameSet) -> LiveResult:
        """Reconstruct one set with the motion test (both modes) into a :class:`LiveResult`."""
        res, full_scale, recon_ms = self._run_engine(engine, fs)
        return self._live(engine, fs, res, full_scale, recon_ms)

    def process_bracket(self, engine: Reconstructor, fs: FrameSet) -> LiveResult | None:
        """One set of an exposure bracket: None for the first of a pair (kept); for the second
        (another exposure) both fused per pixel, the smaller-σ valid member winning
        (:func:`~app.recon.fusion.fuse_exposures`, as ``reconstruct`` does with several sets)."""
        res, full_scale, recon_ms = self._run_engine(engine, fs)
        first, self._bracket_first = self._bracket_first, (fs, res, recon_ms)
        e = float(fs.exposure_ms)
        if first is None or abs(float(first[0].exposure_ms) - e) <= 1e-3 * e + 1e-3:
            return None  # no partner yet (or a lost set left two of one exposure)
        self._bracket_first = None
        pair = sorted([first, (fs, res, recon_ms)], key=lambda m: float(m[0].exposure_ms))
        fused = fuse_exposures([m[1] for m in pair], [float(m[0].exposure_ms) for m in pair]).result
        a, b = first[1], res
        moved = None if a.motion is None or b.motion is None else a.motion | b.motion
        # the fused result is this call's own: set in place (a copy would make its points)
        fused.motion, fused.moved_pixels = moved, a.moved_pixels + b.moved_pixels
        fused.scene_moved = a.scene_moved or b.scene_moved
        fused.motion_ms = a.motion_ms + b.motion_ms
        fused.uncertain_moving_pixels = a.uncertain_moving_pixels + b.uncertain_moving_pixels
        fused.noise, fused.noise_source = b.noise, b.noise_source
        fused.phase_error_source = b.phase_error_source
        live = self._live(engine, fs, fused, full_scale, recon_ms + first[2])
        live.exposure_ms = float(pair[0][0].exposure_ms)
        live.bracket_exposures_ms = (float(pair[0][0].exposure_ms), float(pair[1][0].exposure_ms))
        return live

    def _live(self, engine: Reconstructor, fs: FrameSet, res: ReconResult, full_scale: float,
              recon_ms: float) -> LiveResult:
        sched = engine.calibration.pattern
        return LiveResult(
            depth=res.depth, points=LazyPoints.given(res), point_rays=res.point_rays,
            valid=res.valid, reason=res.reason,
            texture=res.texture, modulation=res.modulation, motion=res.motion, mode=fs.mode,
            frame_indices=fs.frame_indices, timestamps=fs.timestamps,
            exposure_ms=float(fs.exposure_ms), led=fs.led, full_scale=full_scale,
            received_s=fs.received_s, published_s=time.monotonic(), recon_ms=recon_ms,
            sigma=res.sigma,
            map_time_s=map_time(fs.timestamps, tuple(sched.frequencies),
                                combined=engine.combine_frequencies),
            moved_pixels=res.moved_pixels, motion_ms=res.motion_ms, scene_moved=res.scene_moved,
            uncertain_moving_pixels=res.uncertain_moving_pixels, noise=res.noise,
            noise_source=res.noise_source, phase_error_source=res.phase_error_source,
            model_sigma=res.model_sigma,
        )
