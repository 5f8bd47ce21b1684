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


# ``meta["no_return"]`` of every real CARMEN log, as measured before the rule was made to ignore wall hits
# spread over neighbouring 1-cm steps at the top of short logs (they must not change with it)
_REAL_NO_RETURN: dict[str, tuple[float, tuple[float, ...]]] = {
    "intel/intel.clf.bz2": (80.0, (81.83,)),
    "intel/intel.gfs.log": (80.0, (81.83,)),
    "fr079/fr079.clf.bz2": (80.0, (81.91,)),
    "fr079/freiburg-079-corrected.log.gz": (80.0, (81.91,)),
    "fr-clinic/fr-clinic_robotlaser.clf.bz2": (81.83, (81.83, 81.91)),
    "radish-corrected/acapulco-corrected.log.gz": (50.0, (50.0, 51.14, 51.15, 51.16)),
    "radish-corrected/belgioioso-corrected.log.gz": (80.0, (81.91,)),
    "radish-corrected/edmonton-corrected.log.gz": (51.1, (51.1, 51.14, 51.15, 51.16)),
    "radish-corrected/fhw-corrected.log.gz": (51.05, (51.05, 51.1)),
    "radish-corrected/freiburg-101-corrected.log.gz": (80.0, (81.91,)),
    "radish-corrected/freiburg-campus-corrected.log.gz": (80.0, (81.83, 81.91)),
    "radish-corrected/infinite-corridor-corrected.log.gz": (51.05, (51.05, 51.06, 51.07, 51.11)),
    "radish-corrected/orebro-corrected.log.gz": (32.759, (32.759, 32.763, 32.767)),
    "radish-corrected/seattle-corrected.log.gz": (80.0, (81.87, 81.91)),
}


@pytest.mark.parametrize("log", sorted(_REAL_NO_RETURN))
def test_no_return_of_every_real_log(log: str) -> None:
    range_m, values_m = _REAL_NO_RETURN[log]
    no_return = read_carmen(data_file(log)).meta["no_return"]
    assert no_return["range_m"] == range_m
    assert tuple(no_return.get("values_m", no_return.get("repeated_maximum_m"))) == values_m
