"""Scenes: names, reference-plane alignment, metrology shapes, motion amplitudes (sparse rays,
cheap)."""

from __future__ import annotations

import numpy as np
import pytest

from app.devices.sim import default_rig, list_scenes
from app.devices.sim.radiometry import material_id
from app.devices.sim.scenes import build_scene
from app.devices.sim.trace import trace


@pytest.fixture(scope="module")
def rig():
    return default_rig(distortion=False)


def _rays(rig, step=37):
    v, u = np.mgrid[0:1032:step, 0:1384:step].astype(float)
    return rig.camera.rays(u, v).reshape(-1, 3)


def test_scene_names():
    assert {"plane", "dof_target", "skin_flap", "intestine_flap", "intestine_pile", "anastomosis",
            "sphere"} <= set(list_scenes())
    with pytest.raises(ValueError, match="scene"):
        build_scene("moon", default_rig())


def test_sphere_points_lie_on_the_sphere(rig):
    scene = build_scene("sphere", rig)
    hits = trace(scene, _rays(rig, 9))
    for sph in scene.spheres:
        d = np.linalg.norm(hits.points - sph.centre, axis=1)
        on = np.abs(d - sph.radius_mm) < 1e-3
        assert on.sum() > 100
        assert np.max(np.abs(d[on] - 4.0)) < 1e-9
    # the plate is the reference plane: height 0 wherever the plate is seen
    plate = hits.material == material_id("white")
    assert np.max(np.abs(rig.reference.height(hits.points[plate]))) < 1e-9


def test_dof_target_spans_twenty_mm(rig):
    hits = trace(build_scene("dof_target", rig), _rays(rig))
    h = rig.reference.height(hits.points)
    assert np.nanmin(h) < 1.0 and np.nanmax(h) > 19.0


def test_flaps_stand_on_the_target(rig):
    target = trace(build_scene("dof_target", rig), _rays(rig, 11))
    for name, thick in (("skin_flap", 2.0), ("intestine_flap", 1.2)):
        hits = trace(build_scene(name, rig), _rays(rig, 11))
        d = np.linalg.norm(hits.points - target.points, axis=1)
        tissue = hits.material == material_id(name.split("_")[0])
        assert tissue.mean() > 0.1
        assert 0.6 * thick < np.nanmedian(d[tissue]) < 1.6 * thick


def test_motion_amplitudes(rig):
    pile = build_scene("intestine_pile", rig)
    xs = np.array([pile.offset(t) for t in np.linspace(0, 8, 161)])
    assert np.ptp(
        np.linalg.norm(xs, axis=1) * np.sign(xs @ pile.surface.axes[:, 0])
    ) == pytest.approx(6.0, abs=0.01)
    ana = build_scene("anastomosis", rig)
    br = np.array([ana.offset(t) @ rig.reference.normal for t in np.linspace(0, 4, 401)])
    assert np.ptp(br) == pytest.approx(1.5, abs=0.01)  # breathing 0.25 Hz, 1.5 mm peak-to-peak
    tips = np.array([ana.tool.path(t)[0] for t in (0.0, 1.5, 3.0)])
    assert np.linalg.norm(tips[1] - tips[0]) > 3.0  # forceps move through the view


def test_running_stitches_stand_072_mm(rig):
    ana = build_scene("anastomosis", rig)
    hf = ana.surface
    suture = hf.material == material_id("suture")
    assert suture.any()
    # highest point of each stitch cross-section over the tissue right beside it
    rows = np.where(suture.any(axis=1))[0]
    best = []
    for r in rows[::25]:
        cols = np.where(suture[r])[0]
        if cols.size < 3 or cols.size > 40:
            continue
        side = hf.heights[r, [max(cols[0] - 3, 0), min(cols[-1] + 3, suture.shape[1] - 1)]].mean()
        best.append(hf.heights[r, cols].max() - side)
    assert len(best) > 5
    assert np.median(best) == pytest.approx(0.72, abs=0.08)


def test_bright_suture_variant_differs_only_in_the_thread(rig):
    from app.devices.sim.radiometry import REFLECTANCE

    dark, bright = build_scene("anastomosis", rig), build_scene("anastomosis_bright", rig)
    assert bright.name == "anastomosis_bright"
    np.testing.assert_array_equal(dark.surface.heights, bright.surface.heights)
    thread = dark.surface.material == material_id("suture")
    np.testing.assert_array_equal(thread, bright.surface.material == material_id("suture_bright"))
    np.testing.assert_array_equal(dark.surface.material[~thread], bright.surface.material[~thread])
    # in the green light used for measurement the violet thread is darker, the undyed one brighter
    assert (
        REFLECTANCE["suture"]["green"]
        < REFLECTANCE["intestine"]["green"]
        < REFLECTANCE["suture_bright"]["green"]
    )
