"""Atomic output files (datasets.files): complete under their name, or not there at all."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.files import atomic_output, write_text_atomic


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path) -> None:
    path = tmp_path / "a.txt"
    write_text_atomic(path, "old\n")
    with pytest.raises(RuntimeError), atomic_output(path) as tmp:
        tmp.write_text("half")
        raise RuntimeError("disk full")
    assert path.read_text() == "old\n" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_npz_through_a_temporary_with_its_suffix(tmp_path) -> None:
    path = tmp_path / "c.npz"
    with atomic_output(path, suffix=".npz") as tmp:
        np.savez(tmp, x=np.arange(3))
    with np.load(path) as z:
        np.testing.assert_array_equal(z["x"], np.arange(3))
    assert oct(path.stat().st_mode & 0o777) == "0o644" and [p.name for p in tmp_path.iterdir()] == ["c.npz"]
