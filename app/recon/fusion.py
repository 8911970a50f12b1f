"""Exposure bracketing: one depth map from sets of one scene taken at different exposures.

A scene can span more light than one exposure holds. A white drape next to a grey organ, or a
surface lit at grazing incidence beside one lit face-on, are examples. The exposure that keeps
the bright parts unsaturated leaves the dim ones with too little modulation for the validity
rule. A longer exposure measures the dim parts and clips the bright ones. The high-dynamic-range
fringe technique takes each pixel from the exposure that measures it best (Zhang & Yau, Opt.
Eng. 48(3):033604, 2009).

:func:`fuse_exposures` takes, per pixel, the valid member with the smallest depth σ (each member's
σ, validity rule and reasons are its own, so the fused pixel keeps its uncertainty). A pixel that
no member validates keeps the reason of the member that saw it best: the unsaturated one with the
highest modulation, or SATURATED when every member clipped it. Modulation and texture are scaled
to the first member's exposure, so the fused texture is one image and not a mosaic.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from app.core.reasons import Reason
from app.recon.reconstructor import ReconResult

_T = TypeVar("_T", bound=np.generic)


@dataclass(frozen=True)
class FusedExposures:
    """A bracket's fused result.

    Attributes:
        result: the fused :class:`~app.recon.reconstructor.ReconResult` (``elapsed_ms`` and
            ``recovered`` summed over the members).
        member: (H, W) int8 index of the member each pixel comes from (−1: none valid).
        exposures_ms: the members' exposures, ms.
    """

    result: ReconResult
    member: npt.NDArray[np.int8]
    exposures_ms: tuple[float, ...]

    def valid_from(self, index: int) -> int:
        """How many fused valid pixels come from member ``index``."""
        return int(np.count_nonzero(self.member == index))


def fuse_exposures(results: Sequence[ReconResult], exposures_ms: Sequence[float]) -> FusedExposures:
    """Fuse reconstructions of one scene at several exposures (module docstring).

    Args:
        results: K ≥ 1 results of equal image size, all with or all without ``phase``.
        exposures_ms: their K exposures, ms, > 0 (modulation and texture are scaled to the
            first one's).

    Returns:
        :class:`FusedExposures`.
    """
    members = list(results)
    times = [float(t) for t in exposures_ms]
    if not members:
        raise ValueError("results: need at least one reconstruction")
    if len(times) != len(members):
        raise ValueError(f"exposures_ms: {len(times)} exposures for {len(members)} results")
    if not all(math.isfinite(t) and t > 0.0 for t in times):
        raise ValueError(f"exposures_ms: must be finite and > 0, got {times}")
    if len(members) > 127:
        raise ValueError(f"results: at most 127 members, got {len(members)}")
    shape = members[0].depth.shape
    if any(r.depth.shape != shape for r in members):
        raise ValueError(f"results: image sizes differ: {[r.depth.shape for r in members]}")
    if len({r.phase is None for r in members}) > 1:
        raise ValueError("results: some have a phase map and some do not")
    if any(r.sigma.shape != shape for r in members):
        raise ValueError("results: every member needs its per-pixel sigma")

    # modulation and texture in the first member's codes
    scale = [times[0] / t for t in times]
    modulation = [(r.modulation * s).astype(np.float32)
                  for r, s in zip(members, scale, strict=True)]
    sigma = np.stack([np.where(r.valid, r.sigma, np.inf) for r in members])
    best = np.argmin(sigma, axis=0)
    # invalid everywhere: the member that saw the pixel best keeps its reason
    unsat_mod = np.stack([np.where(r.reason == Reason.SATURATED, -np.inf, m)
                          for r, m in zip(members, modulation, strict=True)])
    seen = np.argmax(unsat_mod, axis=0)
    any_valid: npt.NDArray[np.bool_] = np.asarray(np.stack([r.valid for r in members]).any(axis=0),
                                                  np.bool_)
    pick = np.where(any_valid, best, seen)[None]

    def take(arrays: list[npt.NDArray[_T]]) -> npt.NDArray[_T]:
        stack = np.stack(arrays)
        index = pick if stack.ndim == 3 else pick[..., None]
        out: npt.NDArray[_T] = np.take_along_axis(stack, index, axis=0)[0]
        return out

    # members of one fast engine make their points from their depth: the fused result makes
    # them from its picked depth on demand (the same values), the others' are picked now
    rays = members[0].point_rays
    lazy = rays is not None and all(r.point_rays is rays for r in members)
    fused = ReconResult(
        depth=take([r.depth for r in members]),
        points=None if lazy else take([r.points for r in members]),
        point_rays=rays if lazy else None,
        valid=any_valid,
        reason=take([r.reason for r in members]),
        modulation=take(modulation),
        texture=take([(r.texture * s).astype(np.float32)
                      for r, s in zip(members, scale, strict=True)]),
        phase=(None if members[0].phase is None
               else take([r.phase for r in members if r.phase is not None])),
        elapsed_ms=float(sum(r.elapsed_ms for r in members)),
        sigma=take([r.sigma for r in members]),
        model_sigma=members[0].model_sigma,  # one calibration: σ_model follows the fused depth
        recovered=int(sum(r.recovered for r in members)),
    )
    member = np.where(any_valid, best, -1).astype(np.int8)
    return FusedExposures(fused, member, tuple(times))
