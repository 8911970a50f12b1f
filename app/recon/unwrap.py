"""Temporal phase unwrapping with a consistency check: hierarchical (Le et al. 2018) and heterodyne.

The k = 1 phase is absolute. Each finer frequency k_n takes its fringe order from the
previous unwrapped phase scaled by the frequency ratio:

    e      = (k_n / k_{n−1}) · φ_uw(k_{n−1}) − φ_w(k_n)
    m      = round(e / 2π)
    φ_uw   = φ_w(k_n) + 2π m

With correct orders the residual ``d = e − 2π m`` is pure noise, ≈ (k_n/k_{n−1})·σ_{n−1};
once |d| approaches π the rounding can pick the neighbouring order. A pixel is
*consistent* only if |d| < ``consistency_rad`` at every step. The default π/2 sits
at half the ambiguity distance: for a well-modulated pixel |d| is ≈ 0.1 rad, so the
test rejects only pixels whose noise is already within a factor 2 of an order error
(such pixels are marked invalid, never guessed).

Heterodyne (multi-wavelength) schedules have no single-fringe pattern. Beats of two
wrapped phases, ``wrap(φ_b − φ_a)``, behave like a pattern of ``k_b − k_a`` fringes;
beats of beats shrink further until one spans at most one fringe over the field (it is
absolute). That phase then unwraps, by the same rounding rule and check, the highest
beat of each level down to the finest pattern (Towers et al., Opt. Lett. 28(11) 887,
2003; Reich et al., Opt. Eng. 36(5), 1997). :func:`unwrap_chain` lists the steps as
integer combinations of the wrapped phases; the hierarchical chain is the identity.

The fixed per-step threshold cannot see every wrong order of a heterodyne chain: when the
scene moves between frequency groups the beats shift together and the chain can settle on
an order m fine periods off with every step's residual small. After the chain, every
coarser frequency is therefore tested against the solved finest phase Φ
(:func:`order_residuals_consistent`): ``wrap(φ_k − Φ·k/k_max)`` must be noise within a stated
false-alarm rate, and a pixel whose noise is too large for a slip of any m to show up, even
when motion between the groups (up to a stated bound) moves the residuals, is inconsistent
as well (:func:`order_slip_margin`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from statistics import NormalDist

import numpy as np
import numpy.typing as npt

from app.core.schedule import DEFAULT_UNWRAP

TWO_PI = 2.0 * math.pi
DEFAULT_CONSISTENCY_RAD = 0.5 * math.pi
#: per-pixel false-alarm rate of the heterodyne order test on a still scene
#: (the motion test's default)
DEFAULT_FALSE_ALARM_RATE = 1e-4
#: the heterodyne order test's guard against slips hidden by motion between the frequency groups:
#: none by default (a still capture set); the live instrument guards against a change of the finest
#: phase by up to LIVE_MAX_MOTION_RAD between consecutive groups (1/21 fringe). For [30, 35, 36] the
#: margin is then 0.464 rad (0.276 from 0.47 rad up): wrong orders stay visible for σ(r) ≤ 0.057
#: rad, which keeps 84-87 % of the twin's breathing tissue at rest valid (0.29 at 0.9 rad, 0.94 at
#: 0.2 rad, where slips in dark pixels passed during the breathing benchmark; see order_slip_margin)
DEFAULT_MAX_MOTION_RAD = 0.0
LIVE_MAX_MOTION_RAD = 0.3
#: phase error of every wrapped phase that the sensor noise model does not hold (projector gamma,
#: defocus, mixed pixels), rad, added in quadrature in the heterodyne order test. On the CFPE rig's
#: real captures (12 steps) the residuals' median is 0.01 rad at a predicted σ of 0.0075; the valid
#: share of usable pixels is 98.3 / 99.1 / 99.3 / 99.3 / 99.2 % for
#: 0.01 / 0.015 / 0.02 / 0.025 / 0.03 rad (chain alone 99.4 %), at 4 steps with the gamma table
#: 89.6 / 92.7 / 94.0 / 94.6 / 94.7 % (95.8 %):
#: larger floors use up the margin a wrong order needs to show.
PHASE_FLOOR_RAD = 0.025

F64 = npt.NDArray[np.float64]


def check_consistency_rad(consistency_rad: float) -> float:
    """Validate the unwrapping threshold: 0 < value ≤ π radians."""
    if not (math.isfinite(consistency_rad) and 0.0 < consistency_rad <= math.pi):
        raise ValueError(f"consistency_rad: must be in (0, π], got {consistency_rad}")
    return float(consistency_rad)


def _check_frequencies(frequencies: Sequence[float], n: int, *,
                       first_one: bool = True) -> list[float]:
    freqs = [float(k) for k in frequencies]
    if len(freqs) != n:
        raise ValueError(f"frequencies: {len(freqs)} given for {n} phase maps")
    if not freqs or any(b <= a for a, b in zip(freqs, freqs[1:], strict=False)) or freqs[0] <= 0:
        raise ValueError(f"frequencies: need 0 < k_0 < k_1 < ..., got {freqs}")
    if first_one and freqs[0] != 1:
        raise ValueError(f"frequencies: need 1 = k_0 < k_1 < ..., got {freqs}")
    return freqs


def unwrap_chain(frequencies: Sequence[float], method: str = DEFAULT_UNWRAP) -> tuple[F64, F64]:
    """The unwrapping steps of a schedule as combinations of its wrapped phases.

    Args:
        frequencies: the K fringe counts, increasing.
        method: ``"hierarchical"`` (k_0 = 1; the chain is the identity) or
            ``"heterodyne"`` (K ≥ 3; beats of neighbouring frequencies, level by level).

    Returns:
        ``(coefs, freqs)``: (S, K) float64 integer coefficients and (S,) fringe counts;
        step ``s`` is the phase ``wrap(coefs[s] · φ_w)`` of ``freqs[s]`` fringes. Step 0
        spans at most one fringe (absolute); the last is the finest pattern itself.
    """
    if method == "hierarchical":
        freqs = _check_frequencies(frequencies, len(frequencies))
        return np.eye(len(freqs)), np.asarray(freqs)
    if method != "heterodyne":
        raise ValueError(f"unwrap: must be 'hierarchical' or 'heterodyne', got {method!r}")
    freqs = _check_frequencies(frequencies, len(frequencies), first_one=False)
    n = len(freqs)
    if n < 3:
        raise ValueError(f"frequencies: heterodyne unwrapping needs at least 3, got {n}")
    level = [(f, np.eye(n)[i]) for i, f in enumerate(freqs)]
    tops = [level[-1]]
    while level[0][0] > 1.0 + 1e-9:
        if len(level) < 2:
            raise ValueError(f"frequencies: {freqs} beat down to {level[0][0]:.4g} fringes, "
                             "not <= 1 (not absolute)")
        beats = []
        for (fa, ca), (fb, cb) in zip(level, level[1:], strict=False):
            beats.append((fb - fa, cb - ca) if fb >= fa else (fa - fb, ca - cb))
        level = sorted(beats, key=lambda b: b[0])
        if level[0][0] < 1e-6:
            raise ValueError(f"frequencies: {freqs} give a zero beat (two equal differences)")
        tops.append(level[-1])
    steps = [level[0], *([] if len(level) == 1 else tops[-1:]), *reversed(tops[:-1])]
    return np.stack([c for _, c in steps]), np.asarray([f for f, _ in steps])


def unwrap_phases(
    wrapped: npt.ArrayLike,
    frequencies: Sequence[float],
    method: str = DEFAULT_UNWRAP,
    *,
    consistency_rad: float = DEFAULT_CONSISTENCY_RAD,
    phase_var: npt.ArrayLike | None = None,
    false_alarm_rate: float = DEFAULT_FALSE_ALARM_RATE,
    max_motion_rad: float = DEFAULT_MAX_MOTION_RAD,
) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Unwrap every frequency, hierarchically or by heterodyne beats (see :func:`unwrap_chain`).

    Args:
        wrapped: (K, H, W) wrapped phases in [0, 2π), radians.
        frequencies: the K fringe counts, increasing.
        method: ``"hierarchical"`` or ``"heterodyne"``.
        consistency_rad: largest accepted |residual − rounded residual| at every step, (0, π].
        phase_var: (K, H, W) variance of each wrapped phase, rad² (the sensor noise through
            the modulation). Heterodyne only: with it, the chain's finest phase must also pass
            :func:`order_residuals_consistent` (None: not tested).
        false_alarm_rate: α of that test, (0, 1), and
        max_motion_rad: the motion between groups it guards against (:func:`order_slip_margin`).

    Returns:
        ``(unwrapped, consistent)`` as :func:`unwrap_hierarchical`. For heterodyne, the
        finest phase comes from the chain and every other from it by the frequency ratio;
        a pixel is also inconsistent when its absolute beat phase lies outside the field,
        [−s, 2π·f0 + s] with s = ``consistency_rad``·f0/f1, or fails the order test.
    """
    wrapped = np.asarray(wrapped, dtype=np.float64)
    if wrapped.ndim != 3:
        raise ValueError(f"wrapped: expected shape (K, H, W), got {wrapped.shape}")
    if method == "hierarchical":
        return unwrap_hierarchical(wrapped, frequencies, consistency_rad=consistency_rad)
    coefs, steps = unwrap_chain(frequencies, method)
    if len(frequencies) != wrapped.shape[0]:
        raise ValueError(f"frequencies: {len(frequencies)} given for {wrapped.shape[0]} phase maps")
    threshold = check_consistency_rad(consistency_rad)
    prev = absolute_phase(np.mod(np.tensordot(coefs[0], wrapped, axes=1), TWO_PI), steps[0])
    # the absolute beat covers 2π·f0 of the circle; beyond it (by more than the first step
    # tolerates) lies no point of the field: noise, not fringes
    slack = threshold * steps[0] / steps[1]
    consistent = (prev >= -slack) & (prev <= TWO_PI * steps[0] + slack)
    for s in range(1, len(steps)):
        phw = np.mod(np.tensordot(coefs[s], wrapped, axes=1), TWO_PI)
        e = (steps[s] / steps[s - 1]) * prev - phw
        order = np.floor(e / TWO_PI + 0.5)
        consistent &= np.abs(e - TWO_PI * order) < threshold
        prev = phw + TWO_PI * order
    freqs = np.asarray(frequencies, dtype=np.float64)
    if phase_var is not None:
        consistent &= order_residuals_consistent(wrapped, prev, phase_var, frequencies,
                                                 false_alarm_rate, max_motion_rad)
    out = np.empty_like(wrapped)
    for i in range(len(freqs) - 1):
        e = (freqs[i] / freqs[-1]) * prev - wrapped[i]
        out[i] = wrapped[i] + TWO_PI * np.floor(e / TWO_PI + 0.5)
    out[-1] = prev
    return out, consistent


def order_test_bound(n_frequencies: int,
                     false_alarm_rate: float = DEFAULT_FALSE_ALARM_RATE) -> float:
    """z of the order test: ``Φ⁻¹(1 − α / (2(K − 1)))`` (two-sided, Bonferroni over K − 1 tests)."""
    if int(n_frequencies) != n_frequencies or n_frequencies < 2:
        raise ValueError(f"n_frequencies: need an integer >= 2, got {n_frequencies}")
    if not (0.0 < false_alarm_rate < 1.0):
        raise ValueError(f"false_alarm_rate: must be in (0, 1), got {false_alarm_rate}")
    return float(NormalDist().inv_cdf(1.0 - false_alarm_rate / (2.0 * (n_frequencies - 1))))


def _slip_points(freqs: list[float], max_motion_rad: float) -> F64:
    """|residual displacement| of every slip m, motion direction and sampled ρ (see
    :func:`order_slip_front`), (N, K − 1), less the sampling step's bound
    (never above the truth)."""
    if not (math.isfinite(max_motion_rad) and max_motion_rad >= 0.0):
        raise ValueError(f"max_motion_rad: must be finite and >= 0, got {max_motion_rad}")
    k = np.asarray(freqs, dtype=np.float64)
    n = len(k)
    m = np.arange(1, max(2, math.ceil(k[-1])), dtype=np.float64)
    m = np.concatenate([m, -m])[:, None, None]
    d = -TWO_PI * m * k[None, None, :-1] / k[-1]
    if max_motion_rad == 0.0:
        x: F64 = d[:, 0, :]
        return np.abs(x - TWO_PI * np.floor(x / TWO_PI + 0.5))
    n_rho = 2001
    rho = np.linspace(-max_motion_rad, max_motion_rad, n_rho)[None, :, None]
    out = []
    for newest in range(n):
        place = {(newest + 1 + i) % n: i for i in range(n)}  # group -> its place, oldest first
        mu = np.array([k[g] / k[-1] * (place[g] - place[n - 1]) for g in range(n - 1)])
        x = d + rho * mu[None, None, :]
        step_rad = 2.0 * max_motion_rad / (n_rho - 1)
        r = np.abs(x - TWO_PI * np.floor(x / TWO_PI + 0.5)) - 0.5 * np.abs(mu) * step_rad
        out.append(np.maximum(r, 0.0).reshape(-1, n - 1))
    return np.concatenate(out)


def order_slip_front(
    frequencies: Sequence[float], max_motion_rad: float = DEFAULT_MAX_MOTION_RAD,
    max_points: int = 8
) -> F64:
    """The smallest residual displacements a wrong fringe order can leave, per coarser frequency.

    A finest phase Φ off by m whole periods (|m| < k_max: the field) predicts ``φ_k = Φ·k/k_max``
    off by ``d_k(m) = wrap(−2π·m·k/k_max)`` (wrapped to [−π, π)). When the scene moves between
    the frequency groups, group k sees the finest phase changed by ρ·(t_k − t_K) (ρ: change
    per group interval, t: the group's place in the set), which adds ``ρ·μ_k``,
    ``μ_k = (k/k_max)·(t_k − t_K)``; the groups of a set are a cyclic order of the schedule's
    (whole sets: frequency order; rolling: any rotation), so there are K directions μ. The
    rows returned are the Pareto-minimal vectors ``|wrap(d(m) + ρ·μ)|`` over every m, direction
    and |ρ| ≤ ``max_motion_rad``: every wrong order moves the residuals at least as far as one
    of them in every frequency. Beyond ``max_points`` rows, the neighbours whose merge loses the
    least are merged into their componentwise minimum (a stricter, never a looser, row).

    For [30, 35, 36] and no motion: m = ±1 gives (2π/6, 2π/36) = (1.047, 0.175) rad (φ_35
    hardly moves, φ_30 by a sixth of a turn) and m = ±6 gives (0, 2π/6) (φ_30 back on its own
    fringe); every other m is dominated by these two. Motion can cancel part of a slip (see
    :func:`order_slip_margin`).

    Args:
        frequencies: the K ≥ 2 fringe counts, increasing.
        max_motion_rad: the largest change of the finest phase between consecutive groups, ≥ 0.
        max_points: at most this many rows, ≥ 1.

    Returns:
        (P, K − 1) float64 rad, sorted by the first column.
    """
    freqs = _check_frequencies(frequencies, len(frequencies), first_one=False)
    if int(max_points) != max_points or max_points < 1:
        raise ValueError(f"max_points: need an integer >= 1, got {max_points}")
    grid = 0.005  # rad: rounded down (never looser), so the staircase has few steps
    pts = np.floor(_slip_points(freqs, max_motion_rad) / grid + 1e-6) * grid
    if pts.shape[1] == 1:
        front = pts[[np.argmin(pts[:, 0])]]
    # a staircase: by the first coordinate, keep each new minimum of the second
    elif pts.shape[1] == 2:
        order = np.lexsort((pts[:, 1], pts[:, 0]))
        p = pts[order]
        run_min = np.minimum.accumulate(p[:, 1])
        keep = np.concatenate([[True], p[1:, 1] < run_min[:-1]])
        front = p[keep]
    else:  # more dimensions: the Chebyshev margin on every axis (stricter than the front)
        front = np.full((1, pts.shape[1]), pts.max(axis=1).min())
    rows = [tuple(r) for r in front]
    # merge the neighbours (by the first coordinate) that lose the least
    while len(rows) > max_points:
        cost = [np.prod(np.abs(np.subtract(rows[i + 1], rows[i]))) for i in range(len(rows) - 1)]
        i = int(np.argmin(cost))
        rows[i:i + 2] = [tuple(np.minimum(rows[i], rows[i + 1]))]
    return np.asarray(rows, dtype=np.float64)


def order_slip_margin(frequencies: Sequence[float],
                      max_motion_rad: float = DEFAULT_MAX_MOTION_RAD) -> float:
    """How close to 0 a wrong order can bring the residuals (Chebyshev norm, all frequencies), rad:
    the smallest ``max_k |wrap(d_k(m) + ρ·μ_k)|`` of :func:`order_slip_front`'s vectors.

    For [30, 35, 36]: 2π/6 = 1.047 rad with no motion, 0.46 for |ρ| ≤ 0.3 rad per group
    interval, and 0.276 for every bound from 0.47 to 0.9 rad (m = ∓35 ≡ ±1 with ρ = ∓0.46 in
    the rolling order newest-30: the motion cancels most of φ_30's slip); above 0.9 it falls
    fast (0.05 at 1.2 rad: with unbounded motion a heterodyne set cannot tell its orders
    apart, whatever its noise).
    """
    freqs = _check_frequencies(frequencies, len(frequencies), first_one=False)
    return float(_slip_points(freqs, max_motion_rad).max(axis=1).min())


def order_residuals_consistent(
    wrapped: npt.ArrayLike,
    finest: npt.ArrayLike,
    phase_var: npt.ArrayLike,
    frequencies: Sequence[float],
    false_alarm_rate: float = DEFAULT_FALSE_ALARM_RATE,
    max_motion_rad: float = DEFAULT_MAX_MOTION_RAD,
) -> npt.NDArray[np.bool_]:
    """Noise-aware test of a heterodyne chain's fringe order, per pixel.

    Every coarser frequency's measured wrapped phase must agree with the one the solved
    finest phase Φ predicts: ``r_k = wrap(φ_k − Φ·k/k_max)``, whose noise (independent
    phases) has variance ``v_k = var φ_k + (k/k_max)²·var φ_K``, each var φ with the unmodelled
    error :data:`PHASE_FLOOR_RAD` added in quadrature. With z from
    :func:`order_test_bound`, a pixel passes when ``|r_k| ≤ z·√v_k`` for every k < K: on a
    still scene (Gaussian phase noise) it fails with probability ≤ α.

    A wrong order (with motion between the groups up to ``max_motion_rad``) moves the
    residuals by at least one row q of :func:`order_slip_front` in every frequency. A pixel is
    also inconsistent unless, for every row, some frequency has ``q_k ≥ 2z·√v_k``: then a slip
    lands at least z·σ beyond the bound there and is missed with probability ≤ α/(2(K − 1)).
    For [30, 35, 36] and α = 1e-4 (z = 4.06), without motion: σ(r_35) ≤ (π/3)/(2z) = 0.129 rad,
    and σ(r_30) ≤ 0.129 rad or σ(r_35) ≤ 0.021 rad; with 0.3 rad between groups (the live
    instrument's) every σ(r_k) ≤ 0.057 rad suffices (:func:`order_slip_margin`: 0.464 rad).

    Args:
        wrapped: (K, H, W) wrapped phases, radians.
        finest: (H, W) unwrapped finest phase Φ, radians.
        phase_var: (K, H, W) variance of each wrapped phase, rad² (inf/NaN: fails).
        frequencies: the K fringe counts, increasing.
        false_alarm_rate: α, (0, 1).
        max_motion_rad: the motion between groups guarded against, rad (:func:`order_slip_margin`).

    Returns:
        (H, W) bool: the order is confirmed.
    """
    wrapped = np.asarray(wrapped, dtype=np.float64)
    var = np.asarray(phase_var, dtype=np.float64)
    phi = np.asarray(finest, dtype=np.float64)
    if wrapped.ndim != 3 or var.shape != wrapped.shape:
        raise ValueError(f"phase_var: shape {var.shape} must equal wrapped shape {wrapped.shape}")
    if phi.shape != wrapped.shape[1:]:
        raise ValueError(f"finest: shape {phi.shape} must be {wrapped.shape[1:]}")
    freqs = _check_frequencies(frequencies, wrapped.shape[0], first_one=False)
    k = np.asarray(freqs)
    z = order_test_bound(len(k), false_alarm_rate)
    front = order_slip_front(freqs, max_motion_rad)
    ok = np.ones(phi.shape, dtype=bool)
    v = []
    for i in range(len(k) - 1):
        ratio = k[i] / k[-1]
        x = wrapped[i] - ratio * phi
        r = x - TWO_PI * np.floor(x / TWO_PI + 0.5)
        vi = var[i] + ratio**2 * var[-1] + PHASE_FLOOR_RAD**2 * (1.0 + ratio**2)
        with np.errstate(invalid="ignore"):
            ok &= r * r <= z * z * vi
        v.append(vi)
    for q in front:
        seen = np.zeros(phi.shape, dtype=bool)
        for i, vi in enumerate(v):
            with np.errstate(invalid="ignore"):
                seen |= q[i] * q[i] >= 4.0 * z * z * vi
        ok &= seen
    return ok


def absolute_phase(wrapped: npt.ArrayLike, fringes: float) -> F64:
    """The phase of a pattern of ``fringes`` ≤ 1 over the field: values in the unused part of
    the circle (beyond 2π·fringes, from noise at the field's start) are moved below 0 by
    splitting that gap in half. For one fringe the phase is returned unchanged."""
    wrapped = np.asarray(wrapped, dtype=np.float64)
    return np.where(wrapped > math.pi * (1.0 + fringes), wrapped - TWO_PI, wrapped)


def unwrap_hierarchical(
    wrapped: npt.ArrayLike,
    frequencies: Sequence[float],
    *,
    consistency_rad: float = DEFAULT_CONSISTENCY_RAD,
) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Unwrap every frequency hierarchically.

    Args:
        wrapped: (K, H, W) wrapped phases, radians; ``wrapped[0]`` (k = 1) in [0, 2π).
        frequencies: the K fringe counts, ``frequencies[0] == 1``, increasing.
        consistency_rad: largest accepted |residual − rounded residual|, radians, (0, π].

    Returns:
        ``(unwrapped, consistent)``: (K, H, W) float64 absolute phases
        (``unwrapped[i] ≈ 2π k_i x / w``) and an (H, W) bool mask of pixels whose every
        rounding step passed the check.
    """
    wrapped = np.asarray(wrapped, dtype=np.float64)
    if wrapped.ndim != 3:
        raise ValueError(f"wrapped: expected shape (K, H, W), got {wrapped.shape}")
    freqs = _check_frequencies(frequencies, wrapped.shape[0])
    threshold = check_consistency_rad(consistency_rad)
    out = np.empty_like(wrapped)
    out[0] = wrapped[0]
    consistent = np.ones(wrapped.shape[1:], dtype=bool)
    for i in range(1, len(freqs)):
        e = (freqs[i] / freqs[i - 1]) * out[i - 1] - wrapped[i]
        order = np.floor(e / TWO_PI + 0.5)  # round half up, the same rule as the fast path
        consistent &= np.abs(e - TWO_PI * order) < threshold
        out[i] = wrapped[i] + TWO_PI * order
    return out, consistent


def combine_frequencies(
    unwrapped: npt.ArrayLike, modulation: npt.ArrayLike, frequencies: Sequence[float], steps: int
) -> F64:
    """Noise-optimal phase from all frequencies, in the finest frequency's units.

    Each unwrapped map estimates the finest phase as ``(k_max/k_i)·φ_i`` with variance
    ∝ (k_max/k_i)² / (N·B_i²); inverse-variance weighting gives weights ∝ N·B_i²·k_i².

    Args:
        unwrapped: (K, H, W) absolute phases, radians.
        modulation: (K, H, W) modulation B per frequency, codes.
        frequencies: the K fringe counts.
        steps: phase shifts N per frequency.

    Returns:
        (H, W) float64 phase of the finest frequency, radians (NaN where all B are 0).
    """
    phi = np.asarray(unwrapped, dtype=np.float64)
    mod = np.asarray(modulation, dtype=np.float64)
    if phi.ndim != 3 or mod.shape != phi.shape:
        raise ValueError(f"modulation: shape {mod.shape} must equal unwrapped shape {phi.shape}")
    freqs = _check_frequencies(frequencies, phi.shape[0], first_one=False)
    k = np.asarray(freqs, dtype=np.float64)[:, None, None]
    weight = steps * mod**2 * k**2
    wsum = weight.sum(axis=0)
    est = (weight * (k[-1] / k) * phi).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(wsum > 0.0, est / np.where(wsum > 0.0, wsum, 1.0), np.nan)
