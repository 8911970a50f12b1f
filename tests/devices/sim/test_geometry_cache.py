"""The simulator's traced geometry on disk: same frames as tracing, keys, bad files, pruning."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from app.core.schedule import PatternSchedule
from app.devices.sim import geometry_cache
from app.devices.sim import world as world_mod
from app.devices.sim.optics import rig_by_name
from app.devices.sim.render import Renderer
from app.devices.sim.scenes import build_scene
from app.devices.sim.world import SimulatedWorld

SCENE = "intestine_flap"


def _frame(renderer: Renderer, pattern: int) -> np.ndarray:
    state = np.array([12345], np.uint64)
    return renderer.render(pattern, 0.0, state, exposure_ms=30.0, bits=8)


def test_a_renderer_from_cached_geometry_renders_the_same_frames(tmp_path: Path) -> None:
    rig = rig_by_name("default", distortion=True)
    traced = Renderer(build_scene(SCENE, rig), rig)
    key = geometry_cache.cache_key((SCENE, rig.name, True, PatternSchedule()))
    geometry_cache.save(tmp_path, key, traced.geometry())
    (stored,) = tmp_path.glob("sim-geometry-*.npz")
    assert key in stored.name and not list(tmp_path.glob(".*.tmp"))  # written whole, renamed
    loaded = geometry_cache.load(tmp_path, key)
    assert loaded is not None and set(loaded) == set(traced.geometry())
    cached = Renderer(build_scene(SCENE, rig), rig, geometry=loaded)
    for pattern in (0, 5, 15):
        assert np.array_equal(_frame(cached, pattern), _frame(traced, pattern))
    assert np.array_equal(cached.truth(0.0)[0], traced.truth(0.0)[0], equal_nan=True)


def test_keys_follow_every_parameter() -> None:
    base = (SCENE, "default", True, PatternSchedule(), 1.0)
    keys = {geometry_cache.cache_key(base),
            geometry_cache.cache_key(("anastomosis", *base[1:])),
            geometry_cache.cache_key((SCENE, "endoscope", *base[2:])),
            geometry_cache.cache_key((*base[:3], PatternSchedule((1, 6, 36), 4), 1.0)),
            geometry_cache.cache_key((*base[:4], 2.2))}
    assert len(keys) == 5 and geometry_cache.cache_key(base) in keys


def test_an_unreadable_file_is_removed_and_traced_again(tmp_path: Path) -> None:
    bad = tmp_path / "sim-geometry-0123.npz"
    bad.write_bytes(b"PK\x03\x04 not a zip archive")
    assert geometry_cache.load(tmp_path, "0123") is None
    assert not bad.exists()
    assert geometry_cache.load(tmp_path, "absent") is None


def test_at_most_max_files_are_kept_least_recently_used_first(tmp_path: Path) -> None:
    arrays = {"a": np.arange(3.0)}
    for i in range(geometry_cache.MAX_FILES + 2):
        geometry_cache.save(tmp_path, f"k{i}", arrays)
        os.utime(tmp_path / f"sim-geometry-k{i}.npz", (1000.0 + i, 1000.0 + i))
    geometry_cache.load(tmp_path, "k2")  # used now: the newest
    geometry_cache.save(tmp_path, "new", arrays)
    kept = sorted(p.name for p in tmp_path.glob("sim-geometry-*.npz"))
    assert len(kept) == geometry_cache.MAX_FILES
    assert "sim-geometry-k2.npz" in kept and "sim-geometry-new.npz" in kept


def test_a_world_with_a_cache_folder_stores_its_scene_for_the_next_start(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(world_mod, "_RENDERERS", {})  # no renderer of an earlier test in memory
    first = SimulatedWorld(SCENE, seed=1, cache_dir=tmp_path)
    frame = first.render(3, 0.0, exposure_ms=30.0, gain=1.0, bits=8)
    t0 = time.monotonic()
    while not list(tmp_path.glob("sim-geometry-*.npz")) and time.monotonic() - t0 < 60.0:
        time.sleep(0.1)  # written by a background thread
    assert len(list(tmp_path.glob("sim-geometry-*.npz"))) == 1
    monkeypatch.setattr(world_mod, "_RENDERERS", {})  # a new process: only the disk remembers

    def no_tracing(self: Renderer) -> None:
        raise AssertionError("the scene was traced again")

    monkeypatch.setattr(Renderer, "_trace_geometry", no_tracing)
    second = SimulatedWorld(SCENE, seed=1, cache_dir=tmp_path)
    assert np.array_equal(second.render(3, 0.0, exposure_ms=30.0, gain=1.0, bits=8), frame)
