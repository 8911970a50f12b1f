"""The depth models a calibration file may name, by name.

The factory sits above the contract (:mod:`app.core.depth_model`) and its
implementations so that the contract never imports its own subclasses.
"""

from __future__ import annotations

import math
from typing import Any

from app.core.depth_model import DepthModel, SupportedRegion
from app.core.eq5 import Eq5Model
from app.core.geometric import GeometricModel, PipelineFit

#: every depth model by the ``name`` it carries in a calibration file
DEPTH_MODELS: dict[str, type[DepthModel]] = {
    Eq5Model.name: Eq5Model, GeometricModel.name: GeometricModel,
}
MODEL_NAMES = tuple(DEPTH_MODELS)


def depth_model_from_dict(data: Any) -> DepthModel:
    """Parse a ``model`` object of a version-2 calibration file."""
    if not isinstance(data, dict):
        raise ValueError("model: expected an object")
    name = data.get("name")
    if name not in DEPTH_MODELS:
        raise ValueError(f"model: unknown name {name!r} (expected one of {list(DEPTH_MODELS)})")
    region = SupportedRegion.from_dict(data.get("supported_region"))
    kind = DEPTH_MODELS[name]
    model = kind.from_params(data, region)
    jack = data.get("jackknife", [])
    alt = data.get("alternative")
    if not isinstance(jack, list) or not all(isinstance(p, dict) for p in jack):
        raise ValueError("model.jackknife: expected a list of objects")
    if alt is not None and not isinstance(alt, dict):
        raise ValueError("model.alternative: expected an object")
    weight = data.get("alternative_weight", 1.0)
    if (isinstance(weight, bool) or not isinstance(weight, int | float)
            or not 0.0 <= float(weight) <= 1.0):
        raise ValueError("model.alternative_weight: expected a number in 0..1")
    try:
        model.jackknife = [kind.from_params(p, SupportedRegion()) for p in jack]
        model.alternative = None if alt is None else kind.from_params(alt, SupportedRegion())
    except ValueError as exc:
        raise ValueError(f"model.jackknife: {exc}") from None
    model.alternative_weight = float(weight)
    pipeline = data.get("pipeline_jackknife", [])
    if not isinstance(pipeline, list):
        raise ValueError("model.pipeline_jackknife: expected a list of objects")
    if pipeline and not isinstance(model, GeometricModel):
        raise ValueError("model.pipeline_jackknife: only the geometric model carries one")
    lens = data.get("lens_alternative")
    if lens is not None and not isinstance(model, GeometricModel):
        raise ValueError("model.lens_alternative: only the geometric model carries one")
    if isinstance(model, GeometricModel):
        try:
            model.pipeline = [PipelineFit.from_dict(p) for p in pipeline]
            model.lens_alternative = None if lens is None else PipelineFit.from_dict(lens)
            model.lens_verified_px = _ellipse("lens_verified_px", data.get("lens_verified_px"))
        except ValueError as exc:
            raise ValueError(f"model.{exc}") from None
    return model


def _ellipse(name: str, value: Any) -> tuple[float, float, float, float] | None:
    """(cx, cy, rx, ry) px from a list of 4 finite numbers with rx, ry > 0 (None stays None)."""
    if value is None:
        return None
    try:
        cx, cy, rx, ry = (float(x) for x in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected 4 numbers (cx, cy, rx, ry)") from None
    if not all(math.isfinite(x) for x in (cx, cy, rx, ry)) or rx <= 0 or ry <= 0:
        raise ValueError(f"{name}: expected 4 finite numbers, rx, ry > 0")
    return cx, cy, rx, ry
