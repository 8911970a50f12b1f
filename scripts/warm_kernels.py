"""Compile the reconstruction's numba kernels into ``NUMBA_CACHE_DIR`` before they are needed.

    python scripts/warm_kernels.py uint8 [uint16 …]

Reconstructs a small set of the analytic rig per frame dtype, through the same public path a
user takes (``Reconstructor(cal).run(frames)``, the noise fitted to the set), so the kernels
compiled are the ones a later process loads: the fused kernel for that dtype, the noise fit's
and the points' kernels. The fused kernel takes ~45 s to compile per dtype on a 2-core
machine, half of it numba's own passes (``NUMBA_OPT=0`` still takes 40 s), and a fresh
checkout has no cache. ``make test`` runs this beside the type check, one dtype per process
(staggered, so the two never rewrite numba's cache index at once), so the suite starts with
the kernels cached. Prints one line per dtype with its seconds; exit code 2 on a bad argument.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.jit import configure_numerics

configure_numerics()  # before numba is imported: the settings the suite's processes run with

import numpy as np  # noqa: E402

from app.core.limits import full_scale  # noqa: E402
from app.devices.sim.analytic_rig import Rig, bump_surface  # noqa: E402
from app.recon import Reconstructor  # noqa: E402

#: the frame dtypes the fused kernel is specialised for, with the sensor bit depth the set is
#: rendered at (a 12-bit camera in 16-bit words)
FRAME_DTYPES: dict[str, tuple[type, int]] = {"uint8": (np.uint8, 8), "uint16": (np.uint16, 12)}


def warm(dtype_name: str) -> float:
    """Reconstruct a 96 × 64 set of ``dtype_name`` frames once; returns the seconds taken."""
    frame_type, bit_depth = FRAME_DTYPES[dtype_name]
    top = full_scale(bit_depth)
    scale = (top + 1) / 256
    rig = Rig(width=96, height=64, focal_px=120.0)
    t0 = time.perf_counter()
    frames = rig.render(bump_surface(rig), background=110 * scale, amplitude=90 * scale,
                        noise=1.0 * scale, dtype=frame_type, max_code=top)
    result = Reconstructor(rig.calibration(), max_code=top).run(frames)
    if not result.valid.any():
        raise RuntimeError("the warm-up set reconstructed no valid pixel")
    _ = result.points  # made on first read, by its own kernel
    return time.perf_counter() - t0


def main(argv: list[str]) -> int:
    unknown = [a for a in argv if a not in FRAME_DTYPES]
    if not argv or unknown:
        print(f"warm_kernels: give frame dtypes among {', '.join(FRAME_DTYPES)}"
              f"{f' (not {unknown[0]!r})' if unknown else ''}", file=sys.stderr)
        return 2
    for name in argv:
        print(f"warm_kernels: {name} kernels ready in {warm(name):.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
