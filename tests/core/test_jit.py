"""numba's process settings (app/core/jit.py): threading layer and 512-bit vectors."""

from __future__ import annotations

import pytest

from app.core.jit import WIDE_VECTORS, configure_numba, host_cpu_features, wide_vector_features

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
    env = {"NUMBA_THREADING_LAYER": "omp", "NUMBA_CPU_FEATURES": "+sse2"}
    configure_numba(env)
    assert env == {"NUMBA_THREADING_LAYER": "omp", "NUMBA_CPU_FEATURES": "+sse2"}


def test_configure_sets_the_defaults_from_this_host() -> None:
    env: dict[str, str] = {}
    configure_numba(env)
    assert env["NUMBA_THREADING_LAYER"] == "workqueue"
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
