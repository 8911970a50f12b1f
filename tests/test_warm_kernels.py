"""scripts/warm_kernels.py: it compiles the fused kernel the product's paths then run.

``make test`` runs it before the suite so a fresh checkout's first reconstructions load the
kernel from numba's cache instead of compiling it (~45 s a frame dtype); a warm-up whose
argument types drifted from the product's would compile a specialisation nobody uses.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

from app.devices.sim.ideal import ideal_calibration
from app.devices.sim.offline import render_capture_set
from app.devices.sim.optics import rig_by_name
from app.recon import Reconstructor
from app.recon import fast as fast_recon

TOOL = Path(__file__).resolve().parents[1] / "scripts" / "warm_kernels.py"

pytestmark = pytest.mark.slow


def _warm_kernels() -> ModuleType:
    spec = importlib.util.spec_from_file_location("warm_kernels", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(("rig", "dtype_name"), [("default", "uint8"), ("endoscope", "uint16")])
def test_the_twins_sets_run_the_specialisation_the_warm_up_compiled(rig: str,
                                                                   dtype_name: str) -> None:
    warm_kernels = _warm_kernels()
    warm_kernels.warm(dtype_name)
    compiled = set(fast_recon.fused_kernel.signatures)
    capture, _, _ = render_capture_set("dof_target", seed=2, rig=rig)
    assert capture.frames.dtype.name == dtype_name
    result = Reconstructor(ideal_calibration(rig_by_name(rig))).run(capture.frames)
    assert result.valid.mean() > 0.5
    assert set(fast_recon.fused_kernel.signatures) == compiled


def test_an_unknown_dtype_is_one_line_and_exit_code_2() -> None:
    proc = subprocess.run([sys.executable, str(TOOL), "float32"], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "warm_kernels: give frame dtypes among uint8, uint16 (not 'float32')"]
    assert proc.stdout == ""
