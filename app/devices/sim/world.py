"""The simulated world the three sim devices share: scene, rig, light and projector sequence."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import numpy.typing as npt

from app.core.limits import DEFAULT_LED
from app.core.schedule import PatternSchedule
from app.devices.sim import geometry_cache
from app.devices.sim.optics import SimRig, rig_by_name
from app.devices.sim.radiometry import SensorModel
from app.devices.sim.render import Renderer
from app.devices.sim.scenes import Scene, build_scene

READOUT_MS = 1000.0 / 45.0  # sensor readout: frame period = max(exposure, readout)

# Renderers of named scenes are read-only after their precompute: worlds share them.
_RENDERERS: dict[tuple[object, ...], Renderer] = {}
_RENDERERS_LOCK = threading.Lock()
_MAX_RENDERERS = 3


def shared_renderer(name: str, rig: SimRig, schedule: PatternSchedule, sensor: SensorModel,
                    gamma: float, distortion: bool, cache_dir: Path | None = None) -> Renderer:
    """The renderer of a named scene on a named rig, shared in memory and, with ``cache_dir``,
    its traced geometry kept on disk for the next start (:mod:`geometry_cache`)."""
    key = (name, rig.name, distortion, schedule, sensor, gamma)
    with _RENDERERS_LOCK:
        r = _RENDERERS.get(key)
        if r is None:
            disk_key = geometry_cache.cache_key(key) if cache_dir is not None else ""
            geometry = geometry_cache.load(cache_dir, disk_key) if cache_dir is not None else None
            r = Renderer(build_scene(name, rig), rig, schedule=schedule, sensor=sensor,
                         projector_gamma=gamma, geometry=geometry)
            if cache_dir is not None and geometry is None:
                geometry_cache.save_in_background(cache_dir, disk_key, r.geometry())
            if len(_RENDERERS) >= _MAX_RENDERERS:
                _RENDERERS.pop(next(iter(_RENDERERS)))
            _RENDERERS[key] = r
        return r


def release_shared_renderers() -> int:
    """Forget the renderers worlds share (~0.3 GB each with their caches); how many were held.

    A world that holds one keeps it; the next world of the same scene builds it again (from
    the disk cache when it has one). For a long-lived process that has finished with a scene.
    """
    with _RENDERERS_LOCK:
        n = len(_RENDERERS)
        _RENDERERS.clear()
    return n


class SimulatedWorld:
    """One scene seen by one rig; the projector's state decides what light falls on it.

    Attributes:
        epoch: ``time.monotonic()`` origin of scene time (scene time = timestamp − epoch).
        projector_on: whether the projector sequence runs (it then triggers the camera).
        led, current: the projector's LED and its current fraction.
    """

    def __init__(self, scene: str | Scene = "anastomosis", *, rig: SimRig | str | None = None,
                 schedule: PatternSchedule | None = None, sensor: SensorModel | None = None,
                 seed: int | None = None, distortion: bool = True,
                 projector_gamma: float | None = None, cache_dir: Path | None = None) -> None:
        """``rig``: a rig preset's name (see optics.RIG_NAMES; default ``"default"``) or a SimRig;
        ``projector_gamma``: the DMD response exponent (None: the rig's); ``cache_dir``: where a
        named scene's traced geometry is kept between starts (None: not)."""
        self._rig_named = not isinstance(rig, SimRig)  # named scenes may then share renderers
        self._named = scene if isinstance(scene, str) and self._rig_named else None
        self._distortion = distortion
        self._cache_dir = cache_dir
        self.rig = rig if isinstance(rig, SimRig) else rig_by_name(rig or "default",
                                                                   distortion=distortion)
        self.scene = build_scene(scene, self.rig) if isinstance(scene, str) else scene
        self.schedule = schedule or PatternSchedule()
        self.sensor = sensor or SensorModel()
        self._projector_gamma = (self.rig.projector_gamma if projector_gamma is None
                                 else projector_gamma)
        self._renderer: Renderer | None = None
        self._lock = threading.Lock()
        self.seed_seq = np.random.SeedSequence(seed)
        self.rng_state = np.zeros(1, np.uint64)
        self.reseed(seed)
        self.epoch = time.monotonic()
        self.projector_on = False
        self.led: str = DEFAULT_LED
        self.current = 0.5
        self._position = 0

    @property
    def renderer(self) -> Renderer:
        """Built on first use (the geometry precompute takes a few seconds)."""
        with self._lock:
            if self._renderer is None:
                if self._named is not None:
                    self._renderer = shared_renderer(self._named, self.rig, self.schedule,
                                                     self.sensor, self._projector_gamma,
                                                     self._distortion, self._cache_dir)
                else:
                    self._renderer = Renderer(self.scene, self.rig, schedule=self.schedule,
                                              sensor=self.sensor,
                                              projector_gamma=self._projector_gamma)
            return self._renderer

    def set_scene(self, scene: str | Scene) -> None:
        """Show another scene (a named one or a :class:`Scene`), e.g. a calibration board at a pose.

        Its renderer is built here, before the swap (the geometry precompute takes seconds), so
        the camera keeps delivering frames of the old scene meanwhile instead of timing out.
        """
        built = build_scene(scene, self.rig) if isinstance(scene, str) else scene
        renderer = Renderer(built, self.rig, schedule=self.schedule, sensor=self.sensor,
                            projector_gamma=self._projector_gamma)
        with self._lock:
            self.scene = built
            self._named = scene if isinstance(scene, str) and self._rig_named else None
            self._renderer = renderer

    def reseed(self, seed: int | None) -> None:
        """Restart the sensor-noise generator (same seed → same noise)."""
        state = int(np.random.default_rng(np.random.SeedSequence(seed)).integers(1, 2**63))
        self.rng_state[0] = np.uint64(state)

    def set_schedule(self, schedule: PatternSchedule) -> None:
        if schedule != self.schedule:
            self.schedule = schedule
            with self._lock:
                self._renderer = None

    def start_sequence(self) -> None:
        self._position = 0
        self.projector_on = True

    def stop_sequence(self) -> None:
        self.projector_on = False

    def trigger(self) -> int:
        """The projector shows its next pattern and triggers the camera; -1 if it is not running."""
        if not self.projector_on:
            return -1
        idx = self._position
        self._position = (self._position + 1) % self.schedule.n_frames
        return idx

    def render(self, pattern_index: int, t_s: float, *, exposure_ms: float, gain: float, bits: int
               ) -> npt.NDArray[np.uint8] | npt.NDArray[np.uint16]:
        return self.renderer.render(pattern_index, t_s, self.rng_state, exposure_ms=exposure_ms,
                                    gain=gain, led=self.led, current=self.current, bits=bits)

    def truth(self, t_s: float) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """True depth (H, W) and points (H, W, 3) at scene time ``t_s`` (see Renderer.truth)."""
        return self.renderer.truth(t_s)

    def noise_sigma(self, mean_dn: npt.ArrayLike, *, bits: int = 8,
                    gain: float = 1.0) -> npt.NDArray[np.float64]:
        """Predicted temporal noise σ (DN) of a pixel with noise-free mean ``mean_dn`` (DN)."""
        return self.sensor.noise_sigma(mean_dn, bits=bits, gain=gain)
