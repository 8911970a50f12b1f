"""The fused kernel with a projector-gamma phase-error table: the same as the numpy path with it."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest
from numba import njit

from app.core.reasons import Reason
from app.core.schedule import PatternSchedule
from app.devices.sim.ideal import ideal_calibration
from app.devices.sim.offline import render_capture_set
from app.devices.sim.optics import rig_by_name
from app.devices.sim.world import SimulatedWorld
from app.recon import Reconstructor, SensorNoise, fast
from app.recon.gamma import PhaseErrorLUT

TWO_PI = 2 * math.pi
FREQS = (1.0, 4.0, 12.0, 36.0)
GAMMA = 1.5  # the twin's DMD response exponent, left uncorrected


@njit(cache=False)
def _kernel_apply(w: npt.NDArray[np.float32], table: npt.NDArray[np.float32],
                  scale: np.float32) -> npt.NDArray[np.float32]:  # pragma: no cover - compiled
    out = np.empty_like(w)
    for i in range(w.shape[0]):
        out[i] = fast._lut_correct(w[i], table, scale)
    return out


def test_kernel_lookup_equals_apply_across_the_circle():
    """Linear interpolation between bin centres, circular at 0 and 2π, as ``apply`` does."""
    rng = np.random.default_rng(4)
    lut = PhaseErrorLUT(rng.normal(0.0, 0.05, (1, 16)), 4, (1.0,))
    edge = np.array([0.0, 1e-7, TWO_PI / 32, TWO_PI / 16, math.pi, TWO_PI - 1e-6, TWO_PI - 1e-3])
    w = np.concatenate([rng.uniform(0.0, TWO_PI, 100_000), edge]).astype(np.float32)
    got = _kernel_apply(w, lut.kernel_table()[0], np.float32(16 / TWO_PI)).astype(np.float64)
    want = lut.apply(w.astype(np.float64)[None, None])[0, 0]
    diff = np.angle(np.exp(1j * (got - want)))
    assert np.abs(diff).max() < 2e-6
    assert got.min() >= 0.0 and got.max() < TWO_PI


@pytest.fixture(scope="module")
def gamma_twin() -> tuple[PhaseErrorLUT, np.ndarray]:
    """A table learned by ``PhaseErrorLUT.learn`` from a 12-step capture of the 45° target on a
    twin whose projector has gamma 1.5, and a 4-step tissue set of the same twin."""
    twelve = PatternSchedule(frequencies=FREQS, steps=12)
    world = SimulatedWorld("dof_target", schedule=twelve, seed=1, projector_gamma=GAMMA)
    ref, _, _ = render_capture_set("dof_target", exposure_ms=10.0, world=world)
    lut = PhaseErrorLUT.learn(ref.frames, 12, 4, frequencies=FREQS, max_code=255)
    cs, _, _ = render_capture_set("intestine_flap", exposure_ms=15.0, world=SimulatedWorld(
        "intestine_flap", seed=2, projector_gamma=GAMMA))
    return lut, cs.frames


def test_fused_kernel_with_a_learned_table_equals_the_numpy_path(gamma_twin):
    lut, frames = gamma_twin
    assert (lut.amplitude_rad() > 0.005).all()  # the gamma's error is there to remove
    cal = ideal_calibration(rig_by_name("default"))
    noise = SensorNoise.typical(255)  # the set's own estimate takes the gamma's harmonics for noise
    rec = Reconstructor(cal, with_phase=True, phase_error=lut, noise=noise)
    a = rec.run(frames, fast=False)
    b = rec.run(frames, fast=True)
    assert np.array_equal(a.reason, b.reason)
    ok = a.valid
    assert ok.mean() > 0.5
    assert np.abs(a.phase[ok] - b.phase[ok]).max() < 1e-4
    assert np.abs(a.depth[ok] - b.depth[ok]).max() < 1e-4
    np.testing.assert_allclose(b.sigma[ok], a.sigma[ok], rtol=1e-4)
    # the table is applied: the phase moves by about its size
    plain = Reconstructor(cal, with_phase=True, noise=noise).run(frames, fast=True)
    both = ok & plain.valid
    moved = np.sqrt(np.mean((b.phase[both] - plain.phase[both]) ** 2))
    assert 0.5 * lut.amplitude_rad()[-1] < moved < 2.0 * lut.amplitude_rad()[-1]


def test_fused_kernel_with_a_table_equals_the_numpy_path_on_clipped_samples(gamma_twin):
    """The 45° target at 40 ms: its bright half clips and is refitted (rows refitted whole and
    spans of rows), with the table applied to the refitted phases as to the others."""
    lut, _ = gamma_twin
    cs, _, _ = render_capture_set("dof_target", exposure_ms=40.0, world=SimulatedWorld(
        "dof_target", seed=3, projector_gamma=GAMMA))
    rec = Reconstructor(ideal_calibration(rig_by_name("default")), with_phase=True, phase_error=lut,
                        noise=SensorNoise.typical(255))
    a = rec.run(cs.frames, fast=False)
    b = rec.run(cs.frames, fast=True)
    assert a.recovered == b.recovered > 10_000
    assert np.array_equal(a.reason, b.reason)
    ok = a.valid
    assert ok.mean() > 0.2
    assert np.abs(a.phase[ok] - b.phase[ok]).max() < 1e-4
    assert np.abs(a.depth[ok] - b.depth[ok]).max() < 1e-4


def test_the_table_is_refused_for_another_schedule():
    lut = PhaseErrorLUT(np.zeros((3, 16)), 4, (1.0, 6.0, 36.0))
    cal = ideal_calibration(rig_by_name("default"))
    with pytest.raises(ValueError, match="^frequencies"):
        Reconstructor(cal, phase_error=lut)
    with pytest.raises(ValueError, match="^phase_error"):
        Reconstructor(cal, phase_error="table.json")  # type: ignore[arg-type]


def test_tables_compare_and_hash_by_content():
    a = PhaseErrorLUT(np.linspace(-0.01, 0.01, 32).reshape(2, 16), 4, (1.0, 4.0))
    b = PhaseErrorLUT.from_dict(a.to_dict())
    c = PhaseErrorLUT(a.error_rad * 2, 4, (1.0, 4.0))
    assert a == b and hash(a) == hash(b) and a.digest() == b.digest()
    assert a != c and a.digest() != c.digest()




def test_a_learned_table_without_a_series_is_looked_up(gamma_twin):
    """The twin's learned table carries the learning's noise in every harmonic: no short series
    reproduces it, so the kernel looks it up whether or not the series is allowed."""
    lut, frames = gamma_twin
    assert lut.series is None
    cal = ideal_calibration(rig_by_name("default"))
    noise = SensorNoise.typical(255)
    a = Reconstructor(cal, with_phase=True, phase_error=lut, noise=noise).run(frames)
    b = Reconstructor(cal, with_phase=True, phase_error=lut, noise=noise,
                      phase_error_series=False).run(frames)
    assert np.array_equal(a.reason, b.reason)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.phase, b.phase)


@pytest.mark.parametrize("scene, exposure_ms, seed, combine", [
    ("intestine_flap", 15.0, 2, False), ("dof_target", 40.0, 3, False),
    ("intestine_flap", 15.0, 2, True)])
def test_the_sets_own_table_as_a_series_gives_the_tables_depth(scene, exposure_ms, seed,
                                                               combine):
    """A γ 1.5 twin set's own table (its 2nd harmonic, :mod:`app.recon.gamma_model`) has a
    series; the fused kernel evaluates it (4 × 4 schedule) and gives the table's depth within
    1e-4 mm, its phase within 1e-4 rad, σ within 1e-4 relative and the same reason codes, and
    is as close to the numpy path (the table) as the look-ups are. The 45° target at 40 ms clips:
    its rows are refitted whole and in spans, with the series as with the table. With the
    frequencies combined the kernel takes its general row-by-row path (as heterodyne schedules
    do), which evaluates the series too."""
    from app.recon.noise import resolve_set_noise

    rig = rig_by_name("default", distortion=False)
    cal = ideal_calibration(rig)
    cs, _, _ = render_capture_set(scene, exposure_ms=exposure_ms, world=SimulatedWorld(
        scene, seed=seed, projector_gamma=GAMMA, rig=rig))
    est = resolve_set_noise(cs.frames, cal.pattern, cs.max_code)
    lut = est.phase_error
    assert lut is not None and lut.series is not None
    assert lut.amplitude_rad().min() > 0.005  # the gamma's error is there to remove
    series = Reconstructor(cal, with_phase=True, noise=est.noise, combine_frequencies=combine)
    table = Reconstructor(cal, with_phase=True, noise=est.noise, combine_frequencies=combine,
                          phase_error_series=False)
    a = table.run(cs.frames, max_code=cs.max_code, phase_error=lut)
    b = series.run(cs.frames, max_code=cs.max_code, phase_error=lut)
    c = table.run(cs.frames, max_code=cs.max_code, phase_error=lut, fast=False)
    assert a.phase is not None and b.phase is not None and c.phase is not None
    assert a.phase_error_source == b.phase_error_source == "given"
    assert np.array_equal(a.reason, b.reason)
    # the look-ups differ from the numpy path at a few pixels of the tissue set
    # (UNWRAP_INCONSISTENT there, UNCERTAIN in the kernel: float32 borderlines; how many sit on
    # the border depends on the set's noise fit); the series adds no other
    assert np.array_equal(c.reason != b.reason, c.reason != a.reason)
    differ = c.reason != b.reason
    assert np.sum(differ) <= 1e-5 * differ.size
    borderline = {int(Reason.UNWRAP_INCONSISTENT), int(Reason.UNCERTAIN)}
    assert set(np.unique(c.reason[differ]).tolist()) <= borderline
    assert set(np.unique(b.reason[differ]).tolist()) <= borderline
    assert a.recovered == b.recovered == c.recovered
    if scene == "dof_target":
        assert b.recovered > 10_000
    ok = a.valid
    assert ok.mean() > 0.2
    assert np.abs(a.depth[ok] - b.depth[ok]).max() < 1e-4
    assert np.abs(c.depth[ok] - b.depth[ok]).max() < 1e-4
    assert np.abs(a.phase[ok] - b.phase[ok]).max() < 1e-4
    assert np.abs(c.phase[ok] - b.phase[ok]).max() < 1e-4
    np.testing.assert_allclose(b.sigma[ok], a.sigma[ok], rtol=1e-4)
    # the series ran: float32 phases that are not the look-ups' bit for bit
    assert np.mean(a.phase[ok] != b.phase[ok]) > 0.01
