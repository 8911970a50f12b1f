"""The live instrument: devices, acquisition and reconstruction threads, latest results."""

from app.service.instrument import Instrument, NotReady

__all__ = ["Instrument", "NotReady"]
