"""One error family for every device backend."""

from __future__ import annotations


class DeviceError(Exception):
    """Base of every device failure; ``str()`` is a one-line reason for users."""


class DeviceNotFound(DeviceError):
    """The device is not there (no port, no camera, no host)."""


class DeviceTimeout(DeviceError):
    """The device did not answer or deliver a frame in time."""


class DeviceDisconnected(DeviceError):
    """The link to an opened device went away (unplugged, closed socket)."""


class ProtocolError(DeviceError):
    """The device answered something the protocol does not allow, or an ERR reply."""


class IncompleteSet(DeviceError):
    """A fringe set is missing, duplicated or out-of-order frames."""


class DeviceStateError(DeviceError):
    """A call that the device's current state does not allow (e.g. grab before start)."""
