"""Fringe frames → metric depth and points: the :class:`Reconstructor` and ``compute_phase``."""

from __future__ import annotations

import logging
import math
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from functools import cached_property
from types import ModuleType
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import numpy.typing as npt

from app.core.calibration import Calibration
from app.core.depth_model import HeightTables
from app.core.reasons import assign_reasons
from app.core.schedule import PatternSchedule
from app.recon.gamma import SERIES_MAX_HARMONICS, PhaseErrorLUT
from app.recon.model import (
    SINGULAR_RTOL,
    ModelTables,
    calibration_height_tables,
    evaluate_height_slope,
    outside_volume,
    pixel_tables,
)
from app.recon.model_sigma import ModelSigmaTable, model_sigma_table, zero_table
from app.recon.noise import resolve_set_noise
from app.recon.phase import check_stack, resolve_levels, wrapped_phase
from app.recon.points import (
    LazyPoints,
    PointRays,
    RayTables,
    calibration_ray_tables,
    points_from_height,
    ray_quotients,
)
from app.recon.sensor import NoiseSource
from app.recon.sensor import SensorNoise as SensorNoise  # re-exported: its historical home
from app.recon.unwrap import (
    DEFAULT_CONSISTENCY_RAD,
    DEFAULT_FALSE_ALARM_RATE,
    DEFAULT_MAX_MOTION_RAD,
    PHASE_FLOOR_RAD,
    check_consistency_rad,
    order_slip_front,
    order_test_bound,
    unwrap_chain,
    unwrap_phases,
)
from app.recon.unwrap import (
    combine_frequencies as combine_phases,
)
from app.recon.validity import (
    DEFAULT_GROSS_ERROR_MM,
    DEFAULT_ORDER_ERROR_RATE,
    PHASOR_TAIL_COEFS,
    PHASOR_TAIL_T_MAX,
    max_depth_sigma_mm,
    min_phasor_snr,
    modulation_threshold,
    phasor_tail_factor_sq,
)

if TYPE_CHECKING:  # imported at run time by run(): the motion test needs numba
    from app.recon.motion import MotionTest

log = logging.getLogger(__name__)

F32 = npt.NDArray[np.float32]

_fast: ModuleType | None
try:
    from app.recon import fast as _fast
except ImportError as exc:  # numba missing or broken: the numpy oracle still works
    log.warning("numba fast path unavailable (%s); using the numpy path", exc)
    _fast = None


def phase_variance_factor(modulation_sq: npt.ArrayLike, steps: int) -> npt.NDArray[np.float64]:
    """var(φ)/σ_I² of the N-step phase: ``N / (2·m2)`` with ``m2 = (Σ I cosδ)² + (Σ I sinδ)²
    = (N·B/2)²`` (so ``2 / (N·B²)``)."""
    with np.errstate(divide="ignore"):
        return steps / (2.0 * np.asarray(modulation_sq, np.float64))


#: which projector-gamma table a run applied: the reconstructor's learned one, one passed to the
#: run, the set's own (an N = 4 set, :mod:`app.recon.gamma_model`), or none
PhaseErrorSource = Literal["learned", "given", "set", "none"]


def _choose_table(learned: PhaseErrorLUT | None, given: PhaseErrorLUT | None,
                  from_set: PhaseErrorLUT | None) -> tuple[PhaseErrorLUT | None, PhaseErrorSource]:
    """The phase-error table a run applies and :attr:`ReconResult.phase_error_source`."""
    if learned is not None:
        return learned, "learned"
    if given is not None:
        return given, "given"
    if from_set is not None:
        return from_set, "set"
    return None, "none"


#: the fused kernel's phase-error arguments (:class:`app.recon.fast.PhaseArgs`): the (K, bins + 2)
#: float32 table, bins/2π, apply it?, the (K, 7) float32 series coefficients, evaluate them?
KernelLUT = tuple[F32, np.float32, bool, F32, bool]


def _kernel_lut(table: PhaseErrorLUT | None, k: int, series: bool = True) -> KernelLUT:
    """The fused kernel's phase-error arguments for ``table`` and K = ``k`` frequencies: its
    Fourier series too where ``series`` and the table has one in the fused kernel's form
    (period 4, ≤ 3 harmonics: an N = 4 table; the kernel evaluates it instead of the table)."""
    no_series = np.zeros((k, 1 + 2 * SERIES_MAX_HARMONICS), np.float32)
    if table is None:
        return np.zeros((k, 2), np.float32), np.float32(1.0), False, no_series, False
    bins = table.error_rad.shape[1]
    fit = table.series if series else None
    if fit is None or fit.period != 4:
        return table.kernel_table(), np.float32(bins / (2.0 * np.pi)), True, no_series, False
    return (table.kernel_table(), np.float32(bins / (2.0 * np.pi)), True,
            fit.kernel_coefficients(), True)


@dataclass
class PhaseResult:
    """Calibration-free phase of one fringe set (all (H, W)).

    Attributes:
        phase: float32 unwrapped finest-frequency phase, radians, NaN where invalid.
        modulation: float32 finest-frequency modulation B, codes.
        background: float32 A, the mean of all frames, codes.
        texture: float32 A + B (finest frequency), codes, for display.
        reason: uint8 :class:`~app.core.reasons.Reason` (OK, SATURATED,
            LOW_MODULATION or UNWRAP_INCONSISTENT).
        recovered: pixels with clipped samples whose phase was fitted from the rest.
    """

    phase: F32
    modulation: F32
    background: F32
    texture: F32
    reason: npt.NDArray[np.uint8]
    recovered: int = 0


@dataclass
class ReconResult:
    """One reconstructed fringe set (all (H, W) unless noted).

    Attributes:
        depth: float32 height above the reference plane, mm, NaN invalid.
        points: (H, W, 3) float32 camera-frame points, mm, NaN invalid. The fast path makes
            them on the first read, from :attr:`depth` as it is then and :attr:`point_rays`
            (float32, as the kernel made them before), and keeps them: a set whose points
            nobody reads never pays for them (:class:`~app.recon.points.LazyPoints`).
            Constructed with an array, that array.
        point_rays: the rays the points are made from (None: ``points`` given).
        valid: bool, ``reason == Reason.OK``.
        reason: uint8 :class:`~app.core.reasons.Reason` code.
        modulation: float32 finest-frequency modulation B, codes.
        texture: float32 A + B, codes, for display.
        phase: float32 unwrapped finest phase used for depth, radians, NaN invalid;
            None unless the reconstructor was made with ``with_phase=True``.
        elapsed_ms: wall time of the reconstruction (JIT compilation excluded), ms.
        sigma: float32 total 1-σ depth uncertainty, mm, NaN invalid: ``√(sigma_noise² +
            sigma_model²)``. Its parts: :attr:`sigma_noise`, the sensor noise of the pixel's
            intensities through the modulation to the phase and through the model's ∂z/∂φ
            (independent between pixels), and :attr:`sigma_model`, the calibration's own
            uncertainty at the pixel and its height (the depth model's jackknife over board
            poses, :mod:`app.recon.model_sigma`; shared between nearby pixels).
        model_sigma: the table :attr:`sigma_model` is evaluated from; None when the
            calibration carries no uncertainty (a file without a jackknife): σ_model is then 0.
        recovered: pixels with clipped samples whose phase was fitted from the rest
            (see :mod:`app.recon.phase`).
        motion: with a motion test (``motion_test=True`` or ``run(..., motion=...)``), the
            grown (H, W) bool motion mask (:mod:`app.recon.motion`; those pixels are invalid
            with reason MOTION unless saturated), else None; ``moved_pixels`` its count,
            ``scene_moved`` whether any window was flagged, ``uncertain_moving_pixels`` valid
            pixels made UNCERTAIN by the moving-scene σ bound, ``motion_ms`` the test's wall
            time, ms.
        noise: the camera noise model the set was reconstructed with.
        noise_source: where ``noise`` came from: ``"given"`` (passed to ``run`` or the
            constructor), ``"set"`` (fitted to this set's N-step residual, N > 3) or
            ``"nominal"`` (:meth:`SensorNoise.typical`: the set could not give it).
        noise_note: why the set could not give its noise ("" otherwise).
        phase_error_source: the projector-gamma table the wrapped phases were corrected with:
            ``"learned"`` (the constructor's, from ``fringescope gamma``), ``"given"`` (passed
            to ``run``), ``"set"`` (inferred from this set's 2nd harmonic under a power-law
            projector, :mod:`app.recon.gamma_model`) or ``"none"``.
    """

    depth: F32
    valid: npt.NDArray[np.bool_]
    reason: npt.NDArray[np.uint8]
    modulation: F32
    texture: F32
    phase: F32 | None
    elapsed_ms: float
    points: LazyPoints = LazyPoints()
    point_rays: PointRays | None = None
    sigma: F32 = field(default_factory=lambda: np.empty((0, 0), np.float32))
    recovered: int = 0
    motion: npt.NDArray[np.bool_] | None = None
    moved_pixels: int = 0
    scene_moved: bool = False
    uncertain_moving_pixels: int = 0
    motion_ms: float = 0.0
    noise: SensorNoise | None = None
    noise_source: NoiseSource = "given"
    noise_note: str = ""
    model_sigma: ModelSigmaTable | None = None
    phase_error_source: PhaseErrorSource = "none"

    @property
    def sigma_model(self) -> F32:
        """(H, W) float32 the calibration's 1-σ height uncertainty, mm, NaN invalid (computed
        on each access from :attr:`depth`; 0 where the calibration carries none)."""
        if self.model_sigma is None:
            zero = np.where(np.isfinite(self.sigma), np.float32(0.0), np.float32(np.nan))
            return zero.astype(np.float32)
        return self.model_sigma.sigma_mm(self.depth)

    @property
    def sigma_noise(self) -> F32:
        """(H, W) float32 the sensor-noise part of :attr:`sigma`, mm, NaN invalid."""
        return split_noise(self.sigma, self.sigma_model)


def split_noise(sigma: F32, sigma_model: F32) -> F32:
    """The sensor-noise part ``√(σ² − σ_model²)`` of total σ maps (float32, mm)."""
    with np.errstate(invalid="ignore"):
        var = np.maximum(sigma * sigma - sigma_model * sigma_model, np.float32(0.0))
        return np.sqrt(var).astype(np.float32)


def _phase_numpy(
    frames: npt.NDArray[Any], schedule: PatternSchedule, max_code: int, min_modulation: float,
    consistency_rad: float, combine: bool, phase_error: PhaseErrorLUT | None = None,
    noise: SensorNoise | None = None,
    snr_min: float | None = None,
    false_alarm_rate: float | None = DEFAULT_FALSE_ALARM_RATE,
    max_motion_rad: float = DEFAULT_MAX_MOTION_RAD,
) -> tuple[npt.NDArray[np.float64], Any, npt.NDArray[np.uint8]]:
    """Oracle phase chain: (finest phase f64, WrappedPhase, phase-stage reason).

    ``noise``: the camera's (None: :meth:`SensorNoise.typical` of ``max_code``). ``snr_min``
    (a_min): LOW_MODULATION where the weakest frequency's B is below
    ``max(min_modulation, a_min·√(2/N)·σ_I(A))`` (:mod:`app.recon.validity`); None: below
    ``min_modulation`` alone. Heterodyne orders are tested against ``noise`` at
    ``false_alarm_rate`` (None: no such test) and ``max_motion_rad``
    (:func:`~app.recon.unwrap.order_residuals_consistent`)."""
    wp = wrapped_phase(frames, schedule.steps, max_code=max_code)
    if phase_error is not None:
        wp = replace(wp, phase=phase_error.apply(wp.phase))
    camera = noise if noise is not None else SensorNoise.typical(max_code)
    phase_var = None
    if schedule.unwrap == "heterodyne" and false_alarm_rate is not None:
        var_i = camera.variance_dn2(wp.background)
        with np.errstate(divide="ignore", invalid="ignore"):
            m2 = (wp.modulation * (schedule.steps / 2.0)) ** 2
            phase_var = var_i * phase_variance_factor(m2, schedule.steps)
    unwrapped, consistent = unwrap_phases(
        wp.phase, schedule.frequencies, schedule.unwrap, consistency_rad=consistency_rad,
        phase_var=phase_var, false_alarm_rate=false_alarm_rate or DEFAULT_FALSE_ALARM_RATE,
        max_motion_rad=max_motion_rad,
    )
    if combine:
        phi = combine_phases(unwrapped, wp.modulation, schedule.frequencies, schedule.steps)
    else:
        phi = unwrapped[-1]
    if snr_min is None:
        threshold: Any = min_modulation
    else:
        threshold = modulation_threshold(wp.background, schedule.steps, snr_min,
                                         camera.read_noise_dn**2, camera.gain_dn_per_e,
                                         min_modulation)
    reason = assign_reasons(
        phi.shape,
        saturated=wp.saturated,
        low_modulation=wp.modulation.min(axis=0) < threshold,
        inconsistent=~consistent,
    )
    return phi, wp, reason


def compute_phase(
    frames: Any,
    schedule: PatternSchedule,
    *,
    max_code: int | None = None,
    min_modulation: float | None = None,
    consistency_rad: float = DEFAULT_CONSISTENCY_RAD,
    combine_frequencies: bool = False,
    phase_error: PhaseErrorLUT | None = None,
    noise: SensorNoise | None = None,
    order_error_rate: float = DEFAULT_ORDER_ERROR_RATE,
    false_alarm_rate: float | None = None,
    max_motion_rad: float = DEFAULT_MAX_MOTION_RAD,
) -> PhaseResult:
    """Unwrapped finest phase of a fringe set, without a calibration (numpy path).

    Args:
        frames: (F, H, W) uint8/uint16 (or a sequence of equal 2-D frames),
            F = ``schedule.n_frames``, frequency-major, shift-minor.
        schedule: the pattern schedule.
        max_code: sensor maximum code (see :func:`app.recon.phase.resolve_levels`).
        min_modulation: an explicit modulation threshold, codes; None → the noise-aware
            rule of :mod:`app.recon.validity` (per pixel, from the schedule and ``noise``).
        consistency_rad: unwrapping consistency threshold, radians.
        combine_frequencies: use the noise-optimal combination of all frequencies.
        phase_error: a learned :class:`~app.recon.gamma.PhaseErrorLUT` subtracted from the
            wrapped phases before unwrapping (projector-gamma correction).
        noise: the camera's :class:`SensorNoise` for the rule and the order test; None →
            :meth:`SensorNoise.typical` for ``max_code``.
        order_error_rate: the rule's bound on undetected fringe-order errors per pixel.
        false_alarm_rate: α of the heterodyne order test (None, the default: not made; a capture
            set is one still instant, and on real frames projector-gamma errors beyond the noise
            model fail it for a few % of pixels), and
        max_motion_rad: the motion between groups it guards against, rad
            (:func:`~app.recon.unwrap.order_residuals_consistent`). The live engine
            (:class:`Reconstructor`) always makes it.

    Returns:
        :class:`PhaseResult`.
    """
    frames = check_stack(frames)
    if not isinstance(schedule, PatternSchedule):
        raise ValueError("schedule: expected a PatternSchedule")
    if frames.shape[0] != schedule.n_frames:
        raise ValueError(f"frames: schedule needs {schedule.n_frames} frames, "
                         f"got {frames.shape[0]}")
    if noise is not None and not isinstance(noise, SensorNoise):
        raise ValueError("noise: expected a SensorNoise")
    explicit = min_modulation is not None
    max_code, min_modulation = resolve_levels(frames.dtype, max_code, min_modulation)
    consistency_rad = check_consistency_rad(consistency_rad)
    snr_min = None if explicit else min_phasor_snr(
        schedule.frequencies, schedule.unwrap, consistency_rad=consistency_rad,
        rate=order_error_rate)
    phi, wp, reason = _phase_numpy(
        frames, schedule, max_code, min_modulation, consistency_rad, combine_frequencies,
        phase_error, noise, snr_min, false_alarm_rate, max_motion_rad,
    )
    mod = wp.modulation[-1]
    return PhaseResult(
        phase=np.where(reason == 0, phi, np.nan).astype(np.float32),
        modulation=mod.astype(np.float32),
        background=wp.background.astype(np.float32),
        texture=(wp.background + mod).astype(np.float32),
        reason=reason,
        recovered=int(np.count_nonzero(wp.recovered)) if wp.recovered is not None else 0,
    )


class Reconstructor:
    """Turns fringe sets into depth maps and point clouds for one calibration.

    Args:
        calibration: a :class:`~app.core.calibration.Calibration` (any depth model).
        max_code: sensor maximum code; None → 255 (uint8) / 65535 (uint16). Pass 4095
            for 12-bit data delivered in uint16.
        min_modulation: minimum modulation B (codes) over all frequencies; None → the
            noise-aware rule (:mod:`app.recon.validity`): per pixel, the least B at which the
            schedule's unwrapping chain makes an undetected fringe-order error with
            probability ≤ ``order_error_rate`` under the camera's ``noise``, and at least
            2 codes; with it, unless ``max_sigma_mm`` is given, pixels whose depth σ makes
            an error beyond ``gross_error_mm`` likelier than ``order_error_rate`` are
            UNCERTAIN. An explicit value replaces the rule (both parts).
        consistency_rad: unwrapping consistency threshold, radians (default π/2).
        height_margin_mm: heights beyond the calibrated range by more than this are
            OUTSIDE_VOLUME, mm.
        combine_frequencies: noise-optimal phase from all frequencies.
        fast: use the fused numba kernel (falls back to numpy if numba is missing).
        with_phase: also return the unwrapped phase (calibration and noise analysis
            need it; live depth does not, and it costs a full-frame write).
        noise: the camera's :class:`SensorNoise` for ``ReconResult.sigma``; None → each
            run fits it to its set (N > 3), else :meth:`SensorNoise.typical` for the
            frames' maximum code (``ReconResult.noise_source`` says which).
        max_sigma_mm: pixels whose σ exceeds this are UNCERTAIN (None: the noise-aware
            rule's bound from ``gross_error_mm``, or no such rule with an explicit
            ``min_modulation``).
        order_error_rate: the noise-aware rule's bound per pixel, (0, 0.1].
        gross_error_mm: the depth error the noise-aware rule keeps below
            ``order_error_rate`` (None: no depth-σ part), mm.
        order_false_alarm_rate: α of the heterodyne order test (a still pixel fails it with
            probability ≤ α; :func:`~app.recon.unwrap.order_residuals_consistent`), (0, 1).
        order_max_motion_rad: the change of the finest phase between consecutive frequency
            groups against which that test still guarantees to see a wrong order, rad (0: a
            still scene; the live instrument uses ``unwrap.LIVE_MAX_MOTION_RAD``).
        phase_error: a learned projector-gamma :class:`~app.recon.gamma.PhaseErrorLUT`
            (``fringescope gamma``) subtracted from every wrapped phase before unwrapping, on
            both paths; None: none. ``ValueError`` unless it was learned for the calibration's
            schedule.
        motion_test: test every set of more than one frequency group for motion between its
            groups (:mod:`app.recon.motion`, its default settings with this reconstructor's
            ``gross_error_mm``) and invalidate the moved pixels, unless a run passes its own
            test; False (the default): only runs given a test are tested. A scene that moves
            while one set is projected shifts each group's phase differently: untested, the
            wrong fringe order that can cause reaches tens of mm on pixels that look valid
            (the twin's forceps at 20 ms). Not the default because on real still 4-step sets
            the test still flags 14-26 % of the pixels (README, Rolling mode and motion).
        phase_error_series: whether the fused kernel may evaluate a phase-error table (this
            one, or a run's) as its Fourier series (:attr:`PhaseErrorLUT.series`, within
            ``gamma.SERIES_MAX_DEV_RAD`` of the table: on the twin's 1384 × 1032 sets the
            kernel's CPU drops from 4.9–6.9× to 1.2–1.3× that without a table) where the
            table has one; False: always the table (comparisons).

    Per-pixel model and ray tables are computed once here for the calibration's
    image size.
    """

    def __init__(
        self,
        calibration: Calibration,
        *,
        max_code: int | None = None,
        min_modulation: float | None = None,
        consistency_rad: float = DEFAULT_CONSISTENCY_RAD,
        height_margin_mm: float = 2.0,
        combine_frequencies: bool = False,
        fast: bool = True,
        with_phase: bool = False,
        noise: SensorNoise | None = None,
        max_sigma_mm: float | None = None,
        order_error_rate: float = DEFAULT_ORDER_ERROR_RATE,
        gross_error_mm: float | None = DEFAULT_GROSS_ERROR_MM,
        order_false_alarm_rate: float = DEFAULT_FALSE_ALARM_RATE,
        order_max_motion_rad: float = DEFAULT_MAX_MOTION_RAD,
        phase_error: PhaseErrorLUT | None = None,
        phase_error_series: bool = True,
        motion_test: bool = False,
    ) -> None:
        if not isinstance(calibration, Calibration):
            raise ValueError("calibration: expected a Calibration")
        if phase_error is not None:
            if not isinstance(phase_error, PhaseErrorLUT):
                raise ValueError("phase_error: expected a PhaseErrorLUT")
            sched = calibration.pattern
            phase_error.check_schedule(sched.steps, tuple(float(k) for k in sched.frequencies))
        if noise is not None and not isinstance(noise, SensorNoise):
            raise ValueError("noise: expected a SensorNoise")
        if max_sigma_mm is not None and not (math.isfinite(max_sigma_mm) and max_sigma_mm > 0.0):
            raise ValueError(f"max_sigma_mm: must be finite and > 0, got {max_sigma_mm}")
        if not (math.isfinite(height_margin_mm) and height_margin_mm >= 0.0):
            raise ValueError(f"height_margin_mm: must be finite and >= 0, got {height_margin_mm}")
        if min_modulation is not None and not (math.isfinite(min_modulation)
                                               and min_modulation >= 0):
            raise ValueError(f"min_modulation: must be finite and >= 0, got {min_modulation}")
        if max_code is not None and (int(max_code) != max_code or not 1 <= max_code <= 65535):
            raise ValueError(f"max_code: must be an integer in 1..65535, got {max_code}")
        if not (math.isfinite(order_error_rate) and 0.0 < order_error_rate <= 0.1):
            raise ValueError(f"order_error_rate: must be in (0, 0.1], got {order_error_rate}")
        self.calibration = calibration
        self.phase_error = phase_error
        self.phase_error_series = bool(phase_error_series)
        self.order_error_rate = float(order_error_rate)
        self.max_code = max_code
        self.min_modulation = min_modulation
        self.consistency_rad = check_consistency_rad(consistency_rad)
        self.height_margin_mm = float(height_margin_mm)
        self.combine_frequencies = bool(combine_frequencies)
        self.with_phase = bool(with_phase)
        self.noise = noise
        self.max_sigma_mm = None if max_sigma_mm is None else float(max_sigma_mm)
        self.gross_error_mm = gross_error_mm
        self._sigma_limit_mm = self.max_sigma_mm  # what the UNCERTAIN test uses
        # the rule's error g, whose phase θ_g the noise's phasor tail is weighed at (0: none)
        self._tail_gross_mm = 0.0
        if max_sigma_mm is None and min_modulation is None and gross_error_mm is not None:
            self._sigma_limit_mm = max_depth_sigma_mm(gross_error_mm, self.order_error_rate)
            self._tail_gross_mm = float(gross_error_mm)
        self.order_false_alarm_rate = float(order_false_alarm_rate)
        order_test_bound(2, self.order_false_alarm_rate)  # ValueError naming false_alarm_rate
        self.order_max_motion_rad = float(order_max_motion_rad)
        order_slip_front((1.0, 2.0), self.order_max_motion_rad)  # ValueError naming max_motion_rad
        self.fast = bool(fast) and _fast is not None
        if fast and _fast is None:
            log.warning("fast=True requested but numba is unavailable; using numpy")
        self.motion_test = bool(motion_test) and _fast is not None
        if motion_test and _fast is None:
            log.warning("the motion test needs numba, which is unavailable: sets are not tested")
        lo, hi = calibration.height_range_mm
        self._bounds_mm = (lo - self.height_margin_mm, hi + self.height_margin_mm)
        self._outputs = _OutputPool()
        if self.fast:
            _ = self._fast_tables
        _ = self._model_sigma_kernel
        if self.min_modulation is None:
            _ = self._snr_min  # the rule's bisection (cached per schedule) outside the first run

    @property
    def sigma_limit_mm(self) -> float | None:
        """The UNCERTAIN test's depth-σ limit, mm: ``max_sigma_mm`` if given, else the validity
        rule's bound from ``gross_error_mm`` (None: no such test)."""
        return self._sigma_limit_mm

    @cached_property
    def _rays(self) -> RayTables:
        return calibration_ray_tables(self.calibration)

    @cached_property
    def model_sigma(self) -> ModelSigmaTable | None:
        """The calibration's own σ per pixel and height (None: the calibration carries none)."""
        return model_sigma_table(self.calibration, self._rays, self._bounds_mm)

    @cached_property
    def _model_sigma_kernel(self) -> ModelSigmaTable:
        return self.model_sigma or zero_table(self.calibration.image_size)

    @cached_property
    def _height_tables(self) -> HeightTables:
        return calibration_height_tables(self.calibration)

    @cached_property
    def _fast_tables(self) -> tuple[HeightTables, npt.NDArray[np.float32],
                                    npt.NDArray[np.float32]]:
        """float32 (height tables, ray quotients (H, W, 3), the same as planes (3, H, W))."""
        t = self._height_tables
        f32 = HeightTables(
            np.ascontiguousarray(t.u_norm, np.float32),
            np.ascontiguousarray(t.row_coefs, np.float32),
            np.ascontiguousarray(t.ray_coefs, np.float32), t.phi0, t.inv_sphi, t.cubic,
            np.ascontiguousarray(t.cross_coefs, np.float32), t.radial_k,
        )
        q = ray_quotients(self._rays)
        return f32, q, np.ascontiguousarray(q.transpose(2, 0, 1))

    @cached_property
    def _point_rays(self) -> PointRays:
        """The fast path's points on demand: the kernel's ray quotients and plane offset."""
        return PointRays(self._fast_tables[1], np.float32(self.calibration.plane_offset_mm))

    @cached_property
    def _fast_schedule(self) -> tuple[F32, F32, F32, F32, F32, np.float32, F32]:
        """float32 (cos δ_n, sin δ_n, frequencies, chain coefficients, chain frequencies, z² of the
        heterodyne order test and its squared slip front (P, K − 1), rad²) of the pattern."""
        sched = self.calibration.pattern
        delta = 2.0 * np.pi * np.arange(sched.steps) / sched.steps
        coefs, steps = unwrap_chain(sched.frequencies, sched.unwrap)
        z = order_test_bound(len(sched.frequencies), self.order_false_alarm_rate)
        front = order_slip_front(sched.frequencies, self.order_max_motion_rad)
        return (np.cos(delta).astype(np.float32), np.sin(delta).astype(np.float32),
                np.asarray(sched.frequencies, np.float32), coefs.astype(np.float32),
                steps.astype(np.float32), np.float32(z * z),
                np.ascontiguousarray(front**2, np.float32))

    @cached_property
    def _fast_lut(self) -> KernelLUT:
        """:meth:`_lut_args` of the constructor's table (made once)."""
        return _kernel_lut(self.phase_error, len(self.calibration.pattern.frequencies),
                           self.phase_error_series)

    def _lut_args(self, table: PhaseErrorLUT | None) -> KernelLUT:
        """The kernel's phase-error table (K, bins + 2) float32, bins/2π and whether to apply it
        (a (K, 2) zero table when there is none), and its series (:data:`KernelLUT`)."""
        if table is self.phase_error:
            return self._fast_lut
        return _kernel_lut(table, len(self.calibration.pattern.frequencies),
                           self.phase_error_series)

    @cached_property
    def _tables64(self) -> tuple[ModelTables, RayTables]:
        rays = self._rays
        return pixel_tables(self._height_tables, ray_quotients(rays, dtype=np.float64)), rays

    @cached_property
    def _region_columns(self) -> tuple[F32, F32, npt.NDArray[np.int64], float, float, F32, F32]:
        """The supported region for the kernel: (gh, W) float32 lower and upper height bounds per
        grid row and column, (H,) grid row of every image row, phase range, (H,) float32 lowest
        and highest supported column of every row (cells and field as in
        :meth:`~app.core.depth_model.SupportedRegion.outside`)."""
        region = self.calibration.model.region
        grid, inv_w, inv_h, p_lo, p_hi = region.kernel_bounds()
        w, h = self.calibration.image_size
        cols = np.minimum((np.arange(w) * inv_w).astype(np.int64), grid.shape[1] - 1)
        rows = np.minimum((np.arange(h) * inv_h).astype(np.int64), grid.shape[0] - 1)
        per_col = grid[:, cols, :]
        u_lo, u_hi = region.column_bounds(h, w)
        return (np.ascontiguousarray(per_col[..., 0], np.float32),
                np.ascontiguousarray(per_col[..., 1], np.float32), rows, p_lo, p_hi, u_lo, u_hi)

    @cached_property
    def _snr_min(self) -> float:
        """a_min of the noise-aware modulation rule for the calibration's schedule."""
        sched = self.calibration.pattern
        return min_phasor_snr(sched.frequencies, sched.unwrap, consistency_rad=self.consistency_rad,
                              rate=self.order_error_rate)

    def _noise(self, max_code: int) -> SensorNoise:
        return self.noise if self.noise is not None else SensorNoise.typical(max_code)

    def run(self, frames: Any, *, fast: bool | None = None, max_code: int | None = None,
            noise: SensorNoise | None = None, motion: MotionTest | None = None,
            phase_error: PhaseErrorLUT | None = None) -> ReconResult:
        """Reconstruct one fringe set.

        Args:
            frames: (F, H, W) uint8/uint16 in capture-set order (F = the calibration's
                ``pattern.n_frames``, H×W its image size), or a sequence of 2-D frames.
            fast: override the constructor's choice of path for this call.
            max_code: override the constructor's sensor maximum code for this call
                (a capture set's ``max_code``, from its ``bit_depth``).
            noise: the camera's noise model for this set (σ, the validity rule, the order
                and motion tests); None → the constructor's, else fitted to this set
                (:func:`app.recon.noise.resolve_set_noise`: N > 3, else the nominal).
            motion: the settings of this set's motion test between its frequency groups
                (:mod:`app.recon.motion`; the moved pixels are invalidated); None: the
                default test where the constructor's ``motion_test`` is set (and the set has
                more than one group), else none.
            phase_error: a projector-gamma table for this set, used where the constructor has
                no learned one (a caller that fitted the set's noise itself passes the
                table :func:`~app.recon.noise.resolve_set_noise` gave with it). None: where
                the noise is fitted to this set, the table its 2nd harmonic gives (N = 4).

        Returns:
            :class:`ReconResult`.
        """
        if noise is not None and not isinstance(noise, SensorNoise):
            raise ValueError("noise: expected a SensorNoise")
        if phase_error is not None:
            if not isinstance(phase_error, PhaseErrorLUT):
                raise ValueError("phase_error: expected a PhaseErrorLUT")
            sched = self.calibration.pattern
            phase_error.check_schedule(sched.steps, tuple(float(k) for k in sched.frequencies))
        if motion is not None:
            from app.recon import motion as motion_module

            if not isinstance(motion, motion_module.MotionTest):
                raise ValueError("motion: expected a MotionTest")
        elif self.motion_test and len(self.calibration.pattern.frequencies) > 1:
            from app.recon import motion as motion_module

            motion = motion_module.MotionTest(gross_error_mm=self.gross_error_mm)
        frames = check_stack(frames)
        self.calibration.check_frames(frames.shape)
        max_code, min_mod = resolve_levels(
            frames.dtype, self.max_code if max_code is None else max_code, self.min_modulation)
        source: NoiseSource = "given"
        note = ""
        set_table: PhaseErrorLUT | None = None
        if noise is not None:
            camera = noise
        elif self.noise is not None:
            camera = self.noise
        else:  # the set's own noise (and gamma), as every path without a measured model
            est = resolve_set_noise(frames, self.calibration.pattern, max_code)
            camera, source, note, set_table = est.noise, est.source, est.note, est.phase_error
        # a table learned against a many-step reference beats one inferred from the set
        table, table_source = _choose_table(self.phase_error, phase_error, set_table)
        use_fast = self.fast if fast is None else (bool(fast) and _fast is not None)
        if use_fast:
            res = self._run_fast(frames, max_code, min_mod, camera, table)
        else:
            res = self._run_numpy(frames, max_code, min_mod, camera, table)
        res.noise, res.noise_source, res.noise_note = camera, source, note
        res.phase_error_source = table_source
        res.model_sigma = self.model_sigma
        res.motion, res.moved_pixels, res.scene_moved = None, 0, False
        res.uncertain_moving_pixels, res.motion_ms = 0, 0.0
        if motion is not None:
            # points not made yet follow the invalidated depth when they are
            mp = motion_module.invalidate_motion(
                frames, len(self.calibration.pattern.frequencies), noise=camera, depth=res.depth,
                points=LazyPoints.given(res), valid=res.valid, reason=res.reason, sigma=res.sigma,
                test=motion, max_code=max_code)
            res.motion, res.moved_pixels, res.scene_moved = mp.mask, mp.moved, mp.scene_moved
            res.uncertain_moving_pixels, res.motion_ms = mp.uncertain, mp.elapsed_ms
            if res.phase is not None and (mp.moved or mp.uncertain):
                res.phase[~res.valid] = np.nan  # NaN where invalid, as every other output
        return res

    def _run_numpy(self, frames: npt.NDArray[Any], max_code: int, min_mod: float,
                   camera: SensorNoise, lut: PhaseErrorLUT | None) -> ReconResult:
        t0 = time.perf_counter()
        cal = self.calibration
        model, rays = self._tables64
        phi, wp, reason = _phase_numpy(
            frames, cal.pattern, max_code, min_mod, self.consistency_rad, self.combine_frequencies,
            phase_error=lut, noise=camera,
            snr_min=None if self.min_modulation is not None else self._snr_min,
            false_alarm_rate=self.order_false_alarm_rate, max_motion_rad=self.order_max_motion_rad,
        )
        height, singular, slope = evaluate_height_slope(model, phi)
        lo, hi = self._bounds_mm
        outside = outside_volume(height, (lo, hi), 0.0)
        outside_field = cal.model.region.outside(height, phi, measured=True)
        steps = cal.pattern.steps
        m2 = (wp.modulation * (steps / 2.0)) ** 2  # (K, H, W) (Σ I cosδ)² + (Σ I sinδ)²
        if self.combine_frequencies:
            k = np.asarray(cal.pattern.frequencies, np.float64)[:, None, None]
            with np.errstate(divide="ignore"):
                vfac = 0.5 * steps * k[-1] ** 2 / (k**2 * m2).sum(axis=0)
        else:
            vfac = phase_variance_factor(m2[-1], steps)
        table = self._model_sigma_kernel
        sigma_model = table.sigma_mm(height.astype(np.float32)).astype(np.float64)
        with np.errstate(invalid="ignore"):
            sigma_noise = np.abs(slope) * np.sqrt(camera.variance_dn2(wp.background) * vfac)
            sigma = np.sqrt(sigma_noise**2 + sigma_model**2)
        uncertain = None
        if self._sigma_limit_mm is not None:
            # the noise part weighed by its phasor tail (app.recon.validity, step 5); a flat or
            # undefined slope takes the cap
            with np.errstate(divide="ignore", invalid="ignore"):
                theta_sq = np.where(np.isfinite(slope) & (slope != 0.0),
                                    self._tail_gross_mm**2 / slope**2, np.inf)
                limit_sq = self._sigma_limit_mm**2
                uncertain = sigma_noise**2 * phasor_tail_factor_sq(theta_sq) \
                    + sigma_model**2 > limit_sq
            # the model's own σ fails the rule: outside the field
            outside_field = outside_field | ~(sigma_model <= self._sigma_limit_mm)
        reason = assign_reasons(
            phi.shape,
            saturated=reason == 2,
            low_modulation=reason == 1,
            inconsistent=reason == 3,
            singular=singular,
            outside=outside,
            outside_field=outside_field,
            uncertain=uncertain,
        )
        valid = reason == 0
        depth = np.where(valid, height, np.nan)
        points = points_from_height(depth, rays, cal.plane_offset_mm)
        mod = wp.modulation[-1]
        return ReconResult(
            depth=depth.astype(np.float32),
            points=points.astype(np.float32),
            valid=valid,
            reason=reason,
            modulation=mod.astype(np.float32),
            texture=(wp.background + mod).astype(np.float32),
            phase=np.where(valid, phi, np.nan).astype(np.float32) if self.with_phase else None,
            elapsed_ms=(time.perf_counter() - t0) * 1e3,
            sigma=np.where(valid, sigma, np.nan).astype(np.float32),
            recovered=int(np.count_nonzero(wp.recovered)) if wp.recovered is not None else 0,
        )

    def _run_fast(self, frames: npt.NDArray[Any], max_code: int, min_mod: float,
                  camera: SensorNoise, table: PhaseErrorLUT | None) -> ReconResult:
        assert _fast is not None
        _fast.warmup(frames.dtype)  # JIT (or cache load) outside the timed region
        t0 = time.perf_counter()
        out = self._outputs.take(frames.shape[1:], self.with_phase)
        out.points = None  # made from this depth on the first read
        out.point_rays = self._point_rays
        with _fast.KERNEL_LOCK:
            self._launch(frames, max_code, min_mod, out, camera, table)
        out.elapsed_ms = (time.perf_counter() - t0) * 1e3
        return out

    def _launch(self, frames: npt.NDArray[Any], max_code: int, min_mod: float, out: ReconResult,
                noise: SensorNoise, table: PhaseErrorLUT | None) -> None:
        assert _fast is not None
        cal = self.calibration
        tables, _, ray_planes = self._fast_tables
        cos_d, sin_d, freqs, chain_c, chain_f, order_z2, order_front2 = self._fast_schedule
        lo, hi = self._bounds_mm
        r_lo, r_hi, rows, p_lo, p_hi, u_lo, u_hi = self._region_columns
        f32 = np.float32
        ph = _fast.PhaseArgs(cos_d, sin_d, freqs, np.int32(max_code), f32(min_mod),
                             f32(self.consistency_rad),
                             chain_c, chain_f, cal.pattern.unwrap == "heterodyne",
                             f32(0.0 if self.min_modulation is not None else self._snr_min ** 2),
                             order_z2, order_front2, f32(PHASE_FLOOR_RAD**2),
                             *self._lut_args(table))
        m = _fast.HeightArgs(
            tables.u_norm, tables.row_coefs, tables.ray_coefs, bool(np.any(tables.ray_coefs)),
            f32(tables.phi0), f32(tables.inv_sphi), f32(tables.cubic),
            tables.cross_coefs, f32(tables.radial_k), tables.radial_k != 0.0, f32(lo), f32(hi),
            f32(SINGULAR_RTOL),
            ray_planes, r_lo, r_hi, rows, f32(p_lo), f32(p_hi), u_lo, u_hi,
            f32(noise.read_noise_dn**2), f32(noise.gain_dn_per_e),
            f32(self._sigma_limit_mm if self._sigma_limit_mm is not None else np.inf),
            self.combine_frequencies, f32(cal.pattern.steps / 2.0), f32(1.0 / cal.pattern.n_frames),
            self._model_sigma_kernel.coefs, self._model_sigma_kernel.rows,
            self._model_sigma_kernel.row_weights,
            f32(self._model_sigma_kernel.mid_mm), f32(self._model_sigma_kernel.inv_half_mm),
            f32(self._tail_gross_mm**2), _TAIL_COEFS, f32(PHASOR_TAIL_T_MAX),
        )
        recovered = np.zeros(frames.shape[1], np.int32)
        o = _fast.Outputs(out.depth, out.reason, out.valid, out.modulation, out.texture,
                          out.phase if out.phase is not None else _NO_PHASE, out.sigma, recovered)
        _fast.fused_kernel(np.ascontiguousarray(frames), ph, m, o)
        out.recovered = int(recovered.sum())


_NO_PHASE = np.empty((0, 0), np.float32)  # the kernel skips the phase output for zero rows
_TAIL_COEFS = np.asarray(PHASOR_TAIL_COEFS, np.float32)


class _OutputPool:
    """Recycles the arrays of results that nobody references any more.

    Fresh output arrays cost a page fault per 4 KiB on first write, a large part of the
    fast path's time. A recent result is reused only when its object and every array
    are referenced by this pool alone (the check ``ndarray.resize(refcheck=True)``
    makes): a caller that keeps the result, an array, a view of one or an exported
    buffer keeps it out of reuse.
    """

    def __init__(self, size: int = 2) -> None:  # the result in use and the one before
        self._recent: list[ReconResult] = []
        self._size = size
        self._lock = threading.Lock()

    def take(self, shape: tuple[int, ...], with_phase: bool) -> ReconResult:
        h, w = shape
        with self._lock:
            # indexed, not iterated: a loop variable would itself count as a reference
            for i in range(len(self._recent)):
                if (_reference_counts(self._recent[i]) == _UNREFERENCED
                        and self._recent[i].depth.shape == (h, w)
                        and (self._recent[i].phase is not None) == with_phase):
                    res = self._recent.pop(i)
                    break
            else:
                res = _new_result(h, w, with_phase)
            self._recent = [res, *self._recent][: self._size]
            return res


def _new_result(h: int, w: int, with_phase: bool) -> ReconResult:
    res = ReconResult(
        depth=np.empty((h, w), np.float32),
        valid=np.empty((h, w), np.bool_),
        reason=np.empty((h, w), np.uint8),
        modulation=np.empty((h, w), np.float32),
        texture=np.empty((h, w), np.float32),
        phase=np.empty((h, w), np.float32) if with_phase else None,
        elapsed_ms=0.0,
        sigma=np.empty((h, w), np.float32),
    )
    # where its points are made on demand (pages faulted once per pooled result, not per set)
    vars(res)["_points_buf"] = np.empty((h, w, 3), np.float32)
    return res


def _reference_counts(res: ReconResult) -> tuple[int, int]:
    """(references to ``res``, most references to any of its arrays, the points' buffer
    counted without the result's own second reference to it once the points are made)."""
    state = vars(res)
    # (no local name for the buffer: it would count as one more reference)
    arrays = [a for a in (res.depth, res.valid, res.reason, res.modulation, res.texture,
                          res.phase, res.sigma, state["_points_buf"]) if a is not None]
    counts = [sys.getrefcount(a) for a in arrays]
    counts[-1] -= state.get("_points") is arrays[-1]
    return sys.getrefcount(res), max(counts)


# The counts of a result held by a list alone, measured the way take() measures them
# (reference counting details differ between Python versions).
_probe = [_new_result(1, 1, True)]
_UNREFERENCED = _reference_counts(_probe[0])
del _probe
