"""CARMEN reader hardening: negative stamps, ROBOTLASER1 resolutions, the no-return rule on short logs."""

from __future__ import annotations

import bz2
from pathlib import Path

import numpy as np
import pytest

from datasets import open_dataset
from datasets.carmen import CarmenError, read_carmen
from datasets.no_return import repeated_maximum_m
from datasets.stamps import NS_PER_S, monotone_stamps_ns
from pipeline.convert import convert_recording
from tests.conftest import data_file


def _one_line(err: pytest.ExceptionInfo, path: Path, *parts: str) -> None:
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{path}: "), message
    for part in parts:
        assert part in message, message


def _lines(relative: str) -> list[bytes]:
    return bz2.decompress(data_file(relative).read_bytes()).split(b"\n")


# ------------------------------------------------------------------------------------ negative stamps


def _assert_shifted(rec, shift: int) -> None:
    """Stamps = the re-stamped logged stamps + one shift for every kind; none negative, order kept."""
    assert rec.meta["stamp_shift_ns"] == shift
    scans = rec.scans.stamps_ns
    odom = rec.odometry.stamps_ns
    assert scans.min() >= 0 and odom.min() >= 0
    assert min(scans.min(), odom.min()) < NS_PER_S  # the earliest stamp lies in [0, 1 s)
    assert np.all(np.diff(scans) > 0) and np.all(np.diff(odom) > 0)
    # relative timing of scans and odometry unchanged: both are the unshifted repair plus one shift
    np.testing.assert_array_equal(scans, monotone_stamps_ns(rec.meta["ipc_stamps_ns"])[0] + shift)
    np.testing.assert_array_equal(odom, monotone_stamps_ns(rec.meta["odometry_ipc_stamps_ns"])[0] + shift)
    np.testing.assert_array_equal(rec.scan_poses.stamps_ns, scans)


@pytest.mark.parametrize(
    ("log", "shift_s"),
    [
        # every scan logged at 0 s: re-stamped -236 ns .. 0; ODOM re-stamped down to -2115.878 s
        ("radish-corrected/orebro-corrected.log.gz", 2116),
        # every scan logged at 0 s: -2007 ns .. 0; ODOM down to -20092.389 s
        ("radish-corrected/freiburg-campus-corrected.log.gz", 20093),
        # scans at 1.01893e9 s, ODOM re-stamped down to -6299.28 s
        ("radish-corrected/belgioioso-corrected.log.gz", 6300),
    ],
)
def test_corrected_logs_with_placeholder_stamps_get_non_negative_stamps(log: str, shift_s: int) -> None:
    rec = read_carmen(data_file(log))
    _assert_shifted(rec, shift_s * NS_PER_S)
    assert rec.reference is not None
    np.testing.assert_array_equal(rec.reference.stamps_ns, rec.scans.stamps_ns)


def test_orebro_converts_to_a_bag(tmp_path: Path) -> None:
    """rosbags' writers refused the negative stamps (ROS time cannot be negative)."""
    source = data_file("radish-corrected/orebro-corrected.log.gz")
    rec = open_dataset(source)
    report = convert_recording(source, tmp_path / "orebro.bag")
    assert report["scans"] == 237
    back = open_dataset(tmp_path / "orebro.bag")
    np.testing.assert_array_equal(back.scans.stamps_ns, rec.scans.stamps_ns)
    np.testing.assert_array_equal(back.odometry.stamps_ns, rec.odometry.stamps_ns)


def _restamped_intel(tmp_path: Path, first_s: float, step_s: float, n_lines: int = 400) -> Path:
    """The first lines of intel.clf with every record's ipc and logger stamp rewritten in line order."""
    out = []
    k = 0
    for line in _lines("intel/intel.clf.bz2")[:n_lines]:
        toks = line.split()
        if toks and toks[0] in (b"FLASER", b"ODOM"):
            stamp = f"{first_s + k * step_s:.6f}".encode()
            toks[-3] = toks[-1] = stamp
            k += 1
            line = b" ".join(toks)
        out.append(line)
    path = tmp_path / "neg.clf"
    path.write_bytes(b"\n".join(out) + b"\n")
    return path


@pytest.mark.parametrize(("first_s", "shift_s"), [(-1000.0, 1000), (-0.5, 1)])
def test_raw_log_with_negative_stamps_is_shifted(tmp_path: Path, first_s: float, shift_s: int) -> None:
    path = _restamped_intel(tmp_path, first_s, 0.1 if first_s < -1 else 0.001)
    rec = open_dataset(path)
    assert rec.meta["restamped"] == {"laser": 0, "odometry": 0}
    _assert_shifted(rec, shift_s * NS_PER_S)
    np.testing.assert_array_equal(rec.scans.stamps_ns, rec.meta["ipc_stamps_ns"] + shift_s * NS_PER_S)


def test_raw_log_whose_shifted_stamps_leave_the_years_is_an_error(tmp_path: Path) -> None:
    path = tmp_path / "span.clf"
    pose = "1.0 2.0 0.5"
    path.write_text(
        f"FLASER 3 1 2 3 {pose} {pose} -7000000000.0 host 1\n"
        f"FLASER 3 1 2 3 {pose} {pose} 7000000000.0 host 2\n"
    )
    with pytest.raises(CarmenError) as err:
        read_carmen(path)
    _one_line(err, path, "-7000000000.000000000 s to 7000000000.000000000 s", "the stamps are damaged")
    corrected = tmp_path / "span-corrected.clf"
    corrected.write_bytes(path.read_bytes())
    rec = read_carmen(corrected)  # a corrected log falls back to line order, as for unorderable stamps
    assert rec.meta["stamps_by_line_order"] and rec.meta["stamp_shift_ns"] == 0
    assert rec.scans.stamps_ns.tolist() == [100_000_000, 200_000_000]


@pytest.mark.parametrize("log", ["intel/intel.gfs.log", "fr079/freiburg-079-corrected.log.gz"])
def test_logs_without_negative_stamps_are_not_shifted(log: str) -> None:
    rec = read_carmen(data_file(log))
    assert rec.meta["stamp_shift_ns"] == 0
    np.testing.assert_array_equal(rec.scans.stamps_ns, monotone_stamps_ns(rec.meta["ipc_stamps_ns"])[0])
    np.testing.assert_array_equal(
        rec.odometry.stamps_ns, monotone_stamps_ns(rec.meta["odometry_ipc_stamps_ns"])[0]
    )


# ------------------------------------------------------------------------------ ROBOTLASER1 resolution


@pytest.mark.parametrize("resolution", ["0", "-0.017453", "-0.0"])
def test_robotlaser_resolution_not_positive(tmp_path: Path, resolution: str) -> None:
    records = _lines("fr-clinic/fr-clinic_robotlaser.clf.bz2")
    lines = [ln for ln in records if ln.startswith(b"ROBOTLASER1")][:5]
    toks = lines[2].split()
    toks[4] = resolution.encode()  # name, laser_type, start_angle, fov, angular_resolution
    lines[2] = b" ".join(toks)
    path = tmp_path / "res.clf"
    path.write_bytes(b"\n".join(lines) + b"\n")
    with pytest.raises(CarmenError) as err:
        read_carmen(path)
    _one_line(err, path, "line 3: ROBOTLASER1 field 5 angular resolution is not positive", f"'{resolution}'")


# -------------------------------------------------------------------------------- no-return on prefixes


def _prefix(lines: list[bytes], scans: int, path: Path) -> Path:
    """The log cut after its ``scans``-th FLASER line."""
    seen = 0
    for i, line in enumerate(lines):
        seen += line.startswith(b"FLASER")
        if seen == scans:
            path.write_bytes(b"\n".join(lines[: i + 1]) + b"\n")
            return path
    raise AssertionError(f"fewer than {scans} scans")


@pytest.mark.parametrize(("log", "code"), [("intel/intel.clf.bz2", 81.83), ("fr079/fr079.clf.bz2", 81.91)])
def test_short_prefixes_give_no_false_no_return_value(tmp_path: Path, log: str, code: float) -> None:
    """The first 300 scans of intel.clf gave 10.69 m: 22 values from 10.69 to 17.14 m (wall hits spread
    over neighbouring 1-cm steps, in the sparse top of a short log) were taken for no-return codes."""
    lines = _lines(log)
    for scans in (80, 300, 1000):
        rec = read_carmen(_prefix(lines, scans, tmp_path / f"first{scans}.clf"))
        no_return = rec.meta["no_return"]
        assert no_return["rule"] == "input.carmen_range_max_m", (scans, no_return)
        assert no_return["range_m"] == 80.0 and no_return["repeated_maximum_m"] == [code]
        assert np.all(rec.scans.range_max_m == 80.0)


def test_a_quantised_wall_hit_at_the_top_of_a_short_log_is_not_a_code() -> None:
    rng = np.random.default_rng(1)
    real = np.round(rng.gamma(2.0, 1.5, 14_000), 2)  # 1-cm steps, as intel.clf
    wall = np.round(rng.normal(17.125, 0.008, 80), 2)  # a far wall: spread over a few 1-cm steps
    assert repeated_maximum_m(np.concatenate([real, wall])) is None
    # two codes of comparable counts side by side in a log of 1-mm steps (orebro: 465 at 32.763 m, 463 at
    # 32.767 m, 33 at 32.759 m) are found
    real_mm = np.round(rng.gamma(2.0, 1.5, 40_000), 3)
    codes = np.concatenate([real_mm, np.full(400, 32.763), np.full(390, 32.767), np.full(30, 32.759)])
    found = repeated_maximum_m(codes)
    assert found is not None and found.values_m == (32.759, 32.763, 32.767)


# ------------------------------------------------------------------------------------ line ends


@pytest.mark.parametrize("line_end", [b"\r\n", b"\r"], ids=["crlf", "cr-only"])
def test_line_ends_of_other_systems_read_as_unix_ones(tmp_path: Path, line_end: bytes) -> None:
    """A log saved with Windows (CRLF) or classic Mac (CR only) line ends reads the arrays of its LF self."""
    lines = _lines("intel/intel.clf.bz2")[:1500]
    unix, other = tmp_path / "lf.clf", tmp_path / "other.clf"
    unix.write_bytes(b"\n".join(lines))
    other.write_bytes(line_end.join(lines))
    a, b = read_carmen(unix), read_carmen(other)
    assert len(a.scans) > 400 and len(b.scans) == len(a.scans)
    np.testing.assert_array_equal(b.scans.stamps_ns, a.scans.stamps_ns)
    np.testing.assert_array_equal(np.concatenate(b.scans.ranges_m), np.concatenate(a.scans.ranges_m))
    np.testing.assert_array_equal(b.odometry.poses_xytheta, a.odometry.poses_xytheta)
