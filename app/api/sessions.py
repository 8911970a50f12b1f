"""Browser sessions and the failed-token throttle (in memory, per process).

The cookie ``POST /api/login`` sets is a random session id, never the token: it expires
(``session_ttl_s``), is revoked at logout, and every session dies when the token changes
(each remembers a digest of the token it was opened with; a restart forgets them all).
Failed token attempts are counted per client address: after a few, that client is refused
(429) for a doubling interval, so guessing the token is slow whatever the parallelism.
"""

from __future__ import annotations

import hashlib
import math
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable

#: session ids: 32 random bytes, URL-safe base64 (43 characters)
SESSION_ID_BYTES = 32
#: sessions kept at most; the oldest is dropped beyond (a browser just logs in again)
MAX_SESSIONS = 1000
#: free failed attempts per client before it is held off
FREE_FAILURES = 5
#: the first hold-off, s; doubled with every further failure up to MAX_HOLD_OFF_S
FIRST_HOLD_OFF_S = 1.0
MAX_HOLD_OFF_S = 60.0
#: client addresses tracked at most (the oldest forgotten beyond)
MAX_CLIENTS = 10_000


def token_digest(token: str) -> str:
    """SHA-256 hex digest of ``token`` (what a session remembers of it)."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


class SessionStore:
    """Random, expiring, revocable session ids bound to the token they were opened with."""

    def __init__(self, ttl_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        if not (math.isfinite(ttl_s) and ttl_s > 0):
            raise ValueError(f"ttl_s: must be a positive number of seconds, got {ttl_s}")
        self.ttl_s = ttl_s
        self._clock = clock
        self._sessions: OrderedDict[str, tuple[float, str]] = OrderedDict()  # id: (expiry, digest)
        self._lock = threading.Lock()

    def open(self, token: str) -> str:
        """A new session id for a client that showed ``token``."""
        sid = secrets.token_urlsafe(SESSION_ID_BYTES)
        with self._lock:
            self._sessions[sid] = (self._clock() + self.ttl_s, token_digest(token))
            while len(self._sessions) > MAX_SESSIONS:
                self._sessions.popitem(last=False)
        return sid

    def valid(self, sid: str, token: str) -> bool:
        """True if ``sid`` is open, not expired, and was opened with ``token``."""
        with self._lock:
            entry = self._sessions.get(sid)
            if entry is None:
                return False
            expiry, digest = entry
            if self._clock() >= expiry:
                del self._sessions[sid]
                return False
        return secrets.compare_digest(digest, token_digest(token))

    def revoke(self, sid: str) -> bool:
        """Close ``sid``; True if it was open."""
        with self._lock:
            return self._sessions.pop(sid, None) is not None

    def revoke_all(self) -> None:
        with self._lock:
            self._sessions.clear()

    def __len__(self) -> int:
        return len(self._sessions)


class FailureThrottle:
    """Per-client count of failed token attempts and the hold-off it earns."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._clients: OrderedDict[str, tuple[int, float]] = OrderedDict()  # (failures, until)
        self._lock = threading.Lock()

    def held_off_s(self, client: str) -> float:
        """Seconds ``client`` must still wait before its next attempt (0: may try)."""
        with self._lock:
            entry = self._clients.get(client)
        return 0.0 if entry is None else max(0.0, entry[1] - self._clock())

    def failed(self, client: str) -> None:
        """Count one failed attempt of ``client``."""
        with self._lock:
            failures = self._clients.pop(client, (0, 0.0))[0] + 1
            extra = failures - FREE_FAILURES
            hold = 0.0 if extra <= 0 else min(MAX_HOLD_OFF_S, FIRST_HOLD_OFF_S * 2.0 ** (extra - 1))
            self._clients[client] = (failures, self._clock() + hold)
            while len(self._clients) > MAX_CLIENTS:
                self._clients.popitem(last=False)

    def succeeded(self, client: str) -> None:
        with self._lock:
            self._clients.pop(client, None)
