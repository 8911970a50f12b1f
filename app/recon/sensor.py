"""The camera's temporal noise model, shared by the engine, the motion test and the estimator."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

#: where a run's noise model came from: passed by the caller, fitted to the set (N > 3), or
#: the nominal sensor (:meth:`SensorNoise.typical`) where the set cannot give it
NoiseSource = Literal["given", "set", "nominal"]


@dataclass(frozen=True)
class SensorNoise:
    """Temporal noise of the camera: ``σ_I² = read_noise_dn² + gain_dn_per_e·I`` (DN², I in DN).

    ``read_noise_dn`` includes everything independent of the signal (read noise, dark
    current, ADC quantisation 1/12 DN²). :meth:`typical` is a generic CMOS/CCD at the
    ADC's full range: full well 16 000 e⁻, read noise 12 e⁻.
    """

    gain_dn_per_e: float
    read_noise_dn: float

    def __post_init__(self) -> None:
        for name in ("gain_dn_per_e", "read_noise_dn"):
            val = getattr(self, name)
            if not (math.isfinite(val) and val >= 0.0):
                raise ValueError(f"{name}: must be finite and >= 0, got {val}")

    @classmethod
    def typical(cls, max_code: int, *, full_well_e: float = 16000.0,
                read_noise_e: float = 12.0) -> SensorNoise:
        g = max_code / full_well_e
        return cls(g, math.sqrt((g * read_noise_e) ** 2 + 1.0 / 12.0))

    def variance_dn2(self, mean_dn: npt.ArrayLike) -> npt.NDArray[np.float64]:
        return self.read_noise_dn**2 + self.gain_dn_per_e * np.maximum(
            np.asarray(mean_dn, np.float64), 0.0)
