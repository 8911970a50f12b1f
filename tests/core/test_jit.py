"""The numeric process settings (app/core/jit.py): numba's threading layer and 512-bit vectors,
OpenBLAS's thread count."""

from __future__ import annotations

import subprocess
import sys

import pytest

from app.core.jit import (
    BLAS_THREADS,
    BLAS_THREADS_VARIABLE,
    WIDE_VECTORS,
    configure_numerics,
    host_cpu_features,
    wide_vector_features,
)

AVX512_HOST = "+sse2,+avx2,+avx512f,+avx512bw,-amx-tile,+fma"


def test_avx512_host_prefers_512_bit_vectors_and_keeps_its_features() -> None:
    features = wide_vector_features(AVX512_HOST)
    assert features == AVX512_HOST + "," + WIDE_VECTORS


def test_a_given_prefer_256_bit_is_replaced_not_contradicted() -> None:
    features = wide_vector_features(AVX512_HOST + ",+prefer-256-bit")
    assert features is not None
    assert features.split(",").count(WIDE_VECTORS) == 1
    assert "+prefer-256-bit" not in features.split(",")


@pytest.mark.parametrize("host", ["+sse2,+avx2,+fma", "+sse2,+avx2,-avx512f", ""])
def test_no_avx512_nothing_to_widen(host: str) -> None:
    assert wide_vector_features(host) is None


def test_configure_keeps_what_is_given() -> None:
    given = {"NUMBA_THREADING_LAYER": "omp", "NUMBA_CPU_FEATURES": "+sse2",
             BLAS_THREADS_VARIABLE: "4"}
    env = dict(given)
    configure_numerics(env)
    assert env == given


def test_configure_sets_the_defaults_from_this_host() -> None:
    env: dict[str, str] = {}
    configure_numerics(env)
    assert env["NUMBA_THREADING_LAYER"] == "workqueue"
    assert env[BLAS_THREADS_VARIABLE] == BLAS_THREADS == "1"
    assert env.get("NUMBA_CPU_FEATURES") == wide_vector_features(host_cpu_features())


def test_the_test_process_compiles_as_configured() -> None:
    """conftest.py configures numba before it is imported: its code generator uses the features
    (so the kernel tests run the code the CLI runs)."""
    import os

    from numba.core.registry import cpu_target

    expected = os.environ.get("NUMBA_CPU_FEATURES")
    _, _, features = cpu_target.target_context.codegen().magic_tuple()
    if expected is None:
        assert WIDE_VECTORS not in features
    else:
        assert features == expected
        assert features.endswith(WIDE_VECTORS)


def test_the_cli_configures_before_numpy_loads() -> None:
    """OpenBLAS reads its thread count once, when numpy loads it: importing the CLI package
    (whose ``main`` configures the process first) must not load numpy."""
    code = "import sys, app.cli; print('numpy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"

