"""Per-pixel motion test between the frequency groups of one fringe set.

For a still scene the background ``A = mean of the N shifted images`` of a frequency group
does not depend on the fringe frequency (the shifts cancel the fringe). Each group's A is
the mean of N frames, so with the camera's noise model ``σ_I² = read² + gain·I``
(:class:`~app.recon.reconstructor.SensorNoise`, DN) its noise is ``σ_A = σ_I/√N`` and the
difference of two groups' A has σ ``√2·σ_A``. A pixel *moved* when the background of some
group differs from the newest group's by more than ``k·√2·σ_A``.

``k`` follows from a stated per-pixel false-alarm rate α (the chance that a still pixel of
one set is flagged): each of the G − 1 older groups is tested against the newest at the
two-sided level α/(G − 1) (Bonferroni), ``k = Φ⁻¹(1 − α / (2(G − 1)))``. The tests share the
newest group, so the true rate is a little below α.

What the test cannot see: pixels with a clipped sample (a clipped sinusoid's mean depends on its
phase, so a still, over-exposed pixel would look moved: they are not tested; the engine refits
them from their unclipped samples), and motion that leaves the background unchanged (a heave of an
evenly lit, untextured surface). Such motion still changes the phase; the engine's
unwrapping consistency test flags it when it breaks the frequency chain.

Motion is spatially coherent and at the rim of a moved region the background change drops
below the threshold while the phase error can still exceed 0.5 mm, so the flagged pixels are
grown by ``grow_px`` (a (2r+1)² square) before they are invalidated. On a still scene the
invalidated fraction is then at most (2r+1)²·α (isolated false alarms grow to squares).

The test is one parallel numba pass over the frames (group sums of a row in a small
buffer), the growth a second pass over the (H, W) mask that invalidates in place in the
engine's output arrays.

**Gross-error bound.** A test in noise units cannot bound a depth error in millimetres: motion
just below the threshold shifts the phase by up to about k·σ_φ (a background drift of
k·√2·σ_A inside the finest group moves its phase by that order), so a pixel's error can reach
(z + k)·σ_z with noise at z σ. Measured on the twin's breathing scene the gross errors
(|error| > 0.5 mm) left by the test are all dark, weakly modulated pixels at 5–7 σ_z, and the
same pixels give gross errors on a STILL scene (noise alone, σ_z up to 0.3 mm). So with a
tolerance E (``gross_error_mm``, 0.5) and a per-pixel rate β (1e-6, z = Φ⁻¹(1 − β/2) = 4.89;
both :mod:`app.recon.validity`'s) a valid pixel needs ``σ_z ≤ E / z`` always (the engine's own
depth-σ rule: a still scene keeps all but its noisiest pixels) and
``σ_z ≤ E / (z + k)`` in a set where the scene moved — more raw flags than a still scene gives
at rate α (:func:`scene_moved`, a one-sided Poisson bound at level α) — with reason UNCERTAIN.
"""

from __future__ import annotations

import math
from statistics import NormalDist
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from numba import njit, prange

from app.core.reasons import Reason
from app.recon.fast import FASTMATH, KERNEL_LOCK
from app.recon.reconstructor import SensorNoise
from app.recon.unwrap import order_test_bound
from app.recon.validity import max_depth_sigma_mm

#: reason code for "moved during the set"
MOTION = int(Reason.MOTION)
_SATURATED = int(Reason.SATURATED)
_UNCERTAIN = int(Reason.UNCERTAIN)

#: default per-pixel false-alarm rate of the motion test on a still scene (per set)
DEFAULT_FALSE_ALARM_RATE = 1e-4
#: moved regions are grown by this many pixels before invalidating: at a region's rim the
#: background change falls below the threshold before the phase change becomes harmless
DEFAULT_GROW_PX = 4


def motion_k(n_groups: int, false_alarm_rate: float = DEFAULT_FALSE_ALARM_RATE) -> float:
    """Threshold in units of the difference's σ for ``n_groups`` groups at a per-pixel rate.

    Args:
        n_groups: frequency groups in a set (G ≥ 2); G − 1 tests are made per pixel.
        false_alarm_rate: α, the per-pixel probability that a still pixel is flagged, in (0, 1).

    Returns:
        ``k = Φ⁻¹(1 − α / (2(G − 1)))`` (Gaussian noise, two-sided, Bonferroni over the tests).
    """
    if int(n_groups) != n_groups or n_groups < 2:
        raise ValueError(f"n_groups: need an integer >= 2, got {n_groups}")
    return order_test_bound(n_groups, false_alarm_rate)  # the same Bonferroni bound as the order test's


def sigma_bounds(gross_error_mm: float, n_groups: int,
                 false_alarm_rate: float = DEFAULT_FALSE_ALARM_RATE) -> tuple[float, float]:
    """Largest 1-σ depth noise (mm) of a valid pixel: (still, moving) for a tolerance E.

    Args:
        gross_error_mm: E > 0, the error a valid pixel may exceed only at the rate β of
            :func:`app.recon.validity.max_depth_sigma_mm`.
        n_groups: frequency groups per set (fixes the motion test's k, :func:`motion_k`).
        false_alarm_rate: the motion test's α.

    Returns:
        ``(E / z, E / (z + k))`` with ``z = Φ⁻¹(1 − β/2)``: noise alone at rate β, and noise plus a
        motion just below the test's threshold (a phase shift of up to k·σ_φ).
    """
    still = max_depth_sigma_mm(gross_error_mm)  # E / z; raises naming gross_error_mm
    z = gross_error_mm / still
    k = motion_k(n_groups, false_alarm_rate)
    return float(still), float(gross_error_mm / (z + k))


def scene_moved(n_flagged: int, n_pixels: int, false_alarm_rate: float = DEFAULT_FALSE_ALARM_RATE) -> bool:
    """Whether ``n_flagged`` raw motion flags among ``n_pixels`` exceed what a still scene gives.

    Still, the count is about Poisson(λ = n·α); it is exceeded at level α when
    ``n_flagged > λ + k·√λ + k²`` with ``k = Φ⁻¹(1 − α)`` (a Gaussian bound widened by k² for
    small λ). A camera noisier than its model raises the count: the stricter bound then holds.
    """
    if n_pixels < 1 or n_flagged < 0:
        raise ValueError(f"n_pixels/n_flagged: need n_pixels >= 1 and n_flagged >= 0, got {n_pixels}, {n_flagged}")
    if not (0.0 < false_alarm_rate < 1.0):
        raise ValueError(f"false_alarm_rate: must be in (0, 1), got {false_alarm_rate}")
    lam = n_pixels * false_alarm_rate
    k = NormalDist().inv_cdf(1.0 - false_alarm_rate)
    return n_flagged > lam + k * math.sqrt(lam) + k * k


_ROWS = 16  # rows per parallel chunk (one scratch allocation per chunk)


@njit(parallel=True, nogil=True, fastmath=FASTMATH, error_model="numpy", cache=True)
def _motion_kernel(frames, n_groups, steps, newest, read2, gain, k2, top_code, mask, row_any, row_tested):  # type: ignore[no-untyped-def]  # pragma: no cover
    """mask[v, u] = some group's background differs from the newest group's beyond k·√2·σ_A, for
    pixels with no sample at ``top_code`` or above (a clipped sample biases its group's mean:
    those are not tested); row_any[v] / row_tested[v] = how many pixels of row v are flagged /
    were tested (int32)."""
    f, h, w = frames.shape
    var_scale = np.float32(2 * steps)  # Var(S_g − S_new) = 2·N·σ_I²(Ā), S = sum of N frames
    half_inv_n = np.float32(0.5 / steps)
    c0 = k2 * var_scale * read2
    c1 = k2 * var_scale * gain * half_inv_n
    n_chunks = (h + _ROWS - 1) // _ROWS
    for chunk in prange(n_chunks):
        sums = np.empty((n_groups, w), np.int32)  # integer group sums of one row: exact
        top = np.empty(w, np.int32)
        for v in range(chunk * _ROWS, min((chunk + 1) * _ROWS, h)):
            for u in range(w):
                top[u] = 0
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
            moved_row = mask[v]
            ref = sums[newest]
            for u in range(w):
                moved_row[u] = False
            for g in range(n_groups):
                if g != newest:
                    row = sums[g]
                    for u in range(w):
                        d = np.float32(row[u] - ref[u])
                        # threshold² = k²·2N·(read² + gain·Ā), Ā = (S_g + S_new)/(2N) ≥ 0
                        moved_row[u] |= d * d > c0 + c1 * np.float32(row[u] + ref[u])
            hits = 0
            tested = 0
            for u in range(w):
                ok = top[u] < top_code
                moved_row[u] &= ok
                hits += moved_row[u]
                tested += ok
            row_any[v] = hits
            row_tested[v] = tested


@njit(nogil=True, fastmath=FASTMATH, error_model="numpy", cache=True)
def _invalidate(depth, sigma, points, valid, reason, v, u, code):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Pixel (v, u) has no depth, for reason ``code``."""
    depth[v, u] = np.nan
    sigma[v, u] = np.nan
    points[v, u, 0] = np.nan
    points[v, u, 1] = np.nan
    points[v, u, 2] = np.nan
    valid[v, u] = False
    reason[v, u] = code


@njit(parallel=True, nogil=True, fastmath=FASTMATH, error_model="numpy", cache=True)
def _grow_kernel(mask, row_any, radius, tmp, out, apply, depth, points, valid, reason,  # type: ignore[no-untyped-def]
                 sigma, motion_code, saturated_code, strict_sigma, uncertain_code):  # pragma: no cover - compiled
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


class MotionPass(NamedTuple):
    """What :func:`invalidate_motion` did: ``mask`` (H, W) bool the grown motion mask, ``moved`` its
    pixel count, ``uncertain`` valid pixels made UNCERTAIN by the moving-scene σ bound,
    ``scene_moved`` whether the raw flags exceeded a still scene's (:func:`scene_moved`)."""

    mask: npt.NDArray[np.bool_]
    moved: int
    uncertain: int
    scene_moved: bool


def _check(frames: npt.NDArray[np.generic], n_groups: int, newest: int) -> tuple[int, int]:
    if not isinstance(frames, np.ndarray) or frames.ndim != 3 or frames.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"frames: expected (F, H, W) uint8/uint16, got {getattr(frames, 'dtype', type(frames))} "
                         f"{getattr(frames, 'shape', '')}")
    f = frames.shape[0]
    if int(n_groups) != n_groups or n_groups < 2 or f % n_groups:
        raise ValueError(f"n_groups: {n_groups} groups do not divide {f} frames (need >= 2)")
    if not -n_groups <= newest < n_groups:
        raise ValueError(f"newest: group index out of range for {n_groups} groups, got {newest}")
    return f // n_groups, newest % n_groups


def motion_mask(
    frames: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
    n_groups: int,
    *,
    noise: SensorNoise,
    newest: int = -1,
    false_alarm_rate: float = DEFAULT_FALSE_ALARM_RATE,
    grow_px: int = 0,
    max_code: int | None = None,
) -> npt.NDArray[np.bool_]:
    """Pixels whose background A differs between a group and the newest group beyond the noise.

    Args:
        frames: (F, H, W) uint8/uint16 in capture-set order, F = n_groups × steps.
        n_groups: frequency groups in the set (consecutive blocks of ``steps`` frames).
        noise: the camera's temporal noise model (DN).
        newest: index (capture-set order) of the group taken last; −1 for a whole set.
        false_alarm_rate: per-pixel false-alarm rate α of the test on a still scene (see :func:`motion_k`).
        grow_px: also flag every pixel within this many pixels (a (2r+1)² square) of a flagged one.
        max_code: the sensor's clipping code (None: the dtype's maximum); a pixel with a sample at
            or above it is not tested (clipping biases a group's mean; the engine's saturation
            refit handles such pixels, and on a still scene they would all look moved).

    Returns:
        (H, W) bool, True where ``|A_g − A_newest| > k·√2·σ_A`` for some group g (then grown).
    """
    steps, newest = _check(frames, n_groups, newest)
    grow = _check_grow(grow_px)
    mask, row_any, _ = _raw_mask(frames, n_groups, steps, newest, noise, false_alarm_rate, max_code)
    if grow == 0:
        return mask
    out = np.empty_like(mask)
    d = np.empty((1, 1), np.float32)
    with KERNEL_LOCK:  # numba's workqueue layer: one parallel launch at a time, process-wide
        _grow_kernel(mask, row_any, grow, np.empty_like(mask), out, False, d, np.empty((1, 1, 3), np.float32),
                     np.empty((1, 1), np.bool_), np.empty((1, 1), np.uint8), d, MOTION, _SATURATED,
                     np.float32(np.inf), _UNCERTAIN)
    return out


def _check_grow(grow_px: int) -> int:
    if int(grow_px) != grow_px or not 0 <= grow_px <= 16:
        raise ValueError(f"grow_px: must be an integer in 0..16, got {grow_px}")
    return int(grow_px)


def _raw_mask(frames: npt.NDArray[np.generic], n_groups: int, steps: int, newest: int, noise: SensorNoise,
              false_alarm_rate: float, max_code: int | None
              ) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.int32], npt.NDArray[np.int32]]:
    if not isinstance(noise, SensorNoise):
        raise ValueError("noise: expected a SensorNoise")
    top = 255 if frames.dtype == np.uint8 else 65535  # _check: uint8 or uint16
    limit = top if max_code is None else int(max_code)
    if not 1 <= limit <= top:
        raise ValueError(f"max_code: must be in 1..{top} for {frames.dtype} frames, got {max_code}")
    k = motion_k(n_groups, false_alarm_rate)
    mask = np.empty(frames.shape[1:], np.bool_)
    row_any = np.empty(frames.shape[1], np.int32)
    row_tested = np.empty(frames.shape[1], np.int32)
    with KERNEL_LOCK:  # numba's workqueue layer: one parallel launch at a time, process-wide
        _motion_kernel(np.ascontiguousarray(frames), n_groups, steps, newest, np.float32(noise.read_noise_dn**2),
                       np.float32(noise.gain_dn_per_e), np.float32(k * k), np.int32(limit), mask, row_any, row_tested)
    return mask, row_any, row_tested


def invalidate_motion(
    frames: npt.NDArray[np.uint8] | npt.NDArray[np.uint16],
    n_groups: int,
    *,
    noise: SensorNoise,
    depth: npt.NDArray[np.float32],
    points: npt.NDArray[np.float32],
    valid: npt.NDArray[np.bool_],
    reason: npt.NDArray[np.uint8],
    sigma: npt.NDArray[np.float32],
    newest: int = -1,
    false_alarm_rate: float = DEFAULT_FALSE_ALARM_RATE,
    grow_px: int = DEFAULT_GROW_PX,
    gross_error_mm: float | None = None,
    max_code: int | None = None,
) -> MotionPass:
    """:func:`motion_mask` (grown by ``grow_px``), then mark those pixels invalid IN PLACE.

    Moved pixels get depth/points/sigma NaN, valid False and reason MOTION, except where the
    engine said SATURATED (the earlier cause, see :mod:`app.core.reasons`). With
    ``gross_error_mm`` E, when the scene moved (:func:`scene_moved` on the raw flags) every other
    valid pixel whose σ exceeds the moving bound of :func:`sigma_bounds` (E / (z + k)) is made
    UNCERTAIN the same way (the still bound E / z is the engine's own validity rule, ``Reconstructor.sigma_limit_mm``).

    Args:
        depth, sigma: (H, W) float32; points: (H, W, 3) float32; valid: (H, W) bool;
            reason: (H, W) uint8 — a :class:`~app.recon.reconstructor.ReconResult`'s arrays.
        (the rest as :func:`motion_mask`)

    Returns:
        a :class:`MotionPass`.
    """
    steps, newest = _check(frames, n_groups, newest)
    grow = _check_grow(grow_px)
    h, w = frames.shape[1:]
    for name, arr, shape, dt in (("depth", depth, (h, w), np.float32), ("sigma", sigma, (h, w), np.float32),
                                 ("points", points, (h, w, 3), np.float32), ("valid", valid, (h, w), np.bool_),
                                 ("reason", reason, (h, w), np.uint8)):
        if not isinstance(arr, np.ndarray) or arr.shape != shape or arr.dtype != dt:
            raise ValueError(f"{name}: expected {np.dtype(dt).name} {shape}, got "
                             f"{getattr(arr, 'dtype', type(arr))} {getattr(arr, 'shape', '')}")
    raw, row_any, row_tested = _raw_mask(frames, n_groups, steps, newest, noise, false_alarm_rate, max_code)
    moving = scene_moved(int(row_any.sum()), max(int(row_tested.sum()), 1), false_alarm_rate)
    strict = np.inf
    if gross_error_mm is not None and moving:
        strict = sigma_bounds(gross_error_mm, n_groups, false_alarm_rate)[1]
    out = np.empty_like(raw)
    with KERNEL_LOCK:
        n, n_unc = _grow_kernel(raw, row_any, grow, np.empty_like(raw), out, True, depth, points, valid, reason,
                                sigma, MOTION, _SATURATED, np.float32(strict), _UNCERTAIN)
    return MotionPass(out, int(n), int(n_unc), moving)


def group_mid_times(timestamps: list[float] | npt.NDArray[np.float64], n_groups: int) -> npt.NDArray[np.float64]:
    """(G,) mean timestamp of each group's frames (capture-set order), the groups' instants."""
    t = np.asarray(timestamps, np.float64)
    if t.ndim != 1 or t.size % n_groups:
        raise ValueError(f"timestamps: {t.size} do not split into {n_groups} groups")
    return t.reshape(n_groups, -1).mean(axis=1)


def map_time(timestamps: list[float] | npt.NDArray[np.float64], frequencies: tuple[float, ...], *,
             combined: bool) -> float:
    """The instant a depth map stands for.

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


def newest_group(frame_indices: list[int], n_groups: int) -> int:
    """Capture-set index of the group holding the frame with the highest counter."""
    if not frame_indices or len(frame_indices) % n_groups:
        raise ValueError(f"frame_indices: {len(frame_indices)} do not split into {n_groups} groups")
    return int(np.argmax(frame_indices)) // (len(frame_indices) // n_groups)


__all__ = ["DEFAULT_FALSE_ALARM_RATE", "DEFAULT_GROW_PX", "MOTION",
           "MotionPass", "group_mid_times", "invalidate_motion", "map_time", "motion_k", "motion_mask", "newest_group",
           "scene_moved", "sigma_bounds"]

