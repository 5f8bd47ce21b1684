"""Exact decimal timestamps, strictly increasing repairs, and the batched number parser."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.numtext import NumberParseError, parse_floats, parse_stamps_ns
from datasets.stamps import decimal_to_ns, longest_increasing_mask, monotone_stamps_ns, ns_to_decimal


@pytest.mark.parametrize(
    ("text", "ns"),
    [
        ("976052857.337530", 976_052_857_337_530_000),
        ("0.000246", 246_000),
        ("12", 12_000_000_000),
        ("-0.958593", -958_593_000),
        ("8.97771e-67", 0),
        ("1.5e3", 1_500_000_000_000),
        ("1.0000000005", 1_000_000_000),  # half to even at the 10th decimal
        ("1.0000000015", 1_000_000_002),
        (".25", 250_000_000),
    ],
)
def test_decimal_to_ns_is_exact(text: str, ns: int) -> None:
    assert decimal_to_ns(text) == ns
    assert decimal_to_ns(text.encode()) == ns


def test_float_parsing_would_not_be_exact() -> None:
    """The reason for parsing text: float64 seconds lose the microseconds of an epoch stamp."""
    assert round(float("976052857.337531") * 1e9) != 976_052_857_337_531_000
    assert decimal_to_ns("976052857.337531") == 976_052_857_337_531_000


@pytest.mark.parametrize("text", ["nan", "inf", "1.2.3", "", "abc", "1e"])
def test_decimal_to_ns_rejects(text: str) -> None:
    with pytest.raises(ValueError):
        decimal_to_ns(text)


def test_ns_to_decimal_round_trip() -> None:
    for ns in [0, 1, 976_052_857_337_530_000, -958_593_000, 5_500_000_000]:
        assert decimal_to_ns(ns_to_decimal(ns)) == ns
    assert ns_to_decimal(5_500_000_000) == "5.500000000"
    assert ns_to_decimal(-958_593_000) == "-0.958593000"


def test_longest_increasing_mask() -> None:
    values = np.array([1, 2, 9, 3, 4, 5, 0, 6])
    assert values[longest_increasing_mask(values)].tolist() == [1, 2, 3, 4, 5, 6]
    assert longest_increasing_mask(np.array([], dtype=np.int64)).tolist() == []


def test_monotone_stamps_repairs_glitches_in_line_order() -> None:
    s = np.array([100, 200, 950, 400, 500, 0, 700, 800], dtype=np.int64)
    fixed, restamped = monotone_stamps_ns(s)
    assert restamped.tolist() == [False, False, True, False, False, True, False, False]
    assert fixed.tolist() == [100, 200, 300, 400, 500, 600, 700, 800]
    # already increasing: untouched
    ok = np.array([1, 5, 9], dtype=np.int64)
    assert monotone_stamps_ns(ok)[0].tolist() == [1, 5, 9] and not monotone_stamps_ns(ok)[1].any()


def test_monotone_stamps_ends_and_ties() -> None:
    s = np.array([999, 10, 20, 30, 20, 20], dtype=np.int64)
    fixed, restamped = monotone_stamps_ns(s)
    assert np.all(np.diff(fixed) > 0)
    assert fixed.tolist() == [0, 10, 20, 30, 40, 50]
    assert restamped.tolist() == [True, False, False, False, True, True]
    # equal stamps closer than one ns per record still come out strictly increasing
    fixed, _ = monotone_stamps_ns(np.array([5, 5, 5, 6], dtype=np.int64))
    assert np.all(np.diff(fixed) > 0)


def test_parse_floats_matches_python_float() -> None:
    rng = np.random.default_rng(1)
    tokens = [f"{x:.{rng.integers(0, 12)}f}" for x in rng.normal(0, 1e4, 20_000)]
    tokens += ["1e5", "nan", "-inf", "+3.5", ".5", "5.", "-0.0", "12345678901234567", "0.000000000001"]
    tokens += [f"{x:.2f}" for x in rng.uniform(0, 82, 300_000)]  # more than one chunk of text
    values = parse_floats(" ".join(tokens).encode())
    np.testing.assert_array_equal(values, np.array([float(t) for t in tokens]))


def test_parse_stamps_matches_decimal() -> None:
    rng = np.random.default_rng(2)
    tokens = [f"{rng.integers(0, 4_000_000_000)}.{rng.integers(0, 10**6):06d}" for _ in range(5000)]
    tokens += ["-0.958593", "8.97771e-67", "0", "1.1234567891", "123.", "9000000000.5"]
    stamps = parse_stamps_ns(" ".join(tokens).encode())
    assert stamps.tolist() == [decimal_to_ns(t) for t in tokens]


@pytest.mark.parametrize(
    ("blob", "index", "token"), [("1 2 x 4", 2, "x"), ("1 2 1.2.3", 2, "1.2.3"), ("1 -", 1, "-")]
)
def test_parse_floats_names_the_bad_token(blob: str, index: int, token: str) -> None:
    with pytest.raises(NumberParseError) as info:
        parse_floats(blob.encode())
    assert info.value.index == index and info.value.token == token


def test_parse_stamps_rejects_nan() -> None:
    with pytest.raises(NumberParseError) as info:
        parse_stamps_ns(b"1.0 nan")
    assert info.value.index == 1
