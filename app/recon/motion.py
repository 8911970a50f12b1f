"""The motion test between the frequency groups of one fringe set, pooled over a window.

For a still scene the background ``A = mean of the N shifted images`` of a frequency group
does not depend on the fringe frequency (the shifts cancel the fringe). With the camera's
noise model ``σ_I² = read² + gain·I`` (:class:`~app.recon.sensor.SensorNoise`, DN) a group's
sum ``S_g`` of N frames has variance ``N·σ_I²``, so per pixel

    ``Q = Σ_g (S_g − S̄)² / (N·σ_I²(Ā))``,  S̄ the mean of the G group sums,

(σ_I² floored at 1/4 DN²: rounding a sub-DN noise to integer codes is not the model's
independent 1/12 DN²) is chi-square with G − 1 degrees of freedom on a still scene (the
homogeneity test of G means of known variance). Noise is independent from pixel to pixel;
motion is spatially coherent. So the test pools the evidence of a k × k window
(``window_px``, odd): the sum ``T`` of Q over the window's m tested pixels is chi-square with
m·(G − 1) degrees of freedom on a still scene, and the window's centre is flagged when ``T``
exceeds that distribution's upper ``α / (2·H·W)`` quantile. A pixel is also flagged on its
own when its Q exceeds the chi-square(G − 1) upper ``α / (2·H·W)`` quantile: a strong change
confined to a pixel or a thin line (a moving edge of fine texture) is diluted in a window (on
the twin's breathing scene such a pixel, Q = 63 in a window sum of 92 against 143, kept a
0.79 mm error). With these 2·H·W tests per map the union bound gives the **false-alarm rate
over the image**: a still map has ANY flagged pixel with probability ≤ α
(``false_alarm_rate``, default 1e-4 per map: one false region in ten thousand maps). A
coherent motion is seen at a much smaller change per pixel than a single-pixel test at the
same image rate needs (G = 4, 1384 × 1032, α = 1e-4: one group's background shifted by 2.4 σ
of its sum in every pixel of a 5 × 5 window is flagged with probability 1/2, one pixel alone
would need 8 σ), and isolated noise flags no longer exist to be grown into holes.

Flagged centres are grown by ``grow_px`` (a (2r+1)² square) before they are invalidated: at
a moved region's rim the background change falls below the threshold while the phase error
can still exceed 0.5 mm.

What the test cannot see: pixels with a clipped sample (a clipped sinusoid's mean depends on
its phase, so a still, over-exposed pixel would look moved: they are left out of the window
sums; the engine refits them from their unclipped samples), and motion that leaves the
background unchanged (a heave of an evenly lit, untextured surface). Such motion still changes
the phase; the engine's unwrapping consistency test flags it when it breaks the frequency
chain.

**Gross-error bound.** A test in noise units cannot bound a depth error in millimetres: a
motion just below the threshold shifts a pixel's phase by up to about k·σ_φ, k the
per-pixel bound of :func:`motion_k` (at the rate ``PIXEL_BOUND_RATE``, 1e-4; a coherent motion
below the window threshold moves each pixel less), so a pixel's error can reach (z + k)·σ_z
with noise at z σ. With a tolerance E (``gross_error_mm``, 0.5) and a per-pixel rate β (1e-6,
z = Φ⁻¹(1 − β/2) = 4.89; both :mod:`app.recon.validity`'s) a valid pixel needs ``σ_z ≤ E / z``
always (the engine's own depth-σ rule) and ``σ_z ≤ E / (z + k)`` in a set where the scene
moved — some window flagged, itself a test at level α — with reason UNCERTAIN.

The window statistic is two parallel numba passes (group sums of a row and their horizontal
window sums; the vertical window sums and the threshold), the growth a third over the (H, W)
mask that invalidates in place in the engine's output arrays.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from numba import njit, prange

from app.core.reasons import Reason
from app.recon.fast import FASTMATH, KERNEL_LOCK
from app.recon.sensor import SensorNoise
from app.recon.unwrap import order_test_bound
from app.recon.validity import max_depth_sigma_mm

#: reason code for "moved during the set"
MOTION = int(Reason.MOTION)
_SATURATED = int(Reason.SATURATED)
_UNCERTAIN = int(Reason.UNCERTAIN)

#: default false-alarm rate of the motion test over the image: the probability that a map of
#: a still scene has any flagged pixel (before growth)
DEFAULT_FALSE_ALARM_RATE = 1e-4
#: default side of the square window whose evidence is pooled, px (odd)
DEFAULT_WINDOW_PX = 5
#: moved regions are grown by this many pixels before invalidating: at a region's rim the
#: background change falls below the threshold before the phase change becomes harmless
DEFAULT_GROW_PX = 4
#: per-pixel rate whose bound k stands for "a motion just below the threshold" in
#: :func:`sigma_bounds` (the single-pixel view of the test; conservative for the window test)
PIXEL_BOUND_RATE = 1e-4


@dataclass(frozen=True)
class MotionTest:
    """What :meth:`Reconstructor.run <app.recon.reconstructor.Reconstructor.run>` needs to test
    a set for motion.

    Attributes:
        false_alarm_rate: α over the image, the probability that a still map has any flagged
            pixel before growth, in (0, 0.5).
        window_px: side of the pooling window, px, odd in 1..15 (1: a per-pixel test).
        grow_px: flagged pixels are grown by this many pixels, 0..16.
        gross_error_mm: tolerance E of the moving-scene σ bound (None: no such bound), mm.
    """

    false_alarm_rate: float = DEFAULT_FALSE_ALARM_RATE
    window_px: int = DEFAULT_WINDOW_PX
    grow_px: int = DEFAULT_GROW_PX
    gross_error_mm: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.false_alarm_rate) and 0.0 < self.false_alarm_rate < 0.5):
            raise ValueError(f"false_alarm_rate: must be in (0, 0.5), got {self.false_alarm_rate}")
        _check_window(self.window_px)
        _check_grow(self.grow_px)
        if self.gross_error_mm is not None:
            max_depth_sigma_mm(self.gross_error_mm)  # ValueError naming gross_error_mm


class MotionPass(NamedTuple):
    """What :func:`invalidate_motion` did: ``mask`` (H, W) bool the grown motion mask, ``moved``
    its pixel count, ``uncertain`` valid pixels made UNCERTAIN by the moving-scene σ bound,
    ``scene_moved`` whether any window was flagged (a test of the whole map at level α),
    ``elapsed_ms`` the pass's wall time."""

    mask: npt.NDArray[np.bool_]
    moved: int
    uncertain: int
    scene_moved: bool
    elapsed_ms: float = 0.0


def motion_k(n_groups: int, false_alarm_rate: float = PIXEL_BOUND_RATE) -> float:
    """Single-pixel threshold in units of a group difference's σ at a per-pixel rate.

    Args:
        n_groups: frequency groups in a set (G ≥ 2); G − 1 differences per pixel.
        false_alarm_rate: the per-pixel probability that a still pixel exceeds it, in (0, 1).

    Returns:
        ``k = Φ⁻¹(1 − α / (2(G − 1)))`` (Gaussian noise, two-sided, Bonferroni over the tests).
    """
    if int(n_groups) != n_groups or n_groups < 2:
        raise ValueError(f"n_groups: need an integer >= 2, got {n_groups}")
    return order_test_bound(n_groups, false_alarm_rate)  # the order test's Bonferroni bound


def sigma_bounds(gross_error_mm: float, n_groups: int,
                 pixel_rate: float = PIXEL_BOUND_RATE) -> tuple[float, float]:
    """Largest 1-σ depth noise (mm) of a valid pixel: (still, moving) for a tolerance E.

    Args:
        gross_error_mm: E > 0, the error a valid pixel may exceed only at the rate β of
            :func:`app.recon.validity.max_depth_sigma_mm`.
        n_groups: frequency groups per set (fixes k, :func:`motion_k`).
        pixel_rate: the per-pixel rate of k.

    Returns:
        ``(E / z, E / (z + k))`` with ``z = Φ⁻¹(1 − β/2)``: noise alone at rate β, and noise
        plus a motion just below the threshold (a phase shift of up to k·σ_φ).
    """
    still = max_depth_sigma_mm(gross_error_mm)  # E / z; raises naming gross_error_mm
    z = gross_error_mm / still
    k = motion_k(n_groups, pixel_rate)
    return float(still), float(gross_error_mm / (z + k))


def _log_gamma_q(a: float, x: float) -> float:
    """log of the regularised upper incomplete gamma function Q(a, x), a > 0, x ≥ 0."""
    if x <= 0.0:
        return 0.0
    log_front = -x + a * math.log(x) - math.lgamma(a)
    if x < a + 1.0:  # the series of P(a, x) converges fast here
        term = total = 1.0 / a
        ap = a
        for _ in range(10_000):
            ap += 1.0
            term *= x / ap
            total += term
            if term < total * 1e-16:
                break
        return math.log1p(-min(math.exp(log_front) * total, 1.0 - 1e-300))
    tiny = 1e-300  # the continued fraction of Q(a, x) (modified Lentz)
    b = x + 1.0 - a
    c = 1.0 / tiny
    d = 1.0 / b
    h = d
    for i in range(1, 10_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        h *= d * c
        if abs(d * c - 1.0) < 1e-16:
            break
    return log_front + math.log(h)


def chi2_sf(x: float, dof: int) -> float:
    """P(X > x) for X chi-square with ``dof`` degrees of freedom (dof ≥ 1, x ≥ 0)."""
    if int(dof) != dof or dof < 1:
        raise ValueError(f"dof: need an integer >= 1, got {dof}")
    if not (math.isfinite(x) and x >= 0.0):
        raise ValueError(f"x: must be finite and >= 0, got {x}")
    return math.exp(_log_gamma_q(dof / 2.0, x / 2.0))


def chi2_isf(p: float, dof: int) -> float:
    """The x with ``chi2_sf(x, dof) = p`` (p in (0, 1)), to a relative 1e-10."""
    if not (0.0 < p < 1.0):
        raise ValueError(f"p: must be in (0, 1), got {p}")
    if int(dof) != dof or dof < 1:
        raise ValueError(f"dof: need an integer >= 1, got {dof}")
    target = math.log(p)
    lo, hi = 0.0, float(dof) + 10.0
    while _log_gamma_q(dof / 2.0, hi / 2.0) > target:
        lo, hi = hi, 2.0 * hi
    while hi - lo > 1e-10 * hi:
        mid = 0.5 * (lo + hi)
        if _log_gamma_q(dof / 2.0, mid / 2.0) > target:
            lo = mid
        else:
            hi = mid
    return hi


@lru_cache(maxsize=32)
def _thresholds(n_groups: int, window_px: int, false_alarm_rate: float,
                n_windows: int) -> npt.NDArray[np.float32]:
    per_window = false_alarm_rate / n_windows
    out = np.full(window_px * window_px + 1, np.inf, np.float32)
    for m in range(1, out.size):
        # rounded up to float32: a float32 sum never passes a threshold below the exact one
        exact = np.float32(chi2_isf(per_window, m * (n_groups - 1)))
        out[m] = np.nextafter(exact, np.float32(np.inf))
    out.setflags(write=False)
    return out


def window_thresholds(n_groups: int, window_px: int, false_alarm_rate: float,
                      n_windows: int) -> npt.NDArray[np.float32]:
    """Per-window thresholds of the pooled statistic T, indexed by the window's tested pixels m.

    Args:
        n_groups: frequency groups G ≥ 2 (each tested pixel adds G − 1 degrees of freedom).
        window_px: side k of the window (odd).
        false_alarm_rate: α over the image, (0, 0.5).
        n_windows: tests made per map (windows and single pixels: 2·H·W), ≥ 1.

    Returns:
        (k² + 1,) float32: entry m is the chi-square(m·(G − 1)) upper ``α / n_windows``
        quantile (entry 0: +∞, an all-untested window is never flagged). Read-only, cached.
    """
    if int(n_groups) != n_groups or n_groups < 2:
        raise ValueError(f"n_groups: need an integer >= 2, got {n_groups}")
    _check_window(window_px)
    if not (math.isfinite(false_alarm_rate) and 0.0 < false_alarm_rate < 0.5):
        raise ValueError(f"false_alarm_rate: must be in (0, 0.5), got {false_alarm_rate}")
    if int(n_windows) != n_windows or n_windows < 1:
        raise ValueError(f"n_windows: need an integer >= 1, got {n_windows}")
    return _thresholds(int(n_groups), int(window_px), float(false_alarm_rate), int(n_windows))


_ROWS = 16  # rows per parallel chunk (one scratch allocation per chunk)
#: the largest change of the light between a set's groups taken for the source, not the scene
MAX_LIGHT_DRIFT = 0.05
#: :func:`group_light` reads every LIGHT_STRIDE-th row and column (a 1384 × 1032 set: 22,000
#: pixels, a median to ~1e-4; 2 ms of a 1384 × 1032 set, every 4th took 16)
LIGHT_STRIDE = 8
#: pixels dimmer than this mean level (codes) say little about the light (rounding)
LIGHT_MIN_LEVEL = 8.0
#: fewer qualifying pixels: the light is taken as steady
LIGHT_MIN_PIXELS = 1000
#: floor of a sample's variance in the test, DN²: where the analog noise is far below 1 DN
#: (dark pixels) rounding to a code is not the model's independent 1/12 DN²; a level near a
#: half code flips between two codes with variance up to 1/4 (measured on the twin's
#: black-level pixels: mean Q 5.0 for G − 1 = 3 with the model alone, 2.9 with the floor)
_MIN_VAR_DN2 = np.float32(0.25)


@njit(parallel=True, nogil=True, fastmath=FASTMATH, error_model="numpy", cache=True)
def _pixel_kernel(frames, n_groups, steps, inv_light, read2,  # type: ignore[no-untyped-def]
                  gain, top_code, radius, q_pixel, qh, mh, hot):  # pragma: no cover - compiled
    """qh[v, u] = the sum over u − r … u + r of the per-pixel chi-square Q of the group sums,
    each divided by its group's light (``inv_light`` (G,) float32 the inverse of
    :func:`group_light`'s) (float32; 0 for an untested pixel: one with a sample at
    ``top_code`` or above), mh[v, u] = how many of those
    pixels were tested (uint8), hot[v, u] = Q > ``q_pixel`` (the single-pixel test). Row-vector
    loops (u innermost) so that they vectorise."""
    f, h, w = frames.shape
    inv_n = np.float32(1.0 / steps)
    inv_gn = np.float32(1.0 / (steps * n_groups))
    inv_g = np.float32(1.0 / n_groups)
    n_chunks = (h + _ROWS - 1) // _ROWS
    for chunk in prange(n_chunks):
        sums = np.empty((n_groups, w), np.int32)  # integer group sums of one row: exact
        top = np.empty(w, np.int32)
        total = np.empty(w, np.int32)
        mean = np.empty(w, np.float32)
        q = np.empty(w, np.float32)
        for v in range(chunk * _ROWS, min((chunk + 1) * _ROWS, h)):
            for u in range(w):
                top[u] = 0
                total[u] = 0
                mean[u] = np.float32(0.0)
            for g in range(n_groups):
                row = sums[g]
                src = frames[g * steps, v]
                for u in range(w):
                    row[u] = np.int32(src[u])
                    top[u] = max(top[u], np.int32(src[u]))
                for n in range(1, steps):
                    src = frames[g * steps + n, v]
                    for u in range(w):
                        row[u] += np.int32(src[u])
                        top[u] = max(top[u], np.int32(src[u]))
                k = inv_light[g]
                for u in range(w):
                    total[u] += row[u]
                    mean[u] += np.float32(row[u]) * k
            for u in range(w):
                mean[u] *= inv_g
                q[u] = np.float32(0.0)
            for g in range(n_groups):
                row = sums[g]
                k = inv_light[g]
                for u in range(w):
                    d = np.float32(row[u]) * k - mean[u]
                    q[u] += d * d
            for u in range(w):
                # σ_I² at Ā, DN², at least the variance a sub-DN noise can take once rounded
                var = max(read2 + gain * np.float32(total[u]) * inv_gn, _MIN_VAR_DN2)
                tested = top[u] < top_code
                q[u] = q[u] * inv_n / var if tested else np.float32(0.0)
                top[u] = 1 if tested else 0
            hot_row = hot[v]
            for u in range(w):
                hot_row[u] = q[u] > q_pixel
            out_q = qh[v]
            out_m = mh[v]
            s = np.float32(0.0)  # running window sums, restarted on every row
            c = 0
            for x in range(min(radius, w)):
                s += q[x]
                c += top[x]
            lo = min(radius + 1, w)
            hi = max(w - radius, lo)
            for u in range(lo):  # the left edge: nothing leaves the window yet
                if u + radius < w:
                    s += q[u + radius]
                    c += top[u + radius]
                out_q[u] = s
                out_m[u] = c
            for u in range(lo, hi):
                s += q[u + radius] - q[u - radius - 1]
                c += top[u + radius] - top[u - radius - 1]
                out_q[u] = s
                out_m[u] = c
            for u in range(hi, w):  # the right edge: nothing enters any more
                s -= q[u - radius - 1]
                c -= top[u - radius - 1]
                out_q[u] = s
                out_m[u] = c


@njit(parallel=True, nogil=True, fastmath=FASTMATH, error_model="numpy", cache=True)
def _window_kernel(qh, mh, hot, radius, thresholds,  # type: ignore[no-untyped-def]
                   mask, row_any):  # pragma: no cover - compiled
    """mask[v, u] = the window sum of Q around (v, u) exceeds ``thresholds[m]`` for its m tested
    pixels, or ``hot[v, u]``; row_any[v] = flagged pixels of row v (int32). Running column sums
    per chunk of rows (restarted per chunk: float32 drift stays far below any threshold)."""
    h, w = qh.shape
    n_chunks = (h + _ROWS - 1) // _ROWS
    full = thresholds.size - 1
    full_thr = thresholds[full]
    for chunk in prange(n_chunks):
        col = np.zeros(w, np.float32)
        cnt = np.zeros(w, np.int32)
        v0 = chunk * _ROWS
        for y in range(max(v0 - radius, 0), min(v0 + radius + 1, h)):
            for u in range(w):
                col[u] += qh[y, u]
                cnt[u] += mh[y, u]
        for v in range(v0, min(v0 + _ROWS, h)):
            row = mask[v]
            partial = 0  # windows with untested pixels (or cut by the border): their own threshold
            for u in range(w):
                row[u] = col[u] > full_thr
                partial += cnt[u] < full
            if partial:
                for u in range(w):
                    if cnt[u] < full:
                        row[u] = col[u] > thresholds[cnt[u]]
            hits = 0
            hot_row = hot[v]
            for u in range(w):
                row[u] |= hot_row[u]
                hits += row[u]
            row_any[v] = hits
            add = v + radius + 1
            sub = v - radius
            if add < h:
                for u in range(w):
                    col[u] += qh[add, u]
                    cnt[u] += mh[add, u]
            if sub >= 0:
                for u in range(w):
                    col[u] -= qh[sub, u]
                    cnt[u] -= mh[sub, u]


def pooled_window_mask(qh: npt.NDArray[np.float32], mh: npt.NDArray[np.uint8],
                       hot: npt.NDArray[np.bool_], window_px: int,
                       thresholds: npt.NDArray[np.float32],
                       ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.int32]]:
    """The window half of the pooled test, for any per-pixel chi-square statistic Q.

    Args:
        qh: (H, W) float32, the sum of Q over the row's pixels u − r … u + r (0 where untested).
        mh: (H, W) uint8, how many of those pixels were tested.
        hot: (H, W) bool, pixels flagged on their own.
        window_px: side k of the window (odd), r = k // 2.
        thresholds: :func:`window_thresholds` for that window (entry m for m tested pixels).

    Returns:
        ((H, W) mask: the k × k window sum exceeds its threshold or ``hot``, (H,) int32 flagged
        pixels per row).
    """
    radius = _check_window(window_px) // 2
    if thresholds.shape != (window_px * window_px + 1,):
        raise ValueError(f"thresholds: expected ({window_px * window_px + 1},), "
                         f"got {thresholds.shape}")
    h, w = qh.shape
    mask = np.empty((h, w), np.bool_)
    row_any = np.empty(h, np.int32)
    with KERNEL_LOCK:
        _window_kernel(qh, mh, hot, radius, thresholds, mask, row_any)
    return mask, row_any


@njit(nogil=True, fastmath=FASTMATH, error_model="numpy", cache=True)
def _invalidate(depth, sigma, points, valid, reason, v, u,  # type: ignore[no-untyped-def]
                code):  # pragma: no cover - compiled
    """Pixel (v, u) has no depth, for reason ``code``."""
    depth[v, u] = np.nan
    sigma[v, u] = np.nan
    if points is not None:  # None: points not made yet (they follow depth when they are)
        points[v, u, 0] = np.nan
        points[v, u, 1] = np.nan
        points[v, u, 2] = np.nan
    valid[v, u] = False
    reason[v, u] = code


@njit(parallel=True, nogil=True, fastmath=FASTMATH, error_model="numpy", cache=True)
def _grow_kernel(mask, row_any, radius, tmp, out, apply,  # type: ignore[no-untyped-def]
                 depth, points, valid, reason, sigma, motion_code, saturated_code, strict_sigma,
                 uncertain_code):  # pragma: no cover - compiled
    """out = mask dilated by a (2r+1)² square (separable; rows without a flagged pixel,
    ``row_any`` 0, are skipped); with ``apply`` invalidate ``out`` in place (MOTION), then every
    other valid pixel whose σ exceeds ``strict_sigma`` (UNCERTAIN; ∞: none).
    Returns (pixels in ``out``, pixels made UNCERTAIN)."""
    h, w = mask.shape
    for v in prange(h):
        if not row_any[v]:
            continue
        src = mask[v]
        dst = tmp[v]
        count = 0  # flagged pixels in the window u − r … u + r: O(W) whatever the density
        for x in range(min(radius, w)):
            count += src[x]
        for u in range(w):
            if u + radius < w:
                count += src[u + radius]
            if u - radius - 1 >= 0:
                count -= src[u - radius - 1]
            dst[u] = count > 0
    counts = np.zeros(h, np.int64)
    ucounts = np.zeros(h, np.int64)
    strict = apply and strict_sigma < np.inf
    for v in prange(h):
        row = out[v]
        for u in range(w):
            row[u] = False
        touched = False
        for y in range(max(v - radius, 0), min(v + radius + 1, h)):
            if row_any[y]:
                touched = True
                t = tmp[y]
                for u in range(w):
                    row[u] |= t[u]
        if touched:
            c = 0
            for u in range(w):
                if row[u]:
                    c += 1
                    if apply and reason[v, u] != saturated_code:
                        _invalidate(depth, sigma, points, valid, reason, v, u, motion_code)
            counts[v] = c
        if strict:
            n = 0
            for u in range(w):
                if valid[v, u] and sigma[v, u] > strict_sigma:
                    _invalidate(depth, sigma, points, valid, reason, v, u, uncertain_code)
                    n += 1
            ucounts[v] = n
    return counts.sum(), ucounts.sum()


def _check(frames: npt.NDArray[np.generic], n_groups: int) -> int:
    if (not isinstance(frames, np.ndarray) or frames.ndim != 3
            or frames.dtype not in (np.uint8, np.uint16)):
        raise ValueError(f"frames: expected (F, H, W) uint8/uint16, got "
                         f"{getattr(frames, 'dtype', type(frames))} {getattr(frames, 'shape', '')}")
    f = int(frames.shape[0])
    if int(n_groups) != n_groups or n_groups < 2 or f % n_groups:
        raise ValueError(f"n_groups: {n_groups} groups do not divide {f} frames (need >= 2)")
    return f // n_groups


def _check_grow(grow_px: int) -> int:
    if int(grow_px) != grow_px or not 0 <= grow_px <= 16:
        raise ValueError(f"grow_px: must be an integer in 0..16, got {grow_px}")
    return int(grow_px)


def _check_window(window_px: int) -> int:
    if int(window_px) != window_px or not 1 <= window_px <= 15 or window_px % 2 == 0:
        raise ValueError(f"window_px: must be an odd integer in 1..15, got {window_px}")
    return int(window_px)


def group_light(frames: npt.NDArray[np.uint8] | npt.NDArray[np.uint16], n_groups: int, *,
                max_code: int | None = None) -> npt.NDArray[np.float64]:
    """Each frequency group's light relative to the set's mean: a real source drifts.

    A still scene under a light that changes between groups scales every pixel's group sum
    by one factor per group (on the real CFPE bench −0.8 … +1.1 % across one set, the same
    at every level), which the per-pixel test would take for motion (2–30 % of those still
    scenes flagged). The factor is the median over pixels of ``S_g / S̄``, from every
    ``LIGHT_STRIDE``-th row and column, unclipped pixels whose mean level is at least
    ``LIGHT_MIN_LEVEL`` codes, renormalised to mean 1; the median ignores a moving minority.
    It is held within ``1 ± MAX_LIGHT_DRIFT``: a larger common change is the scene (a heave
    toward the scope brightens the whole view), left to the test.

    Args:
        frames: (F, H, W) uint8/uint16 in capture-set order, F = n_groups × steps.
        n_groups: frequency groups in the set.
        max_code: the sensor's clipping code (None: the dtype's maximum).

    Returns:
        (G,) float64, mean 1; all ones where fewer than ``LIGHT_MIN_PIXELS`` pixels qualify.
    """
    steps = _check(frames, n_groups)
    top = 255 if frames.dtype == np.uint8 else 65535
    limit = top if max_code is None else int(max_code)
    sub = np.ascontiguousarray(frames[:, ::LIGHT_STRIDE, ::LIGHT_STRIDE]).reshape(
        frames.shape[0], -1)
    # (G, pixels); int32 holds 32767 frames of 65535
    sums = sub.reshape(n_groups, steps, -1).sum(axis=1, dtype=np.int32)
    total = sums.sum(axis=0)
    use = (sub.max(axis=0) < limit) & (total >= LIGHT_MIN_LEVEL * steps * n_groups)
    ones = np.ones(n_groups)
    if np.count_nonzero(use) < LIGHT_MIN_PIXELS:
        return ones
    ratio = sums[:, use].astype(np.float32)
    ratio *= np.float32(n_groups) / total[use].astype(np.float32)
    light: npt.NDArray[np.float64] = np.median(ratio, axis=1).astype(np.float64)
    light /= light.mean()
    return np.clip(light, 1.0 - MAX_LIGHT_DRIFT, 1.0 + MAX_LIGHT_DRIFT)


def _raw_mask(frames: npt.NDArray[np.generic], n_groups: int, steps: int, noise: SensorNoise,
              false_alarm_rate: float, window_px: int, max_code: int | None,
              light_correction: bool = True
              ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.int32]]:
    """(H, W) flagged window centres and (H,) their count per row."""
    if not isinstance(noise, SensorNoise):
        raise ValueError("noise: expected a SensorNoise")
    if noise.read_noise_dn <= 0.0:
        raise ValueError("noise: read_noise_dn must be > 0 (quantisation alone gives 0.29 DN)")
    top = 255 if frames.dtype == np.uint8 else 65535  # _check: uint8 or uint16
    limit = top if max_code is None else int(max_code)
    if not 1 <= limit <= top:
        raise ValueError(f"max_code: must be in 1..{top} for {frames.dtype} frames, got {max_code}")
    h, w = frames.shape[1:]
    # a window and (for windows of more than one pixel) the pixel alone at every pixel
    n_tests = h * w if window_px == 1 else 2 * h * w
    thr = window_thresholds(n_groups, _check_window(window_px), false_alarm_rate, n_tests)
    q_pixel = (np.float32(np.inf) if window_px == 1
               else window_thresholds(n_groups, 1, false_alarm_rate, n_tests)[1])
    radius = window_px // 2
    light = (group_light(frames, n_groups, max_code=limit)  # type: ignore[arg-type]
             if light_correction else np.ones(n_groups))
    qh = np.empty((h, w), np.float32)
    mh = np.empty((h, w), np.uint8)
    hot = np.empty((h, w), np.bool_)
    mask = np.empty((h, w), np.bool_)
    row_any = np.empty(h, np.int32)
    with KERNEL_LOCK:  # numba's workqueue layer: one parallel launch at a time, process-wide
        _pixel_kernel(np.ascontiguousarray(frames), n_groups, steps,
                      (1.0 / light).astype(np.float32),
                      np.float32(noise.read_noise_dn**2), np.float32(noise.gain_dn_per_e),
                      np.int32(limit), radius, q_pixel, qh, mh, hot)
        _window_kernel(qh, mh, hot, radius, thr, mask, row_any)
    return mask, row_any


def motion_mask(
    frames: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
    n_groups: int,
    *,
    noise: SensorNoise,
    false_alarm_rate: float = DEFAULT_FALSE_ALARM_RATE,
    window_px: int = DEFAULT_WINDOW_PX,
    grow_px: int = 0,
    max_code: int | None = None,
    light_correction: bool = True,
) -> npt.NDArray[np.bool_]:
    """Pixels around which the frequency groups' backgrounds differ beyond the noise.

    Args:
        frames: (F, H, W) uint8/uint16 in capture-set order, F = n_groups × steps.
        n_groups: frequency groups in the set (consecutive blocks of ``steps`` frames).
        noise: the camera's temporal noise model (DN).
        false_alarm_rate: α over the image: a still map has any flagged pixel with
            probability ≤ α (see the module docstring).
        window_px: side of the pooling window, odd (1: each pixel alone).
        grow_px: also flag every pixel within this many pixels (a (2r+1)² square) of a
            flagged one.
        max_code: the sensor's clipping code (None: the dtype's maximum); a pixel with a
            sample at or above it is left out (clipping biases a group's mean).
        light_correction: divide each group's sums by its light (:func:`group_light`);
            False: the light is taken as steady (comparisons).

    Returns:
        (H, W) bool, True where the window's chi-square sum exceeds its threshold (then grown).
    """
    steps = _check(frames, n_groups)
    grow = _check_grow(grow_px)
    mask, row_any = _raw_mask(frames, n_groups, steps, noise, false_alarm_rate, window_px,
                              max_code, light_correction)
    if grow == 0:
        return mask
    out = np.empty_like(mask)
    d = np.empty((1, 1), np.float32)
    with KERNEL_LOCK:
        _grow_kernel(mask, row_any, grow, np.empty_like(mask), out, False, d,
                     np.empty((1, 1, 3), np.float32), np.empty((1, 1), np.bool_),
                     np.empty((1, 1), np.uint8), d, MOTION, _SATURATED, np.float32(np.inf),
                     _UNCERTAIN)
    return out


def invalidate_motion(
    frames: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
    n_groups: int,
    *,
    noise: SensorNoise,
    depth: npt.NDArray[np.float32],
    points: npt.NDArray[np.float32] | None,
    valid: npt.NDArray[np.bool_],
    reason: npt.NDArray[np.uint8],
    sigma: npt.NDArray[np.float32],
    test: MotionTest,
    max_code: int | None = None,
) -> MotionPass:
    """:func:`motion_mask` (grown by ``test.grow_px``), then mark those pixels invalid IN PLACE.

    Moved pixels get depth/points/sigma NaN, valid False and reason MOTION, except where the
    engine said SATURATED (the earlier cause, see :mod:`app.core.reasons`). With
    ``test.gross_error_mm`` E, when the scene moved (some window flagged) every other valid
    pixel whose σ exceeds the moving bound of :func:`sigma_bounds` (E / (z + k)) is made
    UNCERTAIN the same way.

    Args:
        depth, sigma: (H, W) float32; points: (H, W, 3) float32, or None where the points
            are not made yet (made later from the invalidated depth); valid: (H, W) bool;
            reason: (H, W) uint8 — a :class:`~app.recon.reconstructor.ReconResult`'s arrays.
        test: the test's settings.
        (the rest as :func:`motion_mask`)

    Returns:
        a :class:`MotionPass`.
    """
    t0 = time.perf_counter()
    if not isinstance(test, MotionTest):
        raise ValueError("test: expected a MotionTest")
    steps = _check(frames, n_groups)
    h, w = frames.shape[1:]
    for name, arr, shape, dt in (("depth", depth, (h, w), np.float32),
                                 ("sigma", sigma, (h, w), np.float32),
                                 ("points", points, (h, w, 3), np.float32),
                                 ("valid", valid, (h, w), np.bool_),
                                 ("reason", reason, (h, w), np.uint8)):
        if name == "points" and arr is None:
            continue
        if not isinstance(arr, np.ndarray) or arr.shape != shape or arr.dtype != dt:
            raise ValueError(f"{name}: expected {np.dtype(dt).name} {shape}, got "
                             f"{getattr(arr, 'dtype', type(arr))} {getattr(arr, 'shape', '')}")
    raw, row_any = _raw_mask(frames, n_groups, steps, noise, test.false_alarm_rate,
                             test.window_px, max_code)
    moving = bool(row_any.any())
    strict = np.inf
    if test.gross_error_mm is not None and moving:
        strict = sigma_bounds(test.gross_error_mm, n_groups)[1]
    out = np.empty_like(raw)
    with KERNEL_LOCK:
        n, n_unc = _grow_kernel(raw, row_any, test.grow_px, np.empty_like(raw), out, True, depth,
                                points, valid, reason, sigma, MOTION, _SATURATED,
                                np.float32(strict), _UNCERTAIN)
    return MotionPass(out, int(n), int(n_unc), moving, 1000.0 * (time.perf_counter() - t0))


def group_mid_times(timestamps: list[float] | npt.NDArray[np.float64],
                    n_groups: int) -> npt.NDArray[np.float64]:
    """(G,) mean timestamp of each group's frames (capture-set order), the groups' instants."""
    t = np.asarray(timestamps, np.float64)
    if t.ndim != 1 or t.size % n_groups:
        raise ValueError(f"timestamps: {t.size} do not split into {n_groups} groups")
    mids: npt.NDArray[np.float64] = t.reshape(n_groups, -1).mean(axis=1)
    return mids


def map_time(timestamps: list[float] | npt.NDArray[np.float64], frequencies: tuple[float, ...],
             *, combined: bool) -> float:
    """The instant a depth map stands for, on the timestamps' clock (s).

    The depth comes from the finest frequency's unwrapped phase (the coarser ones only pick
    its fringe order), so the map's instant is the finest group's mid time. With the
    noise-optimal combination (``combined``) each frequency's phase enters with weight
    ∝ k²·B²; for equal modulation that is k², and the instant is the k²-weighted mean of the
    groups' mid times.
    """
    mids = group_mid_times(timestamps, len(frequencies))
    k = np.asarray(frequencies, np.float64)
    if not combined:
        return float(mids[int(np.argmax(k))])
    wts = k * k
    return float((wts * mids).sum() / wts.sum())


__all__ = ["DEFAULT_FALSE_ALARM_RATE", "DEFAULT_GROW_PX", "DEFAULT_WINDOW_PX", "MOTION",
           "PIXEL_BOUND_RATE", "MotionPass", "MotionTest", "chi2_isf", "chi2_sf",
           "group_mid_times", "invalidate_motion", "map_time", "motion_k", "motion_mask",
           "pooled_window_mask", "sigma_bounds", "window_thresholds"]
