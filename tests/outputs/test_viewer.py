"""The viser viewer: decimation, colours, loopback server, paced updates, GUI mirroring, stop."""

from __future__ import annotations

import math
import socket
import threading

import numpy as np
import pytest

from app.outputs.viewer import Viewer, cloud_arrays, decimation_step
from app.recon.colormap import depth_colormap
from tests.helpers.outputs import SurfaceSource, port_is_free, surface_result, wait_for


@pytest.mark.parametrize(("h", "w", "max_points"), [(1032, 1384, 300_000), (684, 608, 1000),
                                                      (10, 10, 100), (10, 10, 99), (1, 5000, 7)])
def test_decimation_step_is_the_smallest_that_fits(h: int, w: int, max_points: int) -> None:
    s = decimation_step(h, w, max_points)
    assert math.ceil(h / s) * math.ceil(w / s) <= max_points
    if s > 1:
        assert math.ceil(h / (s - 1)) * math.ceil(w / (s - 1)) > max_points


def test_decimation_step_sensor_figure() -> None:
    # 1384 × 1032: stride 2 leaves 692·516 = 357 072 > 300 000, stride 3 leaves 462·344.
    assert decimation_step(1032, 1384, 300_000) == 3
    with pytest.raises(ValueError, match="^max_points"):
        decimation_step(10, 10, 0)


def test_cloud_arrays_keeps_valid_points_and_colours_by_height() -> None:
    res = surface_result(120, 160, invalid_border=5)
    xyz, rgb, step = cloud_arrays(res, max_points=5000)
    assert step == decimation_step(120, 160, 5000) == 2
    sub_valid = res.valid[::2, ::2]
    assert xyz.dtype == np.float32 and xyz.shape == (int(sub_valid.sum()), 3) and len(xyz) <= 5000
    assert np.isfinite(xyz).all()
    np.testing.assert_array_equal(xyz, res.points[::2, ::2][sub_valid])
    # The same TURBO colours, same 0–35 mm range, as the REST colormap.
    np.testing.assert_array_equal(rgb, depth_colormap(res.depth[::2, ::2], (0.0, 35.0))[sub_valid])
    # The bump's top (10 mm) is cyan-green in 0–35 mm, the plane (0 mm) dark blue.
    top = rgb[np.argmax(res.depth[::2, ::2][sub_valid])]
    assert top[1] > 150 and top[2] > 60 and top[0] < 120
    assert tuple(rgb[0]) == tuple(depth_colormap(np.zeros((1, 1), np.float32))[0, 0])


def test_cloud_arrays_texture_mode_is_gray_by_full_scale() -> None:
    res = surface_result(40, 60, invalid_border=0)
    _, rgb, step = cloud_arrays(res, max_points=10_000, color_mode="texture")
    assert step == 1
    expected = np.clip(res.texture * (255.0 / 255.0), 0, 255).astype(np.uint8).ravel()
    np.testing.assert_array_equal(rgb[:, 0], expected)
    assert (rgb[:, 0] == rgb[:, 1]).all() and (rgb[:, 1] == rgb[:, 2]).all()
    with pytest.raises(ValueError, match="^color_mode"):
        cloud_arrays(res, 100, color_mode="rainbow")


def test_cloud_arrays_sigma_mode_colours_the_noise() -> None:
    res = surface_result(40, 60, invalid_border=0)
    res.sigma = np.linspace(0.0, 0.1, res.depth.size, dtype=np.float32).reshape(res.depth.shape)
    _, rgb, _ = cloud_arrays(res, max_points=10_000, color_mode="sigma")
    np.testing.assert_array_equal(rgb, depth_colormap(res.sigma, (0.0, 0.1)).reshape(-1, 3))
    res.sigma = None  # a result without σ: the NaN colour, no error
    _, rgb, _ = cloud_arrays(res, max_points=10_000, color_mode="sigma")
    assert len(rgb) == res.valid.sum()


@pytest.fixture()
def source() -> SurfaceSource:
    return SurfaceSource()


def test_viewer_serves_on_loopback_updates_in_place_and_stops(source: SurfaceSource) -> None:
    before = set(threading.enumerate())
    viewer = Viewer(source, max_points=2000, max_rate_hz=50.0, only_when_watched=False)
    viewer.start()
    try:
        port = viewer.port
        assert port > 0 and viewer.server.get_host() == "127.0.0.1"
        with socket.create_connection(("127.0.0.1", port), timeout=2):
            pass
        source.publish(surface_result(120, 160))
        assert wait_for(lambda: viewer.updates >= 1, 10)
        cloud = viewer._cloud
        assert cloud is not None
        first = np.array(cloud.points)
        assert cloud.points.dtype == np.float32 and 0 < len(first) <= 2000
        # The next result updates the same handle in place (a moved bump: new points).
        source.publish(surface_result(120, 160, shift_px=20.0))
        assert wait_for(lambda: viewer.last_seq == 2 and viewer.updates >= 2, 10)
        assert viewer._cloud is cloud
        assert not np.array_equal(np.array(cloud.points), first)
        assert len(cloud.colors) == len(cloud.points)
    finally:
        viewer.stop()
    assert port_is_free(port)
    assert not viewer.running
    # Every thread the viewer (and viser) started is gone.
    assert wait_for(lambda: not (set(threading.enumerate()) - before), 5), \
        [t.name for t in set(threading.enumerate()) - before]


def test_viewer_paces_updates(source: SurfaceSource) -> None:
    viewer = Viewer(source, max_points=500, max_rate_hz=4.0, only_when_watched=False)
    viewer.start()
    try:
        stop = threading.Event()

        def flood() -> None:  # 100 results a second, far faster than 4 Hz
            i = 0
            while not stop.wait(0.01):
                i += 1
                source.publish(surface_result(30, 40, shift_px=float(i % 7)))

        t = threading.Thread(target=flood)
        t.start()
        wait_for(lambda: viewer.updates >= 1, 10)
        u0, s0 = viewer.updates, source.store.seq
        threading.Event().wait(2.0)
        stop.set()
        t.join()
        pushed, published = viewer.updates - u0, source.store.seq - s0
        assert published > 60
        assert 4 <= pushed <= 10  # ~4 Hz over 2 s
        # After the flood, the newest result is shown.
        assert wait_for(lambda: viewer.last_seq == source.store.seq, 3)
    finally:
        viewer.stop()


def test_viewer_mirrors_instrument_settings(source: SurfaceSource) -> None:
    viewer = Viewer(source, max_points=500)
    viewer.start()
    try:
        slider, led = viewer._gui["exposure"], viewer._gui["led"]
        assert slider.value == 30.0 and led.value == "green"
        source.exposure_ms, source.led = 55.0, "blue"  # changed elsewhere (REST)
        assert wait_for(lambda: slider.value == 55.0 and led.value == "blue", 5)
        # Mirroring must not echo back into the instrument.
        assert source.calls == []
        assert (slider.min, slider.max) == (1.0, 100.0)
    finally:
        viewer.stop()


def test_viewer_rejects_bad_arguments(source: SurfaceSource) -> None:
    with pytest.raises(ValueError, match="^max_points"):
        Viewer(source, max_points=0)
    with pytest.raises(ValueError, match="^max_rate_hz"):
        Viewer(source, max_rate_hz=0)
    with pytest.raises(RuntimeError):
        _ = Viewer(source).port


def test_initial_view_tilts_up_about_the_cloud_centre() -> None:
    from app.outputs.viewer import initial_view

    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(-10, 10, 5000), rng.uniform(-10, 10, 5000),
                           np.full(5000, 60.0)]).astype(np.float32)
    position, look_at, fov = initial_view(xyz, tilt_deg=30.0)
    np.testing.assert_allclose(look_at, [0, 0, 60], atol=0.5)
    # Same distance as the scope's camera centre, 30° upward (−y is up in the camera frame).
    np.testing.assert_allclose(
        np.linalg.norm(position - look_at), np.linalg.norm(look_at), rtol=1e-6
    )
    np.testing.assert_allclose(
        position, look_at + [0, -60 * np.sin(np.pi / 6), -60 * np.cos(np.pi / 6)], atol=0.5
    )
    # Half extent 9.6 mm at 60 mm: 2.4·atan(9.6/60) ≈ 21.8°.
    assert np.deg2rad(20) <= fov <= np.deg2rad(25)
    with pytest.raises(ValueError, match="^xyz"):
        initial_view(np.zeros((0, 3), np.float32))
