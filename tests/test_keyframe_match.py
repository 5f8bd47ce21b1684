"""Finding the scans of a corrected keyframe log in its raw log: by logger stamp, else by content and line
order (intel.gfs.log -> intel.clf, freiburg-079-corrected -> fr079.clf, and modified copies in tmp_path)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from datasets.carmen import match_scans
from datasets.errors import DatasetError
from datasets.keyframe_match import ScanMatch, _longest_increasing, match_keyframe_scans
from datasets.registry import open_dataset
from datasets.types import Recording
from pipeline.evaluate_slam import match_reference, match_reference_counted
from tests.conftest import data_file

# measured: indices of today's stamp matching (all ranges equal; no two raw scans have equal ranges)
INTEL_FIRST, INTEL_LAST, INTEL_SUM = 169, 13_583, 6_345_012
FR079_FIRST, FR079_LAST, FR079_SUM = 1, 4_933, 11_735_907


@pytest.fixture(scope="module")
def intel_clf() -> Recording:
    return open_dataset(data_file("intel/intel.clf.bz2"))


@pytest.fixture(scope="module")
def intel_gfs() -> Recording:
    return open_dataset(data_file("intel/intel.gfs.log"))


@pytest.fixture(scope="module")
def intel_match(intel_gfs: Recording, intel_clf: Recording) -> ScanMatch:
    return match_keyframe_scans(intel_gfs, intel_clf)


def _rewrite(
    tmp_path: Path,
    stamp: Callable[[str], str] = lambda t: t,
    ranges: Callable[[int, list[str]], list[str]] = lambda j, r: r,
) -> Path:
    """A copy of intel.gfs.log in tmp_path with every FLASER / ODOM ipc and logger stamp passed through
    ``stamp`` and the ranges of FLASER record j through ``ranges(j, texts)``."""
    out = []
    j = 0
    for line in data_file("intel/intel.gfs.log").read_text().splitlines():
        toks = line.split()
        if toks and toks[0] in ("FLASER", "ODOM"):
            toks[-3], toks[-1] = stamp(toks[-3]), stamp(toks[-1])
            if toks[0] == "FLASER":
                n = int(toks[1])
                toks[2 : 2 + n] = ranges(j, toks[2 : 2 + n])
                j += 1
            line = " ".join(toks)
        out.append(line)
    path = tmp_path / "intel.gfs.log"  # named as a corrected log, so that its poses are the reference
    path.write_text("\n".join(out) + "\n")
    return path


def _assert_same_as_stamps(found: ScanMatch, keyframes: Recording, full: Recording) -> None:
    idx = found.indices
    assert np.all(np.diff(idx) > 0)
    assert (int(idx[0]), int(idx[-1]), int(idx.sum())) == (INTEL_FIRST, INTEL_LAST, INTEL_SUM)
    for j in range(0, len(idx), 7):
        np.testing.assert_array_equal(keyframes.scans.ranges_m[j], full.scans.ranges_m[int(idx[j])])


def test_intel_matches_by_stamp_as_before(intel_gfs: Recording, intel_clf: Recording, intel_match) -> None:
    found = intel_match
    assert found.counts == {"stamp": 910, "content_order": 0, "unmatched": 0}
    assert np.all(found.matched) and found.unmatched.size == 0
    # the corrected log writes the ranges exactly (%g of 2-decimal values): no rounding to tolerate
    assert np.all(found.range_error_m == 0.0)
    _assert_same_as_stamps(found, intel_gfs, intel_clf)
    clf_logger = intel_clf.meta["logger_stamps_ns"]
    assert np.abs(clf_logger[found.indices] - intel_gfs.meta["logger_stamps_ns"]).max() <= 5_000_000
    # the thin path returns the same indices
    np.testing.assert_array_equal(match_scans(intel_gfs, intel_clf), found.indices)


def test_fr079_matches_by_stamp_as_before() -> None:
    raw = open_dataset(data_file("fr079/fr079.clf.bz2"))
    corrected = open_dataset(data_file("fr079/freiburg-079-corrected.log.gz"))
    found = match_keyframe_scans(corrected, raw)
    assert found.counts == {"stamp": 4_791, "content_order": 0, "unmatched": 0}
    idx = found.indices
    assert (int(idx[0]), int(idx[-1]), int(idx.sum())) == (FR079_FIRST, FR079_LAST, FR079_SUM)
    assert np.all(np.diff(idx) > 0) and np.all(found.range_error_m == 0.0)
    # without any stamps, content and line order find the same scans
    no_stamps = {k: v for k, v in corrected.meta.items() if k != "logger_stamps_ns"}
    by_content = match_keyframe_scans(_with_meta(corrected, no_stamps), raw)
    assert by_content.counts == {"stamp": 0, "content_order": 4_791, "unmatched": 0}
    np.testing.assert_array_equal(by_content.indices, idx)


def _with_meta(rec: Recording, meta: dict) -> Recording:
    from dataclasses import replace

    return replace(rec, meta=meta)


@pytest.mark.parametrize(
    ("name", "stamp"),
    [("zero", lambda t: "0"), ("shifted by 1000 s", lambda t: f"{float(t) + 1000.0:.6f}")],
)
def test_intel_with_unusable_stamps_matches_by_content_and_order(
    tmp_path: Path, intel_clf: Recording, intel_match: ScanMatch, name: str, stamp: Callable
) -> None:
    gfs = open_dataset(_rewrite(tmp_path, stamp=stamp))
    found = match_keyframe_scans(gfs, intel_clf)
    assert found.counts == {"stamp": 0, "content_order": 910, "unmatched": 0}, name
    np.testing.assert_array_equal(found.indices, intel_match.indices)
    assert set(found.methods.tolist()) == {"content_order"}
    _assert_same_as_stamps(found, gfs, intel_clf)
    # evaluate slam's matching says how
    scans, rows, counts = match_reference_counted(intel_clf, gfs)
    assert counts == found.counts
    np.testing.assert_array_equal(scans, intel_match.indices)
    np.testing.assert_array_equal(rows, np.arange(910))


def test_stamps_wrong_for_a_block_are_bridged_by_content(
    tmp_path: Path, intel_clf: Recording, intel_match: ScanMatch
) -> None:
    # keyframes 300-399 carry stamps 3 s late: the stamp window holds other scans, content finds theirs
    lines = data_file("intel/intel.gfs.log").read_text().splitlines()
    flaser = [i for i, line in enumerate(lines) if line.startswith("FLASER")]
    for i in flaser[300:400]:
        toks = lines[i].split()
        toks[-3] = toks[-1] = f"{float(toks[-1]) + 3.0:.6f}"
        lines[i] = " ".join(toks)
    path = tmp_path / "intel.gfs.log"
    path.write_text("\n".join(lines) + "\n")
    found = match_keyframe_scans(open_dataset(path), intel_clf)
    assert found.counts == {"stamp": 810, "content_order": 100, "unmatched": 0}
    assert set(found.methods[300:400].tolist()) == {"content_order"}
    np.testing.assert_array_equal(found.indices, intel_match.indices)


def test_rounded_ranges_within_the_tolerance_still_match(
    tmp_path: Path, intel_clf: Recording, intel_match: ScanMatch
) -> None:
    # a corrected log whose ranges are 4 mm off (e.g. rounded differently) on every other beam
    def shift(j: int, texts: list[str]) -> list[str]:
        return [f"{float(t) + (0.004 if b % 2 else 0.0):.3f}" for b, t in enumerate(texts)]

    with_stamps = match_keyframe_scans(open_dataset(_rewrite(tmp_path, ranges=shift)), intel_clf)
    assert with_stamps.counts == {"stamp": 910, "content_order": 0, "unmatched": 0}
    np.testing.assert_array_equal(with_stamps.indices, intel_match.indices)
    np.testing.assert_allclose(with_stamps.range_error_m, 0.004, atol=1e-5)
    (tmp_path / "zero").mkdir()
    no_stamps = match_keyframe_scans(
        open_dataset(_rewrite(tmp_path / "zero", stamp=lambda t: "0", ranges=shift)), intel_clf
    )
    assert no_stamps.counts == {"stamp": 0, "content_order": 910, "unmatched": 0}
    np.testing.assert_array_equal(no_stamps.indices, intel_match.indices)


@pytest.mark.parametrize("stamps", ["kept", "zero"])
def test_a_scan_missing_from_the_raw_log_is_reported(
    tmp_path: Path, intel_clf: Recording, intel_match: ScanMatch, stamps: str
) -> None:
    # keyframe 500's ranges exist nowhere in intel.clf (every beam 0.5 m longer)
    def alter(j: int, texts: list[str]) -> list[str]:
        return [f"{float(t) + 0.5:.2f}" for t in texts] if j == 500 else texts

    stamp = (lambda t: t) if stamps == "kept" else (lambda t: "0")
    path = _rewrite(tmp_path, stamp=stamp, ranges=alter)
    gfs = open_dataset(path)
    found = match_keyframe_scans(gfs, intel_clf)
    assert found.unmatched.tolist() == [500]
    assert found.indices[500] == -1 and found.methods[500] == "unmatched"
    assert np.isnan(found.range_error_m[500])
    expected = {"stamp": 909, "content_order": 0} if stamps == "kept" else {"stamp": 0, "content_order": 909}
    assert found.counts == {**expected, "unmatched": 1}
    keep = np.arange(910) != 500
    np.testing.assert_array_equal(found.indices[keep], intel_match.indices[keep])
    # the indices-only path refuses, naming the scan
    with pytest.raises(DatasetError, match=r"1 of 910 scans .* the first is scan 500"):
        match_scans(gfs, intel_clf)
    # evaluate slam uses the matched scans only, with their reference rows
    scans, rows = match_reference(intel_clf, gfs)
    np.testing.assert_array_equal(rows, np.flatnonzero(keep))
    np.testing.assert_array_equal(scans, intel_match.indices[keep])
    assert match_reference_counted(intel_clf, gfs)[2] == found.counts


def test_longest_increasing_subsequence() -> None:
    assert _longest_increasing(np.array([], dtype=np.int64)).tolist() == []
    values = np.array([5, 1, 6, 2, 7, 3, 8, 3, 9])
    picked = _longest_increasing(values)
    assert len(picked) == 5 and np.all(np.diff(values[picked]) > 0) and np.all(np.diff(picked) > 0)
    assert len(_longest_increasing(np.array([3, 3, 3]))) == 1  # strictly increasing
