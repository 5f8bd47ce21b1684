"""Bad CARMEN input (SPEC section 8): one exact line naming the file, from the reader and from the CLI."""

from __future__ import annotations

import bz2
import gzip
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

import run
from datasets import open_dataset
from datasets.carmen import CarmenError, read_carmen
from datasets.config import InputConfig
from datasets.errors import DatasetError
from tests.conftest import REPO


def flaser(ranges: str, ipc: str, n: int | None = None, pose: str = "1.0 2.0 0.5") -> str:
    count = len(ranges.split()) if n is None else n
    return f"FLASER {count} {ranges} {pose} {pose} {ipc} host {ipc}"


def odom(ipc: str, pose: str = "1.0 2.0 0.5") -> str:
    return f"ODOM {pose} 0 0 0 {ipc} host {ipc}"


def log_text(*records: str) -> str:
    return "\n".join(["# a CARMEN log", *records]) + "\n"


GOOD = log_text(
    flaser("1.0 2.0 3.0", "10.000000"),
    odom("10.050000"),
    flaser("1.1 2.1 3.1", "10.200000"),
    odom("10.250000"),
    flaser("1.2 2.2 3.2", "10.400000"),
)


def _gzip_bytes(text: str) -> bytes:
    return gzip.compress(text.encode() * 200)


def _bz2_bytes(text: str) -> bytes:
    return bz2.compress(text.encode() * 200)


def _flip(data: bytes, at: int) -> bytes:
    return data[:at] + bytes([data[at] ^ 0xFF]) + data[at + 1 :]


# name -> (file name, content, expected message after "{path}: ")
BAD: dict[str, tuple[str, bytes, str]] = {
    "empty": ("empty.clf", b"", "empty file, not a CARMEN log"),
    "not carmen text": (
        "notes.log",
        b"hello\nworld\n",
        "not a CARMEN log: no FLASER, RLASER or ROBOTLASER1 records",
    ),
    "binary": (
        "image.clf",
        bytes(range(256)) * 4,
        "binary data, not a CARMEN log (expected text records such as FLASER)",
    ),
    "only odometry": (
        "odom.clf",
        log_text(odom("1.0"), odom("2.0")).encode(),
        "not a CARMEN log: no FLASER, RLASER or ROBOTLASER1 records",
    ),
    "truncated gzip": (
        "cut.clf.gz",
        _gzip_bytes(GOOD)[:60],
        "truncated or corrupt gzip file (the data ends before its end marker)",
    ),
    "corrupt gzip": (
        "flipped.log.gz",
        _flip(_gzip_bytes(GOOD), -6),  # in the CRC-32 trailer
        "corrupt gzip file (bad compressed data or checksum)",
    ),
    "not gzip": ("plain.clf.gz", GOOD.encode(), "not a gzip file (named .gz but no gzip header)"),
    "truncated bzip2": (
        "cut.clf.bz2",
        _bz2_bytes(GOOD)[:-40],
        "truncated or corrupt bzip2 file (the data ends before its end marker)",
    ),
    "corrupt bzip2": (
        "flipped.clf.bz2",
        _flip(_bz2_bytes(GOOD), len(_bz2_bytes(GOOD)) // 2),
        "corrupt bzip2 file (bad compressed data)",
    ),
    "fewer fields": (
        "short.clf",
        log_text(odom("1.0"), flaser("1.0 2.0", "1.1", n=3)).encode(),
        "line 3: FLASER says 3 readings but has 13 fields instead of 14",
    ),
    "more fields": (
        "long.clf",
        log_text(flaser("1.0 2.0 3.0 4.0", "1.1", n=3)).encode(),
        "line 2: FLASER says 3 readings but has 15 fields instead of 14",
    ),
    "bad count": ("count.clf", b"FLASER three 1 2 3\n", "line 1: reading count 'three' is not an integer"),
    "empty scan": (
        "zero.clf",
        log_text(flaser("", "1.0", n=0)).encode(),
        "line 2: empty scan (FLASER with 0 readings)",
    ),
    "nan range": (
        "nan.clf",
        log_text(flaser("1.0 2.0 3.0", "1.0"), flaser("1.0 nan 3.0", "1.2")).encode(),
        "line 3: FLASER field 4 is not finite ('nan')",
    ),
    "inf pose": (
        "inf.clf",
        log_text(flaser("1.0 2.0 3.0", "1.0", pose="1.0 inf 0.5")).encode(),
        "line 2: FLASER field 7 is not finite ('inf')",
    ),
    "nan odometry": (
        "nanodom.clf",
        log_text(flaser("1.0 2.0 3.0", "1.0"), odom("1.1", pose="NaN 0 0")).encode(),
        "line 3: ODOM field 2 is not finite ('NaN')",
    ),
    "not a number": (
        "word.clf",
        log_text(flaser("1.0 2.0 3.0", "1.0"), flaser("1.0 abc 3.0", "1.2")).encode(),
        "line 3: FLASER field 4 'abc' is not a number",
    ),
    "negative range": (
        "negative.clf",
        log_text(flaser("1.0 2.0 3.0", "1.0"), flaser("1.0 2.0 -1.5", "1.2")).encode(),
        "line 3: negative range -1.5 m (beam 2 of the FLASER scan)",
    ),
    "bad stamp": (
        "stamp.clf",
        log_text(flaser("1.0 2.0 3.0", "1.0.0")).encode(),
        "line 2: FLASER ipc timestamp '1.0.0' is not a finite decimal number of seconds",
    ),
    "nan stamp": (
        "nanstamp.clf",
        log_text(flaser("1.0 2.0 3.0", "nan")).encode(),
        "line 2: FLASER ipc timestamp 'nan' is not a finite decimal number of seconds",
    ),
    "scan stamps backwards": (
        "backwards.clf",
        log_text(
            flaser("1.0 2.0 3.0", "10.000000"),
            flaser("1.0 2.0 3.0", "11.000000"),
            flaser("1.0 2.0 3.0", "5.5"),
        ).encode(),
        "line 4: timestamps go backwards: FLASER at 5.500000000 s is 5.500 s before line 3 "
        "(more than input.carmen_stamp_jitter_s = 1 s); a SLAM-corrected log takes any stamps but is known "
        "by its name: keep 'corrected' or '.gfs.' in it",
    ),
    "odometry stamps backwards": (
        "odomback.clf",
        log_text(flaser("1.0 2.0 3.0", "10.0"), odom("100.0"), odom("20.0")).encode(),
        "line 4: timestamps go backwards: ODOM at 20.000000000 s is 80.000 s before line 3 "
        "(more than input.carmen_stamp_jitter_s = 1 s); a SLAM-corrected log takes any stamps but is known "
        "by its name: keep 'corrected' or '.gfs.' in it",
    ),
    "odometry fields": (
        "odomfields.clf",
        log_text(flaser("1.0 2.0 3.0", "10.0"), "ODOM 1 2 3 4 5 6 7 8").encode(),
        "line 3: ODOM has 9 fields instead of 10 (x y theta tv rv accel ipc_timestamp hostname "
        "logger_timestamp)",
    ),
}


@pytest.fixture(params=sorted(BAD), ids=sorted(BAD))
def bad_file(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[Path, str]:
    name, content, message = BAD[request.param]
    path = tmp_path / name
    path.write_bytes(content)
    return path, f"{path}: {message}"


def test_reader_message(bad_file: tuple[Path, str]) -> None:
    path, message = bad_file
    with pytest.raises(DatasetError) as info:
        open_dataset(path)
    assert str(info.value) == message
    assert "\n" not in str(info.value)


def test_cli_convert_one_line_exit_1(bad_file: tuple[Path, str]) -> None:
    path, message = bad_file
    out = path.parent / "out.bag"
    result = subprocess.run(
        [sys.executable, "run.py", "convert", str(path), str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 1, result.stderr
    assert result.stderr == f"error: {message}\n"
    assert "Traceback" not in result.stderr
    assert not out.exists()
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "absent.clf"
    with pytest.raises(DatasetError) as info:
        read_carmen(path, InputConfig())
    assert str(info.value) == f"{path}: no such file or directory"


def test_directory_named_like_a_log(tmp_path: Path) -> None:
    path = tmp_path / "folder.clf"
    path.mkdir()
    with pytest.raises(DatasetError) as info:
        read_carmen(path, InputConfig())
    assert str(info.value) == f"{path}: is a directory, not a CARMEN log"


def _deny_reading(monkeypatch: pytest.MonkeyPatch, path: Path) -> None:
    """Make ``path`` unreadable: chmod when that works, else (root ignores modes) refuse in read_bytes."""
    path.chmod(0)
    try:
        path.read_bytes()
    except PermissionError:
        return
    original: Callable[[Path], bytes] = Path.read_bytes

    def read_bytes(self: Path) -> bytes:
        if self == path:
            raise PermissionError(13, "Permission denied", str(self))
        return original(self)

    monkeypatch.setattr(Path, "read_bytes", read_bytes)


def test_unreadable_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    path = tmp_path / "locked.clf"
    path.write_text(GOOD)
    _deny_reading(monkeypatch, path)
    message = f"{path}: cannot read the file: permission denied"
    with pytest.raises(DatasetError) as info:
        open_dataset(path)
    assert str(info.value) == message
    # through the command line (in-process, so that the refusal also applies when tests run as root)
    out = tmp_path / "out.bag"
    assert run.main(["convert", str(path), str(out)]) == 1
    captured = capsys.readouterr()
    assert captured.err == f"error: {message}\n" and captured.out == ""
    assert not out.exists()


def test_missing_laser_type(tmp_path: Path) -> None:
    path = tmp_path / "front.clf"
    path.write_text(GOOD)
    with pytest.raises(CarmenError) as info:
        open_dataset(path, carmen_laser="RLASER")
    assert str(info.value) == f"{path}: no RLASER records (input.carmen_laser); the log has FLASER (3)"


def test_good_log_reads(tmp_path: Path) -> None:
    """The template the bad files are made from is itself good (so each bad file fails for its one flaw)."""
    for name, content in [
        ("good.clf", GOOD.encode()),
        ("good.clf.gz", gzip.compress(GOOD.encode())),
        ("good.log.bz2", bz2.compress(GOOD.encode())),
    ]:
        path = tmp_path / name
        path.write_bytes(content)
        rec = open_dataset(path)
        assert len(rec.scans) == 3 and len(rec.odometry) == 2
        assert rec.scans.stamps_ns.tolist() == [10_000_000_000, 10_200_000_000, 10_400_000_000]
        assert rec.scans[2].ranges_m.tolist() == pytest.approx([1.2, 2.2, 3.2])


def test_small_step_back_is_jitter_and_restamped(tmp_path: Path) -> None:
    path = tmp_path / "jitter.clf"
    path.write_text(
        log_text(
            flaser("1 2 3", "10.0"), flaser("1 2 3", "10.9"), flaser("1 2 3", "10.4"), flaser("1 2 3", "10.6")
        )
    )
    rec = open_dataset(path)
    assert rec.meta["restamped"]["laser"] == 1
    # line order kept; the stamp 0.5 s ahead of its neighbours is moved between them
    assert rec.scans.stamps_ns.tolist() == [10_000_000_000, 10_200_000_000, 10_400_000_000, 10_600_000_000]
    assert rec.meta["ipc_stamps_ns"][1] == 10_900_000_000
    with pytest.raises(CarmenError, match="timestamps go backwards"):
        open_dataset(path, carmen_stamp_jitter_s=0.1)


def test_corrected_log_accepts_any_stamps(tmp_path: Path) -> None:
    """Corrected logs keep line order whatever their stamps (freiburg-079-corrected has 0 and negatives)."""
    text = log_text(flaser("1 2 3", "10.0"), flaser("1 2 3", "11.0"), flaser("1 2 3", "5.5"), odom("0"))
    raw = tmp_path / "run.clf"
    raw.write_text(text)
    with pytest.raises(CarmenError, match="timestamps go backwards"):
        open_dataset(raw)
    corrected = tmp_path / "run-corrected.clf"
    corrected.write_text(text)
    rec = open_dataset(corrected)
    assert rec.meta["restamped"]["laser"] == 1
    assert rec.scans.stamps_ns.tolist() == [10_000_000_000, 11_000_000_000, 12_000_000_000]
    assert rec.reference is not None


def test_a_pipe_is_refused_not_waited_on(tmp_path: Path) -> None:
    """A FIFO named like a log (or a configuration) blocked forever in open(); it is refused at once."""
    import os

    from datasets.errors import ConfigError
    from pipeline.config import load_config

    fifo = tmp_path / "in.clf"
    os.mkfifo(fifo)
    with pytest.raises(DatasetError, match=r"in\.clf: not a regular file \(a pipe, socket or device\)"):
        open_dataset(fifo)
    with pytest.raises(ConfigError, match=r"in\.clf: not a regular file"):
        load_config(fifo)


def test_convert_and_simulate_check_the_output_folder_is_writable_first(tmp_path: Path, monkeypatch) -> None:
    """An output folder that cannot be written into (permissions, a read-only disk) failed after the input
    was read, or the world made, with a message of the catch-all handler; it is now refused first."""
    import tempfile

    import pipeline.convert as convert_module
    from datasets.simulation import output as simulation_output

    def denied(*_args, **_kwargs):
        raise PermissionError(13, "Permission denied")

    def never(*_args, **_kwargs):
        raise AssertionError("read before the output was checked")

    monkeypatch.setattr(tempfile, "TemporaryFile", denied)
    monkeypatch.setattr(convert_module, "open_dataset", never)
    monkeypatch.setattr(simulation_output, "make_world", never)
    log = tmp_path / "in.clf"
    log.write_text("FLASER 3 1.0 1.0 1.0 0 0 0 0 0 0 1.0 host 1.0\n")
    with pytest.raises(DatasetError, match=rf"out\.bag: cannot write into {tmp_path} \(Permission denied\)"):
        convert_module.convert_recording(log, tmp_path / "out.bag")
    with pytest.raises(DatasetError, match=r"sim\.mcap: cannot write into .*\(Permission denied\)"):
        simulation_output.simulate("loop", tmp_path / "sim.mcap")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.clf"]
