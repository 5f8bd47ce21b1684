"""Relations files (Kuemmerle et al. 2009): exact round trip, and one-line errors for bad lines."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from datasets.errors import DatasetError
from datasets.relations import Relations, read_relations, write_relations

SAMPLE = """# intel-like relations
976052862.437150 976052864.834490 -0.026 0.007 0 0 0 0.019

976052890.238001 976052893.637986 1.3051 -0.0419 0.0 0.0 0.0 -1.5704
"""


def test_read_sample(tmp_path: Path) -> None:
    path = tmp_path / "intel.relations"
    path.write_text(SAMPLE)
    rel = read_relations(path)
    assert len(rel) == 2
    assert rel.stamps1_ns.tolist() == [976_052_862_437_150_000, 976_052_890_238_001_000]
    assert rel.stamps2_ns.dtype == np.int64 and rel.stamps2_ns[1] == 976_052_893_637_986_000
    np.testing.assert_allclose(rel.stamps1_s, [976052862.43715, 976052890.238001])
    np.testing.assert_array_equal(rel.xyz_m[0], [-0.026, 0.007, 0.0])
    np.testing.assert_array_equal(rel.rpy_rad[1], [0.0, 0.0, -1.5704])


def test_round_trip_is_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 200
    s1 = rng.integers(0, 2_000_000_000_000_000_000, n)
    rel = Relations(s1, s1 + rng.integers(1, 10**10, n), rng.normal(0, 3, (n, 3)), rng.normal(0, 1, (n, 3)))
    path = tmp_path / "out.relations"
    write_relations(path, rel)
    back = read_relations(path)
    for name in ("stamps1_ns", "stamps2_ns", "xyz_m", "rpy_rad"):
        np.testing.assert_array_equal(getattr(back, name), getattr(rel, name))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.relations"]  # no temporary left behind
    # and a file read, written and read again is unchanged
    src = tmp_path / "src.relations"
    src.write_text(SAMPLE)
    write_relations(path, read_relations(src))
    again, original = read_relations(path), read_relations(src)
    for name in ("stamps1_ns", "stamps2_ns", "xyz_m", "rpy_rad"):
        np.testing.assert_array_equal(getattr(again, name), getattr(original, name))
    assert path.read_text().splitlines()[1].split()[:2] == ["976052862.43715", "976052864.83449"]


BAD_LINES = {
    "too few fields": (
        "1.0 2.0 0 0 0 0 0",
        "line 2: expected 8 fields (t1 t2 x y z roll pitch yaw), found 7",
    ),
    "too many fields": (
        "1.0 2.0 0 0 0 0 0 0 9",
        "line 2: expected 8 fields (t1 t2 x y z roll pitch yaw), found 9",
    ),
    "word": ("1.0 2.0 0 zero 0 0 0 0", "line 2: 'zero' is not a number"),
    "nan": ("1.0 2.0 0 0 nan 0 0 0", "line 2: non-finite value 'nan'"),
    "inf": ("1.0 2.0 0 0 0 0 0 -inf", "line 2: non-finite value '-inf'"),
    "bad stamp": ("1.0 2.0.1 0 0 0 0 0 0", "line 2: timestamp '2.0.1' is not a decimal number"),
    "nan stamp": ("nan 2.0 0 0 0 0 0 0", "line 2: timestamp 'nan' is not a decimal number"),
    "huge yaw": ("1.0 2.0 0 0 0 0 0 1e300", "line 2: angle beyond 1000 rad"),
    "huge translation": ("1.0 2.0 -3e7 0 0 0 0 0", "line 2: translation beyond 1e+07 m"),
    "itself by a motion": (
        "1.5 1.5 0.2 0 0 0 0 0.1",
        "line 2: relates a scan to itself (both stamps 1.5) by a motion",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_LINES))
def test_bad_line_is_one_line_error(tmp_path: Path, case: str) -> None:
    line, message = BAD_LINES[case]
    path = tmp_path / "bad.relations"
    path.write_text(f"# header\n{line}\n3.0 4.0 0 0 0 0 0 0\n")
    with pytest.raises(DatasetError) as info:
        read_relations(path)
    assert str(info.value) == f"{path}: {message}"


def test_missing_empty_and_binary_files(tmp_path: Path) -> None:
    missing = tmp_path / "none.relations"
    with pytest.raises(DatasetError) as info:
        read_relations(missing)
    assert str(info.value) == f"{missing}: no such file or directory"
    empty = tmp_path / "empty.relations"
    empty.write_text("# only a comment\n\n")
    with pytest.raises(DatasetError) as info:
        read_relations(empty)
    assert str(info.value) == f"{empty}: no relations (t1 t2 x y z roll pitch yaw per line)"
    binary = tmp_path / "blob.relations"
    binary.write_bytes(bytes(range(256)))
    with pytest.raises(DatasetError) as info:
        read_relations(binary)
    assert str(info.value) == f"{binary}: not a relations file (not plain text)"


def test_inconsistent_shapes_rejected() -> None:
    with pytest.raises(DatasetError, match="relations: 2 first stamps, 1 second stamps"):
        Relations(np.array([1, 2]), np.array([3]), np.zeros((2, 3)), np.zeros((2, 3)))


def test_write_refuses_non_finite(tmp_path: Path) -> None:
    rel = Relations(np.array([1]), np.array([2]), np.array([[np.nan, 0, 0]]), np.zeros((1, 3)))
    path = tmp_path / "x.relations"
    with pytest.raises(DatasetError, match="non-finite"):
        write_relations(path, rel)
    assert not path.exists()
