"""The live change map: a reference kept in the data folder, and each new map compared with it.

The reference (depth, σ, points and where it came from) is written atomically to
``<data_dir>/reference/reference.npz`` (``reference.json`` beside it: the description, for
people) and read back at start, so it survives a restart. While one is set, every published
depth map is handed to a thread of its own (newest wins: the reconstruction thread never waits
for it) that compares it (:func:`app.analysis.change.compare`) and publishes a
:class:`LiveChange` in its slot.
"""

from __future__ import annotations

import io
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from app.analysis.change import ChangeResult, compare
from app.atomic import atomic_write_bytes, atomic_write_text
from app.capture.captureset import CaptureSet
from app.core.calibration import Calibration
from app.core.errors import Conflict, InvalidRequest, NotFound
from app.recon.change import ChangeTest, pixel_area_mm2, summarize
from app.recon.reconstructor import ReconResult
from app.service.reconstruction import LiveResult
from app.service.store import LatestSlot, NewestQueue

log = logging.getLogger("fringescope.service.change")

F32 = npt.NDArray[np.float32]
REFERENCE_FORMAT = "fringescope.reference/1"


class ReferenceMismatch(Conflict):
    """The reference and the current maps cannot be compared (409)."""


@dataclass(frozen=True)
class Reference:
    """A reference depth map.

    Attributes:
        depth, sigma: (H, W) float32 mm, NaN invalid (σ the sensor noise's); points: (H, W, 3)
            float32 mm; sigma_model: (H, W) the calibration's own 1-σ there, mm, or None (a
            reference kept before it was stored: taken as 0).
        created: ISO time it was taken; source: where it came from (``{"kind": "live",
            "seq": n}``, ``{"kind": "recording", "recording": NAME, "index": i}`` or
        ``{"kind": "upload"}``); calibration: the calibration's creation time (its identity).
    """

    depth: F32
    sigma: F32
    points: F32
    created: str
    source: dict[str, Any]
    calibration: str
    sigma_model: F32 | None = None

    @property
    def valid_share(self) -> float:
        return float(np.isfinite(self.depth).mean())

    def describe(self) -> dict[str, Any]:
        h, w = self.depth.shape
        return {"created": self.created, "source": self.source, "valid_share": self.valid_share,
                "image_size": [w, h], "calibration": self.calibration}


@dataclass
class LiveChange:
    """One change map of a live depth map (``seq`` the depth map's), with its figures."""

    result: ChangeResult
    seq: int
    created: str
    summary: dict[str, Any]
    _cache: dict[Any, bytes] = field(default_factory=dict, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def cached(self, key: Any, make: Callable[[], bytes]) -> bytes:
        with self._lock:
            if key not in self._cache:
                self._cache[key] = make()
            return self._cache[key]


def _summary(result: ChangeResult, area: F32 | None) -> dict[str, Any]:
    cm = result.cmap
    sm = summarize(cm, area)
    reg = result.registration
    return {
        "mode": result.mode,
        "compared_pixels": cm.compared,
        "changed_pixels": cm.changed_pixels,
        "changed_share": cm.changed_share,
        "changed_area_mm2": sm.changed_area_mm2,
        "rise_mm": sm.rise_mm, "rise_sigma_mm": sm.rise_sigma_mm,
        "rise_px": list(sm.rise_px) if sm.rise_px else None,
        "sink_mm": sm.sink_mm, "sink_sigma_mm": sm.sink_sigma_mm,
        "sink_px": list(sm.sink_px) if sm.sink_px else None,
        "false_alarm_rate": cm.test.false_alarm_rate,
        "registration": None if reg is None else {
            "ok": reg.ok, "note": reg.note, "residual_mm": reg.residual_mm,
            "overlap": reg.overlap, "rotation_deg": reg.rotation_deg,
            "translation_mm": reg.translation_mm, "transform": reg.transform.tolist(),
            "elapsed_ms": reg.elapsed_ms},
        "elapsed_ms": result.elapsed_ms,
    }


class ReferenceStore:
    """The reference on disk (atomic writes) and in memory; thread-safe."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self._lock = threading.Lock()
        self._ref: Reference | None = None
        self._load()

    @property
    def reference(self) -> Reference | None:
        with self._lock:
            return self._ref

    def _load(self) -> None:
        data_path = self.folder / "reference.npz"
        if not data_path.is_file():
            return
        try:
            with np.load(data_path) as z:
                arrays = {k: np.asarray(z[k], np.float32) for k in ("depth", "sigma", "points")}
                model = np.asarray(z["sigma_model"], np.float32) if "sigma_model" in z else None
                meta = json.loads(str(z["meta"]))
            if meta.get("format") != REFERENCE_FORMAT:
                raise ValueError(f"format {meta.get('format')!r}")
            self._ref = Reference(arrays["depth"], arrays["sigma"], arrays["points"],
                                  str(meta["created"]), dict(meta["source"]),
                                  str(meta["calibration"]), model)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("reference in %s not loaded: %s", self.folder, exc)

    def set(self, ref: Reference) -> None:
        meta = json.dumps({"format": REFERENCE_FORMAT, "created": ref.created,
                           "source": ref.source, "calibration": ref.calibration})
        buf = io.BytesIO()
        # one file holds the arrays and what they are: replaced atomically as a whole
        if ref.sigma_model is None:
            np.savez(buf, depth=ref.depth, sigma=ref.sigma, points=ref.points,
                     meta=np.array(meta))
        else:
            np.savez(buf, depth=ref.depth, sigma=ref.sigma, points=ref.points,
                     meta=np.array(meta), sigma_model=ref.sigma_model)
        self.folder.mkdir(parents=True, exist_ok=True)
        with self._lock:
            atomic_write_bytes(self.folder / "reference.npz", buf.getvalue())
            # a copy of the description for people; the service reads the npz only
            atomic_write_text(self.folder / "reference.json",
                              json.dumps(json.loads(meta), indent=2) + "\n")
            self._ref = ref

    def clear(self) -> bool:
        """Forget the reference; False when there was none."""
        with self._lock:
            had = self._ref is not None
            self._ref = None
            for name in ("reference.npz", "reference.json"):
                (self.folder / name).unlink(missing_ok=True)
            return had


class ChangeService:
    """Compares every published depth map with the reference, on a thread of its own.

    Args:
        folder: where the reference is kept.
        calibration: the active calibration now (None: none yet).
        test: the changed-pixel test.
    """

    def __init__(self, folder: Path, calibration: Callable[[], Calibration | None],
                 test: ChangeTest | None = None) -> None:
        self.store = ReferenceStore(folder)
        self.slot: LatestSlot[LiveChange] = LatestSlot()
        self.test = test or ChangeTest()
        self._calibration = calibration
        self._queue: NewestQueue[tuple[int, LiveResult]] = NewestQueue(1)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._area: tuple[int, F32] | None = None  # (id of the reference points, pixel areas)
        self.last_error: str | None = None
        self._recent: dict[int, LiveChange] = {}  # the newest maps' changes, by depth seq
        self._recent_lock = threading.Lock()
        self._recent_cond = threading.Condition(self._recent_lock)

    # -- lifecycle ---------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="change", daemon=True)
            self._thread.start()

    def close(self, timeout_s: float) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def threads(self) -> list[threading.Thread]:
        return [self._thread] if self._thread is not None else []

    # -- the hook ------------------------------------------------------------------------
    def on_map(self, seq: int, result: LiveResult) -> None:
        """A new depth map was published (reconstruction thread): queue it, never wait."""
        if self.store.reference is not None and result.sigma is not None:
            self._queue.put((seq, result))

    def _run(self) -> None:
        while not self._stop.is_set():
            item = self._queue.get(0.2)
            if item is None:
                continue
            seq, result = item
            sigma_noise = result.sigma_noise
            if sigma_noise is None:
                continue
            try:
                # the sensor noise only: one pixel's calibration error is the same in both maps and
                # cancels in their difference
                change = self.compute(result.depth, sigma_noise, result.points, seq,
                                      result.sigma_model)
            except (ValueError, Conflict) as exc:
                self.last_error = str(exc)
                continue
            except Exception as exc:  # a fault in one comparison must not end the live change map
                log.exception("change map of result %d failed", seq)
                self.last_error = f"change map failed: {type(exc).__name__}: {exc}"
                continue
            if change is not None:
                with self._recent_lock:
                    self._recent[seq] = change
                    while len(self._recent) > 16:
                        self._recent.pop(next(iter(self._recent)))
                    self._recent_cond.notify_all()
                self.slot.publish(change)

    def latest_delta(self) -> F32 | None:
        """The newest change map's Δ (mm), or None (no reference, or none made yet)."""
        if self.store.reference is None:
            return None
        _, change = self.slot.latest()
        return None if change is None else change.result.cmap.delta

    def change_for(self, seq: int, wait_s: float) -> LiveChange | None:
        """The change map of depth map ``seq``, waiting up to ``wait_s`` for it (None: none)."""
        deadline = time.monotonic() + wait_s
        with self._recent_cond:
            while seq not in self._recent:
                left = deadline - time.monotonic()
                if left <= 0 or self._stop.is_set():
                    return None
                self._recent_cond.wait(min(left, 0.1))
            return self._recent[seq]

    # -- the comparison ---------------------------------------------------------------------
    def compute(self, depth: F32, sigma: F32, points: F32, seq: int = 0,
                sigma_model: F32 | None = None) -> LiveChange | None:
        """The change of one map against the reference (None when no reference is set);
        ``sigma_model`` the map's calibration 1-σ (used once registered)."""
        ref = self.store.reference
        if ref is None:
            return None
        self.check_comparable(ref, depth.shape)
        cal = self._calibration()
        assert cal is not None  # check_comparable refused the map without one
        result = compare(depth, sigma, points, ref.depth, ref.sigma, ref.points,
                         camera_matrix=cal.camera_matrix, dist_coeffs=cal.dist_coeffs,
                         test=self.test, sigma_model=sigma_model,
                         ref_sigma_model=ref.sigma_model)
        if result.mode != "failed" and result.cmap.compared == 0:
            raise ReferenceMismatch("no pixel is valid in both the map and the reference: "
                                    "nothing to compare")
        self.last_error = None
        return LiveChange(result, seq, datetime.now(UTC).isoformat(timespec="milliseconds"),
                          _summary(result, self._areas(ref)))

    def _areas(self, ref: Reference) -> F32:
        key = id(ref.points)
        if self._area is None or self._area[0] != key:
            self._area = (key, pixel_area_mm2(ref.points))
        return self._area[1]

    def check_comparable(self, ref: Reference, shape: tuple[int, ...]) -> None:
        """409 unless ``shape`` and the active calibration are the reference's."""
        if tuple(ref.depth.shape) != tuple(shape):
            raise ReferenceMismatch(
                f"the reference is {ref.depth.shape[1]}x{ref.depth.shape[0]} px, the maps "
                f"{shape[1]}x{shape[0]} px: set a new reference")
        cal = self._calibration()
        if cal is None:
            raise ReferenceMismatch("no calibration is active")
        if cal.created != ref.calibration:
            raise ReferenceMismatch(
                f"the reference was taken with the calibration of {ref.calibration}, the "
                f"instrument now uses the one of {cal.created}: set a new reference")

    # -- the reference -----------------------------------------------------------------------
    def set_reference(self, depth: F32, sigma: F32 | None, points: F32,
                      source: dict[str, Any], sigma_model: F32 | None = None) -> Reference:
        """Keep a map as the reference (422 without σ or valid pixels, 409 without a
        calibration); ``sigma`` its sensor-noise σ, ``sigma_model`` its calibration σ."""
        cal = self._calibration()
        if cal is None:
            raise Conflict("no calibration is active: a reference needs one")
        if sigma is None:
            raise InvalidRequest("the map has no σ: it cannot be a reference")
        if not np.isfinite(depth).any():
            raise InvalidRequest("the map has no valid pixel: it cannot be a reference")
        ref = Reference(np.ascontiguousarray(depth, np.float32),
                        np.ascontiguousarray(sigma, np.float32),
                        np.ascontiguousarray(points, np.float32),
                        datetime.now(UTC).isoformat(timespec="milliseconds"), source,
                        cal.created,
                        None if sigma_model is None
                        else np.ascontiguousarray(sigma_model, np.float32))
        self.store.set(ref)
        self.slot.clear()
        with self._recent_lock:
            self._recent.clear()
        return ref

    def reference_from_capture(self, capture: CaptureSet,
                               reconstruct: Callable[[CaptureSet], ReconResult],
                               source: dict[str, Any]) -> Reference:
        """Reconstruct a capture set with the active calibration and keep it as the reference."""
        res = reconstruct(capture)
        sigma = res.sigma_noise if res.sigma.size else None
        model = res.sigma_model if res.sigma.size else None
        return self.set_reference(res.depth, sigma, res.points, source, model)

    def reference_from_recording(self, recordings: Path, name: str, index: int,
                                 reconstruct: Callable[[CaptureSet], ReconResult]) -> Reference:
        """Set ``index`` of recording ``name`` (under ``recordings``) as the reference (404
        when either does not exist)."""
        from app.capture import read_capture_set
        from app.capture.recording import read_session

        try:
            session = read_session(recordings, name)
        except (FileNotFoundError, NotADirectoryError):
            raise NotFound(f"no recording {name!r}") from None
        sets = session.get("sets", [])
        if not 0 <= index < len(sets):
            raise NotFound(f"recording {name!r} has {len(sets)} sets: no index {index}")
        capture = read_capture_set(recordings / name / str(sets[index]["folder"]))
        return self.reference_from_capture(capture, reconstruct, {
            "kind": "recording", "recording": name, "index": index})

    def reference(self) -> Reference:
        ref = self.store.reference
        if ref is None:
            raise NotFound("no reference is set")
        return ref

    def clear_reference(self) -> None:
        if not self.store.clear():
            raise NotFound("no reference is set")
        self.slot.clear()

    def latest(self, timeout_s: float = 0.0) -> LiveChange:
        """The newest change map (404 without a reference, 409 when none could be made)."""
        ref = self.store.reference
        if ref is None:
            raise NotFound("no reference is set: POST /api/reference first")
        _, change = self.slot.latest()
        if change is None and timeout_s > 0:
            deadline = time.monotonic() + timeout_s
            while change is None and time.monotonic() < deadline:
                _, change = self.slot.wait_newer(0, max(0.0, deadline - time.monotonic()))
        if change is None:
            raise Conflict(self.last_error or "no change map yet: no depth map since the "
                                              "reference was set")
        return change


__all__ = ["ChangeService", "LiveChange", "Reference", "ReferenceMismatch", "ReferenceStore"]
