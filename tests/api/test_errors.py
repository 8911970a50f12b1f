"""Errors reach clients through one mapping: domain errors with their reason, bugs as a logged 500.

Malformed zip uploads of every kind are 4xx naming the fault (the app is built but not
started: the upload is refused before the instrument is asked for anything).
"""

from __future__ import annotations

import io
import json
import logging
import struct
import zipfile
import zlib
from pathlib import Path

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.api.errors import install_error_handlers
from app.config import Settings
from app.core.errors import Conflict, DeviceUnavailable, DomainError, InvalidRequest, NotFound
from app.main import create_app

CAPTURE = json.dumps({"format": "fringescope.capture/1", "exposure_ms": 20.0, "led": "green",
                      "frames": [f"frame_{i:02d}.png" for i in range(16)]}).encode()


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> TestClient:
    settings = Settings(data_dir=tmp_path_factory.mktemp("errors"), viewer=False, autostart=False,
                        max_upload_mb=1.0)
    return TestClient(create_app(settings))  # no lifespan: nothing starts


def _zip(members: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=method) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _post_zip(client: TestClient, data: bytes) -> tuple[int, str]:
    r = client.post("/api/reconstruct", content=data, headers={"content-type": "application/zip"})
    return r.status_code, r.json().get("detail", "")


def _patch_local_header(data: bytes, offset: int, fmt: str, value: int) -> bytes:
    """Change a field of the first member's local header (and the central directory's copy)."""
    out = bytearray(data)
    struct.pack_into(fmt, out, offset, value)
    central = out.find(b"PK\x01\x02")
    struct.pack_into(fmt, out, central + offset + 2, value)  # central fields sit 2 bytes further
    return bytes(out)


def test_bad_crc_is_422(client: TestClient) -> None:
    data = bytearray(_zip({"capture.json": CAPTURE}, zipfile.ZIP_STORED))
    data[30 + len("capture.json") + 5] ^= 0xFF  # flip a byte of the stored content
    code, detail = _post_zip(client, bytes(data))
    assert code == 422 and "CRC" in detail, detail


def test_encryption_flag_is_422(client: TestClient) -> None:
    data = _patch_local_header(_zip({"capture.json": CAPTURE}), 6, "<H", 0x1)
    code, detail = _post_zip(client, data)
    assert code == 422 and "encrypted" in detail, detail


def test_unknown_compression_method_is_422(client: TestClient) -> None:
    data = _patch_local_header(_zip({"capture.json": CAPTURE}), 8, "<H", 99)
    code, detail = _post_zip(client, data)
    assert code == 422 and "compression method 99" in detail, detail


@pytest.mark.parametrize("keep", [0.3, 0.7, 0.95])
def test_truncated_zip_is_422(client: TestClient, keep: float) -> None:
    data = _zip({"capture.json": CAPTURE, "frame_00.png": bytes(range(256)) * 64})
    code, detail = _post_zip(client, data[: int(len(data) * keep)])
    assert code == 422 and "zip" in detail, detail


def test_corrupt_deflate_stream_is_422(client: TestClient) -> None:
    payload = b"x" * 5000
    data = bytearray(_zip({"capture.json": CAPTURE, "frame_00.png": payload}))
    start = data.find(b"PK\x03\x04", 10) + 30 + len("frame_00.png")
    data[start:start + 4] = b"\xff\xff\xff\xff"
    code, detail = _post_zip(client, bytes(data))
    assert code == 422 and "corrupt" in detail, detail


def test_zip_bomb_ratio_is_refused(client: TestClient) -> None:
    # ~1000x, under the size limit
    bomb = _zip({"capture.json": CAPTURE, "frame_00.png": b"\0" * 900_000})
    assert len(bomb) < 5_000
    code, detail = _post_zip(client, bomb)
    assert code == 422 and "zip bomb" in detail, detail


def test_lying_size_header_is_caught(client: TestClient) -> None:
    """A member that unpacks to more than its header claims is refused, not written."""
    real = b"\0" * 200_000
    data = _zip({"capture.json": CAPTURE, "frame_00.png": real})
    out = bytearray(data)
    second = out.find(b"PK\x03\x04", 10)
    struct.pack_into("<I", out, second + 22, 1000)  # local uncompressed size
    central = out.find(b"PK\x01\x02", out.find(b"PK\x01\x02") + 4)
    struct.pack_into("<I", out, central + 24, 1000)  # central uncompressed size
    code, detail = _post_zip(client, bytes(out))
    assert 400 <= code < 500, detail
    assert "frame_00.png" in detail, detail


def test_unpacked_size_over_the_limit_is_413(client: TestClient) -> None:
    big = _zip({"capture.json": CAPTURE, "frame_00.png": zlib.compress(b"")[:0] + bytes(1_100_000)})
    code, detail = _post_zip(client, big)
    assert code in (413, 422) and detail


@pytest.mark.parametrize("name", ["../capture.json", "/etc/capture.json", "set/../../capture.json",
                                  "C:/capture.json", "..\\capture.json"])
def test_path_traversal_is_422(client: TestClient, name: str) -> None:
    code, detail = _post_zip(client, _zip({name: CAPTURE}))
    assert code == 422 and "outside" in detail, detail


@pytest.mark.parametrize("body", [b"", b"hello", b"PK\x05\x06" + b"\0" * 18, b"PK\x03\x04garbage"])
def test_not_a_zip_is_422(client: TestClient, body: bytes) -> None:
    code, detail = _post_zip(client, body)
    assert code == 422 and "zip" in detail, detail


def test_multipart_zip_with_traversal_is_422(client: TestClient) -> None:
    data = _zip({"../../capture.json": CAPTURE})
    r = client.post("/api/reconstruct", files=[("file", ("set.zip", data, "application/zip"))])
    assert r.status_code == 422 and "outside" in r.json()["detail"]


def test_calibration_upload_that_is_not_a_calibration_is_422(client: TestClient) -> None:
    for body in (b"[1, 2]", b"{}", b'{"format": "fringescope.calibration/1"}', b"\xff\xfe"):
        r = client.put(
            "/api/calibration/file", content=body, headers={"content-type": "application/json"}
        )
        assert r.status_code == 422 and r.json()["detail"], (body, r.text)


def test_no_session_is_a_conflict_not_503(client: TestClient) -> None:
    for method, path in (
        ("GET", "/api/calibration/session"),
        ("GET", "/api/calibration/session/poses"),
        ("POST", "/api/calibration/session/solve"),
        ("POST", "/api/calibration/session/activate"),
    ):
        r = client.request(method, path)
        assert r.status_code == 409 and "session" in r.json()["detail"], (path, r.text)


def _app_raising(exc: BaseException) -> FastAPI:
    app = FastAPI()
    install_error_handlers(app)

    @app.get("/boom")
    def boom() -> None:
        raise exc

    return app


@pytest.mark.parametrize(
    "exc, code",
    [
        (InvalidRequest("bad x"), 422),
        (Conflict("not now"), 409),
        (NotFound("no y"), 404),
        (DeviceUnavailable("unplugged"), 503),
    ],
)
def test_each_domain_error_has_its_status_and_reason(exc: DomainError, code: int) -> None:
    r = TestClient(_app_raising(exc)).get("/boom")
    assert r.status_code == code and r.json() == {"detail": exc.detail}


@pytest.mark.parametrize(
    "exc", [ValueError("x: must be positive"), IndexError("list index"), KeyError("k")]
)
def test_anything_else_is_a_logged_500(exc: Exception, caplog: pytest.LogCaptureFixture) -> None:
    """A ValueError or IndexError from a bug is not the client's fault: 500, traceback in the
    log."""
    with caplog.at_level(logging.ERROR, logger="fringescope.api"):
        r = TestClient(_app_raising(exc), raise_server_exceptions=False).get("/boom")
    assert r.status_code == 500 and type(exc).__name__ in r.json()["detail"]
    assert str(exc) not in r.json()["detail"] or isinstance(exc, KeyError)
    record = next(rec for rec in caplog.records if rec.name == "fringescope.api")
    assert record.exc_info is not None and record.exc_info[0] is type(exc)


def test_every_route_documents_what_it_can_answer(tmp_path: Path) -> None:
    """Each operation that needs the instrument lists 503; one that takes input lists 422 with a
    schema."""
    spec = create_app(Settings(data_dir=tmp_path, viewer=False)).openapi()
    # these answer without the instrument: the legend and the health/sign-in routes
    no_instrument = {"/api/reason/legend", "/healthz", "/api/auth", "/api/login", "/api/logout"}
    for path, item in spec["paths"].items():
        for method, op in item.items():
            codes = set(op["responses"])
            assert "503" in codes or path in no_instrument, (method, path, codes)
            if op.get("parameters") or op.get("requestBody"):
                assert "422" in codes, (method, path, codes)
                assert (
                    "detail"
                    in op["responses"]["422"]["content"]["application/json"]["schema"]["properties"]
                )


# -- hostile names, nesting and numbers in uploads ---------------------------------------------
def test_a_zip_member_name_of_300_characters_is_422(client: TestClient) -> None:
    members = {"set/capture.json": CAPTURE, "set/" + "f" * 300 + ".png": b"x"}
    code, detail = _post_zip(client, _zip(members))
    assert code == 422 and "304 characters long" in detail and "\n" not in detail, detail


def test_a_multipart_file_name_of_300_characters_is_422(client: TestClient) -> None:
    files = [("files", ("capture.json", CAPTURE, "application/json")),
             ("files", ("g" * 300 + ".png", b"x", "image/png"))]
    r = client.post("/api/phase", files=files)
    assert r.status_code == 422 and "304 characters long" in r.json()["detail"], r.text


def test_a_capture_json_nested_100000_deep_is_422(client: TestClient) -> None:
    deep = b'{"format": "fringescope.capture/1", "x": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    for body in (deep, b"[" * 100_000):
        code, detail = _post_zip(client, _zip({"capture.json": body}, zipfile.ZIP_STORED))
        assert code == 422 and detail.startswith("capture.json: JSON nested 100"), detail


def test_non_finite_numbers_in_capture_json_are_422_naming_the_key(client: TestClient) -> None:
    meta = CAPTURE.replace(b'"exposure_ms": 20.0', b'"exposure_ms": NaN')
    code, detail = _post_zip(client, _zip({"capture.json": meta}))
    assert code == 422, detail
    assert detail.startswith("capture.json.exposure_ms: NaN is not a finite"), detail


def test_a_frame_that_is_not_png_or_tiff_is_refused_before_decoding(client: TestClient) -> None:
    import cv2
    import numpy as np

    from tests.helpers.hostile import capture_json

    ok, jpeg = cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))
    frames = {f"frame_{i:02d}.png": jpeg.tobytes() for i in range(16)}
    members = {"capture.json": capture_json(), **frames}
    code, detail = _post_zip(client, _zip(members))
    assert code == 422 and detail == "frame_00.png: not a PNG, TIFF or .npy.zst frame", detail


def test_a_calibration_file_nested_100000_deep_is_422_and_unchanged(client: TestClient) -> None:
    deep = (b'{"format": "fringescope.calibration/2", "model": ' + b'{"a": ' * 100_000 + b"1"
            + b"}" * 100_001)
    as_json = {"content-type": "application/json"}
    r = client.put("/api/calibration/file", content=deep, headers=as_json)
    assert r.status_code == 422, r.text
    assert r.json()["detail"].startswith("body: JSON nested 100001 levels"), r.text
    as_text = {"content-type": "text/plain"}
    r = client.put("/api/calibration/file", content=b'{"format": NaN}', headers=as_text)
    assert r.status_code == 422 and r.json()["detail"].startswith("body.format: NaN"), r.text
