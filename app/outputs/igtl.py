"""OpenIGTLink server: the live depth, texture, point cloud and status for 3D Slicer and others.

Off unless ``FRINGESCOPE_IGTL_PORT`` is set (18944 is the convention). Every new depth
result is pushed, once, to every connected client as four messages (device names):

- ``FringescopeDepth`` — IMAGE, float32 height above the reference plane in mm (NaN invalid),
  one slice ``(1, H, W)``;
- ``FringescopeTexture`` — IMAGE, uint8 texture (A + B scaled by the sensor's full scale);
- ``FringescopeCloud`` — POLYDATA, the valid points in the camera frame, mm, decimated to at
  most ``max_points`` (every k-th valid pixel in raster order), one poly-vertex cell;
- ``FringescopeStatus`` — STRING, the instrument's status as JSON.
- ``FringescopeChange`` — IMAGE, float32 change Δ against the change reference in mm (NaN
  where not compared), placed like the depth image; sent while a reference is set.

Coordinates: the camera frame (x right, y down, z along the optical axis, mm) is sent as the
world frame (flagged RAS, so Slicer takes it as is). Both images lie in the plane through the
reference plane's point on the optical axis, perpendicular to the axis; pixel (0, 0) at the
back-projection of that pixel onto it, spacing the footprint of one pixel there
(``z_ref / fx``, ``z_ref / fy``). The cloud is metric and needs no placement.

Transport. pyigtl's own ``OpenIGTLinkServer`` is not used: it serves one client at a time
(a ``TCPServer``, not threading), shares one outgoing deque of up to 100 whole messages
between clients (hundreds of MB of images for a client that stalls), installs SIGINT/SIGTERM
handlers (which only works from the main thread) and binds only 127.0.0.1 or an interface
name. Here pyigtl packs and parses every message (header, CRC, content); a small threading
server keeps, per client, only the newest packed message of each device: a slow client loses
old messages instead of queueing them, and a client leaving changes nothing for the others.

Security: OpenIGTLink has no authentication or encryption. The server binds
``FRINGESCOPE_IGTL_HOST`` (default 127.0.0.1); any other address needs
``FRINGESCOPE_IGTL_ALLOW_REMOTE=true`` (see :func:`check_igtl_settings`).

Received TRANSFORM messages (a tracked scope's pose) are kept, the newest per device, in
:attr:`IgtlServer.poses` (a :class:`~app.service.poses.TrackerPoses` the recorder reads too);
the recorder stores them with each recorded set.
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import socketserver
import struct
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import pyigtl

from app.config import is_loopback
from app.service.poses import ReceivedTransform, TrackerPoses
from app.service.store import LatestSlot, NewestQueue

log = logging.getLogger("fringescope.outputs.igtl")

DEPTH_DEVICE = "FringescopeDepth"
TEXTURE_DEVICE = "FringescopeTexture"
CLOUD_DEVICE = "FringescopeCloud"
STATUS_DEVICE = "FringescopeStatus"
CHANGE_DEVICE = "FringescopeChange"
DEVICES = (DEPTH_DEVICE, TEXTURE_DEVICE, CLOUD_DEVICE, STATUS_DEVICE)

HEADER_SIZE = pyigtl.MessageBase.IGTL_HEADER_SIZE
MAX_BODY_BYTES = 1 << 20  # received messages are small (TRANSFORM: 48 bytes); refuse floods


def check_igtl_settings(host: str, port: int | None, allow_remote: bool) -> None:
    """Raise ``ValueError`` if the OpenIGTLink port would open off loopback without consent."""
    if port is None:
        return
    if not is_loopback(host) and not allow_remote:
        raise ValueError(
            f"igtl_host: refusing to open OpenIGTLink (no authentication) on {host}; set "
            "FRINGESCOPE_IGTL_ALLOW_REMOTE=true to allow it, or use 127.0.0.1"
        )


def image_placement(camera_matrix: npt.ArrayLike, plane_normal: npt.ArrayLike,
                    plane_offset_mm: float) -> npt.NDArray[np.float64]:
    """(4, 4) ijk→camera-frame matrix (mm) placing an ``(H, W)`` image of the camera.

    The image lies in the plane ``z = z_ref`` where the reference plane (``n·X`` with
    ``plane_normal`` and ``plane_offset_mm`` as in :func:`app.recon.points.points_from_height`,
    i.e. height 0) crosses the optical axis. Column i (u) runs along x, row j (v) along y,
    spacing ``z_ref / fx`` and ``z_ref / fy`` mm; k (the single slice) along z, spacing 1 mm.

    Args:
        camera_matrix: (3, 3) intrinsics, pixels.
        plane_normal: (3,) unit normal of the reference plane, camera frame.
        plane_offset_mm: the reference plane's offset, mm.
    """
    k = np.asarray(camera_matrix, np.float64)
    n = np.asarray(plane_normal, np.float64).ravel()
    if k.shape != (3, 3) or not np.all(np.isfinite(k)) or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise ValueError("camera_matrix: need finite (3, 3) intrinsics with fx, fy > 0, "
                         f"got {k.tolist()}")
    if n.shape != (3,) or not np.all(np.isfinite(n)) or abs(n[2]) < 1e-9:
        raise ValueError(f"plane_normal: need 3 finite values with a z component, got {n.tolist()}")
    z_ref = -float(plane_offset_mm) / n[2]
    if not np.isfinite(z_ref) or z_ref <= 0:
        raise ValueError("plane_offset_mm: the reference plane must lie in front of the "
                         f"camera, got z = {z_ref}")
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    m = np.eye(4)
    m[0, 0], m[1, 1] = z_ref / fx, z_ref / fy
    m[:3, 3] = (-cx * z_ref / fx, -cy * z_ref / fy, z_ref)
    return m


def decimate_points(points: npt.NDArray[np.float32], valid: npt.NDArray[np.bool_],
                    max_points: int) -> npt.NDArray[np.float32]:
    """(n, 3) float32: the valid, finite points (raster order), every k-th if
    more than ``max_points``.

    Args:
        points: (H, W, 3) camera-frame points, mm.
        valid: (H, W) bool.
        max_points: the most points returned (>= 1).
    """
    if max_points < 1:
        raise ValueError(f"max_points: must be >= 1, got {max_points}")
    pts = np.asarray(points).reshape(-1, 3)
    fin = np.isfinite(pts)
    ok = np.asarray(valid).reshape(-1) & fin[:, 0] & fin[:, 1] & fin[:, 2]  # (all(axis=1) is slow)
    idx = np.flatnonzero(ok)
    if idx.size > max_points:
        step = -(-idx.size // max_points)
        idx = idx[::step]
    return np.ascontiguousarray(pts[idx], dtype=np.float32)


#: POLYDATA attribute types (OpenIGTLink ``IGTL_POLY_ATTR_TYPE_*``) and their components:
#: scalar (1-255 components, given), vector (3), normal (3), tensor (9); the upper nibble
#: of the type byte flags point (0) or cell (1) data.
_ATTR_COMPONENTS = {0: None, 1: 3, 2: 3, 3: 9}


@dataclass(frozen=True)
class PolyAttribute:
    """One POLYDATA attribute: ``data`` (n, components) float32; ``kind`` its type byte."""

    name: str
    kind: int
    data: npt.NDArray[np.float32]


class CloudMessage(pyigtl.PolyDataMessage):  # type: ignore[misc]
    """POLYDATA with the content codec of the OpenIGTLink specification (all big-endian).

    pyigtl 0.3.4 packs the vertex array in the machine's byte order (little-endian on
    x86/ARM) and its unpack raises ``TypeError`` (it indexes a ``struct.Struct``), which its
    client thread swallows: a stock client receives no cloud and reports nothing. This codec
    follows the reference library (``igtl_polydata.c``, the one 3D Slicer links): a header
    of ten uint32 (points, then count and byte size of vertices, lines, polygons, triangle
    strips, then the number of attributes), the points as float32 x, y, z, each cell array
    VTK-style ``[n, i0, …, in-1]`` as uint32, then the attributes (headers of type uint8,
    components uint8, count uint32; NUL-terminated names padded to an even length; float32
    data). Header, CRC and framing stay pyigtl's. ``attributes`` is a list of
    :class:`PolyAttribute` (or None).
    """

    _ARRAYS = ("vertices", "lines", "polygons", "triangle_strips")

    @staticmethod
    def _cells(array: Any) -> int:
        if array is None:
            return 0
        a = np.asarray(array, np.int64).ravel()
        count, i = 0, 0
        while i < a.size:
            count += 1
            i += int(a[i]) + 1
        return count

    def _pack_content(self) -> bytes:
        pts = np.zeros((0, 3)) if self.points is None else np.asarray(self.points).reshape(-1, 3)
        attrs: list[PolyAttribute] = list(self.attributes or [])
        head = [len(pts)]
        for name in self._ARRAYS:
            arr = getattr(self, name)
            head += [self._cells(arr), 0 if arr is None else 4 * int(np.asarray(arr).size)]
        head.append(len(attrs))
        out = struct.pack(">10I", *head) + np.ascontiguousarray(pts, dtype=">f4").tobytes()
        for name in self._ARRAYS:
            arr = getattr(self, name)
            if arr is not None:
                out += np.ascontiguousarray(np.asarray(arr).ravel(), dtype=">u4").tobytes()
        names = b""
        for a in attrs:
            data = np.asarray(a.data, np.float32)
            rows = data.reshape(len(data), -1)
            out += struct.pack(">BBI", a.kind, rows.shape[1], rows.shape[0])
            names += a.name.encode("ascii") + b"\0"
        out += names + (b"\0" if len(names) % 2 else b"")
        for a in attrs:
            out += np.ascontiguousarray(a.data, dtype=">f4").tobytes()
        return out

    def _unpack_content(self, content: bytes) -> None:
        """Decode ``content`` per the specification; ``ValueError`` if its sizes disagree."""
        view, pos = memoryview(content), 0

        def take(n_bytes: int, what: str) -> memoryview:
            nonlocal pos
            if n_bytes < 0 or pos + n_bytes > len(view):
                raise ValueError(f"content: POLYDATA {what} needs {n_bytes} bytes at {pos}, "
                                 f"the message has {len(view)}")
            pos += n_bytes
            return view[pos - n_bytes:pos]

        head = struct.unpack(">10I", take(40, "header"))
        n_points = head[0]
        self.points = np.frombuffer(take(12 * n_points, "points"), ">f4").reshape(-1, 3)
        self.points = self.points.astype(np.float32)
        for i, name in enumerate(self._ARRAYS):
            size = head[2 + 2 * i]
            if size % 4:
                raise ValueError(f"content: POLYDATA {name} size {size} is not a multiple of 4")
            cells = np.frombuffer(take(size, name), ">u4").astype(np.uint32)
            setattr(self, name, cells if head[1 + 2 * i] else None)
        kinds = [struct.unpack(">BBI", take(6, "attribute header")) for _ in range(head[9])]
        names = []
        for _ in kinds:
            end = bytes(view[pos:pos + 256]).find(b"\0")
            if end < 0:
                raise ValueError("content: POLYDATA attribute name has no terminating NUL")
            names.append(bytes(take(end + 1, "attribute name"))[:-1].decode("ascii", "replace"))
        if sum(len(n) + 1 for n in names) % 2:
            take(1, "attribute name padding")
        attrs = []
        for (kind, n_comp, count), name in zip(kinds, names, strict=True):
            comps = _ATTR_COMPONENTS.get(kind & 0x0F) or n_comp
            data = np.frombuffer(take(4 * comps * count, f"attribute {name!r}"), ">f4")
            attrs.append(PolyAttribute(name, kind, data.reshape(count, comps).astype(np.float32)))
        self.attributes = attrs or None


def register_codecs() -> type[CloudMessage]:
    """Make pyigtl decode (and build) POLYDATA per the specification; returns the class used.

    Call once in a pyigtl client before it receives, e.g. ``pyigtl.OpenIGTLinkClient``: its
    ``FringescopeCloud`` messages then carry ``points`` ((n, 3) float32, mm) and ``vertices``.
    Idempotent; affects only the POLYDATA type of this process's pyigtl.
    """
    from pyigtl import messages

    messages.message_type_to_class_constructor["POLYDATA"] = CloudMessage
    return CloudMessage


class _Client:
    """One connection: a sender thread sending the newest packed message of each device."""

    def __init__(self, sock: socket.socket, address: Any) -> None:
        self.sock = sock
        self.address = address
        self._pending: OrderedDict[str, bytes] = OrderedDict()
        self._cond = threading.Condition()
        self._closed = False
        self.in_flight = 0  # bytes of the message being written now
        self.sent_messages = 0
        self.dropped_messages = 0

    def offer(self, device: str, data: bytes) -> None:
        with self._cond:
            if device in self._pending:
                self.dropped_messages += 1
                del self._pending[device]
            self._pending[device] = data  # newest per device, sent in arrival order
            self._cond.notify()

    def pending_bytes(self) -> int:
        with self._cond:
            return sum(len(b) for b in self._pending.values()) + self.in_flight

    def pending_messages(self) -> int:
        with self._cond:
            return len(self._pending) + (1 if self.in_flight else 0)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._pending.clear()
            self._cond.notify_all()
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)

    def send_loop(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._closed or bool(self._pending))
                if self._closed:
                    return
                _, data = self._pending.popitem(last=False)
                self.in_flight = len(data)
            try:
                self.sock.sendall(data)
            except OSError:
                self.close()
                return
            finally:
                with self._cond:
                    self.in_flight = 0
            self.sent_messages += 1


class _Handler(socketserver.BaseRequestHandler):
    server: _TcpServer

    def handle(self) -> None:
        owner = self.server.owner
        sock: socket.socket = self.request
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = _Client(sock, self.client_address)
        sender = threading.Thread(target=client.send_loop, name="fringescope-igtl-send",
                                  daemon=True)
        sender.start()
        owner._add(client)
        try:
            self._receive(sock, owner)
        finally:
            owner._remove(client)
            client.close()
            sender.join(5.0)

    def _receive(self, sock: socket.socket, owner: IgtlServer) -> None:
        while not owner.stopping:
            header = _recv_exact(sock, HEADER_SIZE)
            if header is None:
                return
            fields = pyigtl.MessageBase.parse_header(header)
            size = int(fields["body_size"])
            if size > MAX_BODY_BYTES:
                log.warning("OpenIGTLink client %s sent a %d-byte %s: disconnected",
                            self.client_address, size, fields["message_type"])
                return
            body = _recv_exact(sock, size)
            if body is None:
                return
            if fields["message_type"] == "TRANSFORM":
                msg = pyigtl.TransformMessage()
                try:
                    msg.unpack(fields, body)
                except (struct.error, ValueError) as exc:
                    log.warning("bad TRANSFORM from %s: %s", self.client_address, exc)
                    continue
                owner._received_transform(msg)


def _recv_exact(sock: socket.socket, n: int) -> bytes | None:
    buf = bytearray()
    while len(buf) < n:
        try:
            chunk = sock.recv(n - len(buf))
        except OSError:
            return None
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


class _TcpServer(socketserver.ThreadingTCPServer):
    allow_reuse_address = True
    daemon_threads = True

    def __init__(self, address: tuple[str, int], owner: IgtlServer) -> None:
        self.owner = owner
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        super().__init__(address, _Handler)


class IgtlServer:
    """Pushes every new result of ``results`` to all OpenIGTLink clients (see the module doc).

    Args:
        results: the live result slot (:class:`~app.service.store.LatestSlot`); the server
            subscribes to it.
        host, port: where to listen (port 0 picks a free one; see :attr:`port`).
        max_points: most points in one POLYDATA message.
        status: returns the instrument's status dict (sent as JSON).
        placement: returns the (4, 4) image placement (:func:`image_placement`) or ``None``
            (no calibration: identity, 1 mm pixels).
        poses: where received TRANSFORMs are kept (None: a store of its own).
    """

    def __init__(self, results: LatestSlot[Any], *, host: str = "127.0.0.1", port: int = 18944,
                 max_points: int = 100_000, status: Callable[[], dict[str, Any]] | None = None,
                 placement: Callable[[], npt.NDArray[np.float64] | None] | None = None,
                 poses: TrackerPoses | None = None,
                 changes: LatestSlot[Any] | None = None) -> None:
        if max_points < 1:
            raise ValueError(f"max_points: must be >= 1, got {max_points}")
        self.results = results
        self.host, self._port = host, port
        self.max_points = max_points
        self._status = status
        self._placement = placement
        self._queue: NewestQueue[tuple[int, Any] | None] = NewestQueue(maxsize=1)
        self._clients: list[_Client] = []
        self._lock = threading.Lock()
        self._server: _TcpServer | None = None
        self._threads: list[threading.Thread] = []
        self._unsubscribe: Callable[[], None] | None = None
        self.stopping = False
        self.poses = poses if poses is not None else TrackerPoses()
        self._last: list[tuple[str, bytes]] | None = None
        self.pushed = 0  # results packed and offered to the clients
        self.pushed_seq = 0  # the result sequence number pushed last
        self.last_error: str | None = None
        # the change map against a reference (its own slot; pushed when it comes)
        self.changes = changes
        self._last_change: tuple[str, bytes] | None = None
        self._unsubscribe_changes: Callable[[], None] | None = None

    @property
    def port(self) -> int:
        return self._server.server_address[1] if self._server is not None else self._port

    # -- lifecycle ----------------------------------------------------------------------
    def start(self) -> None:
        """Bind, then serve and push on daemon threads (``OSError`` if the port is taken)."""
        if self._server is not None:
            return
        self._server = _TcpServer((self.host, self._port), self)
        serve = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
                                 name="fringescope-igtl-serve", daemon=True)
        push = threading.Thread(target=self._push_loop, name="fringescope-igtl-push", daemon=True)
        self._threads = [serve, push]
        for t in self._threads:
            t.start()
        self._unsubscribe = self.results.subscribe(self._on_result)
        if self.changes is not None:
            self._unsubscribe_changes = self.changes.subscribe(self._on_change)
        seq, latest = self.results.latest()
        if latest is not None:
            self._queue.put((seq, latest))
        log.info("OpenIGTLink server on %s:%d", self.host, self.port)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Disconnect every client and join the threads (idempotent)."""
        if self._server is None or self.stopping:
            return
        self.stopping = True
        if self._unsubscribe is not None:
            self._unsubscribe()
        if self._unsubscribe_changes is not None:
            self._unsubscribe_changes()
        self._queue.put(None)
        self._server.shutdown()
        self._server.server_close()
        with self._lock:
            clients = list(self._clients)
        for c in clients:
            c.close()
        for t in self._threads:
            t.join(timeout_s)

    # -- figures ------------------------------------------------------------------------
    def clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def pending_bytes(self) -> int:
        """Bytes queued for (or being written to) all clients: bounded by design."""
        with self._lock:
            return sum(c.pending_bytes() for c in self._clients)

    def pending_messages(self) -> int:
        with self._lock:
            return sum(c.pending_messages() for c in self._clients)

    def latest_transforms(self) -> dict[str, dict[str, str | float | list[list[float]]]]:
        return self.poses.latest()

    # -- internals ----------------------------------------------------------------------
    def _on_result(self, seq: int, result: Any) -> None:
        # called on the reconstruction thread: hand over, never block
        self._queue.put((seq, result))

    def _on_change(self, _seq: int, change: Any) -> None:
        """A change map (the change thread): ``FringescopeChange``, float32 Δ in mm (NaN not
        compared), placed like the depth image, packed once and offered to every client."""
        try:
            matrix = self._placement() if self._placement is not None else None
            delta = np.ascontiguousarray(np.asarray(change.result.cmap.delta, np.float32)[None])
            data = pyigtl.ImageMessage(delta, ijk_to_world_matrix=np.eye(4) if matrix is None
                                       else matrix, world_coordinate_system="ras",
                                       timestamp=time.time(), device_name=CHANGE_DEVICE).pack()
        except Exception as exc:  # a bad map must not end the stream
            log.exception("OpenIGTLink: packing the change map failed")
            self.last_error = f"OpenIGTLink: packing the change map failed: {exc}"
            return
        with self._lock:
            self._last_change = (CHANGE_DEVICE, data)
            clients = list(self._clients)
        for c in clients:
            c.offer(CHANGE_DEVICE, data)

    def _add(self, client: _Client) -> None:
        with self._lock:
            self._clients.append(client)
            latest = self._last
            change = self._last_change
        log.info("OpenIGTLink client connected: %s", client.address)
        if latest is not None:  # a new client gets the latest result at once
            for device, data in latest:
                client.offer(device, data)
        if change is not None:
            client.offer(*change)

    def _remove(self, client: _Client) -> None:
        with self._lock:
            if client in self._clients:
                self._clients.remove(client)
        log.info("OpenIGTLink client left: %s", client.address)

    def _received_transform(self, msg: Any) -> None:
        rec = ReceivedTransform(str(msg.device_name), np.asarray(msg.matrix, float).tolist(),
                                float(msg.timestamp), time.time())
        self.poses.put(rec)

    def _push_loop(self) -> None:
        while not self.stopping:
            item = self._queue.get(0.5)
            if item is None:
                continue
            try:
                packed = self._pack(*item)
            except Exception as exc:  # a bad result must not end the stream
                log.exception("OpenIGTLink: packing failed")
                self.last_error = f"OpenIGTLink: packing failed: {exc}"
                continue
            with self._lock:
                self._last = packed
                clients = list(self._clients)
            for c in clients:
                for device, data in packed:
                    c.offer(device, data)
            self.pushed += 1
            self.pushed_seq = item[0]

    def _pack(self, seq: int, res: Any) -> list[tuple[str, bytes]]:
        """The four messages of a result, packed once for all clients."""
        ts = time.time()
        matrix = self._placement() if self._placement is not None else None
        if matrix is None:
            matrix = np.eye(4)
        depth = np.ascontiguousarray(np.asarray(res.depth, np.float32)[None])
        tex = np.asarray(res.texture, np.float32) * (255.0 / max(float(res.full_scale), 1e-9))
        tex8 = np.clip(np.nan_to_num(tex, nan=0.0), 0, 255).astype(np.uint8)[None]
        pts = decimate_points(res.points, res.valid, self.max_points)
        n = len(pts)
        verts = np.concatenate([[n], np.arange(n)]).astype(np.uint32) if n else None
        status = self._status() if self._status is not None else {}
        status = {**status, "seq": int(seq)}
        msgs = [
            pyigtl.ImageMessage(depth, ijk_to_world_matrix=matrix, world_coordinate_system="ras",
                                timestamp=ts, device_name=DEPTH_DEVICE),
            pyigtl.ImageMessage(tex8, ijk_to_world_matrix=matrix, world_coordinate_system="ras",
                                timestamp=ts, device_name=TEXTURE_DEVICE),
            CloudMessage(points=pts, vertices=verts, timestamp=ts, device_name=CLOUD_DEVICE),
            pyigtl.StringMessage(json.dumps(status, default=str), timestamp=ts,
                                 device_name=STATUS_DEVICE),
        ]
        return [(m.device_name, m.pack()) for m in msgs]

