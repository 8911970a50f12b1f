"""3-D measurements (issue 17) on the latest result or on a recorded set, delegating to
:mod:`app.analysis.measure`; bad clicks become ``InvalidRequest`` (HTTP 422) with one line.

Live maps have holes (pixels the motion test or the validity rule took out), so the service
measures through them: an area fills them, a length's or profile's click in a hole too wide
to snap across is filled from the valid points around it (``fill_holes``); each answer
carries its ``coverage``, and only one below ``MIN_COVERAGE`` (50 %) is refused."""

from __future__ import annotations

import math
import time
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from app.analysis.measure import MIN_COVERAGE, measure
from app.core.calibration import Calibration
from app.core.errors import InvalidRequest


class MeasurableResult(Protocol):
    """What a measurement reads of a result (``LiveResult`` and ``ReconResult`` both have it)."""

    @property
    def points(self) -> npt.NDArray[np.float32]: ...
    @property
    def valid(self) -> npt.NDArray[np.bool_]: ...
    @property
    def reason(self) -> npt.NDArray[np.uint8]: ...
    @property
    def sigma(self) -> npt.NDArray[np.float32] | None: ...
    @property
    def sigma_noise(self) -> npt.NDArray[np.float32] | None: ...


def _noise_sigma(result: MeasurableResult) -> npt.NDArray[np.float32] | None:
    """The independent (sensor-noise) part of the result's σ: the calibration's part is shared
    between points and enters a measurement through its own covariance."""
    sigma = result.sigma_noise if result.sigma is not None and result.sigma.size else None
    return sigma if sigma is not None and sigma.size else None


def _nonneg(x: Any) -> float | None:
    return float(x) if isinstance(x, int | float) and math.isfinite(x) and x >= 0 else None


def calibration_terms(cal: Any) -> tuple[npt.NDArray[np.float64] | None, float, float]:
    """(reference-plane normal, calibration σ in mm, its correlation length in mm) of a
    calibration (None: (None, 0, 0)).

    σ is the active depth model's systematic held-out height error per point and the length
    its correlation length (``held_out[model]["systematic_mm"]``, ``["correlation_mm"]``:
    :func:`app.calib.fitting.error_structure`, which takes the board points' own noise out).
    A file from before that split gives its held-out RMS, independent between points (an
    upper bound: it includes the board points' noise); 0 when the file has neither.
    """
    if cal is None:
        return None, 0.0, 0.0
    held = (getattr(cal, "held_out", None) or {}).get(getattr(cal.model, "name", ""), {})
    normal = np.asarray(cal.plane_normal, np.float64)
    sys_mm, length_mm = _nonneg(held.get("systematic_mm")), _nonneg(held.get("correlation_mm"))
    if sys_mm is not None and length_mm is not None:
        return normal, sys_mm, length_mm
    return normal, _nonneg(held.get("rms_mm")) or 0.0, 0.0


def measure_result(result: MeasurableResult, spec: dict[str, Any],
                   plane_normal: npt.ArrayLike | None = None, calibration_sigma_mm: float = 0.0,
                   calibration_length_mm: float = 0.0,
                   calibration: Calibration | None = None) -> dict[str, Any]:
    """One measurement (``spec``: kind, points, optional reference and snap_px) as a JSON-able dict.

    ``plane_normal`` is the calibration's reference-plane normal (the direction of the
    per-pixel height noise); None takes the optical axis. ``calibration_sigma_mm`` and
    ``calibration_length_mm``: see :func:`calibration_terms`; ``calibration``: its depth
    model's own uncertainty, correlated between the points (replaces the two when it has one).
    """
    t0 = time.perf_counter()
    sigma = _noise_sigma(result)
    try:
        m = measure(spec["kind"], result.points, result.valid, sigma, spec["points"],
                    reference=spec.get("reference"), snap_px=float(spec.get("snap_px", 3.0)),
                    plane_normal=plane_normal, reason=result.reason,
                    calibration_sigma_mm=calibration_sigma_mm,
                    calibration_length_mm=calibration_length_mm, calibration=calibration,
                    fill_holes=True)
    except ValueError as exc:  # the clicks (the only user input) do not fit this result
        raise InvalidRequest(f"{spec['kind']}: {exc}"
                             if not str(exc).startswith(spec["kind"]) else str(exc)) from None
    out = m.to_dict()
    out["coverage"] = m.extra.get("coverage", 1.0)
    out["min_coverage"] = MIN_COVERAGE
    out["elapsed_ms"] = round(1e3 * (time.perf_counter() - t0), 3)
    return out


def summary(measured: dict[str, Any]) -> dict[str, Any]:
    """The compact form kept in a recording's metadata (no profile samples)."""
    keep = ("kind", "value_mm", "sigma_mm", "unit", "snapped", "coverage")
    out = {k: measured[k] for k in keep}
    out["sigma_noise_mm"] = measured["extra"].get("sigma_noise_mm")
    out["pixels"] = [p["pixel"] for p in measured["points"]]
    return out


def measure_specs(result: MeasurableResult, specs: list[dict[str, Any]],
                  plane_normal: npt.ArrayLike | None = None, calibration_sigma_mm: float = 0.0,
                  calibration_length_mm: float = 0.0) -> list[dict[str, Any]]:
    """Every spec measured on ``result`` (compact); one that does not fit says why in ``error``."""
    out: list[dict[str, Any]] = []
    for spec in specs:
        try:
            out.append(summary(measure_result(result, spec, plane_normal, calibration_sigma_mm,
                                                  calibration_length_mm)))
        except InvalidRequest as exc:
            out.append({"kind": spec.get("kind"), "pixels": spec.get("points"),
                        "error": exc.detail})
    return out


def measurement_segments(result: MeasurableResult, specs: list[dict[str, Any]],
                         plane_normal: npt.ArrayLike | None = None,
                         calibration_sigma_mm: float = 0.0,
                         calibration_length_mm: float = 0.0
                         ) -> tuple[npt.NDArray[np.float32],
                                    list[tuple[npt.NDArray[np.float32], str]]]:
    """What the 3-D view draws for ``specs`` on ``result``: line segments and
    labels, camera frame, mm.

    Returns (segments (N, 2, 3) float32, [(label position (3,), "value ± σ unit"), …]); a
    spec that does not fit the result draws nothing.
    """
    from app.analysis.measure import measure as measure_fn

    segs: list[tuple[Any, Any]] = []
    labels: list[tuple[npt.NDArray[np.float32], str]] = []
    sigma = _noise_sigma(result)
    for spec in specs:
        try:
            m = measure_fn(spec["kind"], result.points, result.valid, sigma, spec["points"],
                           reference=spec.get("reference"), snap_px=float(spec.get("snap_px", 3.0)),
                           plane_normal=plane_normal, calibration_sigma_mm=calibration_sigma_mm,
                           calibration_length_mm=calibration_length_mm, fill_holes=True)
        except (ValueError, KeyError):
            continue
        p = np.array([q.point_mm for q in m.points], np.float64)
        kind = m.kind
        if kind == "length":
            segs.append((p[0], p[1]))
        elif kind == "point_to_line":
            d = (p[2] - p[1]) / np.linalg.norm(p[2] - p[1])
            foot = p[1] + ((p[0] - p[1]) @ d) * d
            segs += [(p[1], p[2]), (p[0], foot)]
        elif kind == "depth":
            n = np.cross(p[2] - p[1], p[3] - p[1])
            n /= np.linalg.norm(n)
            segs += [(p[1], p[2]), (p[2], p[3]), (p[3], p[1]),
                     (p[0], p[0] - ((p[0] - p[1]) @ n) * n)]
        elif kind == "area":  # a vertex in a hole has no point: its two edges are not drawn
            segs += [(p[i], p[(i + 1) % len(p)]) for i in range(len(p))
                     if np.isfinite(p[i]).all() and np.isfinite(p[(i + 1) % len(p)]).all()]
        elif kind == "profile" and m.profile is not None:
            uv = m.profile.pixels
            ok = np.isfinite(m.profile.height_mm)
            pts = np.asarray(result.points[uv[:, 1], uv[:, 0]], np.float64)
            segs += [(pts[i], pts[i + 1]) for i in range(len(pts) - 1) if ok[i] and ok[i + 1]]
        unit = "mm²" if kind == "area" else "mm"
        sig = "?" if not np.isfinite(m.sigma_mm) else f"{m.sigma_mm:.3f}"
        drawn = p[np.isfinite(p).all(axis=1)]
        if len(drawn):
            labels.append((drawn.mean(axis=0).astype(np.float32),
                           f"{m.value_mm:.3f} ± {sig} {unit}"))
    arr = np.array(segs, np.float32).reshape(-1, 2, 3)
    return arr, labels
