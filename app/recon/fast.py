"""The fast path: one fused, parallel numba kernel from raw frames to depth and σ.

Rows are processed in blocks (``prange``), row by row through block-local buffers:

1. Phase, then height: for the paper's schedule (4
   frequencies × 4 steps) one loop per row reads all 16 frames of a pixel and keeps
   everything in registers — Σ I sinδ and Σ I cosδ as differences of frames, the coarse
   levels with a cheaper atan2 (they only pick fringe orders), the finest with the
   precise one, the hierarchical unwrapping with its consistency test and the phase
   stage's reason code. A projector-gamma phase-error table is applied to every wrapped
   phase: as its Fourier series in 4φ (:attr:`app.recon.gamma.PhaseErrorLUT.series`),
   evaluated from the pixel's phasor in the same vectorised loop, where the table has one;
   else by scalar look-ups in a pass of their own (they do not vectorise: ~5× the CPU).
   Any other schedule (any N ≥ 3, heterodyne unwrapping), and the noise-optimal
   combination of frequencies, takes a general row-by-row path with the same semantics
   (the series too). Then a scan of the row's codes finds pixels with a clipped sample; a
   row that has some is refitted whole, branch-free, from the unclipped samples
   (saturation-tolerant phase), and its SATURATED pixels take the result; on
   unsaturated data that scan is all it costs. The height
   stage (:func:`_height_row`, both paths) evaluates the depth model's closed form
   (:mod:`app.core.depth_model`: per-row polynomial coefficients, plus the ray quotient
   terms for the geometric model), σ (sensor noise → phase via the modulation → ∂z/∂φ),
   the supported region and the final reason code, and writes every output of the row in
   the same pixel loop: reason/valid, depth, σ, modulation/texture.
2. The optional phase, from the block's buffers once its rows are done. The 3-D
   points are not the kernel's: they follow from depth and the rays on demand
   (:class:`app.recon.points.PointRays`), which spares most sets a (H, W, 3) write.

The kernel takes named tuples (:class:`PhaseArgs`, :class:`HeightArgs`, :class:`Outputs`);
reason codes are used by name.

Each helper is compiled (and vectorised by LLVM) as its own function over 1-D rows;
inside one big parallel body LLVM could not prove the buffers distinct. Semantics are
those of the numpy oracle (``phase``/``unwrap``/``model``/``points``); only the
arithmetic is float32. ``fastmath`` excludes ``nnan``/``ninf`` because NaN marks
invalid pixels. The JIT result is cached on disk (``cache=True``).

The threading layer and the vector width are the entry points' settings, not this module's
(:func:`app.core.jit.configure_numerics`): the CLI, the tests, the benchmarks, the Makefile and
the container set ``NUMBA_THREADING_LAYER=workqueue`` (OpenMP's spinning threads are 8x slower on 2
cores), numba reads it when the first parallel kernel is compiled; on an AVX-512 CPU the CLI,
the tests and ``bench_recon`` also let LLVM use 512-bit vectors (its tuning keeps 256: the
kernel's float32 loops then take ~30 % more CPU).
"""

from __future__ import annotations

import math
import threading
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from numba import njit, prange

from app.core.depth_model import COLUMN_ITERATIONS
from app.core.reasons import Reason

# All flags of fastmath=True except nnan/ninf (outputs carry NaN on purpose).
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}
ROWS_PER_BLOCK = 8
PAPER_SPAN = 64  # pixels: the 4 × 4 schedule's closed-form refit skips spans without clipping
REFIT_SPAN = 512  # pixels: the saturation refit skips spans of a row without a clipped sample
# numba's workqueue threading layer aborts the process when two threads launch parallel
# kernels at once: every launch holds this lock (the kernel itself releases the GIL).
KERNEL_LOCK = threading.Lock()


class PhaseArgs(NamedTuple):
    """The phase stage's inputs: float32 cos δ_n, sin δ_n (N,), fringe counts (K,), sensor
    maximum code, minimum modulation (codes) and unwrapping consistency threshold (rad);
    ``chain_c`` (S, K), ``chain_f`` (S,) float32: the unwrapping steps of
    :func:`app.recon.unwrap.unwrap_chain`, used when ``heterodyne``; ``snr_min2``: a_min² of
    the noise-aware modulation rule (:mod:`app.recon.validity`; 0: ``min_mod`` alone). The
    kernel's test is ``m2min < max(m2(min_mod), a_min²·(N/2)·(read_var + gain·A))``. The
    heterodyne chain's order test (:func:`app.recon.unwrap.order_residuals_consistent`):
    ``order_z2`` z² of its bound and ``order_front2`` (P, K − 1) the squared
    :func:`~app.recon.unwrap.order_slip_front`, ``order_floor2`` the unmodelled phase variance of
    every wrapped phase (``unwrap.PHASE_FLOOR_RAD``²), rad². ``lut`` (K, bins + 2) float32 the
    projector-gamma phase-error table (:meth:`app.recon.gamma.PhaseErrorLUT.kernel_table`)
    subtracted from every wrapped phase when ``use_lut``, ``lut_scale`` its bins/2π; ``series``
    (K, 7) float32 the same table as a Fourier series in 4φ
    (:meth:`app.recon.gamma.PhaseErrorSeries.kernel_coefficients`), which every path evaluates
    instead of the table when ``use_series``."""

    cos_t: npt.NDArray[np.float32]
    sin_t: npt.NDArray[np.float32]
    freqs: npt.NDArray[np.float32]
    max_code: np.int32
    min_mod: np.float32
    cons_rad: np.float32
    chain_c: npt.NDArray[np.float32]
    chain_f: npt.NDArray[np.float32]
    heterodyne: bool
    snr_min2: np.float32
    order_z2: np.float32
    order_front2: npt.NDArray[np.float32]
    order_floor2: np.float32
    lut: npt.NDArray[np.float32]
    lut_scale: np.float32
    use_lut: bool
    series: npt.NDArray[np.float32]
    use_series: bool


class HeightArgs(NamedTuple):
    """The height stage's inputs (float32 scalars): the model's
    :class:`~app.core.depth_model.HeightTables` (``u_norm``, ``row_coefs``, ``ray_coefs``,
    ``phi0``, ``inv_sphi``, ``cubic``, ``cross_coefs``, ``radial_k``; ``use_rays`` when
    ``ray_coefs`` are not all zero, ``use_cross`` when ``radial_k`` is not zero), the
    volume ``lo``..``hi`` mm, ``sing_rtol``, ``ray_q`` (3, H, W): the ray quotients' planes
    (read when ``use_rays``; planar, so that the row loop loads each contiguously),
    the supported region (``region_lo``, ``region_hi`` (gh, W) height bounds mm per
    grid row and column, ``region_rows`` (H,) the grid row of every image row, phase
    range rad, ``field_u_lo``/``field_u_hi`` (H,) the supported columns of every row: the
    camera-field limit of :meth:`~app.core.depth_model.SupportedRegion.column_bounds`), the
    sensor noise (``read_var`` DN², ``gain`` DN/e⁻), ``max_sigma``
    mm, ``combine`` (noise-optimal phase), ``half_steps`` N/2 and ``inv_frames`` 1/F; the
    model's own σ: ``sm_coefs`` (R, 5, W), ``sm_rows`` (H,), ``sm_weights`` (H,), ``sm_mid`` and
    ``sm_inv_half`` of
    :class:`~app.recon.model_sigma.ModelSigmaTable`; the gross-error test's phasor tail
    (:mod:`app.recon.validity`, step 5): ``gross_sq`` g² mm² (0: no tail weight), ``tail_coefs``
    (4,) and ``tail_t_max`` of :func:`~app.recon.validity.phasor_tail_factor_sq`."""

    u_norm: npt.NDArray[np.float32]
    row_coefs: npt.NDArray[np.float32]
    ray_coefs: npt.NDArray[np.float32]
    use_rays: bool
    phi0: np.float32
    inv_sphi: np.float32
    cubic: np.float32
    cross_coefs: npt.NDArray[np.float32]
    radial_k: np.float32
    use_cross: bool
    lo: np.float32
    hi: np.float32
    sing_rtol: np.float32
    ray_q: npt.NDArray[np.float32]
    region_lo: npt.NDArray[np.float32]
    region_hi: npt.NDArray[np.float32]
    region_rows: npt.NDArray[np.int64]
    phase_lo: np.float32
    phase_hi: np.float32
    field_u_lo: npt.NDArray[np.float32]
    field_u_hi: npt.NDArray[np.float32]
    read_var: np.float32
    gain: np.float32
    max_sigma: np.float32
    combine: bool
    half_steps: np.float32
    inv_frames: np.float32
    sm_coefs: npt.NDArray[np.float32]
    sm_rows: npt.NDArray[np.int64]
    sm_weights: npt.NDArray[np.float32]
    sm_mid: np.float32
    sm_inv_half: np.float32
    gross_sq: np.float32
    tail_coefs: npt.NDArray[np.float32]
    tail_t_max: np.float32


class Outputs(NamedTuple):
    """The kernel's (H, W) outputs; ``phase`` with zero rows is skipped;
    ``recovered`` (H,) int32: per row, the pixels refitted from their unclipped samples."""

    depth: npt.NDArray[np.float32]
    reason: npt.NDArray[np.uint8]
    valid: npt.NDArray[np.bool_]
    modulation: npt.NDArray[np.float32]
    texture: npt.NDArray[np.float32]
    phase: npt.NDArray[np.float32]
    sigma: npt.NDArray[np.float32]
    recovered: npt.NDArray[np.int32]


# reason codes by name (values of app.core.reasons.Reason)
_OK = np.uint8(Reason.OK)
_LOW_MODULATION = np.uint8(Reason.LOW_MODULATION)
_SATURATED = np.uint8(Reason.SATURATED)
_INCONSISTENT = np.uint8(Reason.UNWRAP_INCONSISTENT)
_OUTSIDE_VOLUME = np.uint8(Reason.OUTSIDE_VOLUME)
_MODEL_SINGULAR = np.uint8(Reason.MODEL_SINGULAR)
_OUTSIDE_FIELD = np.uint8(Reason.OUTSIDE_FIELD)
_UNCERTAIN = np.uint8(Reason.UNCERTAIN)

_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_F3 = np.float32(3.0)
_PI = np.float32(math.pi)
_HALF_PI = np.float32(0.5 * math.pi)
_COLUMN_ITERATIONS = COLUMN_ITERATIONS  # Newton steps of a radial projector lens
_TWO_PI = np.float32(2.0 * math.pi)
_INV_TWO_PI = np.float32(1.0 / (2.0 * math.pi))
_TINY = np.float32(1e-30)
_NAN = np.float32(np.nan)
_INF = np.float32(np.inf)
_SHIFT = np.float32(64.0)  # orders stay far above -64
_ROUND_SHIFT = np.float32(64.5)
# atan(a) ≈ a·P(a²) on [0, 1]: weighted least-squares minimax fit, max error 3.7e-8 rad
# in float64 (1.2e-7 evaluated in float32; see tests/recon/test_fast.py).
_A0 = np.float32(0.9999993356608105)
_A1 = np.float32(-0.33329860955265084)
_A2 = np.float32(0.1994656676652332)
_A3 = np.float32(-0.13908632720069006)
_A4 = np.float32(0.09642201479625472)
_A5 = np.float32(-0.05591234645397164)
_A6 = np.float32(0.021862953185210254)
_A7 = np.float32(-0.004054562176639915)
# The coarse levels' atan: 5 terms fitted the same way, max error 1.2e-5 rad
# (orders need ≪ π/ratio).
_C0 = np.float32(0.9998663502225011)
_C1 = np.float32(-0.3303051326177987)
_C2 = np.float32(0.1801607941668026)
_C3 = np.float32(-0.08515867977071649)
_C4 = np.float32(0.020846294370275874)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _octant(y, x):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """atan2's reduction: (a = min/max of |x|, |y| in [0, 1], and the three folds)."""
    ax = abs(x)
    ay = abs(y)
    return min(ax, ay) / max(max(ax, ay), _TINY), ay > ax, x < _F0, y < _F0


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _unfold(r, steep, left, below):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """atan(a) in [0, π/4] back to the full angle in [0, 2π), branch-free."""
    r = _HALF_PI - r if steep else r
    r = _PI - r if left else r
    r = _TWO_PI - r if below else r
    return _F0 if r >= _TWO_PI else r


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def atan2_0_2pi(y, x):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Branch-free float32 atan2 mapped to [0, 2π) (float32 in and out)."""
    a, steep, left, below = _octant(y, x)
    s = a * a
    p = ((((((_A7 * s + _A6) * s + _A5) * s + _A4) * s + _A3) * s + _A2) * s + _A1) * s + _A0
    return _unfold(p * a, steep, left, below)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def atan2_coarse(y, x):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Branch-free float32 atan2 in [0, 2π), error ≤ 1.2e-5 rad: enough to pick fringe orders."""
    a, steep, left, below = _octant(y, x)
    s = a * a
    return _unfold(((((_C4 * s + _C3) * s + _C2) * s + _C1) * s + _C0) * a, steep, left, below)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _order_step(prev, phw, ratio):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """One hierarchical step: (unwrapped phase, |residual| before rounding)."""
    e = ratio * prev - phw
    # floor(e/2π + 1/2) by truncating a shifted, positive value (vectorises)
    order = np.float32(np.int32(e * _INV_TWO_PI + _ROUND_SHIFT)) - _SHIFT
    return phw + order * _TWO_PI, abs(e - order * _TWO_PI)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _lut_correct(w, row, scale):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """The wrapped phase ``w`` in [0, 2π) less the phase-error table's error at ``w``, in [0, 2π):
    :meth:`app.recon.gamma.PhaseErrorLUT.apply` in float32. ``row`` (bins + 2,) is one frequency's
    :meth:`~app.recon.gamma.PhaseErrorLUT.kernel_table` (padded circularly: no modulo), ``scale``
    bins/2π; x = w·scale + 1/2 ∈ [1/2, bins + 1/2) so its truncation is the floor. The index is
    clamped to the row: a saturation refit without enough samples gives w = NaN, whose int32 is
    arbitrary (an N = 4 set's own gamma table reached that path on the general kernel and read
    far outside the row); such a pixel is SATURATED and its value unused."""
    x = w * scale + np.float32(0.5)
    j = min(max(np.int32(x), np.int32(0)), np.int32(row.shape[0] - 2))
    t = x - np.float32(j)
    e0 = row[j]
    r = w - (e0 + t * (row[j + 1] - e0))
    r = r + _TWO_PI if r < _F0 else r
    return r - _TWO_PI if r >= _TWO_PI else r


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _series_error(y, x, q, c):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """The phase-error series (:class:`app.recon.gamma.PhaseErrorSeries`: period 4, 3
    harmonics) at φ = atan2(y, x), rad, from the phasor (x, y) and q = x² + y² (float32).
    ``c`` = (a_0, a_1, b_1, a_2, b_2, a_3, b_3), one row of
    :meth:`~app.recon.gamma.PhaseErrorSeries.kernel_coefficients`. e^{i4φ} = ((x + iy)²/q)²,
    then e^{i8φ}, e^{i12φ} by complex products: no atan2 and no look-up, so the pixel loop
    vectorises. q = 0 (no fringe) reads e = a_0."""
    inv = _F1 / max(q, _TINY)
    c2 = (x * x - y * y) * inv
    s2 = np.float32(2.0) * x * y * inv
    c4 = c2 * c2 - s2 * s2
    s4 = np.float32(2.0) * c2 * s2
    c8 = c4 * c4 - s4 * s4
    s8 = np.float32(2.0) * c4 * s4
    c12 = c8 * c4 - s8 * s4
    s12 = c8 * s4 + s8 * c4
    return c[0] + (c[1] * c4 + c[2] * s4) + (c[3] * c8 + c[4] * s8) + (c[5] * c12 + c[6] * s12)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _series_correct(w, y, x, q, c):  # type: ignore[no-untyped-def]  # pragma: no cover
    """The wrapped phase ``w`` = atan2(y, x) in [0, 2π) less the series' error
    (:func:`_series_error`), in [0, 2π): :func:`_lut_correct` without the table."""
    r = w - _series_error(y, x, q, c)
    r = r + _TWO_PI if r < _F0 else r
    return r - _TWO_PI if r >= _TWO_PI else r


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _series_row(ser, k):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Row ``k`` of the (K, 7) series coefficients as a tuple of scalars: read once per row,
    outside the pixel loop (loads from an array inside it could alias the row's stores, which
    kept LLVM from vectorising)."""
    r = ser[k]
    return (r[0], r[1], r[2], r[3], r[4], r[5], r[6])


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _mask(c, dev, m2min, top, cons_rad, m2_min, top_code,  # type: ignore[no-untyped-def]
          tot):  # pragma: no cover
    # the phase stage's causes: SATURATED > LOW_MODULATION > UNWRAP_INCONSISTENT
    # (> the height stage's)
    # m2_min = (floor, k0, k1): LOW_MODULATION below max(floor, k0 + k1·Σ I) (PhaseArgs.snr_min2)
    c = _INCONSISTENT if dev >= cons_rad else c
    c = _LOW_MODULATION if m2min < max(m2_min[0], m2_min[1] + m2_min[2] * tot) else c
    return _SATURATED if top >= top_code else c


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _px4(frames, b, v, u):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """N = 4 at pixel (v, u) from frame b on (δ = 0, π/2, π, 3π/2, so −Σ I sinδ = I3 − I1
    and Σ I cosδ = I0 − I2): (y, x, x² + y², Σ I, max I).

    ``frames`` is the whole C-contiguous stack: a (16, W) row view would have a run-time
    stride, and LLVM only vectorises such loads for bytes."""
    i0 = np.float32(frames[b, v, u])
    i1 = np.float32(frames[b + 1, v, u])
    i2 = np.float32(frames[b + 2, v, u])
    i3 = np.float32(frames[b + 3, v, u])
    yy = i3 - i1
    xx = i0 - i2
    return yy, xx, xx * xx + yy * yy, (i0 + i1) + (i2 + i3), max(max(i0, i1), max(i2, i3))


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _paper_row(frames, v, chain, cons_rad, m2_min, top_code,  # type: ignore[no-untyped-def]
               total, m2, prev, code, lut_rows):  # pragma: no cover - compiled
    """Phase 1 of row ``v`` for 4 frequencies × 4 steps (the height follows in
    :func:`_height_row`): coarse atan2 for the levels that only pick orders, the precise one
    for the finest. ``chain`` = (r1, r2, r3: the fringe-count ratios, the (4, bins + 2)
    phase-error table, bins/2π, whether to apply it to every wrapped phase:
    :func:`_lut_correct`; ``lut_rows`` (6, ≥ W) float32 scratch for that case)."""
    r1, r2, r3, lut, scale, use_lut, ser, use_ser = chain
    l0, l1, l2, l3 = lut[0], lut[1], lut[2], lut[3]
    # one loop per choice, each written out: a run-time switch, or a helper too large for LLVM to
    # inline, in the pixel loop kept LLVM from vectorising it
    # the table as a series of the phasor: one vectorised pass. Past the first level the
    # corrected phase is not wrapped: a hierarchical step's result and residual do not change
    # when its wrapped phase moves by 2π (the order absorbs it), and the wrap's selects cost
    if use_ser:
        c0, c1, c2, c3 = (_series_row(ser, 0), _series_row(ser, 1), _series_row(ser, 2),
                          _series_row(ser, 3))
        for u in range(frames.shape[2]):
            y0, x0, q0, tt, mx = _px4(frames, 0, v, u)
            y1, x1, q1, t1, m1 = _px4(frames, 4, v, u)
            y2, x2, q2, t2, m2_ = _px4(frames, 8, v, u)
            y3, x3, q, t3, m3 = _px4(frames, 12, v, u)
            qmin = min(min(q0, q1), min(q2, q))
            p = _series_correct(atan2_coarse(y0, x0), y0, x0, q0, c0)
            p, d1 = _order_step(p, atan2_coarse(y1, x1) - _series_error(y1, x1, q1, c1), r1)
            p, d2 = _order_step(p, atan2_coarse(y2, x2) - _series_error(y2, x2, q2, c2), r2)
            p, d3 = _order_step(p, atan2_0_2pi(y3, x3) - _series_error(y3, x3, q, c3), r3)
            dev = max(max(d1, d2), d3)
            tot = (tt + t1) + (t2 + t3)
            total[u] = tot
            prev[u] = p
            m2[u] = q
            top = max(max(mx, m1), max(m2_, m3))
            code[u] = _mask(_OK, dev, qmin, top, cons_rad, m2_min, top_code, tot)
    elif use_lut:  # three passes: the table's look-ups do not vectorise (no gathers), the rest does
        w = lut_rows
        for u in range(frames.shape[2]):
            y0, x0, q0, tt, mx = _px4(frames, 0, v, u)
            y1, x1, q1, t1, m1 = _px4(frames, 4, v, u)
            y2, x2, q2, t2, m2_ = _px4(frames, 8, v, u)
            y3, x3, q, t3, m3 = _px4(frames, 12, v, u)
            w[0, u] = atan2_coarse(y0, x0)
            w[1, u] = atan2_coarse(y1, x1)
            w[2, u] = atan2_coarse(y2, x2)
            w[3, u] = atan2_0_2pi(y3, x3)
            w[4, u] = min(min(q0, q1), min(q2, q))
            w[5, u] = max(max(mx, m1), max(m2_, m3))
            total[u] = (tt + t1) + (t2 + t3)
            m2[u] = q
        for u in range(frames.shape[2]):
            w[0, u] = _lut_correct(w[0, u], l0, scale)
            w[1, u] = _lut_correct(w[1, u], l1, scale)
            w[2, u] = _lut_correct(w[2, u], l2, scale)
            w[3, u] = _lut_correct(w[3, u], l3, scale)
        for u in range(frames.shape[2]):
            p, d1 = _order_step(w[0, u], w[1, u], r1)
            p, d2 = _order_step(p, w[2, u], r2)
            p, d3 = _order_step(p, w[3, u], r3)
            prev[u] = p
            code[u] = _mask(_OK, max(max(d1, d2), d3), w[4, u], w[5, u], cons_rad, m2_min, top_code,
                            total[u])
    else:
        for u in range(frames.shape[2]):
            y0, x0, q0, tt, mx = _px4(frames, 0, v, u)
            y1, x1, q1, t1, m1 = _px4(frames, 4, v, u)
            y2, x2, q2, t2, m2_ = _px4(frames, 8, v, u)
            y3, x3, q, t3, m3 = _px4(frames, 12, v, u)
            qmin = min(min(q0, q1), min(q2, q))
            p = atan2_coarse(y0, x0)
            p, d1 = _order_step(p, atan2_coarse(y1, x1), r1)
            p, d2 = _order_step(p, atan2_coarse(y2, x2), r2)
            p, d3 = _order_step(p, atan2_0_2pi(y3, x3), r3)
            dev = max(max(d1, d2), d3)
            tot = (tt + t1) + (t2 + t3)
            total[u] = tot
            prev[u] = p
            m2[u] = q
            top = max(max(mx, m1), max(m2_, m3))
            code[u] = _mask(_OK, dev, qmin, top, cons_rad, m2_min, top_code, tot)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _px4_fit(frames, b, v, u, top_code):  # type: ignore[no-untyped-def]  # pragma: no cover
    """N = 4 at pixel (v, u) from frame b on, fitted to its unclipped samples (I < ``top_code``):
    (y, x, x² + y², clipped samples). With δ = 0, π/2, π, 3π/2 every sinusoid has I0 + I2 =
    I1 + I3 (= 2A), so one clipped sample is its prediction from the other three, which is the
    least-squares fit of A + a cos δ + b sin δ to them (three samples, three unknowns): with
    r = (I0 + I2) − (I1 + I3), I0 → I0 − r, I1 → I1 + r, I2 → I2 − r, I3 → I3 + r.
    Closed form and branch-free; with two or more clipped the result is meaningless (not taken)."""
    i0 = np.float32(frames[b, v, u])
    i1 = np.float32(frames[b + 1, v, u])
    i2 = np.float32(frames[b + 2, v, u])
    i3 = np.float32(frames[b + 3, v, u])
    c0 = _F1 if i0 >= top_code else _F0
    c1 = _F1 if i1 >= top_code else _F0
    c2 = _F1 if i2 >= top_code else _F0
    c3 = _F1 if i3 >= top_code else _F0
    r = (i0 + i2) - (i1 + i3)
    yy = (i3 - i1) + r * (c3 - c1)
    xx = (i0 - i2) - r * (c0 - c2)
    return yy, xx, xx * xx + yy * yy, (c0 + c1) + (c2 + c3)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _paper_fit_row(frames, v, chain, cons_rad, m2_min, top_code,  # type: ignore[no-untyped-def]
                   total, m2, prev, code):  # pragma: no cover - compiled
    """:func:`_paper_row` and its saturation refit in one pass, for rows where clipping is
    widespread: every pixel's phase from :func:`_px4_fit` (on an unclipped pixel the same
    arithmetic and result as :func:`_px4`), SATURATED only where a frequency has two clipped
    samples; returns the pixels with a clipped sample that were refitted (float32)."""
    r1, r2, r3, lut, scale, use_lut, ser, use_ser = chain
    l0, l1, l2, l3 = lut[0], lut[1], lut[2], lut[3]
    n_refit = _F0
    # one loop per choice, each written out: a run-time switch, or a helper too large for LLVM to
    # inline, in the pixel loop kept LLVM from vectorising it
    if use_ser:  # past the first level not wrapped (as _paper_row)
        c0, c1, c2, c3 = (_series_row(ser, 0), _series_row(ser, 1), _series_row(ser, 2),
                          _series_row(ser, 3))
        for u in range(frames.shape[2]):
            tot = _px16_total(frames, v, u)
            total[u] = tot
            y0, x0, q0, n0 = _px4_fit(frames, 0, v, u, top_code)
            y1, x1, q1, n1 = _px4_fit(frames, 4, v, u, top_code)
            y2, x2, q2, n2 = _px4_fit(frames, 8, v, u, top_code)
            y3, x3, q, n3 = _px4_fit(frames, 12, v, u, top_code)
            qmin = min(min(q0, q1), min(q2, q))
            p = _series_correct(atan2_coarse(y0, x0), y0, x0, q0, c0)
            p, d1 = _order_step(p, atan2_coarse(y1, x1) - _series_error(y1, x1, q1, c1), r1)
            p, d2 = _order_step(p, atan2_coarse(y2, x2) - _series_error(y2, x2, q2, c2), r2)
            p, d3 = _order_step(p, atan2_0_2pi(y3, x3) - _series_error(y3, x3, q, c3), r3)
            dev = max(max(d1, d2), d3)
            prev[u] = p
            m2[u] = q
            n_max = max(max(n0, n1), max(n2, n3))
            top = top_code if n_max > _F1 else _F0
            code[u] = _mask(_OK, dev, qmin, top, cons_rad, m2_min, top_code, tot)
            n_refit += _F1 if (n_max > _F0) & (n_max <= _F1) else _F0
    elif use_lut:
        for u in range(frames.shape[2]):
            tot = _px16_total(frames, v, u)
            total[u] = tot
            y0, x0, q0, n0 = _px4_fit(frames, 0, v, u, top_code)
            y1, x1, q1, n1 = _px4_fit(frames, 4, v, u, top_code)
            y2, x2, q2, n2 = _px4_fit(frames, 8, v, u, top_code)
            y3, x3, q, n3 = _px4_fit(frames, 12, v, u, top_code)
            qmin = min(min(q0, q1), min(q2, q))
            p = _lut_correct(atan2_coarse(y0, x0), l0, scale)
            p, d1 = _order_step(p, _lut_correct(atan2_coarse(y1, x1), l1, scale), r1)
            p, d2 = _order_step(p, _lut_correct(atan2_coarse(y2, x2), l2, scale), r2)
            p, d3 = _order_step(p, _lut_correct(atan2_0_2pi(y3, x3), l3, scale), r3)
            dev = max(max(d1, d2), d3)
            prev[u] = p
            m2[u] = q
            n_max = max(max(n0, n1), max(n2, n3))
            top = top_code if n_max > _F1 else _F0
            code[u] = _mask(_OK, dev, qmin, top, cons_rad, m2_min, top_code, tot)
            n_refit += _F1 if (n_max > _F0) & (n_max <= _F1) else _F0
    else:
        for u in range(frames.shape[2]):
            tot = _px16_total(frames, v, u)
            total[u] = tot
            y0, x0, q0, n0 = _px4_fit(frames, 0, v, u, top_code)
            y1, x1, q1, n1 = _px4_fit(frames, 4, v, u, top_code)
            y2, x2, q2, n2 = _px4_fit(frames, 8, v, u, top_code)
            y3, x3, q, n3 = _px4_fit(frames, 12, v, u, top_code)
            qmin = min(min(q0, q1), min(q2, q))
            p = atan2_coarse(y0, x0)
            p, d1 = _order_step(p, atan2_coarse(y1, x1), r1)
            p, d2 = _order_step(p, atan2_coarse(y2, x2), r2)
            p, d3 = _order_step(p, atan2_0_2pi(y3, x3), r3)
            dev = max(max(d1, d2), d3)
            prev[u] = p
            m2[u] = q
            n_max = max(max(n0, n1), max(n2, n3))
            top = top_code if n_max > _F1 else _F0
            code[u] = _mask(_OK, dev, qmin, top, cons_rad, m2_min, top_code, tot)
            n_refit += _F1 if (n_max > _F0) & (n_max <= _F1) else _F0
    return n_refit


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _px16_total(frames, v, u):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Σ I of the 16 frames at (v, u), summed as :func:`_paper_row` sums them."""
    return (_px4_total(frames, 0, v, u) + _px4_total(frames, 4, v, u)) + (
        _px4_total(frames, 8, v, u) + _px4_total(frames, 12, v, u))


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _px4_total(frames, b, v, u):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Σ I of the 4 frames from b on at (v, u), summed as :func:`_px4` sums them."""
    return (np.float32(frames[b, v, u]) + np.float32(frames[b + 1, v, u])) + (
        np.float32(frames[b + 2, v, u]) + np.float32(frames[b + 3, v, u]))


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _paper_refit_row(frames, v, chain, cons_rad, m2_min, top_code,  # type: ignore[no-untyped-def]
                     total, m2, prev, code, rscratch):  # pragma: no cover - compiled
    """:func:`_paper_row`'s saturation refit (4 frequencies × 4 steps): the SATURATED pixels of
    row ``v`` with at most one clipped sample per frequency take the phase of :func:`_px4_fit`
    (finest m2, phase-stage code judged as unclipped); their count. Spans of PAPER_SPAN pixels
    without a SATURATED code are skipped (clipping is local: highlights), the others refitted
    branch-free into ``rscratch`` (≥ 2, ≥ PAPER_SPAN float32) with :func:`_paper_row`'s
    arithmetic (``total`` keeps the frames' sums), then taken."""
    width = frames.shape[2]
    n_taken = 0
    r_code = np.empty(PAPER_SPAN, np.uint8)
    for u0 in range(0, width, PAPER_SPAN):
        u1 = min(width, u0 + PAPER_SPAN)
        n_sat = _count_saturated(code[u0:u1])
        if n_sat > 0:  # a refitted code is never SATURATED: the count that drops was taken
            m = u1 - u0
            r_prev, r_m2, rc = rscratch[0, :m], rscratch[1, :m], r_code[:m]
            _paper_refit_span(frames, v, u0, u1, chain, cons_rad, m2_min, top_code,
                              total[u0:u1], r_m2, r_prev, rc)
            _take_paper_refit(m2[u0:u1], prev[u0:u1], code[u0:u1], r_m2, r_prev, rc)
            n_taken += n_sat - _count_saturated(code[u0:u1])
    return n_taken


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _paper_refit_span(  # type: ignore[no-untyped-def]
        frames, v, u0, u1, chain, cons_rad, m2_min, top_code,
        total, m2, prev, code):  # pragma: no cover - compiled
    """:func:`_paper_row` with :func:`_px4_fit` over the pixels u0..u1 − 1 of row ``v`` into the
    span's ``m2``, ``prev``, ``code`` (SATURATED where a frequency has two clipped samples;
    ``total`` the span's frame sums). The row's codes are not read here: a byte test beside the
    float ones kept LLVM from vectorising."""
    r1, r2, r3, lut, scale, use_lut, ser, use_ser = chain
    l0, l1, l2, l3 = lut[0], lut[1], lut[2], lut[3]
    # one loop per choice, each written out: a run-time switch, or a helper too large for LLVM to
    # inline, in the pixel loop kept LLVM from vectorising it
    if use_ser:  # past the first level not wrapped (as _paper_row)
        c0, c1, c2, c3 = (_series_row(ser, 0), _series_row(ser, 1), _series_row(ser, 2),
                          _series_row(ser, 3))
        for u in range(u0, u1):
            y0, x0, q0, n0 = _px4_fit(frames, 0, v, u, top_code)
            y1, x1, q1, n1 = _px4_fit(frames, 4, v, u, top_code)
            y2, x2, q2, n2 = _px4_fit(frames, 8, v, u, top_code)
            y3, x3, q, n3 = _px4_fit(frames, 12, v, u, top_code)
            qmin = min(min(q0, q1), min(q2, q))
            p = _series_correct(atan2_coarse(y0, x0), y0, x0, q0, c0)
            p, d1 = _order_step(p, atan2_coarse(y1, x1) - _series_error(y1, x1, q1, c1), r1)
            p, d2 = _order_step(p, atan2_coarse(y2, x2) - _series_error(y2, x2, q2, c2), r2)
            p, d3 = _order_step(p, atan2_0_2pi(y3, x3) - _series_error(y3, x3, q, c3), r3)
            dev = max(max(d1, d2), d3)
            i = u - u0
            prev[i] = p
            m2[i] = q
            # two clipped samples in a frequency: top = top_code, so SATURATED (not taken)
            top = top_code if max(max(n0, n1), max(n2, n3)) > _F1 else _F0
            code[i] = _mask(_OK, dev, qmin, top, cons_rad, m2_min, top_code, total[i])
    elif use_lut:
        for u in range(u0, u1):
            y0, x0, q0, n0 = _px4_fit(frames, 0, v, u, top_code)
            y1, x1, q1, n1 = _px4_fit(frames, 4, v, u, top_code)
            y2, x2, q2, n2 = _px4_fit(frames, 8, v, u, top_code)
            y3, x3, q, n3 = _px4_fit(frames, 12, v, u, top_code)
            qmin = min(min(q0, q1), min(q2, q))
            p = _lut_correct(atan2_coarse(y0, x0), l0, scale)
            p, d1 = _order_step(p, _lut_correct(atan2_coarse(y1, x1), l1, scale), r1)
            p, d2 = _order_step(p, _lut_correct(atan2_coarse(y2, x2), l2, scale), r2)
            p, d3 = _order_step(p, _lut_correct(atan2_0_2pi(y3, x3), l3, scale), r3)
            dev = max(max(d1, d2), d3)
            i = u - u0
            prev[i] = p
            m2[i] = q
            # two clipped samples in a frequency: top = top_code, so SATURATED (not taken)
            top = top_code if max(max(n0, n1), max(n2, n3)) > _F1 else _F0
            code[i] = _mask(_OK, dev, qmin, top, cons_rad, m2_min, top_code, total[i])
    else:
        for u in range(u0, u1):
            y0, x0, q0, n0 = _px4_fit(frames, 0, v, u, top_code)
            y1, x1, q1, n1 = _px4_fit(frames, 4, v, u, top_code)
            y2, x2, q2, n2 = _px4_fit(frames, 8, v, u, top_code)
            y3, x3, q, n3 = _px4_fit(frames, 12, v, u, top_code)
            qmin = min(min(q0, q1), min(q2, q))
            p = atan2_coarse(y0, x0)
            p, d1 = _order_step(p, atan2_coarse(y1, x1), r1)
            p, d2 = _order_step(p, atan2_coarse(y2, x2), r2)
            p, d3 = _order_step(p, atan2_0_2pi(y3, x3), r3)
            dev = max(max(d1, d2), d3)
            i = u - u0
            prev[i] = p
            m2[i] = q
            # two clipped samples in a frequency: top = top_code, so SATURATED (not taken)
            top = top_code if max(max(n0, n1), max(n2, n3)) > _F1 else _F0
            code[i] = _mask(_OK, dev, qmin, top, cons_rad, m2_min, top_code, total[i])


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _take_paper_refit(m2, prev, code, r_m2, r_prev, r_code):  # type: ignore[no-untyped-def]
    # pragma: no cover - compiled
    """Where ``code`` is SATURATED and the refit's ``r_code`` is not: the refit's values. Two
    branch-free passes, bytes then floats (so that each vectorises); ``r_code`` ends as the mask."""
    for i in range(code.shape[0]):
        t = (code[i] == _SATURATED) & (r_code[i] != _SATURATED)
        code[i] = r_code[i] if t else code[i]
        r_code[i] = np.uint8(t)
    for i in range(code.shape[0]):
        t = r_code[i] != 0
        prev[i] = r_prev[i] if t else prev[i]
        m2[i] = r_m2[i] if t else m2[i]


# The general path, row by row through buffers: any N, any number of frequencies, and
# the noise-optimal combination.
@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _accumulate(row, s_acc, c_acc, total, top, sn, cn,  # type: ignore[no-untyped-def]
                first):  # pragma: no cover
    if first:
        for u in range(row.shape[0]):
            x = np.float32(row[u])
            s_acc[u] = x * sn
            c_acc[u] = x * cn
    else:
        for u in range(row.shape[0]):
            x = np.float32(row[u])
            s_acc[u] += x * sn
            c_acc[u] += x * cn
    for u in range(row.shape[0]):
        x = np.float32(row[u])
        total[u] += x
        top[u] = max(top[u], x)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _level_row(s_acc, c_acc, prev, m2, m2min, dev, ratio,  # type: ignore[no-untyped-def]
               first, lrow, scale, use_lut, crow, use_ser):  # pragma: no cover
    # one loop per choice (as _paper_row), the wrapped phase corrected by the series ``crow``
    # (:func:`_series_row`) if ``use_ser``, else by the table ``lrow`` if ``use_lut``
    if use_ser:
        for u in range(s_acc.shape[0]):
            yy = -s_acc[u]
            xx = c_acc[u]
            q = xx * xx + yy * yy
            m2[u] = q
            m2min[u] = min(m2min[u], q)
            phw = _series_correct(atan2_0_2pi(yy, xx), yy, xx, q, crow)
            if first:
                prev[u] = phw
            else:
                p, d = _order_step(prev[u], phw, ratio)
                prev[u] = p
                dev[u] = max(dev[u], d)
    elif use_lut:
        for u in range(s_acc.shape[0]):
            yy = -s_acc[u]
            xx = c_acc[u]
            q = xx * xx + yy * yy
            m2[u] = q
            m2min[u] = min(m2min[u], q)
            phw = _lut_correct(atan2_0_2pi(yy, xx), lrow, scale)
            if first:
                prev[u] = phw
            else:
                p, d = _order_step(prev[u], phw, ratio)
                prev[u] = p
                dev[u] = max(dev[u], d)
    else:
        for u in range(s_acc.shape[0]):
            yy = -s_acc[u]
            xx = c_acc[u]
            q = xx * xx + yy * yy
            m2[u] = q
            m2min[u] = min(m2min[u], q)
            phw = atan2_0_2pi(yy, xx)
            if first:
                prev[u] = phw
            else:
                p, d = _order_step(prev[u], phw, ratio)
                prev[u] = p
                dev[u] = max(dev[u], d)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _wrap(x):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """x mod 2π in [0, 2π)."""
    r = x - _TWO_PI * np.float32(np.floor(x * _INV_TWO_PI))
    return _F0 if r >= _TWO_PI else (r + _TWO_PI if r < _F0 else r)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _absolute(ph, f0):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """The phase of ≤ 1 fringe over the field: the unused arc split in half
    (``unwrap.absolute_phase``)."""
    return ph - _TWO_PI if ph > _PI * (_F1 + f0) else ph


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _wrapped_row(s_acc, c_acc, wph, m2, m2min, lrow, scale,  # type: ignore[no-untyped-def]
                 use_lut, crow, use_ser):  # pragma: no cover
    # one loop per choice (as _paper_row), the wrapped phase corrected by the series ``crow``
    # (:func:`_series_row`) if ``use_ser``, else by the table ``lrow`` if ``use_lut``
    if use_ser:
        for u in range(s_acc.shape[0]):
            yy = -s_acc[u]
            xx = c_acc[u]
            q = xx * xx + yy * yy
            m2[u] = q
            m2min[u] = min(m2min[u], q)
            wph[u] = _series_correct(atan2_0_2pi(yy, xx), yy, xx, q, crow)
    elif use_lut:
        for u in range(s_acc.shape[0]):
            yy = -s_acc[u]
            xx = c_acc[u]
            q = xx * xx + yy * yy
            m2[u] = q
            m2min[u] = min(m2min[u], q)
            wph[u] = _lut_correct(atan2_0_2pi(yy, xx), lrow, scale)
    else:
        for u in range(s_acc.shape[0]):
            yy = -s_acc[u]
            xx = c_acc[u]
            q = xx * xx + yy * yy
            m2[u] = q
            m2min[u] = min(m2min[u], q)
            wph[u] = atan2_0_2pi(yy, xx)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _outside_field(p, f0, slack):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """0 if the absolute beat phase ``p`` lies on the field [−slack, 2π·f0 + slack], else ∞
    (a deviation)."""
    return _F0 if (p >= -slack) & (p <= _TWO_PI * f0 + slack) else _INF


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _scaled_row(beat, wph, c, first):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """beat (+)= c·wph over a row: one term of a beat, a plain 1-D loop that LLVM vectorises."""
    if first:
        for u in range(beat.shape[0]):
            beat[u] = c * wph[u]
    else:
        for u in range(beat.shape[0]):
            beat[u] += c * wph[u]


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _chain_row(wphs, coefs, beat, prev, dev, ratio, f0,  # type: ignore[no-untyped-def]
               first, slack):  # pragma: no cover
    """One heterodyne step over a row: the beat Σ c_i φ_i (into the scratch row ``beat``), then
    absolute or unwrapped by ``prev``. Term by term and step by step in 1-D loops: a loop over the
    K coefficients inside the pixel loop kept LLVM from vectorising (30× slower)."""
    first_term = True
    for i in range(coefs.shape[0]):
        if coefs[i] != _F0:
            _scaled_row(beat, wphs[i], coefs[i], first_term)
            first_term = False
    if first:
        for u in range(prev.shape[0]):
            p = _absolute(_wrap(beat[u]), f0)
            prev[u] = p
            dev[u] = _outside_field(p, f0, slack)
    else:
        for u in range(prev.shape[0]):
            p, d = _order_step(prev[u], _wrap(beat[u]), ratio)
            prev[u] = p
            dev[u] = max(dev[u], d)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _residual_row(wph, m2k, m2f, prev, vq, sd2, dev,  # type: ignore[no-untyped-def]
                  ratio, ratio2, z2, floor):  # pragma: no cover - compiled
    """The order test of one coarser frequency: ``sd2`` = var of r = wrap(φ_k − ratio·Φ)
    (``vq`` = σ_I²·N/2 over each m2, plus ``floor``, the unmodelled part); ``dev`` = ∞ where
    r² > z²·sd2."""
    for u in range(prev.shape[0]):
        v = vq[u] / m2k[u] + ratio2 * (vq[u] / m2f[u]) + floor
        sd2[u] = v
        r = _wrap(wph[u] - ratio * prev[u] + _PI) - _PI
        dev[u] = _INF if r * r > z2 * v else dev[u]


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _seen_row(seen, sd2, q2, four_z2, first):  # type: ignore[no-untyped-def]  # pragma: no cover
    """seen (|)= a slip moving this frequency's residual by √q2 clears the bound by z·σ."""
    if first:
        for u in range(seen.shape[0]):
            seen[u] = _F1 if q2 >= four_z2 * sd2[u] else _F0
    else:
        for u in range(seen.shape[0]):
            seen[u] = _F1 if q2 >= four_z2 * sd2[u] else seen[u]


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _seen2_row(sd0, sd1, q0, q1, four_z2, dev):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Three frequencies (two residuals): ``dev`` = ∞ where neither clears the bound by z·σ;
    one pass."""
    for u in range(dev.shape[0]):
        seen = (q0 >= four_z2 * sd0[u]) | (q1 >= four_z2 * sd1[u])
        dev[u] = dev[u] if seen else _INF


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _unseen_row(seen, dev):  # type: ignore[no-untyped-def]  # pragma: no cover
    for u in range(dev.shape[0]):
        dev[u] = _INF if seen[u] == _F0 else dev[u]


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _order_test(wphs, m2s, prev, total, dev, work, freqs,  # type: ignore[no-untyped-def]
                order):  # pragma: no cover
    """:func:`app.recon.unwrap.order_residuals_consistent` over a row: ``dev`` = ∞
    (inconsistent) where a coarser phase disagrees with the finest ``prev`` beyond z·σ, or where
    σ is too large for some wrong order to show. ``order`` = (z², squared slip front (P, K − 1),
    unmodelled variance, read_var, gain, 1/F, N/2); σ_I² from the mean ``total``/F; ``work``
    (K + 1, ≥ W) float32 scratch. Row passes with scalar constants (vectorised)."""
    z2, front2, floor2, read_var, gain, inv_frames, half_n = order
    n_freq = freqs.shape[0]
    k_max = freqs[n_freq - 1]
    vq = work[0]
    seen = work[1]
    for u in range(prev.shape[0]):
        vq[u] = (read_var + gain * max(total[u] * inv_frames, _F0)) * half_n
    for i in range(n_freq - 1):
        ratio = freqs[i] / k_max
        _residual_row(wphs[i], m2s[i], m2s[n_freq - 1], prev, vq, work[2 + i], dev, ratio,
                      ratio * ratio, z2, floor2 * (_F1 + ratio * ratio))
    four_z2 = np.float32(4.0) * z2
    for p in range(front2.shape[0]):
        if n_freq == 3:
            _seen2_row(work[2], work[3], front2[p, 0], front2[p, 1], four_z2, dev)
            continue
        for i in range(n_freq - 1):
            _seen_row(seen, work[2 + i], front2[p, i], four_z2, i == 0)
        _unseen_row(seen, dev)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _weigh_row(wsum, wphi, m2, prev, wk,  # type: ignore[no-untyped-def]
               scale_fine):  # pragma: no cover
    for u in range(prev.shape[0]):
        w = wk * m2[u]  # ∝ N·B²·k²
        wsum[u] += w
        wphi[u] += w * scale_fine * prev[u]


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _combined_row(prev, wsum, wphi):  # type: ignore[no-untyped-def]  # pragma: no cover
    for u in range(prev.shape[0]):
        prev[u] = wphi[u] / wsum[u] if wsum[u] > _F0 else _NAN


class HeightConstants(NamedTuple):
    """One row's scalars of the height stage (float32), from :class:`HeightArgs`: the depth
    model's ``phi0``, ``inv_sphi``, ``cubic``, ``radial_k``, ``sing_rtol``, the volume
    ``lo``..``hi`` mm, the phase range ``p_lo``..``p_hi`` rad, the sensor noise ``read_var`` DN²
    and ``gain`` DN/e⁻, σ_model's ``sm_mid`` and ``sm_inv_half``, the σ bound squared
    ``max_sigma2`` mm², the gross-error test's ``gross_sq`` mm², ``t1``..``t4`` and ``t_max``."""

    phi0: np.float32
    inv_sphi: np.float32
    cubic: np.float32
    radial_k: np.float32
    sing_rtol: np.float32
    lo: np.float32
    hi: np.float32
    p_lo: np.float32
    p_hi: np.float32
    read_var: np.float32
    gain: np.float32
    sm_mid: np.float32
    sm_inv_half: np.float32
    max_sigma2: np.float32
    gross_sq: np.float32
    t1: np.float32
    t2: np.float32
    t3: np.float32
    t4: np.float32
    t_max: np.float32


# Inlined in numba's IR: LLVM's own inliner found it too costly (525 against 250), and a call left
# in the pixel loop kept the loop from being vectorised (the height stage then took 3-4x the CPU
# of everything else in the kernel). Fewer than 30 arguments: CPython passes more as *args,
# which numba's inliner does not take.
@njit(fastmath=FASTMATH, error_model="numpy", cache=True, inline="always")
def _height_px(p, a0, a1, b0, b1, tot, vf, rlo, rhi, c,  # type: ignore[no-untyped-def]
               alpha, beta, s0, s1, s2, s3, s4, row):  # pragma: no cover - compiled
    """Height, σ and reason of one pixel from its closed-form coefficients (module docstring of
    :mod:`app.core.depth_model`; a radial projector lens ``radial_k`` on the pixel's epipolar
    line (``alpha``, ``beta``) solved as :func:`~app.core.depth_model.column_term` solves it);
    ``row`` the row's :class:`HeightConstants`;
    ``c`` is the phase stage's reason. σ is the total: the sensor
    noise through ∂z/∂φ ⊕ the model's own σ (σ_model² = Σ s_k·x^k,
    x = (h − sm_mid)·sm_inv_half, :mod:`app.recon.model_sigma`); a model σ beyond the rule's
    bound (``max_sigma2`` = its square) is outside the calibrated field. The UNCERTAIN test
    weighs the noise variance by (θ_g/sin θ_g)², θ_g² = ``gross_sq``/slope² capped at
    ``t_max``, as 1 + Σ t_k·θ_g^2k (:func:`app.recon.validity.phasor_tail_factor_sq`)."""
    phi0, inv_sphi, cubic, radial_k = row.phi0, row.inv_sphi, row.cubic, row.radial_k
    sing_rtol, lo, hi, p_lo, p_hi = row.sing_rtol, row.lo, row.hi, row.p_lo, row.p_hi
    read_var, gain, sm_mid, sm_inv_half = row.read_var, row.gain, row.sm_mid, row.sm_inv_half
    max_sigma2, gross_sq, t_max = row.max_sigma2, row.gross_sq, row.t_max
    t1, t2, t3, t4 = row.t1, row.t2, row.t3, row.t4
    pp = (p - phi0) * inv_sphi
    if radial_k != _F0:  # Newton on φ' = t·(1 + k·(t² + y²)), y = α + β·t, as column_term
        y = alpha + beta * pp
        t = pp * (_F1 - radial_k * (pp * pp + y * y))
        dt = _F1
        for _ in range(_COLUMN_ITERATIONS):
            y = alpha + beta * t
            dt = _F1 / (_F1 + radial_k * (_F3 * (t * t) + y * y
                                          + np.float32(2.0) * (t * beta * y)))
            t = t - (t * (_F1 + radial_k * (t * t + y * y)) - pp) * dt
    else:
        t = pp + cubic * (pp * pp * pp)
        dt = _F1 + _F3 * cubic * (pp * pp)
    b1p = b1 * t
    dd = b0 + b1p
    inv_dd = _F1 / dd  # one division for the height and its slope
    h = (a0 + a1 * t) * inv_dd
    slope = (a1 * b0 - a0 * b1) * (inv_dd * inv_dd) * inv_sphi * dt
    x = (h - sm_mid) * sm_inv_half
    sm2 = max((((s4 * x + s3) * x + s2) * x + s1) * x + s0, _F0)
    slope2 = slope * slope
    noise_var = slope2 * ((read_var + gain * tot) * vf)
    sig = np.sqrt(noise_var + sm2)
    th2 = min(gross_sq / max(slope2, _TINY), t_max)
    tail2 = _F1 + th2 * (t1 + th2 * (t2 + th2 * (t3 + th2 * t4)))
    singular = abs(dd) <= sing_rtol * (abs(b0) + abs(b1p))
    in_volume = (h >= lo) & (h <= hi)
    in_field = (h >= rlo) & (h <= rhi) & (p >= p_lo) & (p <= p_hi) & (sm2 <= max_sigma2)
    hc = _UNCERTAIN if noise_var * tail2 + sm2 > max_sigma2 else _OK
    hc = _OUTSIDE_FIELD if not in_field else hc
    hc = _OUTSIDE_VOLUME if not in_volume else hc
    hc = _MODEL_SINGULAR if singular else hc
    return h, sig, hc if c == _OK else c


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _lerp_row(out, a, b, w):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """out = a + w·(b − a) over a row (float32)."""
    for u in range(out.shape[0]):
        out[u] = a[u] + w * (b[u] - a[u])


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _height_row(v, prev, m2, total, vfac, code, m,  # type: ignore[no-untyped-def]
                depth, sigma, reason, valid, modulation, texture, mod_scale,
                sm_row):  # pragma: no cover
    """Height stage of row ``v`` (both paths): the final reason code and all the row's outputs
    but the phase: ``depth`` and ``sigma`` (float32, mm; NaN where invalid), ``reason`` (uint8),
    ``valid`` (bool), ``modulation`` B = ``mod_scale``·√m2 and ``texture`` Σ I/F + B (float32,
    codes). In the one pixel loop: a second pass over the block's rows for the last four cost
    ~12 % of the kernel's CPU (re-reading m2, total and the codes). ``code`` (the phase stage's
    reason) is only read; ``sm_row`` (5, ≥ W) float32 scratch takes the row's σ_model
    coefficients.

    The loop is vectorised only while LLVM needs at most 128 run-time checks that its arrays do
    not overlap (numba's arrays carry no ``noalias``; a check per written array and every other
    one): hence the σ_model table's two rows interpolated into ``sm_row`` first (ten arrays read
    in the loop become five), and ``code`` not written (the phase output selects by ``reason``).
    ``tests/recon/test_fast.py`` checks the loop's float divisions are vector ones.

    ``m.region_lo``/``m.region_hi`` are (gh, W): each grid row's height bounds expanded to the
    columns (two contiguous rows, not interleaved pairs: that keeps the loop vectorised)."""
    k = m.row_coefs[v]
    k0, k1, k2, k3, k4, k5 = k[0], k[1], k[2], k[3], k[4], k[5]
    k6, k7, k8, k9, k10, k11 = k[6], k[7], k[8], k[9], k[10], k[11]
    g = m.ray_coefs
    g0, g1, g2, g3, g4, g5 = g[0], g[1], g[2], g[3], g[4], g[5]
    g6, g7, g8, g9, g10, g11 = g[6], g[7], g[8], g[9], g[10], g[11]
    r_lo = m.region_lo[m.region_rows[v]]
    r_hi = m.region_hi[m.region_rows[v]]
    # outside the camera's supported field: no height bound holds
    f_lo, f_hi = m.field_u_lo[v], m.field_u_hi[v]
    inv_frames = m.inv_frames
    un = m.u_norm
    # σ_model² = Σ s_k·x^k of every column, between two table rows (5, W) each
    r0 = m.sm_rows[v]
    sc = m.sm_coefs[r0]
    sd = m.sm_coefs[min(r0 + 1, m.sm_coefs.shape[0] - 1)]
    width = prev.shape[0]
    for i in range(5):
        _lerp_row(sm_row[i, :width], sc[i], sd[i], m.sm_weights[v])
    s0, s1, s2, s3, s4 = (sm_row[0, :width], sm_row[1, :width], sm_row[2, :width],
                          sm_row[3, :width], sm_row[4, :width])
    row = HeightConstants(m.phi0, m.inv_sphi, m.cubic, m.radial_k, m.sing_rtol, m.lo, m.hi,
                          m.phase_lo, m.phase_hi, m.read_var, m.gain, m.sm_mid, m.sm_inv_half,
                          m.max_sigma * m.max_sigma, m.gross_sq, m.tail_coefs[0],
                          m.tail_coefs[1], m.tail_coefs[2], m.tail_coefs[3], m.tail_t_max)
    qx, qy, qz = m.ray_q[0, v], m.ray_q[1, v], m.ray_q[2, v]  # (x, y, 1)/(n·r)
    e = m.cross_coefs
    e0, e1, e2, e3, e4, e5, e6, e7, e8 = e[0], e[1], e[2], e[3], e[4], e[5], e[6], e[7], e[8]
    use_cross = m.use_cross
    # var(φ)/σ_I²: N / (2·m2) of the finest frequency, or the combination's (in vfac)
    combine, half_steps = m.combine, m.half_steps
    use_rays = m.use_rays
    for u in range(width):
        x = un[u]
        a0 = (k2 * x + k1) * x + k0
        a1 = (k5 * x + k4) * x + k3
        b0 = (k8 * x + k7) * x + k6
        b1 = (k11 * x + k10) * x + k9
        alpha = beta = _F0
        if use_rays:  # loop-invariant: the compiler makes two loops (an Eq. (5) model has none)
            q0, q1, q2 = qx[u], qy[u], qz[u]
            a0 += g0 * q0 + g1 * q1 + g2 * q2
            a1 += g3 * q0 + g4 * q1 + g5 * q2
            b0 += g6 * q0 + g7 * q1 + g8 * q2
            b1 += g9 * q0 + g10 * q1 + g11 * q2
            if use_cross:  # the pixel's epipolar line in the projector
                inv_d = _F1 / (e6 * q0 + e7 * q1 + e8 * q2)
                alpha = (e0 * q0 + e1 * q1 + e2 * q2) * inv_d
                beta = (e3 * q0 + e4 * q1 + e5 * q2) * inv_d
        vf = vfac[u] if combine else half_steps / m2[u]
        rl = r_lo[u] if f_lo <= u <= f_hi else _INF
        h, sig, c = _height_px(prev[u], a0, a1, b0, b1, total[u] * inv_frames, vf, rl, r_hi[u],
                               code[u], alpha, beta, s0[u], s1[u], s2[u], s3[u], s4[u], row)
        ok = c == _OK
        depth[u] = h if ok else _NAN
        sigma[u] = sig if ok else _NAN
        reason[u] = c
        valid[u] = ok
        b = mod_scale * np.sqrt(m2[u])
        modulation[u] = b
        texture[u] = total[u] * inv_frames + b


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _heterodyne_row(  # type: ignore[no-untyped-def]
        frames, v, cos_t, sin_t, freqs, chain_c, chain_f, combine, cons_rad, order, scratch,
        total, m2, prev, gl):  # pragma: no cover - compiled
    """Phase of row ``v`` for a heterodyne schedule: every wrapped phase first, then the beat
    chain."""
    n_steps = cos_t.shape[0]
    n_freq = freqs.shape[0]
    s_acc, c_acc, top, m2min, dev, wsum, wphi = (scratch[0], scratch[1], scratch[2], scratch[3],
                                                 scratch[4], scratch[5], scratch[6])
    wphs = scratch[7:7 + n_freq]
    m2s = scratch[7 + n_freq:7 + 2 * n_freq]
    for ki in range(n_freq):
        for n in range(n_steps):
            _accumulate(frames[ki * n_steps + n, v], s_acc, c_acc, total, top, sin_t[n], cos_t[n],
                        n == 0)
        _wrapped_row(s_acc, c_acc, wphs[ki], m2s[ki], m2min, gl[0][ki], gl[1], gl[2],
                     _series_row(gl[3], ki), gl[4])
    _chain_and_weigh(wphs, m2s, chain_c, chain_f, freqs, cons_rad, n_steps, combine, prev, dev,
                     m2, wsum, wphi, total, order, scratch[7 + 2 * n_freq:8 + 3 * n_freq])
    if combine:
        _combined_row(prev, wsum, wphi)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _chain_and_weigh(  # type: ignore[no-untyped-def]
        wphs, m2s, chain_c, chain_f, freqs, cons_rad, n_steps, combine,
        prev, dev, m2, wsum, wphi, total, order, work):  # pragma: no cover - compiled
    """The heterodyne beat chain over a row's wrapped phases ``wphs`` (K, W) into ``prev``/``dev``,
    its order test (:func:`_order_test`; ``total``: the row's frame sums, ``work`` (K + 1, ≥ W)
    scratch), the finest m2, and with ``combine`` every frequency unwrapped by the finest and
    weighed."""
    n_freq = freqs.shape[0]
    k_max = freqs[n_freq - 1]
    slack = cons_rad * chain_f[0] / chain_f[1]
    # m2 is free until the finest m2 is copied in: the beat's scratch row
    for s in range(chain_f.shape[0]):
        _chain_row(wphs, chain_c[s], m2, prev, dev, chain_f[s] / chain_f[max(s - 1, 0)], chain_f[0],
                   s == 0, slack)
    _order_test(wphs, m2s, prev, total, dev, work, freqs, order)
    m2[:] = m2s[n_freq - 1]
    if combine:
        for ki in range(n_freq):
            kk = freqs[ki]
            # every frequency unwrapped by the finest (the oracle's rule), then weighed
            for u in range(prev.shape[0]):
                p, _ = _order_step(prev[u], wphs[ki, u], kk / k_max)
                w = np.float32(n_steps) * kk * kk * m2s[ki, u]
                wsum[u] += w
                wphi[u] += w * (k_max / kk) * p


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _general_row(  # type: ignore[no-untyped-def]
        frames, v, cos_t, sin_t, freqs, chain_c, chain_f, heterodyne, combine, cons_rad,
        m2_min, top_code, scratch, total, m2, prev, vfac, code, order, gl):  # pragma: no cover
    """Phase 1 of row ``v`` for any schedule (hierarchical or heterodyne unwrapping); ``gl`` = (the
    (K, bins + 2) phase-error table, bins/2π, whether to apply it, its (K, 7) series, whether to
    evaluate that instead) for each wrapped phase."""
    n_steps = cos_t.shape[0]
    n_freq = freqs.shape[0]
    k_max = freqs[n_freq - 1]
    s_acc, c_acc, top, m2min, dev, wsum, wphi = (scratch[0], scratch[1], scratch[2], scratch[3],
                                                 scratch[4], scratch[5], scratch[6])
    total[:] = _F0
    top[:] = _F0
    m2min[:] = _INF
    dev[:] = _F0
    wsum[:] = _F0
    wphi[:] = _F0
    if heterodyne:
        _heterodyne_row(frames, v, cos_t, sin_t, freqs, chain_c, chain_f, combine, cons_rad,
                        order, scratch, total, m2, prev, gl)
    else:
        for ki in range(n_freq):
            for n in range(n_steps):
                _accumulate(frames[ki * n_steps + n, v], s_acc, c_acc, total, top, sin_t[n],
                            cos_t[n], n == 0)
            _level_row(s_acc, c_acc, prev, m2, m2min, dev, freqs[ki] / freqs[max(ki - 1, 0)],
                       ki == 0, gl[0][ki], gl[1], gl[2],
                       _series_row(gl[3], ki), gl[4])
            if combine:
                kk = freqs[ki]
                _weigh_row(wsum, wphi, m2, prev, np.float32(n_steps) * kk * kk, k_max / kk)
        if combine:
            _combined_row(prev, wsum, wphi)
    if combine:
        # var(φ) = σ_I²·N²·k_max² / (2·Σ_k N k² m2_k) for the weights of _weigh_row
        for u in range(prev.shape[0]):
            vfac[u] = _combined_vfac(n_steps, k_max, wsum[u])
    for u in range(prev.shape[0]):
        code[u] = _mask(_OK, dev[u], m2min[u], top[u], cons_rad, m2_min, top_code, total[u])


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _combined_vfac(n_steps, k_max, wsum):  # type: ignore[no-untyped-def]  # pragma: no cover
    """var(φ)/σ_I² of the noise-optimal phase with weight sum ``wsum``."""
    return np.float32(0.5) * (np.float32(n_steps) * k_max) ** 2 / wsum if wsum > _F0 else _INF


# Saturation-tolerant phase: a row with SATURATED pixels is refitted whole, branch-free, from the
# unclipped samples of every pixel; only its SATURATED pixels with enough samples take the result.
@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _fit_sums3(row, top_code, k0, k1, k2, x0, x1, x2,  # type: ignore[no-untyped-def]
               weighted, first):  # pragma: no cover - compiled
    """Three of the nine float32 normal-equation sums: x_i (+)= k_i·w (or k_i·w·I if
    ``weighted``) with w = 1 where the sample is unclipped (I < ``top_code``), else 0. Three at
    a time: few enough buffers that LLVM's run-time alias checks still let it vectorise."""
    for u in range(row.shape[0]):
        i = np.float32(row[u])
        w = _F1 if i < top_code else _F0
        t = w * i if weighted else w
        if first:
            x0[u] = k0 * t
            x1[u] = k1 * t
            x2[u] = k2 * t
        else:
            x0[u] += k0 * t
            x1[u] += k1 * t
            x2[u] += k2 * t


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _fit_solve(sums, half, s_acc, c_acc, nmin):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Cramer's rule (float64) on the symmetric 3 × 3 normal equations
    [[s1, sc, ss], [sc, scc, scs], [ss, scs, sss]] (right-hand side [r1, rc, rs]; ``sums``
    (9, ≥ W) in that order), scaled like (Σ I sin δ, Σ I cos δ) (``half`` = N/2):
    ``s_acc`` = b·N/2, ``c_acc`` = a·N/2, ``nmin`` = min(nmin, samples used)."""
    for u in range(s_acc.shape[0]):
        s1 = float(sums[0, u])
        sc = float(sums[1, u])
        ss = float(sums[2, u])
        scc = float(sums[3, u])
        sss = float(sums[4, u])
        scs = float(sums[5, u])
        q1 = float(sums[6, u])
        qc = float(sums[7, u])
        qs = float(sums[8, u])
        m0 = scc * sss - scs * scs
        m1 = sc * sss - scs * ss
        m2 = sc * scs - scc * ss
        det = s1 * m0 - sc * m1 + ss * m2
        da = s1 * (qc * sss - scs * qs) - q1 * m1 + ss * (sc * qs - qc * ss)
        db = s1 * (scc * qs - qc * scs) - sc * (sc * qs - qc * ss) + q1 * m2
        half_n = half / det  # ±∞/NaN where < 3 samples: those pixels are not taken
        s_acc[u] = np.float32(db * half_n)
        c_acc[u] = np.float32(da * half_n)
        nmin[u] = min(nmin[u], np.float32(s1))


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _fit_row(frames, b, v, u0, cos_t, sin_t, top_code,  # type: ignore[no-untyped-def]
             sums, sv, s_acc, c_acc, nmin):  # pragma: no cover - compiled
    """Least squares A + a cos δ + b sin δ over the unclipped samples (I < ``top_code``) of frames
    ``b``.. of row ``v``, for every pixel u0.. u0 + m of a span at once (m = len(``s_acc``); float32
    sums ``sums`` (9, ≥ m), ``sv``: the tuple of its nine rows' first m, made once per span):
    ``s_acc`` = b·N/2, ``c_acc`` = a·N/2; ``nmin`` = min(nmin, samples used)."""
    n_steps = cos_t.shape[0]
    m = s_acc.shape[0]
    for n in range(n_steps):
        row = frames[b + n, v, u0:u0 + m]
        c = cos_t[n]
        s = sin_t[n]
        first = n == 0
        _fit_sums3(row, top_code, _F1, c, s, sv[0], sv[1], sv[2], False, first)
        _fit_sums3(row, top_code, c * c, s * s, c * s, sv[3], sv[4], sv[5], False, first)
        _fit_sums3(row, top_code, _F1, c, s, sv[6], sv[7], sv[8], True, first)
    _fit_solve(sums, 0.5 * n_steps, s_acc, c_acc, nmin)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _count_saturated(code):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    n = 0
    for u in range(code.shape[0]):
        n += code[u] == _SATURATED
    return n


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _take_refit_row(  # type: ignore[no-untyped-def]
        m2, prev, vfac, code, r_m2, r_prev, r_wsum, r_m2min, r_dev, nmin, n_steps, k_max, combine,
        cons_rad, m2_min, top_code, total):  # pragma: no cover - compiled
    """The refitted values where the phase-stage code is SATURATED and every frequency kept ≥ 3
    samples (phase, finest m2, σ factor, phase-stage code); their count."""
    n = 0
    for u in range(code.shape[0]):
        if (code[u] == _SATURATED) & (nmin[u] >= _F3):
            prev[u] = r_prev[u]
            m2[u] = r_m2[u]
            if combine:
                vfac[u] = _combined_vfac(n_steps, k_max, r_wsum[u])
            code[u] = _mask(_OK, r_dev[u], r_m2min[u], _F0, cons_rad, m2_min, top_code, total[u])
            n += 1
    return n


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _refit_span(  # type: ignore[no-untyped-def]
        frames, v, u0, cos_t, sin_t, freqs, chain_c, chain_f, heterodyne, combine, cons_rad, m2_min,
        top_code, m2, prev, vfac, code, rscratch, sums, total, order, gl):  # pragma: no cover
    """Refit the SATURATED pixels of the span u0.. u0 + m of row ``v`` (``m2``, ``prev``,
    ``vfac``, ``code``, ``total``: the span's views) that keep three unclipped samples per
    frequency (phase stage: phase, finest m2, σ factor and phase-stage code; the height stage
    follows); their count.

    The whole span is fitted (float32 sums ``sums`` (9, ≥ m), Cramer in float64) and unwrapped
    like :func:`_general_row` in the float32 rows of ``rscratch`` (10 + 3K, ≥ m; ``total`` the
    span's frame sums, ``order`` the heterodyne order test's constants); then only those pixels
    take the result."""
    n_steps = cos_t.shape[0]
    n_freq = freqs.shape[0]
    k_max = freqs[n_freq - 1]
    m = code.shape[0]
    s_acc, c_acc, m2min, dev, wsum, wphi, r_prev, r_m2, nmin = (
        rscratch[0, :m], rscratch[1, :m], rscratch[2, :m], rscratch[3, :m], rscratch[4, :m],
        rscratch[5, :m], rscratch[6, :m], rscratch[7, :m], rscratch[8, :m])
    wphs = rscratch[9:9 + n_freq, :m]
    m2s = rscratch[9 + n_freq:9 + 2 * n_freq, :m]
    sv = (sums[0, :m], sums[1, :m], sums[2, :m], sums[3, :m], sums[4, :m], sums[5, :m],
          sums[6, :m], sums[7, :m], sums[8, :m])
    m2min[:] = _INF
    dev[:] = _F0
    wsum[:] = _F0
    wphi[:] = _F0
    nmin[:] = _INF
    for ki in range(n_freq):
        _fit_row(frames, ki * n_steps, v, u0, cos_t, sin_t, top_code, sums, sv, s_acc, c_acc, nmin)
        if heterodyne:
            _wrapped_row(s_acc, c_acc, wphs[ki], m2s[ki], m2min, gl[0][ki], gl[1], gl[2],
                         _series_row(gl[3], ki), gl[4])
        else:
            _level_row(s_acc, c_acc, r_prev, r_m2, m2min, dev, freqs[ki] / freqs[max(ki - 1, 0)],
                       ki == 0, gl[0][ki], gl[1], gl[2],
                       _series_row(gl[3], ki), gl[4])
            if combine:
                kk = freqs[ki]
                _weigh_row(wsum, wphi, r_m2, r_prev, np.float32(n_steps) * kk * kk, k_max / kk)
    if heterodyne:
        _chain_and_weigh(wphs, m2s, chain_c, chain_f, freqs, cons_rad, n_steps, combine, r_prev,
                         dev, r_m2, wsum, wphi, total, order,
                         rscratch[9 + 2 * n_freq:10 + 3 * n_freq, :m])
    if combine:
        _combined_row(r_prev, wsum, wphi)
    return _take_refit_row(m2, prev, vfac, code, r_m2, r_prev, wsum, m2min, dev, nmin, n_steps,
                           k_max, combine, cons_rad, m2_min, top_code, total)


@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _refit_row(  # type: ignore[no-untyped-def]
        frames, v, cos_t, sin_t, freqs, chain_c, chain_f, heterodyne, combine, cons_rad, m2_min,
        top_code, m2, prev, vfac, code, rscratch, sums, total, order, gl):  # pragma: no cover
    """Refit the row's SATURATED pixels that keep three unclipped samples per frequency; their
    count. Spans of REFIT_SPAN pixels without a SATURATED code are skipped (clipping is local:
    highlights); the others are refitted whole, branch-free (:func:`_refit_span`; ``rscratch``
    (10 + 3K, REFIT_SPAN) float32, ``sums`` (9, REFIT_SPAN) float32; ``total`` the row's frame
    sums)."""
    width = code.shape[0]
    n = 0
    for u0 in range(0, width, REFIT_SPAN):
        u1 = min(width, u0 + REFIT_SPAN)
        if _count_saturated(code[u0:u1]) > 0:
            n += _refit_span(frames, v, u0, cos_t, sin_t, freqs, chain_c, chain_f, heterodyne,
                             combine, cons_rad, m2_min, top_code, m2[u0:u1], prev[u0:u1],
                             vfac[u0:u1], code[u0:u1], rscratch, sums, total[u0:u1], order, gl)
    return n


# Phase 2: the optional phase output from the block buffers.
@njit(fastmath=FASTMATH, error_model="numpy", cache=True)
def _select_row(out, values, code):  # type: ignore[no-untyped-def]  # pragma: no cover
    for u in range(out.shape[0]):
        out[u] = values[u] if code[u] == _OK else _NAN


@njit(parallel=True, nogil=True, fastmath=FASTMATH, error_model="numpy", cache=True)
def fused_kernel(frames, ph, m, out):  # type: ignore[no-untyped-def]  # pragma: no cover - compiled
    """Raw frames → all per-pixel outputs (see the module docstring). Writes into ``out``.

    ``ph``: :class:`PhaseArgs`; ``m``: :class:`HeightArgs`; ``out``: :class:`Outputs`
    (``out.phase`` is skipped when it has zero rows).
    """
    n_frames, height, width = frames.shape
    cos_t, sin_t, freqs = ph.cos_t, ph.sin_t, ph.freqs
    n_steps = cos_t.shape[0]
    n_freq = freqs.shape[0]
    mod_scale = np.float32(2.0) / np.float32(n_steps)
    # B < min_mod ⇔ x² + y² < (min_mod/mod_scale)²; the noise-aware rule on top
    # (PhaseArgs.snr_min2): m2 < a_min²·(N/2)·σ_I², σ_I² = read_var + gain·Σ I/F
    k0 = ph.snr_min2 * m.half_steps * m.read_var
    m2_min = ((ph.min_mod / mod_scale) * (ph.min_mod / mod_scale), k0,
              ph.snr_min2 * m.half_steps * m.gain * m.inv_frames)
    top_code = np.float32(ph.max_code)
    paper = n_steps == 4 and n_freq == 4 and not m.combine and not ph.heterodyne
    want_phase = out.phase.shape[0] == height
    r1 = freqs[min(1, n_freq - 1)] / freqs[0]
    r2 = freqs[min(2, n_freq - 1)] / freqs[min(1, n_freq - 1)]
    r3 = freqs[n_freq - 1] / freqs[min(2, n_freq - 1)]
    # the phase-error table and its series (PhaseArgs)
    gl = (ph.lut, ph.lut_scale, ph.use_lut, ph.series, ph.use_series)
    # the series replaces the table where given (the paper's schedule only; PhaseArgs)
    chain = (r1, r2, r3, ph.lut, ph.lut_scale, ph.use_lut, ph.series, ph.use_series)
    n_blocks = (height + ROWS_PER_BLOCK - 1) // ROWS_PER_BLOCK
    recovered = out.recovered
    order = (ph.order_z2, ph.order_front2, ph.order_floor2, m.read_var, m.gain, m.inv_frames,
             m.half_steps)  # heterodyne order test
    for blk in prange(n_blocks):
        v0 = blk * ROWS_PER_BLOCK
        n_rows = min(height, v0 + ROWS_PER_BLOCK) - v0
        buf = np.empty((4, ROWS_PER_BLOCK, width), np.float32)
        total, m2, prev, vfac = buf[0], buf[1], buf[2], buf[3]
        code = np.empty((ROWS_PER_BLOCK, width), np.uint8)
        scratch = np.empty((0 if paper else 8 + 3 * n_freq, width), np.float32)
        lut_rows = np.empty((6 if paper and ph.use_lut else 0, width), np.float32)
        # the saturation refit's spans
        rscratch = np.empty((10 + 3 * n_freq, REFIT_SPAN), np.float32)
        sums = np.empty((9, REFIT_SPAN), np.float32)
        sm_row = np.empty((5, width), np.float32)  # the height stage's σ_model coefficients
        # clipping is spatially coherent: where the row above had much of it, one pass that phases
        # and refits every pixel is cheaper than refitting many spans after the plain pass
        wide_clip = False
        for r in range(n_rows):
            v = v0 + r
            n_refit = 0
            if paper and wide_clip:  # phased and refitted in one pass
                n_refit = int(_paper_fit_row(frames, v, chain, ph.cons_rad, m2_min, top_code,
                                             total[r], m2[r], prev[r], code[r]))
            elif paper:
                _paper_row(frames, v, chain, ph.cons_rad, m2_min, top_code, total[r], m2[r],
                           prev[r], code[r], lut_rows)
                # a vectorised byte count; spans refitted only where needed
                if _count_saturated(code[r]) > 0:
                    n_refit = _paper_refit_row(frames, v, chain, ph.cons_rad, m2_min, top_code,
                                               total[r], m2[r], prev[r], code[r], rscratch)
            else:
                _general_row(frames, v, cos_t, sin_t, freqs, ph.chain_c, ph.chain_f, ph.heterodyne,
                             m.combine, ph.cons_rad, m2_min, top_code, scratch, total[r], m2[r],
                             prev[r], vfac[r], code[r], order, gl)
                # With N = 3 a clipped sample leaves 2 in its frequency, fewer than a fit needs:
                # nothing to refit (the scan cost 2-3× the whole kernel)
                if n_steps > 3 and _count_saturated(code[r]) > 0:
                    n_refit = _refit_row(frames, v, cos_t, sin_t, freqs, ph.chain_c, ph.chain_f,
                                         ph.heterodyne, m.combine, ph.cons_rad, m2_min, top_code,
                                         m2[r], prev[r], vfac[r], code[r], rscratch, sums, total[r],
                                         order, gl)
            recovered[v] = n_refit
            if paper:
                wide_clip = (n_refit + _count_saturated(code[r])) * 16 > width
            _height_row(v, prev[r], m2[r], total[r], vfac[r], code[r], m, out.depth[v],
                        out.sigma[v], out.reason[v], out.valid[v], out.modulation[v],
                        out.texture[v], mod_scale, sm_row)
        if want_phase:  # the one output the height stage does not write
            for r in range(n_rows):
                _select_row(out.phase[v0 + r], prev[r], out.reason[v0 + r])


@njit(nogil=True, error_model="numpy", cache=True)
def points_kernel(height, ray_q, offset, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """``out`` (H, W, 3) = (``height`` (H, W) − ``offset``)·``ray_q`` (H, W, 3), float32 and
    without fastmath: IEEE the same as numpy's float32 arithmetic (NaN → NaN), one pass with
    no temporaries (:meth:`app.recon.points.PointRays.points`). Serial: no threading layer."""
    for v in range(height.shape[0]):
        for u in range(height.shape[1]):
            t = height[v, u] - offset
            out[v, u, 0] = t * ray_q[v, u, 0]
            out[v, u, 1] = t * ray_q[v, u, 1]
            out[v, u, 2] = t * ray_q[v, u, 2]


_warm: set[str] = set()


def warmup(dtype: object = np.uint8) -> None:
    """Compile (or load from the disk cache) the kernel for ``dtype`` frames once per process."""
    dt = np.dtype(dtype)  # type: ignore[call-overload]
    if dt.name in _warm:
        return
    with KERNEL_LOCK:
        _warmup_locked(dt)


def _warmup_locked(dt: np.dtype[np.generic]) -> None:
    if dt.name in _warm:
        return
    f32 = np.zeros((2, 3), np.float32)
    frames = np.zeros((4, 2, 3), dt)
    trig = np.ones(4, np.float32)
    ph = PhaseArgs(trig, trig, np.ones(1, np.float32), np.int32(1), np.float32(0), np.float32(1),
                   np.ones((1, 1), np.float32), np.ones(1, np.float32), False, np.float32(0),
                   np.float32(np.inf), np.zeros((1, 1), np.float32), np.float32(0),
                   np.zeros((1, 2), np.float32), np.float32(1), False,
                   np.zeros((1, 7), np.float32), False)
    m = HeightArgs(
        np.zeros(3, np.float32), np.zeros((2, 12), np.float32), np.zeros(12, np.float32), False,
        np.float32(0), np.float32(1), np.float32(0), np.zeros(9, np.float32), np.float32(0), False,
        np.float32(0), np.float32(1), np.float32(1e-5),
        np.zeros((3, 2, 3), np.float32), np.full((1, 3), -np.inf, np.float32),
        np.full((1, 3), np.inf, np.float32),
        np.zeros(2, np.int64), np.float32(-np.inf), np.float32(np.inf),
        np.full(2, -np.inf, np.float32), np.full(2, np.inf, np.float32),
        np.float32(0), np.float32(0), np.float32(np.inf), False, np.float32(2), np.float32(0.25),
        np.zeros((1, 5, 3), np.float32), np.zeros(2, np.int64), np.zeros(2, np.float32),
        np.float32(0), np.float32(1),
        np.float32(0), np.zeros(4, np.float32), np.float32(1),
    )
    out = Outputs(np.empty((2, 3), np.float32), np.empty((2, 3), np.uint8),
                  np.empty((2, 3), np.bool_), f32, f32.copy(), np.empty((0, 3), np.float32),
                  f32.copy(), np.empty(2, np.int32))
    fused_kernel(frames, ph, m, out)
    _warm.add(dt.name)
