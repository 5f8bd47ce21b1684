"""Run folders: complete or absent, never half written; no overwrite without asking."""

from __future__ import annotations

import errno
import os

import pytest

from pipeline.errors import PipelineError
from pipeline.run_folder import check_output_dir, read_summary, staged_run_folder, write_summary


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


def test_errors_name_the_run_folder_not_its_staging_folder(tmp_path) -> None:
    """The staging folder is gone when the message is read: a known error's text and an OS error's file
    names point where the run was going; other errors and messages pass unchanged."""
    out = tmp_path / "run"
    with pytest.raises(PipelineError) as err, staged_run_folder(out) as stage:
        raise PipelineError(f"{stage / 'maps' / 'after.npz'}: cannot write (disk full)")
    assert str(err.value) == f"{out / 'maps' / 'after.npz'}: cannot write (disk full)"
    with pytest.raises(OSError) as err, staged_run_folder(out) as stage:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(stage / "a.png"), None, str(stage / "b"))
    assert (err.value.errno, err.value.filename, err.value.filename2) == (
        errno.ENOSPC,
        str(out / "a.png"),
        str(out / "b"),
    )
    with pytest.raises(PipelineError) as err, staged_run_folder(out) as stage:  # another process's folder
        raise PipelineError(f"{stage}7/a.npz: cannot write")
    assert str(err.value) == f"{tmp_path / 'run.partial-'}{os.getpid()}7/a.npz: cannot write"
    with pytest.raises(FileNotFoundError) as err, staged_run_folder(out):
        raise FileNotFoundError(errno.ENOENT, "gone", str(tmp_path / "input.bag"))
    assert err.value.filename == str(tmp_path / "input.bag")
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
    write_summary(out, {})  # an earlier run
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


def test_a_folder_that_appears_while_the_run_works_is_kept_and_so_is_the_run(tmp_path) -> None:
    """Another run (or the user) writes ``--out`` while this run works: without --overwrite it is not
    replaced at the end, nor is a folder of other files with it; the finished run goes beside it."""
    out = tmp_path / "run"
    with pytest.raises(PipelineError, match=r"run: appeared while the run worked .* kept in \S+run-2$"):
        with staged_run_folder(out) as stage:
            write_summary(stage, {"scans": 3})
            out.mkdir()
            (out / "notes.txt").write_text("mine")
    assert (out / "notes.txt").read_text() == "mine"
    assert read_summary(tmp_path / "run-2") == {"scans": 3}
    # --overwrite of a run folder that the user filled with other files meanwhile
    (tmp_path / "run-2").rename(tmp_path / "run-3")
    write_summary(out, {})
    (out / "notes.txt").unlink()
    with pytest.raises(PipelineError, match=r"changed while the run worked .*not a run folder.* kept in"):
        with staged_run_folder(out, overwrite=True) as stage:
            write_summary(stage, {"scans": 4})
            (out / "summary.json").unlink()
            (out / "notes.txt").write_text("mine")
    assert (out / "notes.txt").read_text() == "mine"
    assert read_summary(tmp_path / "run-2") == {"scans": 4}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run", "run-2", "run-3"]


def test_read_summary_of_incomplete_folder(tmp_path) -> None:
    with pytest.raises(PipelineError, match="not a complete run folder"):
        read_summary(tmp_path)


def test_overwrite_never_deletes_what_the_run_reads_nor_other_files(tmp_path) -> None:
    """--overwrite replaces a run folder or an empty one; a folder that is or holds the input (or the run
    folder being remapped), or that holds other files, is refused before any work, and kept."""
    data = tmp_path / "data"
    data.mkdir()
    log = data / "in.clf"
    log.write_text("FLASER ...")
    for out, read in ((data, log), (data, data), (tmp_path, data)):
        with pytest.raises(PipelineError, match="which this command reads"):
            check_output_dir(out, overwrite=True, reads=[None, read])
    (data / "notes.txt").write_text("mine")
    with pytest.raises(PipelineError, match="not a run folder"), staged_run_folder(data, overwrite=True):
        pass
    assert sorted(p.name for p in data.iterdir()) == ["in.clf", "notes.txt"]
    empty = tmp_path / "empty"
    empty.mkdir()
    check_output_dir(empty, overwrite=True, reads=[log])
    run = tmp_path / "run"
    run.mkdir()
    write_summary(run, {})
    check_output_dir(run, overwrite=True, reads=[log, data])
    check_output_dir(data / "remap", overwrite=True, reads=[data])  # a new folder inside what it reads


def test_a_name_too_long_for_the_staging_folder_fails_before_any_work(tmp_path) -> None:
    """A legal 250-byte --out name became too long once '.partial-PID' was added: an OSError of the
    catch-all handler after the work. It is refused first, saying how long a name may be."""
    check_output_dir(tmp_path / ("a" * 230), overwrite=False)
    with pytest.raises(PipelineError, match=r"a name of 250 bytes is too long for its staging folder"):
        check_output_dir(tmp_path / ("a" * 250), overwrite=False)


def test_an_interrupt_between_the_two_renames_of_an_overwrite_keeps_the_old_run(
    tmp_path, monkeypatch
) -> None:
    """``--overwrite`` retires the old folder, then renames the new one into place. An interrupt between
    the two puts the old run back; and a run killed there (the old run left as ``DIR.replaced-PID``, no
    ``DIR``) gets it back from the next run's clean-up instead of losing it."""
    import subprocess
    import sys
    from pathlib import Path

    from pipeline.run_folder import remove_stale_staging

    out = tmp_path / "run"
    out.mkdir()
    (out / "old.txt").write_text("old")
    write_summary(out, {})
    real_rename = Path.rename

    def interrupted(self, target):
        if self.name.startswith("run.partial-"):
            raise KeyboardInterrupt
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", interrupted)
    with pytest.raises(KeyboardInterrupt), staged_run_folder(out, overwrite=True) as stage:
        write_summary(stage, {"new": 1})
    monkeypatch.undo()
    assert (out / "old.txt").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["run"]

    script = "import os; print(os.getpid())"  # a process that has ended: its pid names the orphan
    dead = int(subprocess.run([sys.executable, "-c", script], capture_output=True, text=True).stdout)
    out.rename(tmp_path / f"run.replaced-{dead}")
    assert remove_stale_staging(out) == [] and (out / "old.txt").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
