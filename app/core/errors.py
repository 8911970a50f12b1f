"""Domain errors: raised on purpose by the service (and the API), mapped to HTTP in one place.

Each carries ``detail``, one line a client can act on. The HTTP mapping lives in
:mod:`app.api.errors`; any other exception is a programming error (HTTP 500, logged).
"""

from __future__ import annotations


class DomainError(Exception):
    """Base of the domain errors; ``detail`` is the reason shown to the client."""

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = str(detail)


class InvalidRequest(DomainError):
    """The request's content is wrong (HTTP 422)."""


class Conflict(DomainError):
    """The request does not fit the current state (HTTP 409), e.g. no calibration session yet."""


class NotFound(DomainError):
    """The named thing does not exist (HTTP 404)."""


class DeviceUnavailable(DomainError):
    """The hardware (or the live pipeline) cannot serve this now (HTTP 503)."""


__all__ = ["Conflict", "DeviceUnavailable", "DomainError", "InvalidRequest", "NotFound"]
