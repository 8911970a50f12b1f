"""One capture set (or an exposure bracket of sets) → its depth files: the job that
``fringescope reconstruct`` runs once and ``fringescope reprocess`` runs per set on Dask.

Both commands call :func:`reconstruct_captures` and :func:`output_files`, so their outputs
are the same bytes for the same calibration and options.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import PurePath
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt

from app.capture import CaptureSet
from app.core.calibration import Calibration
from app.core.limits import DEFAULT_DEPTH_RANGE_MM
from app.recon import ReconResult, Reconstructor, SensorNoise
from app.recon.fusion import FusedExposures
from app.recon.gamma import PhaseErrorLUT
from app.recon.sensor import NoiseSource

#: every file a set's reconstruction can write, in writing order
ALL_FILES = ("depth.npy", "sigma.npy", "sigma_noise.npy", "sigma_model.npy", "points.ply",
             "depth.png", "reason.png")


@dataclass(frozen=True)
class ReconOptions:
    """The reconstruction's options, shared by ``reconstruct`` and ``reprocess``.

    Attributes:
        max_code: sensor maximum code for every set (None: each set's own ``bit_depth``).
        numpy: the numpy reference path instead of the fused numba kernel.
        min_modulation: explicit modulation threshold B, codes (None: the noise-aware rule).
        range_mm: (min, max) of the depth colormap in ``depth.png``, mm.
        phase_error: a projector-gamma table (``fringescope gamma``) subtracted from every
            wrapped phase (None: none); hashed by its content in :meth:`to_dict`.
    """

    max_code: int | None = None
    numpy: bool = False
    min_modulation: float | None = None
    range_mm: tuple[float, float] = DEFAULT_DEPTH_RANGE_MM
    phase_error: PhaseErrorLUT | None = None

    def to_dict(self) -> dict[str, object]:
        """JSON-able form (for the resumption hash and the output metadata)."""
        out = asdict(replace(self, phase_error=None))
        out["range_mm"] = list(self.range_mm)
        out["phase_error"] = None if self.phase_error is None else self.phase_error.digest()
        return out


@dataclass
class SetReconstruction:
    """The result of :func:`reconstruct_captures`.

    Attributes:
        result: the set's (or the bracket's fused) :class:`~app.recon.ReconResult`.
        fused: the bracket's fusion (None for one set).
        exposures_ms: the members' exposures, ms.
        fast: whether the numba kernel ran (False: the numpy path).
    """

    result: ReconResult
    fused: FusedExposures | None
    exposures_ms: tuple[float, ...]
    fast: bool

    def bracket_note(self) -> str:
        """`` fused from 5 ms (40.0%), 20 ms (58.1%);`` for a bracket, else ``""``."""
        if self.fused is None:
            return ""
        size = self.result.valid.size
        shares = (f"{e:g} ms ({100 * self.fused.valid_from(i) / size:.1f}%)"
                  for i, e in enumerate(self.exposures_ms))
        return " fused from " + ", ".join(shares) + ";"


def check_bracket(captures: Sequence[CaptureSet], names: Sequence[str]) -> None:
    """``ValueError`` naming the set unless all ``captures`` share one schedule and frame shape."""
    if len(captures) != len(names) or not captures:
        raise ValueError("captures: need one name per capture set, and at least one set")
    first, first_name = captures[0], PurePath(names[0]).name
    for name, c in zip(names[1:], captures[1:], strict=True):
        if c.schedule != first.schedule:
            raise ValueError(f"{name}: a bracket's sets need one schedule; {first_name} has "
                             "another")
        if c.frames.shape != first.frames.shape:
            raise ValueError(f"{name}: frames {c.frames.shape[1:]} differ from {first_name}'s "
                             f"{first.frames.shape[1:]}")


def new_reconstructor(calibration: Calibration, options: ReconOptions,
                      noise: SensorNoise | None = None) -> Reconstructor:
    """The :class:`~app.recon.Reconstructor` the options ask for (its per-pixel tables built)."""
    return Reconstructor(calibration, max_code=options.max_code, fast=not options.numpy,
                         noise=noise, min_modulation=options.min_modulation,
                         phase_error=options.phase_error)


def reconstruct_captures(
    captures: Sequence[CaptureSet], calibration: Calibration, options: ReconOptions, *,
    base: Reconstructor | None = None,
) -> SetReconstruction:
    """Reconstruct one set, or fuse an exposure bracket of sets of one scene.

    Args:
        captures: K ≥ 1 capture sets of one schedule and frame shape (checked by the caller
            with :func:`check_bracket`); ``calibration`` must already apply to their schedule.
        calibration: the calibration, restated for the sets' schedule.
        options: the reconstruction's options.
        base: a reconstructor made by :func:`new_reconstructor` for the same calibration and
            options, whose per-pixel tables are reused (a batch builds them once per worker);
            None builds them here. The outputs are the same either way.

    Returns:
        :class:`SetReconstruction`; σ uses the camera noise the sets show (the N-step
        residual, N > 3: the first set that has it; else the typical sensor).
    """
    from app.recon.noise import resolve_set_noise

    noise: SensorNoise | None = None
    table: PhaseErrorLUT | None = None  # the projector's gamma as that set shows it (N = 4)
    source: NoiseSource = "nominal"
    note = ""
    for c in captures:  # the first set that shows its noise gives it to the bracket
        est = resolve_set_noise(c.frames, c.schedule, options.max_code or c.max_code)
        source, note = est.source, est.note
        if source == "set":
            noise, table = est.noise, est.phase_error
            break
    # the tables are the calibration's alone; the noise is this set's, passed with the call
    rec = new_reconstructor(calibration, options, None) if base is None else base
    # each set at its own bit_depth unless told; without a fitted noise each run's nominal
    members = [rec.run(c.frames, max_code=options.max_code or c.max_code, noise=noise,
                       phase_error=table)
               for c in captures]
    for m in members:
        m.noise_source, m.noise_note = source, note
        if table is not None and m.phase_error_source == "given":
            m.phase_error_source = "set"  # the table passed is this set's own
    exposures = tuple(c.exposure_ms for c in captures)
    if len(members) == 1:
        return SetReconstruction(members[0], None, exposures, rec.fast)
    from app.recon.fusion import fuse_exposures

    fused = fuse_exposures(members, exposures)
    fused.result.noise_source, fused.result.noise_note = source, note
    fused.result.phase_error_source = members[0].phase_error_source
    return SetReconstruction(fused.result, fused, exposures, rec.fast)


#: writes one output file's bytes to an open binary file
FileWriter = Callable[[BinaryIO], None]


def write_npy(fh: BinaryIO, values: npt.NDArray[Any]) -> None:
    """Write ``values`` to ``fh`` as ``np.save(fh, values, allow_pickle=False)`` does, byte
    for byte.

    A C-contiguous array as the whole of a new local file goes past the page cache
    (:func:`app.atomic.write_direct`), elsewhere as its header and then its own memory, in
    one write each, into a file whose size is reserved first
    (:func:`app.atomic.preallocate`); any other array through ``np.save``.
    """
    from app.atomic import preallocate, write_direct

    head = io.BytesIO()
    try:
        if not values.flags.c_contiguous or values.dtype.hasobject:
            raise ValueError("not one block of plain values")
        np.lib.format.write_array_header_1_0(head,
                                             np.lib.format.header_data_from_array_1_0(values))
    except ValueError:  # or a header too long for format 1.0: numpy's own way
        np.save(fh, values, allow_pickle=False)
        return
    header = head.getvalue()
    data = values.reshape(-1).view(np.uint8).data  # its memory, not a copy
    size = len(header) + values.nbytes
    try:
        fd = fh.fileno()
    except (AttributeError, OSError):  # io.UnsupportedOperation: an in-memory file
        fd = -1
    if fd >= 0:
        fh.flush()
        if fh.tell() == 0 and write_direct(fd, (header, data), size):
            fh.seek(size)  # the file object's position where the descriptor's is
            return
        preallocate(fd, fh.tell() + size)
    fh.write(header)
    while data:  # a buffered file writes it all at once; a raw one may take several calls
        data = data[fh.write(data):]


def output_writers(recon: SetReconstruction, options: ReconOptions,
                   names: Sequence[str] = ALL_FILES) -> dict[str, FileWriter]:
    """Writers of the output files ``names`` (a subset of :data:`ALL_FILES`), in that order.

    Each writes its file's bytes (see :func:`output_files`) to an open binary file; the
    ``.npy`` arrays are written by :func:`write_npy`.
    """
    from app.batch.reasonpng import reason_png_indexed
    from app.capture.ply import ply_bytes
    from app.recon import render_depth_png

    unknown = [n for n in names if n not in ALL_FILES]
    if unknown:
        raise ValueError(f"names: unknown output files {unknown}; choose from {list(ALL_FILES)}")
    res = recon.result

    def array(values: Callable[[], npt.NDArray[np.float32]]) -> FileWriter:
        return lambda fh: write_npy(fh, values())

    def encoded(make: Callable[[], bytes]) -> FileWriter:
        def write(fh: BinaryIO) -> None:
            fh.write(make())
        return write

    makers: dict[str, FileWriter] = {
        "depth.npy": array(lambda: res.depth),
        "sigma.npy": array(lambda: res.sigma),
        "sigma_noise.npy": array(lambda: res.sigma_noise),
        "sigma_model.npy": array(lambda: res.sigma_model),
        "points.ply": encoded(lambda: ply_bytes(res.points, res.valid, res.texture, res.sigma,
                                                sigma_noise=res.sigma_noise,
                                                sigma_model=res.sigma_model)),
        "depth.png": encoded(lambda: render_depth_png(res.depth, options.range_mm)),
        "reason.png": encoded(lambda: reason_png_indexed(res.reason)),
    }
    return {n: makers[n] for n in names}


def output_files(recon: SetReconstruction, options: ReconOptions,
                 names: Sequence[str] = ALL_FILES) -> dict[str, bytes]:
    """The bytes of the output files ``names`` (a subset of :data:`ALL_FILES`), in that order.

    ``depth.npy``/``sigma.npy``: (H, W) float32 mm, NaN invalid (σ the total, noise ⊕
    calibration); ``sigma_noise.npy``/``sigma_model.npy``: its two parts, the same way;
    ``points.ply``: the valid points with intensity and the three σ; ``depth.png``: the
    colormap over ``options.range_mm``;
    ``reason.png``: the per-pixel reason codes, as a palette PNG (the pixels of
    :func:`app.recon.colormap.reason_png`, see :mod:`app.batch.reasonpng`).
    """
    out = {}
    for name, write in output_writers(recon, options, names).items():
        buf = io.BytesIO()
        write(buf)
        out[name] = buf.getvalue()
    return out


def median_float32(values: npt.NDArray[np.float32]) -> float:
    """``float(np.median(values))`` of a 1-D float32 array, partitioning ``values`` in place.

    Non-negative floats order as their int32 bit patterns, and numpy partitions int32
    several times faster than float32 (measured 1.7 vs 13 ms on 1.4 M values): σ maps take
    that path; an array with negative values goes to ``np.median``. Empty: NaN.
    """
    if values.dtype != np.float32 or values.ndim != 1:
        raise ValueError(f"values: expected a 1-D float32 array, got {values.dtype} "
                         f"{values.shape}")
    n = values.size
    if n == 0:
        return math.nan
    keys = values.view(np.int32)
    if int(keys.max()) > 0x7F800000:  # a NaN (positive sign bit): np.median gives NaN
        return math.nan
    if int(keys.min()) < 0:  # a negative number (or -0.0, a negative NaN): numpy's own way
        return float(np.median(values))
    k = n // 2
    keys.partition(k)
    middle = [int(keys[k])] if n % 2 else [int(keys[:k].max()), int(keys[k])]
    # the mean of the middle one or two in float32, as np.median computes it
    return float(np.mean(np.array(middle, np.int32).view(np.float32)))


@dataclass(frozen=True)
class SetStatistics:
    """A result's figures for the batch table.

    Attributes:
        valid_fraction: share of valid pixels, 0..1.
        median_sigma_mm: median total σ over the valid pixels, mm (NaN: none valid).
        motion_share: share of pixels with reason MOTION, 0..1.
    """

    valid_fraction: float
    median_sigma_mm: float
    motion_share: float


def set_statistics(result: ReconResult) -> SetStatistics:
    """:class:`SetStatistics` of ``result``: a pass over ``valid``, ``sigma`` and ``reason``
    each (the σ of the valid pixels copied once and partitioned in place)."""
    from app.core.reasons import Reason

    size = result.valid.size
    if size == 0:
        return SetStatistics(math.nan, math.nan, math.nan)
    valid_count = int(np.count_nonzero(result.valid))
    sigma = result.sigma[result.valid] if valid_count else np.empty(0, np.float32)
    median = median_float32(sigma) if sigma.dtype == np.float32 else float(np.median(sigma))
    motion = int(np.count_nonzero(result.reason == int(Reason.MOTION)))
    return SetStatistics(valid_count / size, median, motion / size)


def summary_line(recon: SetReconstruction) -> str:
    """``valid 97.1% of 1384x1032 px, height 0.512..18.004 mm, 12.3 ms (fast)``."""
    res = recon.result
    h, w = res.depth.shape
    frac = float(res.valid.mean())
    if frac > 0:
        span = f"height {np.nanmin(res.depth):.3f}..{np.nanmax(res.depth):.3f} mm"
    else:
        span = "height n/a"
    path = "fast" if recon.fast else "numpy"
    return (f"valid {100 * frac:.1f}% of {w}x{h} px,{recon.bracket_note()} {span}, "
            f"{res.elapsed_ms:.1f} ms ({path}), {noise_summary(res)}")


def noise_summary(res: ReconResult) -> str:
    """``noise_source=set (read 1.52 DN, gain 0.0160 DN/e), phase_error=set``; a nominal
    noise says why; ``phase_error`` names the projector-gamma table applied (learned, given, the
    set's own, or none)."""
    text = f"noise_source={res.noise_source}"
    if res.noise is not None:
        text += f" (read {res.noise.read_noise_dn:.2f} DN, gain {res.noise.gain_dn_per_e:.4f} DN/e)"
    if res.noise_note:
        text += f": {res.noise_note}"
    return text + f", phase_error={res.phase_error_source}"
