"""The fringe pattern schedule: which projector images make one depth map (Le et al. 2018, Sec. 2)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

ORIENTATIONS = ("vertical", "horizontal")
UNWRAP_METHODS = ("hierarchical", "heterodyne")


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
    unwrap: str = "hierarchical"
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
            raise ValueError(f"frequencies: hierarchical unwrapping needs integer fringe counts, got {list(freqs)}")
        if self.unwrap == "heterodyne" and len(freqs) < 3:
            raise ValueError(f"frequencies: heterodyne unwrapping needs at least 3, got {len(freqs)}")
        if int(self.steps) != self.steps or self.steps < 3:
            raise ValueError(f"steps: need an integer N >= 3, got {self.steps}")
        if self.width < 2 or self.height < 1:
            raise ValueError(f"width/height: invalid projector size {self.width}x{self.height}")
        if self.orientation not in ORIENTATIONS:
            raise ValueError(f"orientation: must be one of {ORIENTATIONS}, got {self.orientation!r}")
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
            **({"unwrap": self.unwrap} if self.unwrap != "hierarchical" else {}),
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
                unwrap=str(data.get("unwrap", "hierarchical")),
                extra={k: v for k, v in data.items() if k not in known},
            )
        except (TypeError, ValueError) as exc:
            raise ValueError(f"pattern: {exc}") from None


def check_pattern(cal_s: PatternSchedule, cap_s: PatternSchedule, where: str = "capture") -> None:
    """``ValueError`` naming the ``pattern`` key in which a capture set differs from its calibration."""
    for key in ("orientation", "unwrap"):
        if getattr(cal_s, key) != getattr(cap_s, key):
            raise ValueError(f"{where}: pattern.{key} is {getattr(cap_s, key)!r} but the calibration was made "
                             f"with {getattr(cal_s, key)!r}")
    if cal_s != cap_s:  # fringe counts, steps or projector size
        raise ValueError(
            f"{where}: pattern {list(cap_s.frequencies)}x{cap_s.steps} on {cap_s.width}x{cap_s.height} px differs "
            f"from the calibration's {list(cal_s.frequencies)}x{cal_s.steps} on {cal_s.width}x{cal_s.height} px"
        )
