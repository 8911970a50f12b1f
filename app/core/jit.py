"""numba's process-wide settings, made by the entry points before numba is imported.

Importing ``app`` changes no environment variable: the CLI (``fringescope``), the test suite's
``conftest.py`` and the benchmarks call :func:`configure_numba` first, and the processes they
start (Dask's local workers, the server) inherit the result.

- ``NUMBA_THREADING_LAYER=workqueue`` unless given: OpenMP's spinning threads are 8× slower on
  2 cores (:mod:`app.recon.fast`).
- ``NUMBA_CPU_FEATURES``: on a CPU with AVX-512, the host's own features with ``-prefer-256-bit``
  unless given. LLVM's tuning for AVX-512 CPUs prefers 256-bit vectors (against the clock
  penalty of early Skylake servers), which halves the lanes of the fused reconstruction
  kernel's float32 loops; 512-bit vectors cut its CPU time by ~30 % on this project's
  Sapphire Rapids machine with bit-identical outputs (``benchmarks/bench_recon.py``). The
  string names this host's features: a process on another machine must make its own (numba's
  on-disk cache keys its entries by CPU name and features, so the two never mix).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, MutableMapping

#: the LLVM feature that keeps an AVX-512 CPU's loops at 256-bit vectors, switched off
WIDE_VECTORS = "-prefer-256-bit"


def wide_vector_features(host_features: str) -> str | None:
    """The LLVM feature string ``host_features`` ("+avx2,+avx512f,-amx-tile,…", as
    ``llvmlite.binding.get_host_cpu_features().flatten()`` gives it) with 512-bit vectors
    preferred, or None when the CPU has no AVX-512 (nothing to widen)."""
    features = [f for f in host_features.split(",") if f]
    if "+avx512f" not in features:
        return None
    return ",".join([*(f for f in features if f.lstrip("+-") != "prefer-256-bit"), WIDE_VECTORS])


def host_cpu_features() -> str:
    """This machine's LLVM feature string (llvmlite alone: numba is not imported)."""
    import llvmlite.binding as llvm

    llvm.initialize_native_target()
    return str(llvm.get_host_cpu_features().flatten())


def numba_environment(environ: Mapping[str, str]) -> dict[str, str]:
    """The settings of the module docstring that ``environ`` does not give yet (name → value):
    the threading layer, and on an AVX-512 CPU the features preferring 512-bit vectors."""
    missing: dict[str, str] = {}
    if "NUMBA_THREADING_LAYER" not in environ:
        missing["NUMBA_THREADING_LAYER"] = "workqueue"
    if "NUMBA_CPU_FEATURES" not in environ:
        features = wide_vector_features(host_cpu_features())
        if features is not None:
            missing["NUMBA_CPU_FEATURES"] = features
    return missing


def configure_numba(environ: MutableMapping[str, str] | None = None) -> None:
    """Add :func:`numba_environment` to ``environ`` (default ``os.environ``). Call it before numba
    is imported: numba reads ``NUMBA_CPU_FEATURES`` once, when it first compiles or loads a
    kernel."""
    env = os.environ if environ is None else environ
    env.update(numba_environment(env))
