from __future__ import annotations

import numpy as np

from app.core.reasons import PRECEDENCE, Reason, assign_reasons
from app.outputs.encoding import reason_colors, reason_legend
from app.recon.colormap import REASON_COLORS, reason_png


def test_motion_is_a_reason_after_saturation_and_before_every_phase_cause():
    assert Reason.MOTION == 8 and Reason(8).name == "MOTION"
    assert sorted(int(r) for r in Reason) == list(range(len(Reason)))  # codes stay dense
    order = list(PRECEDENCE)
    assert (
        order.index(Reason.SATURATED)
        < order.index(Reason.MOTION)
        < order.index(Reason.LOW_MODULATION)
    )
    assert set(PRECEDENCE) == set(Reason)
    out = assign_reasons((3,), motion=[True, True, False], saturated=[True, False, False],
                         low_modulation=[True, True, True])
    assert list(out) == [Reason.SATURATED, Reason.MOTION, Reason.LOW_MODULATION]


def test_every_reason_has_a_distinct_colour_and_a_legend_name():
    assert set(REASON_COLORS) == set(Reason)
    assert len(set(REASON_COLORS.values())) == len(Reason)
    legend = reason_legend()
    assert legend[str(int(Reason.MOTION))]["name"] == "motion"
    assert set(reason_colors()) == {int(r) for r in Reason}


def test_reason_png_legend_grows_with_the_motion_row():
    import cv2

    img = cv2.imdecode(
        np.frombuffer(reason_png(np.full((10, 10), Reason.MOTION, np.uint8)), np.uint8),
        cv2.IMREAD_COLOR,
    )
    assert img.shape[0] == 10 + 6 + 18 * len(Reason)
    assert tuple(int(c) for c in img[5, 5][::-1]) == REASON_COLORS[Reason.MOTION]
