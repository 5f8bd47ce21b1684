"""Hypothesis profiles of the fuzzing harness.

``ci`` (the default, run by ``make test``): derandomized (the same cases on every run), no example database,
a few dozen cases per property, so the whole harness takes well under a minute. ``long`` (``make fuzz``,
before releases): random cases, thousands per property (``GPOM_FUZZ_EXAMPLES``), the example database in
``.hypothesis/`` so a failure found once is replayed first next time. Every crash found is kept as a
regression input under ``tests/fuzz/corpus/`` and replayed by the plain tests of each fuzz module.
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

_SLOW_OK = [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much]
settings.register_profile(
    "ci", derandomize=True, database=None, max_examples=40, deadline=None, suppress_health_check=_SLOW_OK
)
settings.register_profile(
    "long",
    max_examples=int(os.environ.get("GPOM_FUZZ_EXAMPLES", "6000")),
    deadline=None,
    suppress_health_check=_SLOW_OK,
)
settings.load_profile(os.environ.get("GPOM_FUZZ_PROFILE", "ci"))
