"""The live instrument: devices, acquisition and reconstruction threads, latest results."""

from app.service.instrument import Instrument

__all__ = ["Instrument"]
