"""The depth model's own uncertainty per pixel and height, σ_model, in the form the kernel reads.

A calibration's depth model carries the fits with one board pose left out each (its
jackknife; for the geometric model the whole calibration refitted — camera and its lens model,
reference plane, projector —,
:meth:`app.core.depth_model.DepthModel.total_height_deviations`): their spread at a pixel
and height is the 1-σ error the calibration adds to every depth measured there. It changes
slowly over the image and, per pixel, its variance is close to a quartic in the height (each
leave-one-out fit's deviation is nearly quadratic in it: on the twin's calibrations a quadratic
variance missed the jackknife σ by up to 10 µm, the quartic by < 0.1 µm). So the table holds,
per table row (a band of image rows) and image column, the five coefficients of

    σ_model² ≈ Σ_k c_k·x^k,   x = (h − mid)/half   (h the height above the reference plane, mm;
                                                    mid ± half the table's height range),

fitted by least squares to the jackknife variance at heights across the volume, at table
columns every :data:`COLUMN_STEP_PX` and table rows at the middles of :data:`TABLE_ROWS` bands,
interpolated linearly between both (a radial projector lens's rows change with the image row as
much as with the column). A node where the model is undefined (a ray parallel to the plane, a
singular model) makes the σ of its neighbours infinite (:data:`UNDEFINED_VAR_MM2` in the table,
so that the interpolation stays finite). A pixel's total σ is ``√(σ_noise² + σ_model²)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from app.core.calibration import Calibration
from app.recon.points import RayTables

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
TABLE_ROWS = 32  # bands of image rows (interpolated between the bands' middles)
COLUMN_STEP_PX = 16  # table columns, linearly interpolated between
HEIGHT_NODES = 9  # heights over the volume the polynomial is fitted to
DEGREE = 4  # of the polynomial in the height
#: the table's constant term where the model is undefined: finite, so that interpolating toward
#: it stays a number, and any variance beyond :data:`UNDEFINED_BEYOND_MM2` reads as σ = ∞
UNDEFINED_VAR_MM2 = 1e30
UNDEFINED_BEYOND_MM2 = 1e20


@dataclass(frozen=True)
class ModelSigmaTable:
    """σ_model² = Σ_k c_k·x^k, x = (h − mid_mm)·inv_half_mm, per table row and image column.

    Attributes:
        coefs: (R, DEGREE + 1, W) float32 c_k (mm²) of every table row and image column.
        rows: (H,) int64 table row r of every image row; its c_k are those of r and r + 1
            (the last row: itself) weighed (1 − w, w).
        row_weights: (H,) float32 w of every image row.
        mid_mm, inv_half_mm: the height normalisation, mm and 1/mm.
    """

    coefs: F32
    rows: npt.NDArray[np.int64]
    row_weights: F32
    mid_mm: float = 0.0
    inv_half_mm: float = 1.0

    def row_coefs(self) -> F32:
        """(H, DEGREE + 1, W) float32 c_k of every image row, interpolated as the kernel does."""
        nxt = np.minimum(self.rows + 1, self.coefs.shape[0] - 1)
        a, b = self.coefs[self.rows], self.coefs[nxt]
        return np.asarray(a + self.row_weights[:, None, None] * (b - a), np.float32)

    def sigma_mm(self, height_mm: npt.ArrayLike) -> F32:
        """(H, W) float32 σ_model (mm) at the heights ``height_mm`` (H, W) mm; NaN where the
        height is NaN, +inf where the model is undefined."""
        h = np.asarray(height_mm, np.float32)
        if h.shape != (len(self.rows), self.coefs.shape[2]):
            raise ValueError(
                f"height_mm: expected shape {(len(self.rows), self.coefs.shape[2])}, got {h.shape}"
            )
        c = self.row_coefs()  # (H, DEGREE + 1, W)
        x = (h - np.float32(self.mid_mm)) * np.float32(self.inv_half_mm)
        with np.errstate(invalid="ignore", over="ignore"):
            var = c[:, -1]
            for k in range(c.shape[1] - 2, -1, -1):  # Horner, as the kernel
                var = var * x + c[:, k]
            sig = np.where(var >= np.float32(UNDEFINED_BEYOND_MM2), np.float32(np.inf),
                           np.sqrt(np.maximum(var, np.float32(0.0))))
            return np.asarray(sig, np.float32) + np.where(
                np.isnan(h), np.float32(np.nan), np.float32(0.0)
            )


def zero_table(image_size: tuple[int, int]) -> ModelSigmaTable:
    """The table of a model without a known uncertainty: σ_model = 0 everywhere."""
    w, h = (int(x) for x in image_size)
    return ModelSigmaTable(np.zeros((1, DEGREE + 1, w), np.float32), np.zeros(h, np.int64),
                           np.zeros(h, np.float32))


def model_sigma_table(
    calibration: Calibration,
    rays: RayTables,
    height_range_mm: tuple[float, float],
    *,
    table_rows: int = TABLE_ROWS,
    column_step_px: int = COLUMN_STEP_PX,
    height_nodes: int = HEIGHT_NODES,
) -> ModelSigmaTable | None:
    """σ_model of ``calibration``'s depth model for the kernel (module docstring).

    Args:
        calibration: the calibration; its model's jackknife gives the uncertainty.
        rays: the calibration's per-pixel rays (:func:`app.recon.points.calibration_ray_tables`).
        height_range_mm: (lo, hi) heights the polynomial is fitted over, mm (the volume with its
            margin).
        table_rows, column_step_px, height_nodes: the table's resolution (≥ 1, ≥ 1, > DEGREE).

    Returns:
        The table, or None when the model has no jackknife (its uncertainty is unknown).
    """
    lo, hi = (float(x) for x in height_range_mm)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"height_range_mm: need finite lo < hi, got {height_range_mm}")
    if table_rows < 1 or column_step_px < 1 or height_nodes < DEGREE + 1:
        raise ValueError(
            f"table_rows, column_step_px, height_nodes: need >= 1, >= 1, >= {DEGREE + 1}"
        )
    model = calibration.model
    if len(model.jackknife) < 3:
        return None
    w, h = (int(x) for x in calibration.image_size)
    n_rows = min(table_rows, h)
    band_v = np.minimum(((np.arange(n_rows) + 0.5) * h / n_rows).astype(np.int64), h - 1)
    cols = np.unique(np.append(np.arange(0, w, column_step_px), w - 1))
    hs = np.linspace(lo, hi, height_nodes)
    vv, uu, hh = np.meshgrid(band_v, cols, hs, indexing="ij")  # (R, J, K)
    rxy = np.stack(
        [np.asarray(rays.rx, np.float64)[vv, uu], np.asarray(rays.ry, np.float64)[vv, uu]], axis=-1
    )
    d = model.total_height_deviations(
        uu.ravel().astype(np.float64),
        vv.ravel().astype(np.float64),
        rxy.reshape(-1, 2),
        hh.ravel(),
        calibration.reference_plane,
    )
    var = np.sum(d * d, axis=0).reshape(n_rows, len(cols), height_nodes)
    # least squares on the centred, scaled height keeps the fit well conditioned (and float32 exact)
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    vander = np.vander((hs - mid) / half, DEGREE + 1, increasing=True)  # (K, DEGREE + 1)
    finite = np.all(np.isfinite(var), axis=2)
    fit = np.linalg.lstsq(
        vander, np.where(np.isfinite(var), var, 0.0).reshape(-1, height_nodes).T, rcond=None
    )[0].T.reshape(n_rows, len(cols), DEGREE + 1)
    fit[..., 0] = np.where(finite, fit[..., 0], UNDEFINED_VAR_MM2)  # undefined: σ = ∞
    fit[..., 1:] = np.where(finite[..., None], fit[..., 1:], 0.0)
    u_all = np.arange(w, dtype=np.float64)
    table = np.empty((n_rows, DEGREE + 1, w), np.float32)
    for r in range(n_rows):
        for k in range(DEGREE + 1):
            table[r, k] = _interp_inf(u_all, cols, np.asarray(fit[r, :, k], np.float64))
    # image row → (table row, weight of the next): linear between the bands' middle rows
    pos = np.interp(np.arange(h, dtype=np.float64), band_v.astype(np.float64),
                    np.arange(n_rows, dtype=np.float64))
    rows = np.minimum(np.floor(pos).astype(np.int64), n_rows - 1)
    weights = np.asarray(pos - rows, np.float32)
    return ModelSigmaTable(np.ascontiguousarray(table), rows, weights, mid, 1.0 / half)


def _interp_inf(x: F64, xp: F64, fp: F64) -> F64:
    """Linear interpolation where a node is undefined (:data:`UNDEFINED_VAR_MM2`): columns next
    to it are undefined too."""
    bad = fp >= UNDEFINED_VAR_MM2
    out = np.interp(x, xp, np.where(bad, 0.0, fp))
    near = np.interp(x, xp, bad.astype(np.float64)) > 0.0
    return np.where(near, UNDEFINED_VAR_MM2, out)


__all__ = ["ModelSigmaTable", "model_sigma_table", "zero_table"]
