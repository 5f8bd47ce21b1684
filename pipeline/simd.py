"""The vector width of the compiled cores: 512-bit vectors on CPUs with AVX-512.

The hot loops of :mod:`mapping.core` (and others in ``mapping/`` and ``slam/``) keep a lane index innermost
so that LLVM turns them into SIMD instructions over several queries at once. On CPUs with AVX-512, LLVM's
tuning for Intel's cores carries the feature ``prefer-256-bit``: its loop vectoriser then uses 256-bit
vectors, half the width the CPU offers. Numba compiles for the host's CPU features, or for
``NUMBA_CPU_FEATURES`` when that is set; :func:`prefer_wide_vectors` sets it to the host's features without
that preference, so that the same loops run on 512-bit vectors. Each lane computes the same operations at
either width; only a reduction that the vectoriser splits across vector elements (a ``fastmath`` sum along
the vectorised loop) could add in another order.

Numba reads the variable when it is imported, so this runs before: :mod:`pipeline`'s ``__init__`` calls it,
and every entry point (``run.py``, ``python -m pipeline.warmup``, the tests' ``conftest.py``) imports
:mod:`pipeline` first; the processes they start (a Dask cluster's workers, the benchmarks' runs) inherit
the variable. Numba keys its on-disk cache on the features, so the warm-up of ``make env`` fills the
entries the runs load. A user who sets ``NUMBA_CPU_FEATURES``, ``NUMBA_CPU_NAME`` or ``NUMBA_ENABLE_AVX``
keeps numba's own choice (``NUMBA_ENABLE_AVX=1``, numba's default on such CPUs, restores LLVM's 256-bit
preference).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping, MutableMapping

#: LLVM's tuning feature that halves the vectoriser's width on AVX-512 CPUs.
PREFER_256_BIT = "prefer-256-bit"
#: Numba's variables that choose the compiled code's target; any of them set: the user's choice stands.
USER_TARGET_VARIABLES = ("NUMBA_CPU_FEATURES", "NUMBA_CPU_NAME", "NUMBA_ENABLE_AVX")


def host_cpu_features() -> dict[str, bool]:
    """The host CPU's features as LLVM names them (``{"avx512f": True, ...}``); empty where LLVM cannot
    tell."""
    import llvmlite.binding as llvm  # numba's own dependency; imports no numba

    try:
        return dict(llvm.get_host_cpu_features())
    except RuntimeError:
        return {}


def wide_vector_features(features: Mapping[str, bool]) -> str | None:
    """The ``NUMBA_CPU_FEATURES`` value for CPUs with AVX-512 (``features`` as :func:`host_cpu_features`
    gives them): every feature in LLVM's notation, sorted by name as numba lists the host's, and
    ``-prefer-256-bit``; None without AVX-512."""
    if not features.get("avx512f"):
        return None
    listed = ",".join(f"{'+' if features[name] else '-'}{name}" for name in sorted(features))
    return f"{listed},-{PREFER_256_BIT}"


def prefer_wide_vectors(
    environ: MutableMapping[str, str] | None = None, features: Mapping[str, bool] | None = None
) -> str | None:
    """Set ``NUMBA_CPU_FEATURES`` in ``environ`` (default: this process's environment) so that numba compiles
    for 512-bit vectors on an AVX-512 host (``features``: the host's, by default). Returns the value set, or
    None where it leaves things as they are: no AVX-512, a target variable the user set, or (for this
    process's environment) numba already imported, whose configuration has read the environment."""
    environ = os.environ if environ is None else environ
    if any(name in environ for name in USER_TARGET_VARIABLES):
        return None
    if environ is os.environ and "numba" in sys.modules:
        return None
    value = wide_vector_features(host_cpu_features() if features is None else features)
    if value is not None:
        environ["NUMBA_CPU_FEATURES"] = value
    return value
