"""OpenIGTLink server (issue 16) with pyigtl's own client: decoding, REST equality, clients,
memory."""

from __future__ import annotations

import importlib.metadata
import io
import json
import socket
import struct
import subprocess
import sys
import time
import tracemalloc
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pyigtl
import pytest
from fastapi.testclient import TestClient

from app.config import Settings
from app.main import create_app
from app.outputs.igtl import (
    CLOUD_DEVICE,
    DEPTH_DEVICE,
    STATUS_DEVICE,
    TEXTURE_DEVICE,
    CloudMessage,
    IgtlServer,
    PolyAttribute,
    check_igtl_settings,
    decimate_points,
    image_placement,
    register_codecs,
)
from app.service.reconstruction import LiveResult
from app.service.store import LatestSlot
from tests.helpers.live_app import live_settings, wait_for

register_codecs()  # pyigtl 0.3.4 cannot unpack POLYDATA itself


# -- pure parts ----------------------------------------------------------------------------
def test_image_placement_puts_pixels_on_the_reference_plane_at_the_axis() -> None:
    k = np.array([[1000.0, 0, 690.0], [0, 1250.0, 515.0], [0, 0, 1]])
    # a tilted reference plane n·X + offset = 0 crossing the optical axis at z = 80 mm
    n = np.array([0.0, 0.6, 0.8])
    m = image_placement(k, n, -64.0)
    z = 80.0
    assert m[2, 3] == pytest.approx(z)
    assert m[0, 0] == pytest.approx(z / 1000.0) and m[1, 1] == pytest.approx(z / 1250.0)
    # the principal point (u, v) = (cx, cy) maps onto the optical axis
    p = m @ np.array([690.0, 515.0, 0.0, 1.0])
    np.testing.assert_allclose(p[:3], [0.0, 0.0, z], atol=1e-12)
    # pixel (0, 0) on the ray through it, at z
    p0 = m @ np.array([0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(p0[:3], [-690.0 * z / 1000.0, -515.0 * z / 1250.0, z])
    with pytest.raises(ValueError, match="plane_offset_mm"):
        image_placement(k, n, 64.0)  # plane behind the camera
    with pytest.raises(ValueError, match="camera_matrix"):
        image_placement(np.eye(2), n, -64.0)
    with pytest.raises(ValueError, match="plane_normal"):
        image_placement(k, [1.0, 0.0, 0.0], -64.0)


def test_decimate_points_keeps_only_valid_finite_points_and_bounds_count() -> None:
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(40, 50, 3)).astype(np.float32)
    valid = rng.random((40, 50)) < 0.6
    pts[0, 0] = np.nan
    valid[0, 0] = True  # valid but not finite: dropped
    expected = pts.reshape(-1, 3)[valid.ravel() & np.isfinite(pts.reshape(-1, 3)).all(1)]
    np.testing.assert_array_equal(decimate_points(pts, valid, 10**6), expected)
    small = decimate_points(pts, valid, 100)
    assert 50 <= len(small) <= 100
    np.testing.assert_array_equal(small, expected[:: -(-len(expected) // 100)])
    with pytest.raises(ValueError, match="max_points"):
        decimate_points(pts, valid, 0)


def test_cloud_message_is_big_endian_per_spec_and_round_trips() -> None:
    pts = np.array([[1.5, -2.0, 80.25], [0.0, 3.0, 70.0], [9.0, 9.0, 9.0]], np.float32)
    verts = np.array([3, 0, 1, 2], np.uint32)
    msg = CloudMessage(points=pts, vertices=verts, device_name=CLOUD_DEVICE, timestamp=1.0)
    raw = msg.pack()
    body = raw[pyigtl.MessageBase.IGTL_HEADER_SIZE:]
    head = struct.unpack_from(">10I", body)
    assert head == (3, 1, 16, 0, 0, 0, 0, 0, 0, 0)
    assert np.frombuffer(body, ">f4", 9, 40).reshape(3, 3).tolist() == pts.tolist()
    assert np.frombuffer(body, ">u4", 4, 76).tolist() == [3, 0, 1, 2]
    header = pyigtl.MessageBase.parse_header(raw[:58])
    back = pyigtl.MessageBase.create_message("POLYDATA")
    back.unpack(header, body)
    np.testing.assert_array_equal(back.points, pts)
    assert back.vertices.tolist() == [3, 0, 1, 2] and back.device_name == CLOUD_DEVICE


def reference_polydata() -> tuple[bytes, np.ndarray]:
    """Content laid out by hand as ``igtl_polydata_pack`` (OpenIGTLink's C library) writes it.

    Two points, one vertex cell, one line cell, a 1-component scalar ``sigma`` and a normal
    ``Normal`` per point: names 6 + 7 bytes, so one byte of padding before the data.
    """
    pts = np.array([[1.0, 2.0, 3.0], [-4.5, 0.25, 90.0]], np.float32)
    out = struct.pack(">10I", 2, 1, 12, 1, 12, 0, 0, 0, 0, 2)
    out += b"".join(struct.pack(">f", v) for v in pts.ravel())
    out += struct.pack(">3I", 2, 0, 1) + struct.pack(">3I", 2, 1, 0)
    out += struct.pack(">BBI", 0, 1, 2) + struct.pack(">BBI", 2, 3, 2)
    out += b"sigma\0" + b"Normal\0" + b"\0"
    out += struct.pack(">2f", 0.5, 0.75) + struct.pack(">6f", 0, 0, 1, 0, 1, 0)
    return out, pts


def test_cloud_message_decodes_the_reference_layout_with_attributes() -> None:
    content, pts = reference_polydata()
    msg = CloudMessage()
    msg._unpack_content(content)
    np.testing.assert_array_equal(msg.points, pts)
    assert msg.vertices.tolist() == [2, 0, 1] and msg.lines.tolist() == [2, 1, 0]
    assert msg.polygons is None and msg.triangle_strips is None
    sigma, normal = msg.attributes
    assert (sigma.name, sigma.kind, sigma.data.tolist()) == ("sigma", 0, [[0.5], [0.75]])
    assert (normal.name, normal.kind) == ("Normal", 2)
    assert normal.data.tolist() == [[0, 0, 1], [0, 1, 0]]
    assert msg._pack_content() == content  # and packs back byte for byte
    attr = PolyAttribute("sigma", 0, np.array([[0.5], [0.75]], np.float32))
    again = CloudMessage(points=pts, vertices=[2, 0, 1], lines=[2, 1, 0], attributes=[attr, normal])
    assert again._pack_content() == content


@pytest.mark.parametrize("cut", [0, 39, 40 + 23, 40 + 24 + 12 + 5, -1])
def test_cloud_message_refuses_truncated_content(cut: int) -> None:
    content, _ = reference_polydata()
    with pytest.raises(ValueError, match="content: POLYDATA"):
        CloudMessage()._unpack_content(content[:cut])


def test_remote_host_needs_explicit_consent() -> None:
    check_igtl_settings("127.0.0.1", 18944, False)
    check_igtl_settings("0.0.0.0", None, False)  # off: nothing to check
    with pytest.raises(ValueError, match="FRINGESCOPE_IGTL_ALLOW_REMOTE"):
        check_igtl_settings("0.0.0.0", 18944, False)
    check_igtl_settings("0.0.0.0", 18944, True)
    with pytest.raises(ValueError, match="IGTL_ALLOW_REMOTE"):
        create_app(Settings(igtl_port=18944, igtl_host="192.168.7.2", viewer=False))


# -- a server on a bare result slot --------------------------------------------------------
def make_result(h: int = 120, w: int = 160, seed: int = 0) -> LiveResult:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0, 20, (h, w)).astype(np.float32)
    valid = rng.random((h, w)) < 0.7
    depth[~valid] = np.nan
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float32)
    points = np.stack([uu * 0.1, vv * 0.1, 90.0 - depth], axis=-1).astype(np.float32)
    points[~valid] = np.nan
    return LiveResult(
        depth=depth,
        points=points,
        valid=valid,
        reason=np.zeros((h, w), np.uint8),
        texture=rng.uniform(0, 255, (h, w)).astype(np.float32),
        modulation=np.ones((h, w), np.float32),
        motion=None,
        mode="set",
        frame_indices=list(range(16)),
        timestamps=[0.0] * 16,
        exposure_ms=30.0,
        led="green",
        full_scale=255.0,
        received_s=0.0,
        published_s=0.0,
        recon_ms=1.0,
    )


@pytest.fixture()
def slot_server() -> Iterator[tuple[LatestSlot[Any], IgtlServer]]:
    slot: LatestSlot[Any] = LatestSlot()
    server = IgtlServer(slot, port=0, max_points=5000, status=lambda: {"state": "running"})
    server.start()
    try:
        yield slot, server
    finally:
        server.stop()


def client_for(server: IgtlServer) -> pyigtl.OpenIGTLinkClient:
    return pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=server.port)


def wait_until(cond: Any, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.01)


def test_slot_messages_decode_two_clients_and_reconnect(slot_server: Any) -> None:
    slot, server = slot_server
    a, b = client_for(server), client_for(server)
    try:
        wait_until(lambda: server.clients() == 2)
        res = make_result(seed=1)
        res.seq = slot.publish(res)
        for client in (a, b):
            depth = client.wait_for_message(DEPTH_DEVICE, timeout=10)
            assert depth is not None and depth.image.shape == (1, 120, 160)
            # NaN where invalid, bit for bit
            np.testing.assert_array_equal(depth.image[0], res.depth)
            tex = client.wait_for_message(TEXTURE_DEVICE, timeout=10)
            assert tex.image.dtype == np.uint8 and tex.image.shape == (1, 120, 160)
            cloud = client.wait_for_message(CLOUD_DEVICE, timeout=10)
            np.testing.assert_array_equal(
                cloud.points, decimate_points(res.points, res.valid, 5000)
            )
            assert cloud.vertices[0] == len(cloud.points)
            st = json.loads(client.wait_for_message(STATUS_DEVICE, timeout=10).string)
            assert st == {"state": "running", "seq": 1}
        a.stop()  # one client leaves: the other keeps receiving
        wait_until(lambda: server.clients() == 1)
        res2 = make_result(seed=2)
        res2.seq = slot.publish(res2)
        got = b.wait_for_message(DEPTH_DEVICE, timeout=10)
        np.testing.assert_array_equal(got.image[0], res2.depth)
        a = client_for(server)  # and comes back: it gets the latest result at once
        got = a.wait_for_message(DEPTH_DEVICE, timeout=10)
        np.testing.assert_array_equal(got.image[0], res2.depth)
        assert server.clients() == 2
    finally:
        a.stop()
        b.stop()


#: a stock pyigtl client in a fresh interpreter (nothing of this process's pyigtl patched):
#: argv host, port, "stock" or "helper", output .npy; prints the depth shape and whether a
#: cloud arrived. With "helper" it first calls the public helper, as the README says.
STOCK_CLIENT = """
import json, sys, numpy as np, pyigtl
host, port, mode, out = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4]
if mode == "helper":
    from app.outputs.igtl import register_codecs
    register_codecs()
client = pyigtl.OpenIGTLinkClient(host=host, port=port)
depth = client.wait_for_message("FringescopeDepth", timeout=20)
cloud = client.wait_for_message("FringescopeCloud", timeout=3 if mode == "stock" else 20)
if cloud is not None:
    np.save(out, np.asarray(cloud.points, np.float32))
print(json.dumps({"depth": None if depth is None else list(depth.image.shape),
                  "cloud": cloud is not None,
                  "vertices": None if cloud is None else int(cloud.vertices[0])}))
client.stop()
"""


def run_stock_client(server: IgtlServer, mode: str, out: Path) -> dict[str, Any]:
    proc = subprocess.run([sys.executable, "-c", STOCK_CLIENT, "127.0.0.1", str(server.port), mode,
                           str(out)], capture_output=True, text=True, timeout=120,
                          cwd=Path(__file__).resolve().parents[2])
    assert proc.returncode == 0, proc.stderr
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return result


def test_stock_pyigtl_client_gets_the_cloud_with_the_public_helper(slot_server: Any,
                                                                    tmp_path: Path) -> None:
    slot, server = slot_server
    res = make_result(seed=4)
    res.seq = slot.publish(res)
    wait_until(lambda: server.pushed_seq == res.seq)
    want = decimate_points(res.points, res.valid, 5000)
    got = run_stock_client(server, "helper", tmp_path / "cloud.npy")
    assert got == {"depth": [1, 120, 160], "cloud": True, "vertices": len(want)}
    np.testing.assert_array_equal(np.load(tmp_path / "cloud.npy"), want)
    # why the helper exists: stock 0.3.4 (its __version__ says 0.3.2) drops the cloud silently
    if importlib.metadata.version("pyigtl") == "0.3.4":
        stock = run_stock_client(server, "stock", tmp_path / "none.npy")
        assert stock == {"depth": [1, 120, 160], "cloud": False, "vertices": None}


def test_transform_received_is_kept_for_the_recorder(slot_server: Any) -> None:
    _, server = slot_server
    client = client_for(server)
    try:
        wait_until(lambda: server.clients() == 1)
        pose = np.array([[0, -1, 0, 10], [1, 0, 0, 20], [0, 0, 1, 30], [0, 0, 0, 1]], np.float32)
        client.send_message(pyigtl.TransformMessage(pose, device_name="ScopeToTracker"), wait=True)
        wait_until(lambda: "ScopeToTracker" in server.latest_transforms())
        got = server.latest_transforms()["ScopeToTracker"]
        assert got["matrix"] == pose.tolist()
    finally:
        client.stop()


def server_heap_bytes() -> int:
    """Bytes the IGTL server's own code holds now (allocated in a call from app/outputs/igtl.py:
    its queues, packed messages, per-client buffers), from tracemalloc. The process's RSS is not
    used: it also counts the reader client's decoding and whatever the allocator keeps from the
    tests before (glibc's moving mmap threshold leaves freed multi-MB blocks resident), so it
    moved by more than one set between runs of an unchanged server."""
    snapshot = tracemalloc.take_snapshot().filter_traces(
        [tracemalloc.Filter(True, "*/app/outputs/igtl.py", all_frames=True)]
    )
    return sum(stat.size for stat in snapshot.statistics("filename"))


def test_client_that_never_reads_does_not_grow_the_server(slot_server: Any) -> None:
    slot, server = slot_server
    tracemalloc.start(32)  # deep enough to reach igtl.py from numpy's and pyigtl's allocations
    lazy = socket.create_connection(("127.0.0.1", server.port))
    lazy.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    reader = client_for(server)
    try:
        wait_until(lambda: server.clients() == 2)
        big = [make_result(480, 640, seed=s) for s in range(3)]
        one_set = sum(_packed_sizes(server, big[0]))
        for r in big:  # warm-up: buffers fill, the lazy client's socket blocks
            r.seq = slot.publish(r)
            time.sleep(0.05)
        time.sleep(0.5)
        held0 = server_heap_bytes()
        peak_pending = 0
        for i in range(60):
            r = big[i % 3]
            r.seq = slot.publish(r)
            time.sleep(0.01)
            peak_pending = max(peak_pending, server.pending_bytes())
        wait_until(lambda: server.pushed_seq == slot.seq, 30)
        grown = server_heap_bytes() - held0
        # per client: at most the newest message of each device plus one being written
        assert peak_pending <= 2 * (one_set + max(_packed_sizes(server, big[0])))
        assert server.pending_messages() <= 2 * 5
        assert grown < 3 * one_set, (
            f"the server's heap grew by {grown / 1e6:.1f} MB (one set {one_set / 1e6:.1f} MB)"
        )
        got = reader.wait_for_message(DEPTH_DEVICE, timeout=10)  # the reader is not held up
        assert got is not None
    finally:
        tracemalloc.stop()
        reader.stop()
        lazy.close()


def _packed_sizes(server: IgtlServer, res: LiveResult) -> list[int]:
    return [len(b) for _, b in server._pack(0, res)]


# -- the live app: IMAGE equals REST ----------------------------------------------------------
@pytest.fixture(scope="module")
def live_igtl(
    tmp_path_factory: pytest.TempPathFactory, sim_calibration_file: Path
) -> Iterator[TestClient]:
    settings = live_settings(tmp_path_factory.mktemp("igtl"), sim_calibration_file, igtl_port=0,
                             igtl_max_points=20_000)
    with TestClient(create_app(settings)) as client:
        wait_for(client, lambda st: st["results_published"] >= 1, 120)
        yield client


def test_live_image_equals_rest_depth_bit_for_bit(live_igtl: TestClient) -> None:
    server: IgtlServer = live_igtl.app.state.igtl  # type: ignore[attr-defined]
    assert live_igtl.post("/api/acquisition/stop").status_code == 200
    try:
        time.sleep(1.0)
        inst = live_igtl.app.state.instrument  # type: ignore[attr-defined]
        wait_until(lambda: server.pushed_seq == inst.results.seq, 10)  # the last result is packed
        client = client_for(server)  # a new client gets the latest result at once
        try:
            t0 = time.monotonic()
            msg = client.wait_for_message(DEPTH_DEVICE, timeout=10)
            assert msg is not None and time.monotonic() - t0 < 5
            rest = np.load(io.BytesIO(live_igtl.get("/api/depth/latest?format=npy").content))
            assert msg.image.dtype == np.float32 and msg.image.shape == (1, *rest.shape)
            # bit for bit, NaN included
            assert msg.image[0].tobytes() == rest.astype("<f4").tobytes()
            cal = live_igtl.app.state.instrument.calibration  # type: ignore[attr-defined]
            np.testing.assert_allclose(
                msg.ijk_to_world_matrix[:3, :2],
                image_placement(cal.camera_matrix, cal.plane_normal, cal.plane_offset_mm)[:3, :2],
                rtol=1e-6,
            )
            cloud = client.wait_for_message(CLOUD_DEVICE, timeout=10)
            res = live_igtl.app.state.instrument.latest_result()  # type: ignore[attr-defined]
            want = decimate_points(res.points, res.valid, 20_000)
            np.testing.assert_array_equal(cloud.points, want)
            assert 0 < len(cloud.points) <= 20_000
            z = cloud.points[:, 2]
            assert np.all(np.isfinite(cloud.points)) and 10 < np.median(z) < 500  # mm, in front
            st = json.loads(client.wait_for_message(STATUS_DEVICE, timeout=10).string)
            assert st["state"] in ("stopped", "running") and st["seq"] == res.seq
        finally:
            client.stop()
    finally:
        assert live_igtl.post("/api/acquisition/start").status_code == 200


def test_live_received_transform_is_recorded_with_the_sets(live_igtl: TestClient) -> None:
    server: IgtlServer = live_igtl.app.state.igtl  # type: ignore[attr-defined]
    client = client_for(server)
    try:
        pose = np.array([[1, 0, 0, 5], [0, 1, 0, -3], [0, 0, 1, 120], [0, 0, 0, 1]], np.float32)
        wait_until(lambda: server.clients() >= 1)
        client.send_message(pyigtl.TransformMessage(pose, device_name="ScopeToRef"), wait=True)
        wait_until(lambda: "ScopeToRef" in server.latest_transforms())
        assert live_igtl.post("/api/recording/start", json={"name": "igt-1"}).status_code == 200
        wait_until(lambda: live_igtl.get("/api/recording").json()["sets"] >= 1, 60)
        stopped = live_igtl.post("/api/recording/stop").json()["stopped"]
    finally:
        client.stop()
    first = stopped["sets"][0]
    assert first["igtl_transforms"]["ScopeToRef"]["matrix"] == pose.tolist()
    root = Path(live_igtl.app.state.settings.data_dir) / "recordings" / "igt-1"  # type: ignore[attr-defined]
    capture = json.loads((root / first["folder"] / "capture.json").read_text())
    assert capture["igtl_transforms"]["ScopeToRef"]["matrix"] == pose.tolist()
