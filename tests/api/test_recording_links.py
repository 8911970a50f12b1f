"""Symbolic links planted in a recording are never followed: not zipped, listed, nor read.

The real app (built, its lifespan not needed: recordings are files) over its REST routes,
on a recording written by :class:`Recording` and then tampered with on disk.
"""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.capture.captureset import CaptureSet
from app.capture.recording import Recording, recordings_root
from app.config import Settings
from app.main import create_app

SECRET = b"root:x:0:0:secret-marker-do-not-serve\n"


@pytest.fixture()
def planted(tmp_path: Path) -> Iterator[tuple[TestClient, Path, Path]]:
    """A recording ``op`` of two sets, a secret file outside the data folder, and the client."""
    data = tmp_path / "data"
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "passwd").write_bytes(SECRET)
    rng = np.random.default_rng(0)
    rec = Recording(recordings_root(data), "op")
    for _ in range(2):
        frames = rng.integers(0, 255, size=(16, 12, 16), dtype=np.uint8)
        rec.add_set(
            CaptureSet(frames=frames), depth_mm=rng.uniform(0, 30, (12, 16)).astype(np.float32)
        )
    rec.close()
    client = TestClient(create_app(Settings(data_dir=data, viewer=False, autostart=False)))
    yield client, recordings_root(data) / "op", outside


def _zip_names_and_bytes(client: TestClient, name: str) -> tuple[list[str], bytes]:
    r = client.get(f"/api/recordings/{name}.zip")
    assert r.status_code == 200, r.text
    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        return zf.namelist(), b"".join(zf.read(n) for n in zf.namelist())


def test_a_link_to_a_file_in_a_set_is_not_zipped(planted: tuple[TestClient, Path, Path]) -> None:
    client, rec, outside = planted
    (rec / "set_0000" / "passwd").symlink_to(outside / "passwd")
    (rec / "set_0000" / "notes.txt").symlink_to("/etc/passwd")
    names, content = _zip_names_and_bytes(client, "op")
    assert "op/set_0000/frame_00.png" in names and "op/set_0001/depth.npy" in names
    assert not any(n.endswith(("passwd", "notes.txt")) for n in names), names
    assert SECRET not in content


def test_a_set_folder_that_is_a_link_is_not_listed_zipped_or_read(
    planted: tuple[TestClient, Path, Path],
) -> None:
    client, rec, outside = planted
    shutil.rmtree(rec / "set_0001")
    (outside / "depth.npy").write_bytes(SECRET)
    (rec / "set_0001").symlink_to(outside)  # session.json still lists set_0001
    names, content = _zip_names_and_bytes(client, "op")
    assert not any(n.startswith("op/set_0001") for n in names), names
    assert SECRET not in content
    meta = client.get("/api/recordings/op").json()
    assert [s["folder"] for s in meta["sets"]] == ["set_0000"]
    r = client.get("/api/recordings/op/sets/1/depth")
    assert r.status_code == 404 and SECRET not in r.content, r.text


def test_a_link_to_etc_is_not_followed(planted: tuple[TestClient, Path, Path]) -> None:
    client, rec, _ = planted
    shutil.rmtree(rec / "set_0001")
    (rec / "set_0001").symlink_to("/etc")
    names, content = _zip_names_and_bytes(client, "op")
    assert not any(n.startswith("op/set_0001") for n in names), names
    assert b"root:" not in content


def test_a_linked_depth_map_or_frame_is_not_read(planted: tuple[TestClient, Path, Path]) -> None:
    client, rec, outside = planted
    np.save(outside / "depth.npy", np.full((12, 16), 7.0, np.float32))
    (rec / "set_0000" / "depth.npy").unlink()
    (rec / "set_0000" / "depth.npy").symlink_to(outside / "depth.npy")
    r = client.get("/api/recordings/op/sets/0/depth")
    assert r.status_code == 404 and "symbolic link" in r.json()["detail"], r.text
    assert client.get("/api/recordings/op/sets/1/depth").status_code == 200  # the untouched set
    (rec / "set_0001" / "frame_03.png").unlink()
    (rec / "set_0001" / "frame_03.png").symlink_to(outside / "passwd")
    r = client.post(
        "/api/measure",
        json={"kind": "length", "points": [[1, 1], [5, 5]], "recording": "op", "index": 1},
    )
    assert r.status_code == 404 and "symbolic link" in r.json()["detail"], r.text


def test_a_recording_that_is_a_link_is_not_listed_nor_served(
    planted: tuple[TestClient, Path, Path],
) -> None:
    client, rec, outside = planted
    (rec.parent / "alias").symlink_to(rec)  # another name for "op"
    (rec.parent / "escape").symlink_to(outside)
    listed = [r["name"] for r in client.get("/api/recordings").json()]
    assert listed == ["op"]
    for name in ("alias", "escape"):
        assert client.get(f"/api/recordings/{name}").status_code == 404
        assert client.get(f"/api/recordings/{name}.zip").status_code == 404
        assert client.delete(f"/api/recordings/{name}").status_code == 404
    assert (rec / "session.json").is_file()  # deleting the alias removed nothing


def test_a_linked_session_file_is_not_read(planted: tuple[TestClient, Path, Path]) -> None:
    client, rec, outside = planted
    fake = json.loads((rec / "session.json").read_text())
    (outside / "session.json").write_text(json.dumps({**fake, "name": "forged"}))
    (rec / "session.json").unlink()
    (rec / "session.json").symlink_to(outside / "session.json")
    assert client.get("/api/recordings").json() == []
    r = client.get("/api/recordings/op")
    assert r.status_code == 404 and "forged" not in r.text
    assert client.get("/api/recordings/op.zip").status_code == 404
