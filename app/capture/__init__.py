"""Capture-set and recording I/O."""

from app.capture.captureset import CaptureSet, read_capture_set, write_capture_set

__all__ = ["CaptureSet", "read_capture_set", "write_capture_set"]
