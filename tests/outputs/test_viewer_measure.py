"""The measure tool's lines and values in the 3-D view (issue 17)."""

from __future__ import annotations

import numpy as np
import pytest

from app.analysis.measure import measure
from app.outputs.viewer import Viewer
from app.service.measure import measurement_segments
from tests.helpers.outputs import SurfaceSource, surface_result, wait_for

SPECS = [
    {"kind": "length", "points": [[20, 30], [140, 90]]},
    {"kind": "point_to_line", "points": [[80, 60], [20, 20], [140, 20]]},
    {"kind": "depth", "points": [[80, 60], [20, 20], [140, 20], [80, 110]]},
    {"kind": "profile", "points": [[10, 60], [150, 60]]},
    {"kind": "area", "points": [[40, 30], [120, 30], [120, 90], [40, 90]]},
    # refused (an end outside the image): drawn nothing. A click in the 5-px invalid border
    # is no longer refused: live measurements fill small holes from the valid points around
    {"kind": "length", "points": [[0, 0], [170, 10]]},
]


def test_segments_and_labels_per_kind() -> None:
    res = surface_result(120, 160)
    res.sigma = np.where(res.valid, 0.02, np.nan).astype(np.float32)
    segs, labels = measurement_segments(res, SPECS)
    # 1 + 2 + 4 + (profile: every neighbouring pair of its 141 samples) + 4
    assert segs.shape == (1 + 2 + 4 + 140 + 4, 2, 3) and segs.dtype == np.float32
    np.testing.assert_allclose(segs[0], res.points[[30, 90], [20, 140]], rtol=1e-6)
    assert len(labels) == 5  # the refused length is left out
    m = measure("length", res.points, res.valid, res.sigma, SPECS[0]["points"])
    assert labels[0][1] == f"{m.value_mm:.3f} ± {m.sigma_mm:.3f} mm"
    assert labels[4][1].endswith("mm²")
    # the point-to-line's perpendicular ends on the line, at the reported distance
    p0, foot = segs[2]
    d = measure("point_to_line", res.points, res.valid, None, SPECS[1]["points"]).value_mm
    assert np.linalg.norm(p0 - foot) == pytest.approx(d, rel=1e-5)


def test_viewer_draws_the_measurements() -> None:
    source = SurfaceSource()
    viewer = Viewer(source, max_points=2000, max_rate_hz=50.0, only_when_watched=False)
    specs = SPECS[:1]
    viewer.measure_source = lambda: specs
    viewer.start()
    try:
        source.publish(surface_result(120, 160))
        assert wait_for(lambda: viewer.updates >= 1, 10)
        lines, label = viewer._measure_nodes
        np.testing.assert_allclose(
            np.asarray(lines.points)[0],
            surface_result(120, 160).points[[30, 90], [20, 140]],
            rtol=1e-6,
        )
        assert label.text.endswith(" mm")
        specs = []  # cleared on the dashboard: gone with the next result
        source.publish(surface_result(120, 160, shift_px=5.0))
        assert wait_for(lambda: viewer.updates >= 2, 10)
        assert viewer._measure_nodes == []
    finally:
        viewer.stop()
