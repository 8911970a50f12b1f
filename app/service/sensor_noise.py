"""The camera's temporal noise, measured from the live fringe sets.

The live engine's σ and its validity rule (:mod:`app.recon.validity`) need the camera's
noise, σ_I² = read² + gain·I. :meth:`SensorNoise.typical` is a guess (a generic sensor at the
ADC's range); on the real CFPE captures it was 1.3–1.7× optimistic, which turns the rule's
1e-6 order-error bound into ~1e-3. So the live service measures it: every
``interval_s`` it fits the N-step residual of the newest set
(:func:`app.recon.noise.estimate_sensor_noise`, N > 3); the reconstruction thread
passes the model in use to the engine with every set (``Reconstructor.run(frames,
noise=...)``: σ, the validity rule, the order and motion tests), the engine itself is
never changed.

Read noise and gain belong to the sensor, not to the scene. Motion between a group's frames and
projector harmonics only ADD to the residual, so the quietest estimate seen so far (compared at
a quarter of full scale) is kept: a moving scene can make the noise model too pessimistic
(fewer valid pixels, larger σ) until a stiller set is seen, never too optimistic by more than
the estimate's own scatter (a few per cent in variance over thousands of pixels).

With N = 4 the same fit reads the projector's 2nd harmonic, from which a power-law gamma
gives the phase-error table of the aliased 3rd and 5th (:mod:`app.recon.gamma_model`); the
newest set's table is kept for its schedule and passed with the noise
(``Reconstructor.run(frames, noise=..., phase_error=...)``): the projector, not the
scene, makes it, and the engine uses a learned table instead where it has one.
"""

from __future__ import annotations

import logging
import math
import threading

import numpy as np

from app.core.schedule import PatternSchedule
from app.recon.gamma import PhaseErrorLUT
from app.recon.noise import resolve_set_noise
from app.recon.sensor import SensorNoise

log = logging.getLogger(__name__)

#: the intensity at which two estimates are compared, as a fraction of full scale
REFERENCE_FRACTION = 0.25


class LiveNoise:
    """The quietest noise estimate from the live sets of one sensor range (thread-safe).

    Args:
        interval_s: seconds between estimates (each costs ~0.1 s of the reconstruction
            thread, taken after a result is published); 0 turns measuring off (the engine
            keeps its own model, :meth:`SensorNoise.typical` by default).
    """

    def __init__(self, interval_s: float = 30.0) -> None:
        if not (math.isfinite(interval_s) and interval_s >= 0.0):
            raise ValueError(f"interval_s: must be finite and >= 0, got {interval_s}")
        self.interval_s = float(interval_s)
        self._lock = threading.Lock()
        self._noise: SensorNoise | None = None
        self._table: tuple[PatternSchedule, PhaseErrorLUT] | None = None
        self._max_code: int | None = None
        self._next_s = -math.inf
        self.estimates = 0

    @property
    def current(self) -> SensorNoise | None:
        """The model in use (None: nothing measured yet, or measuring off)."""
        with self._lock:
            return self._noise

    def phase_error(self, schedule: PatternSchedule) -> PhaseErrorLUT | None:
        """The projector-gamma table the newest estimate of ``schedule``'s sets gave (None:
        none yet, N ≠ 4, or it was measured on another schedule)."""
        with self._lock:
            if self._table is None or self._table[0] != schedule:
                return None
            return self._table[1]

    def due(self, now_s: float, schedule: PatternSchedule) -> bool:
        """Whether a set taken now with ``schedule`` should be measured (N = 3 has no residual)."""
        return self.interval_s > 0.0 and schedule.steps > 3 and now_s >= self._next_s

    def update(self, frames: object, schedule: PatternSchedule, max_code: int,
               now_s: float) -> SensorNoise | None:
        """Fit one set's residual; keep it if it is quieter than the model so far (or the sensor
        range changed). Returns the model in use afterwards."""
        self._next_s = now_s + self.interval_s
        found = resolve_set_noise(frames, schedule, max_code)
        if found.source != "set":  # too few usable pixels (dark, saturated): try again later
            log.debug("live noise estimate: %s", found.note)
            return self.current
        est = found.noise
        ref = REFERENCE_FRACTION * max_code
        with self._lock:
            self.estimates += 1
            self._table = None if found.phase_error is None else (schedule, found.phase_error)
            if (self._noise is None or self._max_code != max_code
                    or float(est.variance_dn2(ref)) < float(self._noise.variance_dn2(ref))):
                self._noise, self._max_code = est, max_code
            return self._noise

    def describe(self) -> dict[str, object]:
        """For the status: the model in use and where it comes from."""
        noise = self.current
        with self._lock:
            table = None if self._table is None else self._table[1]
        gamma: dict[str, object] = {"gamma_table_rms_rad": None if table is None else round(
            float(np.sqrt(np.mean(table.error_rad**2))), 6)}
        if noise is None:
            return {"source": "nominal" if self.interval_s > 0 else "nominal (measuring off)",
                    "read_noise_dn": None, "gain_dn_per_e": None, "estimates": self.estimates,
                    **gamma}
        return {"source": "measured", "read_noise_dn": round(noise.read_noise_dn, 4),
                "gain_dn_per_e": round(noise.gain_dn_per_e, 6), "estimates": self.estimates,
                **gamma}
