"""The numeric libraries' process-wide settings (numba, OpenBLAS), made by the entry points
before numpy or numba is imported.

Importing ``app`` changes no environment variable: the CLI (``fringescope``), the test suite's
``conftest.py`` and the benchmarks call :func:`configure_numerics` first, and the processes they
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
- ``OPENBLAS_NUM_THREADS=1`` unless given. The OpenBLAS that numpy and scipy bundle starts one
  thread per CPU and busy-waits between calls; Fringescope's BLAS work is small (the suture
  fit's SVD of a tall Jacobian per step, the noise fit's normal equations), so on a machine
  whose cores also run the acquisition and reconstruction threads the waiting threads take the
  cores from the thread doing the work: 8 suture fits (``feature_height``) took 11–15 s CPU and
  34 s wall with the default threads against 1.9–2.1 s CPU and 6–13 s wall with one, on this
  project's 2-vCPU machine at load 3–5, results bit-identical. OpenBLAS reads the variable once,
  when it loads: set too late, it changes nothing in this process (a warning says so).
"""

from __future__ import annotations

import os
import sys
import warnings
from collections.abc import Mapping, MutableMapping

#: the variable OpenBLAS reads when it loads, and the thread count Fringescope runs it with
BLAS_THREADS_VARIABLE = "OPENBLAS_NUM_THREADS"
BLAS_THREADS = "1"

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


def numeric_environment(environ: Mapping[str, str]) -> dict[str, str]:
    """The settings of the module docstring that ``environ`` does not give yet (name → value):
    numba's threading layer, on an AVX-512 CPU the features preferring 512-bit vectors, and
    OpenBLAS's thread count."""
    missing: dict[str, str] = {}
    if BLAS_THREADS_VARIABLE not in environ:
        missing[BLAS_THREADS_VARIABLE] = BLAS_THREADS
    if "NUMBA_THREADING_LAYER" not in environ:
        missing["NUMBA_THREADING_LAYER"] = "workqueue"
    if "NUMBA_CPU_FEATURES" not in environ:
        features = wide_vector_features(host_cpu_features())
        if features is not None:
            missing["NUMBA_CPU_FEATURES"] = features
    return missing


def configure_numerics(environ: MutableMapping[str, str] | None = None) -> None:
    """Add :func:`numeric_environment` to ``environ`` (default ``os.environ``). Call it before
    numpy and numba are imported: OpenBLAS reads its thread count when it loads, numba
    ``NUMBA_CPU_FEATURES`` when it first compiles or loads a kernel. Warns when this process's
    OpenBLAS has already loaded without the setting (the processes it starts still get it)."""
    env = os.environ if environ is None else environ
    missing = numeric_environment(env)
    if environ is None and BLAS_THREADS_VARIABLE in missing and "numpy" in sys.modules:
        warnings.warn(f"numpy was imported before configure_numerics(): {BLAS_THREADS_VARIABLE} "
                      "is too late for this process", stacklevel=2)
    env.update(missing)
