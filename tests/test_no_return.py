"""No-return readings logged as a fixed number: found per recording, on synthetic and real logs."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.carmen import read_carmen
from datasets.no_return import repeated_maximum_m
from tests.conftest import data_file


def _ranges(rng: np.random.Generator, n: int, codes: dict[float, int]) -> np.ndarray:
    real = np.round(rng.gamma(2.0, 3.0, n), 3)  # a smooth spread of real returns up to ~40 m
    return np.concatenate([real, *[np.full(c, v) for v, c in codes.items()]])


def test_a_repeated_top_value_is_found_and_a_repeated_near_reading_is_not() -> None:
    rng = np.random.default_rng(0)
    r = _ranges(rng, 50_000, {50.0: 400, 51.14: 900, 51.15: 3000})
    found = repeated_maximum_m(r)
    assert found is not None and found.value_m == 50.0 and found.values_m == (50.0, 51.14, 51.15)
    assert found.counts == (400, 900, 3000)
    # a robot parked in front of a wall repeats 1.39 m thousands of times: not at the top, not a code
    parked = np.concatenate([_ranges(rng, 50_000, {}), np.full(4000, 1.39)])
    assert repeated_maximum_m(parked) is None
    # a code too rare to tell from chance is not taken either
    assert repeated_maximum_m(_ranges(rng, 50_000, {80.0: 5})) is None


@pytest.mark.parametrize(
    ("log", "rule", "range_m"),
    [
        ("radish-corrected/edmonton-corrected.log.gz", "the log's repeated maximum reading", 51.1),
        ("radish-corrected/orebro-corrected.log.gz", "the log's repeated maximum reading", 32.759),
        ("intel/intel.gfs.log", "input.carmen_range_max_m", 80.0),  # 81.83 lies beyond 80 m anyway
        ("fr-clinic/fr-clinic_robotlaser.clf.bz2", "the log's repeated maximum reading", 81.83),
    ],
)
def test_the_carmen_reader_says_which_no_return_rule_it_used(log: str, rule: str, range_m: float) -> None:
    rec = read_carmen(data_file(log))
    assert rec.meta["no_return"]["rule"] == rule
    assert rec.meta["no_return"]["range_m"] == pytest.approx(range_m)
    assert np.allclose(rec.scans.range_max_m, range_m, atol=1e-5)
