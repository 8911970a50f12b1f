"""Horizontal fringes in the simulator: the decoded phase follows the projector row, not the
column."""

from __future__ import annotations

import math

import numpy as np

from app.devices.sim import SimulatedWorld, render_capture_set
from app.devices.sim.ideal import ideal_calibration
from app.recon import PatternSchedule, compute_phase


def test_horizontal_fringes_encode_the_projector_row():
    sched = PatternSchedule(orientation="horizontal")
    world = SimulatedWorld("dof_target", seed=4, schedule=sched, distortion=False)
    cap, truth, points = render_capture_set(world.scene, exposure_ms=20.0, world=world, seed=4)
    assert cap.schedule.orientation == "horizontal"
    res = compute_phase(cap.frames, cap.schedule, max_code=cap.max_code)
    ok = (res.reason == 0) & np.isfinite(truth)
    assert ok.mean() > 0.5
    proj = world.rig.projector
    k = sched.frequencies[-1]
    row = proj.row(points.astype(np.float64))
    col = proj.column(points.astype(np.float64))
    expected_row = 2 * math.pi * k * row / sched.height
    expected_col = 2 * math.pi * k * col / sched.width
    err = res.phase[ok] - expected_row[ok]
    print(
        f"\nhorizontal fringes: median |phase - 2 pi k y_p / h| = "
        f"{np.median(np.abs(err)):.3f} rad over {ok.sum()} px"
    )
    assert np.median(np.abs(err)) < 0.1
    assert np.median(np.abs(res.phase[ok] - expected_col[ok])) > 10  # not the column
    # and the ideal calibration of that geometry reads the phase along the same axis
    cal = ideal_calibration(world.rig, sched)
    assert cal.pattern.orientation == "horizontal"
