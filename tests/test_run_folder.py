"""Run folders: complete or absent, never half written; no overwrite without asking."""

from __future__ import annotations

import pytest

from pipeline.errors import PipelineError
from pipeline.run_folder import read_summary, staged_run_folder, write_summary


def test_complete_run_is_renamed_into_place(tmp_path) -> None:
    out = tmp_path / "run"
    with staged_run_folder(out) as stage:
        (stage / "a.txt").write_text("x")
        assert not out.exists()
        write_summary(stage, {"scans": 3})
    assert (out / "a.txt").read_text() == "x"
    assert read_summary(out) == {"scans": 3}
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def test_failure_and_interrupt_leave_nothing(tmp_path) -> None:
    out = tmp_path / "run"
    for exc in (RuntimeError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)), staged_run_folder(out) as stage:
            (stage / "a.txt").write_text("x")
            raise exc
        assert list(tmp_path.iterdir()) == []


def test_missing_summary_is_an_error(tmp_path) -> None:
    with (
        pytest.raises(PipelineError, match=r"without writing summary\.json"),
        staged_run_folder(tmp_path / "r"),
    ):
        pass
    assert list(tmp_path.iterdir()) == []


def test_existing_folder_needs_overwrite(tmp_path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with pytest.raises(PipelineError, match="already exists"), staged_run_folder(out):
        pass
    assert (out / "old.txt").exists()
    # a failed overwrite keeps the old run
    with pytest.raises(RuntimeError), staged_run_folder(out, overwrite=True):
        raise RuntimeError
    assert (out / "old.txt").exists()
    with staged_run_folder(out, overwrite=True) as stage:
        write_summary(stage, {})
    assert not (out / "old.txt").exists() and (out / "summary.json").exists()


def test_read_summary_of_incomplete_folder(tmp_path) -> None:
    with pytest.raises(PipelineError, match="not a complete run folder"):
        read_summary(tmp_path)
