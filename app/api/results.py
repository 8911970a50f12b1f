"""Latest results (depth, texture, reasons, point cloud) and reconstruction of uploads."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from app.api.deps import binary, get_instrument, result_headers
from app.api.errors import COMMON, R400, R409, R413, R415, R422
from app.api.schemas import CAPTURE_UPLOAD, PhaseSummary, ReconstructSummary, ResultMeta
from app.api.upload import capture_from_request
from app.outputs import encoding
from app.recon import ReconResult
from app.service.instrument import Instrument
from app.service.phase import decode_capture
from app.service.reconstruction import LiveResult

router = APIRouter(prefix="/api", tags=["results"])
SigmaField = Literal["depth", "sigma", "sigma_noise", "sigma_model"]
FIELD_HELP = ("depth; or sigma: its total 1-σ uncertainty, mm (sensor noise ⊕ calibration), "
              "sigma_noise / sigma_model: its two parts")


def _field(res: LiveResult | ReconResult, field: SigmaField) -> npt.NDArray[np.float32] | None:
    """The map ``field`` names (None: the result has no σ)."""
    if field == "sigma":
        return res.sigma
    if field == "sigma_noise":
        return res.sigma_noise
    if field == "sigma_model":
        return res.sigma_model
    return res.depth


@router.get("/result/latest", response_model=ResultMeta, responses={**R409, **COMMON})
def latest_meta(inst: Instrument = Depends(get_instrument)) -> dict[str, Any]:
    """Provenance of the latest depth map: frames, exposure, LED, mode, latency."""
    return inst.latest_result().metadata()


@router.get(
    "/depth/latest",
    responses={200: {"content": {"application/octet-stream": {}, "image/png": {},
                                 "image/tiff": {}}},
               **R409, **R422, **COMMON},
)
def depth_latest(
    format: Literal["npy", "png", "color", "tiff"] = "npy",
    min_mm: float | None = Query(None, allow_inf_nan=False, description="colour range start, mm. "
                                 "Rule (422 otherwise): min_mm < max_mm"),
    max_mm: float | None = Query(None, allow_inf_nan=False, description="colour range end, mm"),
    field: SigmaField = Query("depth", description=FIELD_HELP),
    inst: Instrument = Depends(get_instrument),
) -> Response:
    """Depth, mm: ``npy`` float32 (NaN invalid), ``png`` 16-bit µm (0 invalid),
    ``color`` turbo + bar.

    ``field=sigma`` gives the per-pixel total 1-σ depth uncertainty (mm; sensor noise ⊕
    calibration), ``sigma_noise`` and ``sigma_model`` its two parts, in the same encodings
    (``color`` defaults to 0–0.1 mm)."""
    res = inst.latest_result()
    headers = result_headers(res.metadata())
    if field != "depth":
        def sig() -> npt.NDArray[np.float32]:
            arr = _field(res, field)
            return arr if arr is not None else np.full_like(res.depth, np.nan)

        name = {"npy": f"{field}.npy", "png": f"{field}_um.png", "tiff": f"{field}.tiff",
                "color": f"{field}_color.png"}[format]
        if format == "npy":
            data = res.cached(f"{field}-npy", lambda: encoding.npy_bytes(sig()))
            return binary(data, "application/octet-stream", headers, name)
        if format == "png":
            data = res.cached(f"{field}-png", lambda: encoding.depth_png_um(sig()))
            return binary(data, "image/png", headers, name)
        if format == "tiff":
            from app.capture.recording import depth_tiff_bytes

            data = res.cached(f"{field}-tiff", lambda: depth_tiff_bytes(sig()))
            return binary(data, "image/tiff", headers, name)
        srng = encoding.check_range_mm(0.0 if min_mm is None else min_mm,
                                       0.1 if max_mm is None else max_mm)
        data = res.cached((f"{field}-color", srng), lambda: encoding.depth_color_png(sig(), srng))
        return binary(data, "image/png", headers, name)
    if format == "npy":
        data = res.cached("npy", lambda: encoding.npy_bytes(res.depth))
        return binary(data, "application/octet-stream", headers, "depth.npy")
    if format == "png":
        data = res.cached("png", lambda: encoding.depth_png_um(res.depth))
        return binary(data, "image/png", headers, "depth_um.png")
    if format == "tiff":  # 32-bit float TIFF, mm, NaN invalid
        from app.capture.recording import depth_tiff_bytes

        data = res.cached("tiff", lambda: depth_tiff_bytes(res.depth))
        return binary(data, "image/tiff", headers, "depth.tiff")
    rng = encoding.check_range_mm(min_mm, max_mm)
    data = res.cached(("color", rng), lambda: encoding.depth_color_png(res.depth, rng))
    return binary(data, "image/png", headers, "depth_color.png")


@router.get("/texture/latest.png",
            responses={200: {"content": {"image/png": {}}}, **R409, **COMMON})
def texture_latest(inst: Instrument = Depends(get_instrument)) -> Response:
    """Texture A + B, 8-bit, scaled by the sensor's full scale."""
    res = inst.latest_result()
    data = res.cached("texture", lambda: encoding.texture_png(res.texture, res.full_scale))
    return binary(data, "image/png", result_headers(res.metadata()), "texture.png")


@router.get("/reason/latest.png", responses={200: {"content": {"image/png": {}}}, **R409, **COMMON})
def reason_latest(inst: Instrument = Depends(get_instrument)) -> Response:
    """Why pixels are invalid, one colour per reason (legend in the
    X-Fringescope-Reasons header)."""
    res = inst.latest_result()
    data = res.cached("reason", lambda: encoding.reason_png(res.reason))
    headers = {**result_headers(res.metadata()), "X-Fringescope-Reasons": encoding.legend_header()}
    return binary(data, "image/png", headers, "reason.png")


@router.get("/reason/legend")
def reason_legend() -> dict[str, Any]:
    return encoding.reason_legend()


@router.get("/pointcloud/latest.ply",
            responses={200: {"content": {"application/octet-stream": {}}}, **R409, **COMMON})
def pointcloud_latest(inst: Instrument = Depends(get_instrument)) -> Response:
    """Valid points (camera frame, mm) with texture intensity and σ (total, noise and
    calibration), binary PLY."""
    res = inst.latest_result()
    data = res.cached("ply", lambda: encoding.ply_bytes(
        res.points, res.valid, res.texture, res.sigma, res.sigma_noise, res.sigma_model))
    return binary(data, "application/octet-stream", result_headers(res.metadata()), "points.ply")


@router.post(
    "/reconstruct",
    response_model=ReconstructSummary,
    responses={200: {"content": {"application/octet-stream": {}}}, **R400, **R409, **R413, **R415,
               **R422, **COMMON},
    openapi_extra=CAPTURE_UPLOAD,
)
async def reconstruct(
    request: Request, format: Literal["json", "npy"] = "json",
    field: SigmaField = Query("depth", description="format=npy: " + FIELD_HELP),
    inst: Instrument = Depends(get_instrument),
) -> Any:
    """Reconstruct an uploaded capture set (capture.json + frame PNGs, or one .zip).

    σ and the validity rule use the camera noise fitted to the set itself (N > 3), the
    nominal sensor where it cannot give it, as the CLI does (``noise_source`` says which)."""
    limit = int(inst.settings.max_upload_mb * 1024 * 1024)
    cal = inst.calibration  # frames of another size are refused before they are decoded
    size = None if cal is None else cal.image_size
    capture = await capture_from_request(request, limit, frame_size=size)
    res = await run_in_threadpool(inst.calibrations.reconstruct, capture)
    if format == "npy":
        data = _field(res, field)
        data = data if data is not None else np.full_like(res.depth, np.nan)
        return binary(encoding.npy_bytes(data), "application/octet-stream", None, f"{field}.npy")
    finite = res.depth[np.isfinite(res.depth)]
    noise = res.noise
    return ReconstructSummary(
        valid_fraction=float(res.valid.mean()),
        height_min_mm=float(finite.min()) if finite.size else None,
        height_max_mm=float(finite.max()) if finite.size else None,
        elapsed_ms=float(res.elapsed_ms),
        shape=list(res.depth.shape),
        noise_source=res.noise_source,
        noise_note=res.noise_note,
        phase_error_source=res.phase_error_source,
        read_noise_dn=noise.read_noise_dn if noise is not None else float("nan"),
        gain_dn_per_e=noise.gain_dn_per_e if noise is not None else float("nan"),
        sigma_median_mm=_median(res.sigma, res.valid),
        sigma_noise_median_mm=_median(res.sigma_noise, res.valid),
        sigma_model_median_mm=_median(res.sigma_model, res.valid),
    )


def _median(values: npt.NDArray[np.float32], valid: npt.NDArray[np.bool_]) -> float | None:
    return float(np.median(values[valid])) if valid.any() else None


@router.post(
    "/phase",
    response_model=PhaseSummary,
    responses={200: {"content": {"application/octet-stream": {}}}, **R400, **R413, **R415, **R422,
               **COMMON},
    openapi_extra=CAPTURE_UPLOAD,
)
async def phase(
    request: Request, format: Literal["json", "npy"] = "json",
    inst: Instrument = Depends(get_instrument)
) -> Any:
    """Unwrapped phase of an uploaded capture set, no calibration needed
    (``format=npy``: phase.npy)."""
    capture = await capture_from_request(request, int(inst.settings.max_upload_mb * 1024 * 1024))
    res = await run_in_threadpool(decode_capture, capture)
    if format == "npy":
        return binary(encoding.npy_bytes(res.phase), "application/octet-stream", None, "phase.npy")
    finite = res.phase[np.isfinite(res.phase)]
    return PhaseSummary(
        valid_fraction=float(np.isfinite(res.phase).mean()),
        phase_min_rad=float(finite.min()) if finite.size else None,
        phase_max_rad=float(finite.max()) if finite.size else None,
        recovered_pixels=res.recovered,
        bit_depth=capture.bit_depth or (8 if capture.frames.dtype == np.uint8 else 16),
        schedule=capture.schedule.to_dict(),
        shape=list(res.phase.shape),
    )
