"""The fringe pattern schedule: which projector images make one depth map (Le et al. 2018,
Sec. 2)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

ORIENTATIONS = ("vertical", "horizontal")
UnwrapMethod = Literal["hierarchical", "heterodyne"]
UNWRAP_METHODS: tuple[UnwrapMethod, ...] = ("hierarchical", "heterodyne")
#: the paper's temporal unwrapping (the first frequency's phase is absolute)
DEFAULT_UNWRAP: UnwrapMethod = "hierarchical"


@dataclass(frozen=True)
class PatternSchedule:
    """Which fringe images make one depth map.

    Frames are ordered frequency-major, shift-minor: frame ``i`` shows fringe count
    ``frequencies[i // steps]`` with phase shift ``2π (i % steps) / steps``.

    Attributes:
        frequencies: fringe counts across the fringe axis (:attr:`axis_length`), strictly
            increasing. ``hierarchical``: integers, the first equal to 1 (its phase is
            absolute). ``heterodyne``: three or more, any positive values (e.g. 1920/42).
        steps: phase shifts per frequency, N ≥ 3.
        width, height: projector resolution in pixels (DLP3000: 608 × 684).
        orientation: ``"vertical"`` fringes (the phase grows along the projector's width)
            or ``"horizontal"`` (it grows along the height).
        unwrap: ``"hierarchical"`` (the paper's) or ``"heterodyne"`` (multi-wavelength beats).
    """

    frequencies: tuple[float, ...] = (1, 4, 12, 36)
    steps: int = 4
    width: int = 608
    height: int = 684
    orientation: str = "vertical"
    unwrap: str = DEFAULT_UNWRAP
    extra: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        freqs = tuple(int(k) if float(k).is_integer() else float(k) for k in self.frequencies)
        object.__setattr__(self, "frequencies", freqs)
        if self.unwrap not in UNWRAP_METHODS:
            raise ValueError(f"unwrap: must be one of {UNWRAP_METHODS}, got {self.unwrap!r}")
        if len(freqs) < 1 or not all(math.isfinite(k) and k > 0 for k in freqs):
            raise ValueError(f"frequencies: need positive fringe counts, got {list(freqs)}")
        if any(b <= a for a, b in zip(freqs, freqs[1:], strict=False)):
            raise ValueError(f"frequencies: must be strictly increasing, got {list(freqs)}")
        if self.unwrap == "hierarchical" and freqs[0] != 1:
            raise ValueError(f"frequencies: the first must be 1 (absolute phase), got {freqs[0]}")
        if self.unwrap == "hierarchical" and not all(isinstance(k, int) for k in freqs):
            raise ValueError("frequencies: hierarchical unwrapping needs integer fringe counts, "
                             f"got {list(freqs)}")
        if self.unwrap == "heterodyne" and len(freqs) < 3:
            raise ValueError(
                f"frequencies: heterodyne unwrapping needs at least 3, got {len(freqs)}")
        if int(self.steps) != self.steps or self.steps < 3:
            raise ValueError(f"steps: need an integer N >= 3, got {self.steps}")
        if self.width < 2 or self.height < 1:
            raise ValueError(f"width/height: invalid projector size {self.width}x{self.height}")
        if self.orientation not in ORIENTATIONS:
            raise ValueError(
                f"orientation: must be one of {ORIENTATIONS}, got {self.orientation!r}")
        if freqs[-1] * 2 > self.axis_length:
            raise ValueError(f"frequencies: {freqs[-1]} fringes need at least 2 px per period")

    @property
    def axis_length(self) -> int:
        """Projector pixels along which the phase grows: width (vertical) or height (horizontal)."""
        return self.width if self.orientation == "vertical" else self.height

    @property
    def n_frames(self) -> int:
        """Frames per depth map, ``len(frequencies) * steps``."""
        return len(self.frequencies) * self.steps

    @property
    def shifts_rad(self) -> npt.NDArray[np.float64]:
        """Phase shifts δ_n = 2π n / N, shape (N,), radians."""
        return 2.0 * math.pi * np.arange(self.steps) / self.steps

    def frame_index(self, freq_index: int, shift_index: int) -> int:
        """Position of image (frequency ``freq_index``, shift ``shift_index``) in a set."""
        return freq_index * self.steps + shift_index

    def to_dict(self) -> dict[str, Any]:
        """The ``pattern`` object of the capture-set and calibration formats."""
        return {
            **self.extra,
            "frequencies": list(self.frequencies),
            "steps": self.steps,
            "width": self.width,
            "height": self.height,
            "orientation": self.orientation,
            **({"unwrap": self.unwrap} if self.unwrap != DEFAULT_UNWRAP else {}),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PatternSchedule:
        """Parse a ``pattern`` object; unknown keys are kept in ``extra``."""
        if not isinstance(data, dict):
            raise ValueError("pattern: expected an object")
        known = {"frequencies", "steps", "width", "height", "orientation", "unwrap"}
        missing = {"frequencies", "steps"} - data.keys()
        if missing:
            raise ValueError(f"pattern: missing keys {sorted(missing)}")
        try:
            return cls(
                frequencies=tuple(float(k) for k in data["frequencies"]),
                steps=int(data["steps"]),
                width=int(data.get("width", 608)),
                height=int(data.get("height", 684)),
                orientation=str(data.get("orientation", "vertical")),
                unwrap=str(data.get("unwrap", DEFAULT_UNWRAP)),
                extra={k: v for k, v in data.items() if k not in known},
            )
        except (TypeError, ValueError) as exc:
            raise ValueError(f"pattern: {exc}") from None


def check_pattern(cal_s: PatternSchedule, cap_s: PatternSchedule, where: str = "capture") -> None:
    """``ValueError`` naming the ``pattern`` key in which a capture set differs from its
    calibration."""
    for key in ("orientation", "unwrap"):
        if getattr(cal_s, key) != getattr(cap_s, key):
            raise ValueError(f"{where}: pattern.{key} is {getattr(cap_s, key)!r} but the "
                             f"calibration was made with {getattr(cal_s, key)!r}")
    if cal_s != cap_s:  # fringe counts, steps or projector size
        raise ValueError(
            f"{where}: pattern {list(cap_s.frequencies)}x{cap_s.steps} on "
            f"{cap_s.width}x{cap_s.height} px differs from the calibration's "
            f"{list(cal_s.frequencies)}x{cal_s.steps} on {cal_s.width}x{cal_s.height} px"
        )


# -- the named schedules ------------------------------------------------------------------------
# One home for every schedule the instrument can run. The reduced ones keep the paper's finest
# pattern (36 fringes across the DMD width): the depth noise is set by the finest phase, and a
# calibration carries over between schedules with the same finest fringe count, orientation and
# projector size (:func:`calibration_mismatch`). Their coarser frequencies follow the hierarchical
# order-error condition (Zuo et al., "Temporal phase unwrapping algorithms for fringe projection
# profilometry: a comparative review", Opt. Lasers Eng. 85, 84–103, 2016, Sec. 3): at step n the
# error of ``(k_n/k_{n−1})·φ_uw(k_{n−1}) − φ_w(k_n)`` has σ_n = σ_φ·√(r_n² + 1), r_n = k_n/k_{n−1},
# and must stay well below π; for a fixed frame budget and finest count the largest σ_n is
# smallest with equal ratios (a geometric sequence), hence 1 → 6 → 36. See app/analysis/schedules.py
# for the predicted σ and order-error rate of each at the rig's noise, and the README.
DEFAULT_SCHEDULE = "paper-16"

SCHEDULES: dict[str, PatternSchedule] = {
    # Le et al. 2018: 4 frequencies × 4 steps, ratios 4, 3, 3
    "paper-16": PatternSchedule((1, 4, 12, 36), 4),
    # three frequencies, geometric ratios 6, 6; 4 steps (the N-step residual still gives σ_I)
    "geometric-12": PatternSchedule((1, 6, 36), 4),
    # the same three frequencies with 3 steps: 9 frames a depth map
    "geometric-9": PatternSchedule((1, 6, 36), 3),
    # heterodyne (multi-wavelength): no single-fringe pattern; 36 − 35 = 1 is absolute,
    # 35 − 30 = 5 beat
    "heterodyne-9": PatternSchedule((30, 35, 36), 3, unwrap="heterodyne"),
}


def schedule_names() -> list[str]:
    """The registered schedule names, the default first."""
    return list(SCHEDULES)


def schedule_by_name(name: str) -> PatternSchedule:
    """The registered schedule ``name``; ``ValueError`` naming ``schedule`` if there is none."""
    try:
        return SCHEDULES[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"schedule: unknown name {name!r}; known: {', '.join(SCHEDULES)}") from None


def schedule_name_of(schedule: PatternSchedule) -> str | None:
    """The registered name of ``schedule`` (None if it is not one of them)."""
    return next((n for n, s in SCHEDULES.items() if s == schedule), None)


def calibration_mismatch(cal_s: PatternSchedule, s: PatternSchedule) -> str | None:
    """Why a calibration made with ``cal_s`` cannot map the phase of ``s`` to depth (None: it can).

    A calibration's depth model (Eq. (5) or the geometric model) takes the unwrapped phase
    of the finest pattern, in radians: φ = 2π·k_max·x/L of the projector coordinate x along
    the fringe axis of length L. The same (k_max, orientation, L, projector size) gives the
    same φ at every projector point, so the model carries over whatever the coarser
    frequencies, the number of steps or the unwrapping method. Any of those four different
    changes what φ means (a rescaled or rotated projector coordinate): not applied.
    """
    for key in ("orientation", "width", "height"):
        if getattr(cal_s, key) != getattr(s, key):
            return (f"pattern.{key} is {getattr(s, key)!r} but the calibration was made with "
                    f"{getattr(cal_s, key)!r}")
    if cal_s.frequencies[-1] != s.frequencies[-1]:
        return (f"the finest pattern, {s.frequencies[-1]} fringes, differs from the calibration's "
                f"{cal_s.frequencies[-1]} (its phase means another projector coordinate)")
    return None
