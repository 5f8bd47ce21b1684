"""The vector width numba compiles for (pipeline.simd): 512 bits on AVX-512 hosts, users' settings kept."""

from __future__ import annotations

import os

import numba as nb
import numpy as np
import pytest

from pipeline.simd import PREFER_256_BIT, host_cpu_features, prefer_wide_vectors, wide_vector_features

AVX512_HOST = {"avx2": True, "avx512f": True, "avx512bw": True, "sse4.2": True, "xop": False}


def test_wide_features_list_every_host_feature_sorted_and_drop_the_256_bit_preference() -> None:
    value = wide_vector_features(AVX512_HOST)
    assert value == "+avx2,+avx512bw,+avx512f,+sse4.2,-xop,-prefer-256-bit"


def test_no_avx512_no_setting() -> None:
    assert wide_vector_features({"avx2": True, "avx512f": False}) is None
    assert wide_vector_features({"avx2": True}) is None
    env: dict[str, str] = {}
    assert prefer_wide_vectors(env, {"avx2": True}) is None
    assert env == {}


def test_sets_the_variable_on_an_avx512_host() -> None:
    env = {"PATH": "/bin"}
    value = prefer_wide_vectors(env, AVX512_HOST)
    assert value is not None and env["NUMBA_CPU_FEATURES"] == value
    assert value.endswith(f",-{PREFER_256_BIT}")


@pytest.mark.parametrize("name", ["NUMBA_CPU_FEATURES", "NUMBA_CPU_NAME", "NUMBA_ENABLE_AVX"])
def test_a_users_target_setting_stands(name: str) -> None:
    env = {name: "1"}
    assert prefer_wide_vectors(env, AVX512_HOST) is None
    assert env == {name: "1"}


def test_this_process_compiles_for_the_width_set() -> None:
    """conftest.py imports :mod:`pipeline` before numba: numba's code generator got the setting, and a lane
    loop compiles to 512-bit instructions (zmm registers) on an AVX-512 host. Skipped where the host has no
    AVX-512 or where the environment the tests started in chose numba's target itself."""
    expected = wide_vector_features(host_cpu_features())
    if expected is None:
        pytest.skip("the host has no AVX-512: numba keeps its default target")
    users = any(name in os.environ for name in ("NUMBA_CPU_NAME", "NUMBA_ENABLE_AVX"))
    if users or os.environ.get("NUMBA_CPU_FEATURES") not in (None, expected):
        pytest.skip("the environment sets numba's target: the user's choice stands")
    from numba.core.registry import cpu_target

    features = cpu_target.target_context.codegen().magic_tuple()[2]
    assert features.endswith(f",-{PREFER_256_BIT}")

    @nb.njit(fastmath=True)  # not cached: its assembly is inspected
    def lanes(a: np.ndarray, b: np.ndarray) -> None:
        for i in range(a.size):
            a[i] = a[i] * b[i] + 1.0

    a, b = np.ones(64), np.full(64, 2.0)
    lanes(a, b)
    assert np.all(a == 3.0)
    assembly = next(iter(lanes.inspect_asm().values()))
    assert "zmm" in assembly
