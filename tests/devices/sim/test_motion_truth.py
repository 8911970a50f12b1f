"""Moving scenes: the true surface at every frame's instant agrees with what the frames show."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.devices.sim import SimulatedWorld
from app.devices.sim.ideal import ideal_calibration
from app.devices.sim.scenes import build_scene, list_scenes
from app.devices.sim.scenes.tissue import BREATHING_AMPLITUDE_MM, BREATHING_HZ
from app.recon import Reconstructor


@pytest.fixture(scope="module")
def breathing() -> SimulatedWorld:
    w = SimulatedWorld("breathing", seed=2, distortion=False)
    _ = w.renderer
    return w


def test_breathing_and_tool_scenes_exist_and_move():
    from app.devices.sim.optics import default_rig

    rig = default_rig()
    assert {"breathing", "tool"} <= set(list_scenes())
    b = build_scene("breathing", rig)
    n = rig.reference.normal
    ts = np.linspace(0.0, 1.0 / BREATHING_HZ, 401)
    heave = np.array([b.offset(t) @ n for t in ts])
    assert np.ptp(heave) == pytest.approx(2 * BREATHING_AMPLITUDE_MM, rel=1e-3)  # 4 mm peak to peak
    assert b.tool is None
    tool = build_scene("tool", rig)
    assert tool.motion is None and tool.tool is not None
    tips = np.array([tool.tool.path(t)[0] for t in (0.0, 2.5)])
    # quarter period of ±10 mm
    assert np.linalg.norm(tips[1] - tips[0]) == pytest.approx(10.0, abs=1e-6)


def test_truth_heaves_with_the_scene(breathing):
    r = breathing.renderer
    t1 = 1.0 / (4 * BREATHING_HZ)  # the crest: +2 mm toward the scope
    d0, _ = r.truth(0.0)
    d1, _ = r.truth(t1)
    both = np.isfinite(d0) & np.isfinite(d1)
    assert both.mean() > 0.8
    # a heave along the reference normal raises every height by the same amount, whatever
    # the pixel now sees (the tissue is smooth on the scale of the image flow)
    assert np.median(d1[both] - d0[both]) == pytest.approx(BREATHING_AMPLITUDE_MM, abs=0.05)
    # the rendered truth and the exactly traced one agree but for the renderer's tile flow
    dt, _ = r.traced_truth(t1)
    ok = both & np.isfinite(dt)
    assert np.median(np.abs(d1[ok] - dt[ok])) < 0.3  # 0.13 mm measured at the crest


@pytest.mark.parametrize("t_s", [0.0, 0.5, 1.0, 2.7])
def test_frames_rendered_at_an_instant_reconstruct_to_the_truth_at_that_instant(breathing, t_s):
    """A set whose frames are all taken at t (no motion inside it) gives the truth at t:
    the frames and the truth of one instant are the same surface."""
    cal = ideal_calibration(breathing.rig, breathing.schedule)
    frames = np.stack([breathing.render(i, t_s, exposure_ms=30.0, gain=1.0, bits=8)
                       for i in range(breathing.schedule.n_frames)])
    res = Reconstructor(cal).run(frames)
    truth, _ = breathing.truth(t_s)
    ok = res.valid & np.isfinite(truth)
    assert ok.mean() > 0.8
    err = res.depth[ok] - truth[ok]
    assert abs(np.median(err)) < 0.01
    assert np.sqrt(np.mean(err**2)) < 0.06
    # the truth at another instant is a different surface (2 mm·sin(0.5π·Δt) apart)
    other, _ = breathing.truth(t_s + 1.0)
    both = ok & np.isfinite(other)
    shift = BREATHING_AMPLITUDE_MM * (math.sin(2 * math.pi * BREATHING_HZ * (t_s + 1.0))
                                      - math.sin(2 * math.pi * BREATHING_HZ * t_s))
    assert np.median(other[both] - res.depth[both]) == pytest.approx(shift, abs=0.05)


def test_tool_truth_follows_the_tool():
    w = SimulatedWorld("tool", seed=3, distortion=False)
    r = w.renderer
    d_a, _ = r.truth(0.0)
    d_b, _ = r.truth(2.5)  # the tip moved 10 mm along the tissue; the tissue is still
    diff = d_a - d_b
    tool_a, tool_b = diff > 1.0, diff < -1.0  # the forceps at t = 0 / at t = 2.5
    assert tool_a.mean() > 0.005 and tool_b.mean() > 0.005
    still = ~(tool_a | tool_b) & np.isfinite(diff)
    assert np.abs(diff[still]).max() < 1e-4  # the tissue itself did not move
    # frames show the tool where the truth has it: the two instants' frames differ there
    f_a = w.render(0, 0.0, exposure_ms=30.0, gain=1.0, bits=8).astype(float)
    f_b = w.render(0, 2.5, exposure_ms=30.0, gain=1.0, bits=8).astype(float)
    changed = np.abs(f_a - f_b) > 20
    assert changed[tool_a | tool_b].mean() > 0.3
    assert changed[still].mean() < 0.01
