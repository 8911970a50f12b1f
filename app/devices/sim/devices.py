"""Simulated camera, projector and LED/trigger controller sharing one SimulatedWorld."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from app.core.limits import LIVE_BIT_DEPTHS
from app.core.schedule import PatternSchedule
from app.devices.base import (
    Camera,
    CameraCapabilities,
    CameraSettings,
    Controller,
    Frame,
    Projector,
)
from app.devices.errors import DeviceTimeout
from app.devices.sim.faults import FrameFaults, Link
from app.devices.sim.world import READOUT_MS, SimulatedWorld

BUFFER_FRAMES = 8  # frames the simulated camera buffers before it overwrites (drops) old ones


class SimulatedCamera(Camera):
    """Renders the world at each frame's own exposure mid-point.

    With ``realtime`` the frames are paced by the frame period max(exposure, readout);
    a consumer more than BUFFER_FRAMES behind loses frames (index gaps). Without it the
    clock is virtual: grab returns at once and time advances one period per frame.
    """

    def __init__(self, world: SimulatedWorld, *, realtime: bool = True,
                 faults: FrameFaults | None = None, link: Link | None = None,
                 name: str = "sim-camera") -> None:
        super().__init__(name=name)
        self.world = world
        self.realtime = realtime
        self.faults = faults or FrameFaults()
        self.link = link or Link(name)
        self._active = CameraSettings()
        self._index = 0
        self._next_start = 0.0

    def _capabilities(self) -> CameraCapabilities:
        w, h = self.world.rig.image_size
        return CameraCapabilities(width=w, height=h, bit_depths=(8, 12), gain_range=(1.0, 16.0),
                                  hardware_trigger=True)

    def _do_open(self) -> None:
        self.link.check_open()
        _ = self.world.renderer  # precompute the geometry now, not inside the first grab
        self.link.opened()  # armed once open has succeeded, after the (possibly slow) trace

    def _do_close(self) -> None:
        pass

    def _do_configure(self, settings: CameraSettings) -> None:
        self.link.check()
        self._active = settings

    def _do_start(self) -> None:
        self.link.check()
        self._index = 0
        self._next_start = time.monotonic()

    def _do_stop(self) -> None:
        pass

    def frame_period_s(self) -> float:
        return max(self._active.exposure_ms, READOUT_MS) / 1000.0

    def _do_grab(self, timeout_s: float) -> Frame:
        deadline = time.monotonic() + timeout_s
        while True:
            self.link.check()
            s = self._active
            period = self.frame_period_s()
            start = self._next_start
            end = start + s.exposure_ms / 1000.0
            if self.realtime:
                now = time.monotonic()
                behind = int((now - end) / period) - BUFFER_FRAMES
                if behind > 0:  # the ring buffer overflowed: the oldest frames are gone
                    for _ in range(behind):
                        self.world.trigger()
                    self._index += behind
                    self._next_start += behind * period
                    continue
                if end > deadline:
                    time.sleep(max(deadline - now, 0.0))
                    raise DeviceTimeout(f"{self.name}: no frame within {timeout_s:.3f} s")
                if end > now:
                    time.sleep(end - now)
            index = self._index
            self._index += 1
            self._next_start += period
            pattern = self.world.trigger()
            if self.faults.drop():
                continue
            if self.faults.timeout():
                if self.realtime:
                    time.sleep(max(deadline - time.monotonic(), 0.0))
                raise DeviceTimeout(f"{self.name}: frame {index} timed out (simulated)")
            mid = start + s.exposure_ms / 2000.0
            data = self.world.render(pattern, mid - self.world.epoch, exposure_ms=s.exposure_ms,
                                     gain=s.gain, bits=s.bit_depth)
            return Frame(data=data, index=index, timestamp=mid, pattern_index=pattern,
                         exposure_ms=s.exposure_ms, gain=s.gain,
                         led=self.world.led if pattern >= 0 else "",
                         meta={"scene_time_s": mid - self.world.epoch,
                               "current": self.world.current}, bit_depth=s.bit_depth)


class SimulatedProjector(Projector):
    """A DLP3000 whose LED and pattern position drive what the simulated camera sees."""

    def __init__(self, world: SimulatedWorld, *, link: Link | None = None,
                 name: str = "sim-projector") -> None:
        super().__init__(name=name)
        self.world = world
        self.link = link or Link(name)

    def _do_open(self) -> None:
        self.link.check_open()
        self.link.opened()
        self.world.led, self.world.current = self.led, self.led_current

    def _do_close(self) -> None:
        self.world.stop_sequence()

    def _do_load(self, schedule: PatternSchedule, exposure_ms: float) -> None:
        self.link.check()
        w, h = self.world.rig.projector.size
        if (schedule.width, schedule.height) != (w, h):
            raise ValueError(f"schedule: pattern size {schedule.width}x{schedule.height} != "
                             f"DMD {w}x{h}")
        self.world.set_schedule(schedule)

    def _do_set_exposure(self, exposure_ms: float) -> None:
        self.link.check()  # the simulated world's timing follows the camera's exposure

    def _do_set_led(self, led: str, current: float) -> None:
        self.link.check()
        self.world.led, self.world.current = led, current

    def _do_start(self) -> None:
        self.link.check()
        self.world.start_sequence()

    def _do_stop(self) -> None:
        self.world.stop_sequence()


class SimulatedController(Controller):
    """The LED/trigger box: identity, LED, arming and a heartbeat watchdog (``watchdog_s``)."""

    IDENT = "FRINGESCOPE-LEDCTL sim 1.0"

    def __init__(self, world: SimulatedWorld, *, link: Link | None = None, watchdog_s: float = 2.0,
                 name: str = "sim-controller") -> None:
        super().__init__(name=name)
        self.world = world
        self.link = link or Link(name)
        self.watchdog_s = watchdog_s
        self.last_heartbeat = 0.0

    @property
    def watchdog_expired(self) -> bool:
        """True if armed and no heartbeat came within ``watchdog_s`` (the real
        box would cut the LED)."""
        return self.armed and time.monotonic() - self.last_heartbeat > self.watchdog_s

    def _do_open(self) -> None:
        self.link.check_open()
        self.link.opened()

    def _do_close(self) -> None:
        pass

    def _do_identify(self) -> str:
        self.link.check()
        return self.IDENT

    def _do_set_led(self, led: str, current: float) -> None:
        self.link.check()

    def _do_arm(self, armed: bool) -> None:
        self.link.check()
        self.last_heartbeat = time.monotonic()

    def _do_heartbeat(self) -> None:
        self.link.check()
        self.last_heartbeat = time.monotonic()

    def _do_set_sequence_length(self, n_frames: int) -> None:
        self.link.check()


@dataclass
class SimDevices:
    camera: SimulatedCamera
    projector: SimulatedProjector
    controller: SimulatedController
    world: SimulatedWorld


def create_sim_devices(*, scene: str = "anastomosis", seed: int | None = None,
                       bit_depth: int | None = None, drop_rate: float = 0.0,
                       timeout_rate: float = 0.0, disconnect_every_s: float = 0.0,
                       realtime: bool = True, distortion: bool = True,
                       reconnect_delay_s: float = 0.5, rig: str = "default",
                       cache_dir: Path | None = None) -> SimDevices:
    """Camera, projector and controller sharing one simulated world (nothing opened yet).

    ``rig``: the rig preset (optics.RIG_NAMES); ``bit_depth`` None: the rig sensor's native depth;
    ``cache_dir``: where the scene's traced geometry is kept between starts (None: not kept).
    """
    world = SimulatedWorld(scene, seed=seed, distortion=distortion, rig=rig, cache_dir=cache_dir)
    if bit_depth is None:
        bit_depth = world.rig.bit_depth
    if bit_depth not in LIVE_BIT_DEPTHS:
        raise ValueError(f"bit_depth: must be one of {LIVE_BIT_DEPTHS}, got {bit_depth}")
    fault_seed = world.seed_seq.spawn(1)[0]
    camera = SimulatedCamera(world, realtime=realtime,
                             faults=FrameFaults(drop_rate=drop_rate, timeout_rate=timeout_rate,
                                                seed=fault_seed),
                             link=Link("sim-camera", disconnect_every_s=disconnect_every_s,
                                       reconnect_delay_s=reconnect_delay_s))
    camera.configure(bit_depth=bit_depth)
    projector = SimulatedProjector(world, link=Link("sim-projector",
                                                    disconnect_every_s=disconnect_every_s,
                                                    reconnect_delay_s=reconnect_delay_s))
    controller = SimulatedController(world, link=Link("sim-controller",
                                                      disconnect_every_s=disconnect_every_s,
                                                      reconnect_delay_s=reconnect_delay_s))
    return SimDevices(camera, projector, controller, world)
