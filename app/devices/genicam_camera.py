"""A GenICam (GigE Vision / USB3 Vision) camera through ``harvesters`` and a GenTL producer (.cti).

``harvesters`` and ``genicam`` are optional (``pip install fringescope[genicam]``) and
imported only when a camera is opened. Mono8 (or Mono12/Mono16 for ``bit_depth`` 12/16)
is requested where the camera offers it; ``ExposureTime`` (µs), ``Gain`` and the
hardware trigger (``TriggerMode=On``, ``TriggerSource=Line0``) are set where the
node map has them. Pattern index from trigger counting (:class:`~app.devices.base.CountingCamera`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from app.core.limits import EXPOSURE_RANGE_MS
from app.devices.base import CameraCapabilities, CameraSettings, CountingCamera, Frame
from app.devices.errors import DeviceDisconnected, DeviceError, DeviceNotFound, DeviceTimeout
from app.devices.opencv_camera import to_mono

PIXEL_FORMATS = {8: ("Mono8",), 12: ("Mono12", "Mono16"), 16: ("Mono16",)}
SOURCE_BITS = {"Mono8": 8, "Mono12": 12, "Mono16": 16}  # the bits each pixel format fills


def _info(info: Any, key: str) -> Any:
    """A device-info field, None where the producer does not provide it (it raises then)."""
    try:
        return getattr(info, key)
    except Exception:
        return None


def _node(node_map: Any, name: str) -> Any | None:
    return getattr(node_map, name, None) if hasattr(node_map, name) else None


class GenICamCamera(CountingCamera):
    """Camera ``device`` (index, serial number or user-defined name) of GenTL producer ``cti``.

    Args:
        hardware_trigger: expose on Line0 rising edges (the projector / controller trigger).
        schedule_length: patterns per set, for ``Frame.pattern_index``.
    """

    def __init__(self, cti: str | Path, *, device: int | str = 0, hardware_trigger: bool = False,
                 schedule_length: int = 16, name: str | None = None) -> None:
        super().__init__(schedule_length=schedule_length,
                         name=name or f"GenICamCamera({Path(cti).name}:{device})")
        self.cti, self.device, self.hardware_trigger = Path(cti), device, hardware_trigger
        self._harvester: Any = None
        self._ia: Any = None
        self._caps: CameraCapabilities | None = None
        self._source_bits = 16  # a 16-bit sample of unknown format: full scale
        self._timeout_exc: tuple[type[BaseException], ...] = ()
        self.model = ""

    # --- hooks -------------------------------------------------------------------------------
    def _do_open(self) -> None:
        try:
            from genicam.gentl import TimeoutException
            from harvesters.core import Harvester
        except ImportError:
            raise DeviceNotFound(
                "GenICam support needs the optional packages harvesters and genicam") from None
        if not self.cti.is_file():
            raise DeviceNotFound(f"{self.cti}: GenTL producer file not found")
        self._timeout_exc = (TimeoutException,)
        h = Harvester()
        try:
            h.add_file(str(self.cti))
            h.update()
            infos = h.device_info_list
            if not infos:
                raise DeviceNotFound(f"{self.cti.name}: no camera found")
            ia = h.create(self._search_key(infos))
        except DeviceError:
            h.reset()
            raise
        except Exception as exc:  # harvesters raises plain exceptions for a missing camera
            h.reset()
            raise DeviceNotFound(
                f"{self.cti.name}: cannot open camera {self.device!r} ({exc})") from None
        self._harvester, self._ia = h, ia
        try:
            self._configure_new(ia)
        except BaseException:
            self._do_close()  # the state stays CLOSED: release the camera here
            raise

    def _configure_new(self, ia: Any) -> None:
        nm = ia.remote_device.node_map
        self.model = str(getattr(_node(nm, "DeviceModelName"), "value", ""))
        depths = tuple(d for d, names in PIXEL_FORMATS.items() if self._offers(nm, names))
        exp = _node(nm, "ExposureTime")
        gain = _node(nm, "Gain")
        lo, hi = EXPOSURE_RANGE_MS
        if exp:
            lo, hi = max(lo, exp.min / 1000), min(hi, exp.max / 1000)
        self._caps = CameraCapabilities(
            width=int(nm.Width.value), height=int(nm.Height.value), bit_depths=depths or (8,),
            exposure_range_ms=(lo, hi),
            gain_range=(float(gain.min), float(gain.max)) if gain else (1.0, 1.0),
            hardware_trigger=_node(nm, "TriggerMode") is not None,
        )
        self._set_pixel_format(nm, self._settings.bit_depth)
        if self.hardware_trigger:
            for node, value in (("TriggerSelector", "FrameStart"), ("TriggerMode", "On"),
                                ("TriggerSource", "Line0"), ("TriggerActivation", "RisingEdge")):
                if _node(nm, node) is None:
                    if node in ("TriggerSelector", "TriggerActivation"):
                        # optional on some models; FrameStart / rising edge are the defaults
                        continue
                    raise DeviceError(
                        f"{self.model or 'camera'} has no {node} node: no hardware trigger")
                nm.get_node(node).value = value

    def _search_key(self, infos: list[Any]) -> Any:
        if isinstance(self.device, int):
            if not 0 <= self.device < len(infos):
                raise DeviceNotFound(f"{self.cti.name}: camera index {self.device} of {len(infos)}")
            return self.device
        for key in ("serial_number", "user_defined_name", "id_"):
            if any(_info(i, key) == self.device for i in infos):
                return {key: self.device}
        raise DeviceNotFound(f"{self.cti.name}: no camera {self.device!r}")

    @staticmethod
    def _offers(nm: Any, names: tuple[str, ...]) -> bool:
        pf = _node(nm, "PixelFormat")
        return pf is not None and any(n in pf.symbolics for n in names)

    def _set_pixel_format(self, nm: Any, bit_depth: int) -> None:
        pf = _node(nm, "PixelFormat")
        if pf is None:
            return
        for name in PIXEL_FORMATS.get(bit_depth, ()):
            if name in pf.symbolics:
                if pf.value != name:
                    pf.value = name
                break
        self._source_bits = SOURCE_BITS.get(str(pf.value), 16)

    def _do_close(self) -> None:
        ia, h = self._ia, self._harvester
        self._ia = self._harvester = None
        try:
            if ia is not None:
                ia.stop()
                ia.destroy()
        except Exception as exc:  # a vanished camera fails to stop; the handle is dropped anyway
            self.log.debug("close: %s", exc)
        finally:
            if h is not None:
                h.reset()

    def _capabilities(self) -> CameraCapabilities:
        if self._caps is None:
            self._do_open()
            self._do_close()
        assert self._caps is not None
        return self._caps

    def _do_configure(self, settings: CameraSettings) -> None:
        if self._ia is None:
            return
        nm = self._ia.remote_device.node_map
        try:
            if (exp := _node(nm, "ExposureTime")) is not None:
                exp.value = settings.exposure_ms * 1000.0
            if (gain := _node(nm, "Gain")) is not None:
                gain.value = settings.gain
            if not self._ia.is_acquiring():  # PixelFormat is locked while streaming
                self._set_pixel_format(nm, settings.bit_depth)
        except Exception as exc:
            raise DeviceError(f"configure: {exc}") from None

    def _do_start(self) -> None:
        self.sync()
        try:
            self._ia.start()
        except Exception as exc:
            raise DeviceDisconnected(f"cannot start acquisition ({exc})") from None

    def _do_stop(self) -> None:
        try:
            self._ia.stop()
        except Exception as exc:
            raise DeviceDisconnected(f"cannot stop acquisition ({exc})") from None

    def _do_grab(self, timeout_s: float) -> Frame:
        ia = self._ia
        if ia is None:
            raise DeviceDisconnected("camera is not open")
        try:
            with ia.fetch(timeout=timeout_s) as buffer:
                comp = buffer.payload.components[0]
                data = np.array(comp.data, copy=True)  # the buffer is requeued on exit
                channels = data.size // (comp.height * comp.width)
                shape: tuple[int, ...] = (comp.height, comp.width)
                if channels != 1:
                    shape = (comp.height, comp.width, channels)
                image = data.reshape(shape)
        except self._timeout_exc:
            raise DeviceTimeout(f"no frame within {timeout_s:.2f} s") from None
        except Exception as exc:
            raise DeviceDisconnected(f"fetch failed ({exc})") from None
        stamp = time.monotonic()
        data = to_mono(image, self._settings.bit_depth)
        return self._frame(data, stamp, source_bits=self._source_bits, meta={"model": self.model})
