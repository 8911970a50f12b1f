"""Shared simulated worlds (the geometry precompute takes seconds; build each once)."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

from app.devices.sim import SimulatedWorld


@pytest.fixture(scope="session")
def plane_world() -> SimulatedWorld:
    """Matte grey plane, undistorted camera."""
    w = SimulatedWorld("plane", seed=1, distortion=False)
    _ = w.renderer
    return w


@pytest.fixture(scope="session")
def dof_world() -> SimulatedWorld:
    """45° depth-of-field target (heights 0–20 mm), undistorted camera."""
    w = SimulatedWorld("dof_target", seed=2, distortion=False)
    _ = w.renderer
    return w
