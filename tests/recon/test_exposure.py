from __future__ import annotations

import numpy as np
import pytest

from app.recon.exposure import bracket_exposures, choose_exposure, set_statistics
from app.recon.patterns import PatternSchedule, fringe_profile


def synthetic_set(gain: float, schedule: PatternSchedule, shape=(40, 60)) -> np.ndarray:
    """Fringes whose brightness is proportional to ``gain`` (exposure), clipped at 255."""
    h, w = shape
    cols = np.linspace(0, schedule.width - 1, w)
    albedo = np.linspace(0.5, 1.0, h)[:, None]  # brighter rows saturate first
    out = []
    for fi in range(len(schedule.frequencies)):
        for n in range(schedule.steps):
            prof = fringe_profile(schedule, fi, n, columns=cols)[None, :]
            out.append(np.clip(np.rint(gain * albedo * (0.1 + 0.8 * prof)), 0, 255))
    return np.stack(out).astype(np.uint8)


def test_statistics_of_a_known_set():
    s = PatternSchedule()
    sat, mod = set_statistics(synthetic_set(100.0, s), s, 255)
    assert sat == 0.0
    # B = 0.4 * gain * albedo; the median albedo is 0.75
    assert mod == pytest.approx(0.4 * 100 * 0.75, rel=0.05)
    sat, _ = set_statistics(synthetic_set(400.0, s), s, 255)
    assert 0.2 < sat < 1.0


def test_bisection_finds_the_longest_unsaturated_exposure():
    s = PatternSchedule()
    calls: list[float] = []

    def measure(exposure_ms: float) -> tuple[float, float]:
        calls.append(exposure_ms)
        return set_statistics(synthetic_set(10.0 * exposure_ms, s), s, 255)

    res = choose_exposure(measure, saturation_limit=0.005)
    # Saturation starts when 10·e·1.0·0.9 > 254.5, i.e. e > 28.3 ms: 25 ms is the longest below.
    assert res.exposure_ms == 25.0
    assert res.saturated_fraction <= 0.005 and res.warning is None
    assert len(calls) <= 6  # a bisection, not a sweep
    assert all(t.saturated_fraction > 0.005 for t in res.trials if t.exposure_ms > 25.0)


def test_never_unsaturated_warns_and_keeps_the_shortest():
    res = choose_exposure(lambda e: (0.5, 10.0), saturation_limit=0.01, max_exposure_ms=8.0)
    assert res.exposure_ms == 1.0 and res.warning


def test_invalid_arguments():
    with pytest.raises(ValueError, match="saturation_limit"):
        choose_exposure(lambda e: (0.0, 0.0), saturation_limit=1.5)
    with pytest.raises(ValueError, match="max_exposure_ms"):
        choose_exposure(lambda e: (0.0, 0.0), max_exposure_ms=0.5)


def test_ladder_spans_the_exposure_range():
    from app.core.limits import EXPOSURE_RANGE_MS
    from app.recon.exposure import LADDER_MS

    assert (LADDER_MS[0], LADDER_MS[-1]) == EXPOSURE_RANGE_MS


def test_bracket_adds_two_stops_capped_at_the_longest_exposure():
    assert bracket_exposures(20.0) == (20.0, 80.0)
    assert bracket_exposures(40.0) == (40.0, 100.0)  # capped at EXPOSURE_RANGE_MS[1]
    assert bracket_exposures(100.0) == (100.0,)  # already at the cap: one set
    assert bracket_exposures(10.0, stops=1.0) == (10.0, 20.0)
    assert bracket_exposures(10.0, max_exposure_ms=30.0) == (10.0, 30.0)


@pytest.mark.parametrize(
    ("kw", "name"),
    [
        ({"base_ms": 0.0}, "base_ms"),
        ({"base_ms": 150.0}, "base_ms"),
        ({"base_ms": float("nan")}, "base_ms"),
        ({"base_ms": 10.0, "stops": 0.0}, "stops"),
        ({"base_ms": 10.0, "max_exposure_ms": -1.0}, "max_exposure_ms"),
    ],
)
def test_bracket_rejects_bad_input(kw, name):
    with pytest.raises(ValueError, match=name):
        bracket_exposures(**kw)


def _levels(peak_max: float, size: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Peaks A + B spread evenly over (0, peak_max] DN, modulation a third of them."""
    peak = np.linspace(peak_max / size, peak_max, size * size, dtype=np.float32).reshape(size, size)
    return peak, peak / 3


def test_predicted_exposure_scales_the_set_to_the_saturation_limit():
    from app.recon.exposure import LADDER_MS, predicted_exposure_ms

    # the brightest peak (60.3 DN at 33 ms) reaches full scale (100 DN) at 54.7 ms
    peak, mod = _levels(60.0 / 0.995)
    got = predicted_exposure_ms(peak, mod, 33.0, 100.0)
    # the longest ladder step within 33 ms · 100/60 = 55 ms
    assert got == max(e for e in LADDER_MS if e <= 55.0) == 50.0
    # already clipped pixels stay clipped: half the image at full scale → the shortest exposure
    peak[:100] = 100.0
    assert predicted_exposure_ms(peak, mod, 33.0, 100.0) == LADDER_MS[0]


def test_low_signal_names_the_share_and_the_exposure_only_when_most_of_the_roi_is_dark():
    from app.core.reasons import Reason
    from app.recon.exposure import low_signal

    peak, mod = _levels(20.0)
    reason = np.full(peak.shape, int(Reason.OK), np.uint8)
    area = np.zeros(peak.shape, bool)
    area[50:150, 50:150] = True
    assert low_signal(reason, area, peak, mod, 20.0, 255.0) is None
    reason[:, :80] = Reason.LOW_MODULATION
    reason[:, 80:110] = Reason.UNCERTAIN  # 60 of the ROI's 100 columns
    dark = low_signal(reason, area, peak, mod, 20.0, 255.0)
    assert dark is not None and dark.share == pytest.approx(0.6)
    # 20 DN at 20 ms: the longest exposure stays unsaturated
    assert dark.suggested_exposure_ms == 100.0
    assert (
        dark.message()
        == "60% of the ROI is invalid for low signal at 20 ms: "
        "the auto-exposure would choose 100 ms"
    )
    with pytest.raises(ValueError, match="area"):
        low_signal(reason, area[:10], peak, mod, 20.0, 255.0)
    with pytest.raises(ValueError, match="exposure_ms"):
        low_signal(reason, area, peak, mod, 0.0, 255.0)
