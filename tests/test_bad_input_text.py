"""Bad text input: each defect once found in a text reader, as a small deterministic case.

Every case must end in a one-line :class:`~datasets.errors.GpomError` naming the file (and the line or field
where there is one), never in a foreign exception, a warning, a hang or a recording that fails validation.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from datasets.carmen import CarmenError, read_carmen
from datasets.config import InputConfig
from datasets.errors import ConfigError, GpomError
from datasets.kitti import KittiError, read_kitti
from datasets.no_return import repeated_maximum_m
from datasets.numtext import NumberParseError, parse_stamps_ns
from datasets.relations import RelationsError, read_relations
from datasets.stamps import StampRangeError, decimal_to_ns, monotone_stamps_ns
from datasets.validate import MAX_STAMP_NS, validate_recording
from pipeline.config import config_to_yaml, load_config
from slam.trajectory_io import TrajectoryFormatError, read_g2o, read_tum

HUGE_STAMPS = ["1e30", "-1e30", "1e9999999", "99999999999999999999999", "1e99999999999999999999"]


@pytest.fixture(autouse=True)
def _warnings_are_errors():
    """A reader that overflows silently (RuntimeWarning) has a defect too."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        yield


def _write(path: Path, text: str | bytes) -> Path:
    path.write_bytes(text.encode() if isinstance(text, str) else text)
    return path


def _one_line(err: pytest.ExceptionInfo, path: Path, *parts: str) -> None:
    message = str(err.value)
    assert "\n" not in message and str(path) in message, message
    for part in parts:
        assert part in message, message


def flaser(ipc: str = "1.0", ranges: str = "1 2 3", pose: str = "1 2 0.5", logger: str | None = None) -> str:
    n = len(ranges.split())
    return f"FLASER {n} {ranges} {pose} {pose} {ipc} host {logger or ipc}"


def robotlaser(start: str = "-1.57", res: str = "0.017", max_m: str = "81.9", ipc: str = "1.0") -> str:
    return f"ROBOTLASER1 0 {start} 3.14 {res} {max_m} 0.1 0 3 1 2 3 0 1 2 0.5 1 2 0.5 0 0 0 0 0 {ipc} h {ipc}"


# ------------------------------------------------------------------------------------------- stamps


@pytest.mark.parametrize("text", HUGE_STAMPS)
def test_decimal_to_ns_huge_is_a_value_error(text: str) -> None:
    """Was decimal.InvalidOperation / decimal.Overflow / an int beyond int64."""
    with pytest.raises(ValueError, match=r"out of range|not a decimal number"):
        decimal_to_ns(text)
    with pytest.raises(NumberParseError):
        parse_stamps_ns(f"1.0 {text}".encode())


def test_decimal_to_ns_int64_edge() -> None:
    assert decimal_to_ns("9223372036.854775807") == 2**63 - 1
    with pytest.raises(StampRangeError):
        decimal_to_ns("9223372036.854775808")
    assert decimal_to_ns("1e-9999999") == 0


def test_decimal_to_ns_long_texts() -> None:
    """More than 4300 digits (leading zeros included) hit int()'s limit: a wrong 'not a decimal' error."""
    assert decimal_to_ns("0" * 5000 + "1") == 1_000_000_000
    assert decimal_to_ns("0" * 5000 + "1.5") == 1_500_000_000
    with pytest.raises(StampRangeError) as err:
        decimal_to_ns("9" * 5000)
    assert len(str(err.value)) < 120  # the message shows the start of the text only


def test_monotone_stamps_far_apart_do_not_wrap() -> None:
    """int64 differences of stamps ~1.4e19 ns apart wrapped around and gave a non-increasing repair."""
    m = MAX_STAMP_NS
    fixed, restamped = monotone_stamps_ns(np.array([m, -m, 0, m - 5], dtype=np.int64))
    assert np.all(fixed[1:] > fixed[:-1])
    assert restamped.tolist() == [True, False, False, False]


# ------------------------------------------------------------------------------------------- CARMEN


@pytest.mark.parametrize("text", HUGE_STAMPS)
@pytest.mark.parametrize("where", ["ipc", "logger", "odom"])
def test_carmen_huge_stamp(tmp_path: Path, text: str, where: str) -> None:
    records = {
        "ipc": [flaser("1.0"), flaser(text)],
        "logger": [flaser("1.0"), flaser("1.1", logger=text)],
        "odom": [flaser("1.0"), f"ODOM 1 2 0.5 0 0 0 {text} host 1.0"],
    }[where]
    path = _write(tmp_path / "huge.clf", "\n".join(records) + "\n")
    with pytest.raises(CarmenError) as err:
        read_carmen(path)
    _one_line(err, path, "line 2:", f"'{text}'")


def test_carmen_stamp_beyond_2200(tmp_path: Path) -> None:
    """A stamp inside int64 but past 2200 was returned and failed validation."""
    path = _write(tmp_path / "late.clf", flaser("1.0") + "\n" + flaser("9000000000") + "\n")
    with pytest.raises(CarmenError) as err:
        read_carmen(path)
    _one_line(err, path, "line 2:", "ipc timestamp 9000000000.000000000 s is out of range")


def test_carmen_corrected_log_stamps_far_apart(tmp_path: Path) -> None:
    """A corrected log accepts any stamps; ones 1.4e19 ns apart overflowed the repair."""
    lines = [flaser("-7000000000"), flaser("6500000000"), flaser("6000000000")]
    path = _write(tmp_path / "x-corrected.log", "\n".join(lines) + "\n")
    rec = read_carmen(path)
    validate_recording(rec)
    # the negative stamp cannot be shifted to 0 within the years 1740-2200 (ROS time is not negative):
    # line order stamps the corrected log
    assert rec.meta["stamps_by_line_order"] and rec.meta["restamped"]["laser"] == 3


def test_carmen_raw_log_stamps_far_apart(tmp_path: Path) -> None:
    """The backstep check overflowed int64 and missed a step back of 1.4e19 ns."""
    path = _write(tmp_path / "far.clf", flaser("7000000000") + "\n" + flaser("-7000000000") + "\n")
    with pytest.raises(CarmenError) as err:
        read_carmen(path)
    _one_line(err, path, "line 2: timestamps go backwards")


def test_carmen_huge_jitter(tmp_path: Path) -> None:
    """round(1e300 s in ns) = round(inf) raised OverflowError (the configuration rejects inf itself)."""
    path = _write(tmp_path / "j.clf", flaser("2.0") + "\n" + flaser("1.0") + "\n")
    rec = read_carmen(path, InputConfig(carmen_stamp_jitter_s=1e300))
    validate_recording(rec)


def test_flaser_huge_beam_count_is_rejected_without_allocating(tmp_path: Path) -> None:
    path = _write(tmp_path / "count.clf", "FLASER 1000000000000 1 2 3 1 2 0.5 1 2 0.5 1.0 host 1.0\n")
    with pytest.raises(CarmenError) as err:
        read_carmen(path)
    _one_line(err, path, "line 1: FLASER says 1000000000000 readings")


@pytest.mark.parametrize(
    ("record", "field"),
    [
        (flaser(ranges="1 1e300 3"), "FLASER field 4 range is out of range"),
        (flaser(pose="1e300 2 0.5"), "FLASER field 6 pose coordinate (m) is out of range"),
        (flaser(pose="1 -1e8 0.5"), "FLASER field 7 pose coordinate (m) is out of range"),
        (
            "FLASER 3 1 2 3 1 2 1.7e308 1 2 -1.7e308 1.0 host 1.0",
            "FLASER field 8 pose heading (rad) is out of range",
        ),
        (robotlaser(start="1e300"), "ROBOTLASER1 field 3 angle (rad) is out of range"),
        (robotlaser(res="-1e40"), "ROBOTLASER1 field 5 angle (rad) is out of range"),
        (robotlaser(max_m="1e300"), "ROBOTLASER1 field 6 maximum range is out of range"),
        (robotlaser(max_m="0.01"), "ROBOTLASER1 maximum range 0.01 m is not above"),
    ],
    ids=["range", "x", "y", "heading", "start-angle", "resolution", "max-range", "max-below-min"],
)
def test_carmen_huge_values(tmp_path: Path, record: str, field: str) -> None:
    """Huge finite values overflowed (RuntimeWarning) into inf ranges, limits, angles and a NaN mounting."""
    path = _write(tmp_path / "big.clf", record + "\n")
    with pytest.raises(CarmenError) as err:
        read_carmen(path)
    _one_line(err, path, "line 1:", field)


def test_carmen_odom_huge_coordinate(tmp_path: Path) -> None:
    path = _write(tmp_path / "odom.clf", flaser() + "\nODOM 1e300 2 0.5 0 0 0 1.0 host 1.0\n")
    with pytest.raises(CarmenError) as err:
        read_carmen(path)
    _one_line(err, path, "line 2: ODOM field 2 coordinate (m) is out of range")


def test_no_return_ignores_absurd_readings() -> None:
    """1-mm bins of 1e300 m overflowed the int64 cast (RuntimeWarning, garbage bins)."""
    assert repeated_maximum_m(np.full(100, 1e300)) is None


def test_repeated_tiny_reading_is_not_a_maximum_below_the_minimum(tmp_path: Path) -> None:
    """A repeated reading under input.carmen_range_min_m made range_max <= range_min (fails validation)."""
    lines = [flaser(f"{1 + k / 10:.1f}", ranges="0.01 0.01 0.01") for k in range(10)]
    rec = read_carmen(_write(tmp_path / "tiny.clf", "\n".join(lines) + "\n"))
    validate_recording(rec)


# ---------------------------------------------------------------------------------------- relations


@pytest.mark.parametrize("text", HUGE_STAMPS)
def test_relations_huge_stamp(tmp_path: Path, text: str) -> None:
    path = _write(tmp_path / "r.relations", f"# t1 t2 x y z r p y\n1.0 {text} 0 0 0 0 0 0\n")
    with pytest.raises(RelationsError) as err:
        read_relations(path)
    _one_line(err, path, "line 2: timestamp", f"'{text}'")


# ---------------------------------------------------------------------------------------------- TUM


@pytest.mark.parametrize("text", HUGE_STAMPS)
def test_tum_huge_stamp(tmp_path: Path, text: str) -> None:
    """Was OverflowError (int64) or float infinity to integer."""
    path = _write(tmp_path / "t.tum", f"1.0 0 0 0 0 0 0 1\n{text} 0 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError) as err:
        read_tum(path)
    _one_line(err, path, "line 2: stamp", f"'{text}'")


def test_tum_stamp_is_exact() -> None:
    """Stamps with exponents were parsed through a float."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = _write(Path(tmp) / "t.tum", "976052857.337531e0 0 0 0 0 0 0 1\n")
        assert read_tum(path)[0].tolist() == [976_052_857_337_531_000]


def test_tum_huge_quaternion(tmp_path: Path) -> None:
    """inf - inf in the yaw formula gave a NaN pose (and a RuntimeWarning)."""
    path = _write(tmp_path / "q.tum", "1.0 0 0 0 1e300 1e300 -1e300 1e300\n")
    with pytest.raises(TrajectoryFormatError) as err:
        read_tum(path)
    _one_line(err, path, "line 1: quaternion too large")


@pytest.mark.parametrize("quaternion", ["0 0 0 0", "0 0 0.5 0.5", "0 0 2 0"])
def test_tum_quaternion_that_is_not_a_unit_one(tmp_path: Path, quaternion: str) -> None:
    """A zero quaternion read as yaw 0 (a remap with such a file moved the map); a half or doubled one has
    a yaw but is no rotation."""
    path = _write(tmp_path / "q.tum", f"1.0 0 0 0 0 0 0 1\n2.0 1 0 0 {quaternion}\n")
    with pytest.raises(TrajectoryFormatError) as err:
        read_tum(path)
    _one_line(err, path, "line 2: not a unit quaternion")


def test_tum_quaternion_printed_with_few_decimals_is_read(tmp_path: Path) -> None:
    path = _write(tmp_path / "q.tum", "1.0 0 0 0 0 0 0.7071 0.7071\n")
    assert read_tum(path)[1][0, 2] == pytest.approx(np.pi / 2, abs=1e-4)


# ---------------------------------------------------------------------------------------------- g2o


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("VERTEX_SE2 99999999999999999999999 0 0 0\n", "line 1: vertex id '99999999999999999999999' is out"),
        ("VERTEX_SE2 0 0 0 0\nFIX 99999999999999999999999\n", "line 2: vertex id"),
        ("VERTEX_SE2 0 0 0 0\nFIX 5\n", "line 2: FIX of unknown vertex 5"),
        ("VERTEX_SE2 0 nan 0 0\n", "line 1: VERTEX_SE2 value 'nan' is not finite"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 0 0 0 1 0 0 1 0 inf\n", "line 3: EDGE_SE2"),
        (
            "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 0 0 0 1e-320 0 0 1e-320 0 1e-320\n",
            "line 3: information matrix with no finite inverse",
        ),
    ],
    ids=["huge-id", "huge-fix", "unknown-fix", "nan-vertex", "inf-information", "tiny-information"],
)
def test_g2o_bad_numbers(tmp_path: Path, text: str, message: str) -> None:
    """Was OverflowError (ids beyond int64), or NaN / unknown vertices passed on silently."""
    path = _write(tmp_path / "g.g2o", text)
    with pytest.raises(TrajectoryFormatError) as err:
        read_g2o(path)
    _one_line(err, path, message)


# -------------------------------------------------------------------------------------------- KITTI


def _kitti(tmp_path: Path, **files: str | bytes) -> Path:
    _write(tmp_path / "000000.bin", np.zeros((2, 4), np.float32).tobytes())
    for name, text in files.items():
        _write(tmp_path / name.replace("_txt", ".txt"), text)
    return tmp_path


_TR = "Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n"


@pytest.mark.parametrize(
    ("files", "message"),
    [
        ({"times_txt": "1e30\n"}, "times.txt: line 1: time '1e30' s is out of range"),
        ({"times_txt": "99999999999999999999999\n"}, "times.txt: line 1: time"),
        ({"times_txt": "9000000000\n"}, "times.txt: line 1: time '9000000000' s is out of range"),
        (
            {"calib_txt": "Tr: 0 0 0 0 0 0 0 0 0 0 0 0\n", "poses_txt": "1 0 0 0 0 1 0 0 0 0 1 0\n"},
            "calib.txt: Tr is singular",
        ),
        (
            {"calib_txt": _TR, "poses_txt": "1 0 0 1e300 0 1 0 0 0 0 1 0\n"},
            "poses.txt: line 1: the pose in the Velodyne frame",
        ),
        (
            {
                "calib_txt": "Tr: 1e-200 0 0 0 0 1e-200 0 0 0 0 1e-200 0\n",
                "poses_txt": "1e200 0 0 0 0 1 0 0 0 0 1 0\n",
            },
            "poses.txt: line 1: the pose in the Velodyne frame",
        ),
    ],
    ids=["times-1e30", "times-int64", "times-2200", "singular-tr", "huge-pose", "overflowing-product"],
)
def test_kitti_bad_side_files(tmp_path: Path, files: dict[str, str], message: str) -> None:
    """Was decimal.InvalidOperation, OverflowError, LinAlgError, or a NaN reference failing validation."""
    folder = _kitti(tmp_path, **files)
    with pytest.raises(KittiError) as err:
        read_kitti(folder)
    _one_line(err, folder, message)


def test_kitti_frame_number_beyond_int64(tmp_path: Path) -> None:
    path = _write(tmp_path / "99999999999999999999.bin", np.zeros((2, 4), np.float32).tobytes())
    with pytest.raises(KittiError) as err:
        read_kitti(tmp_path)
    _one_line(err, path, "frame number 99999999999999999999 is out of range")


def test_kitti_frame_number_beyond_2200_at_10_hz(tmp_path: Path) -> None:
    """index * 100 ms overflowed int64 (wrapped stamps) for a large frame number."""
    path = _write(tmp_path / "999999999999999.bin", np.zeros((2, 4), np.float32).tobytes())
    with pytest.raises(KittiError) as err:
        read_kitti(tmp_path)
    _one_line(err, path, "beyond the year 2200")


def test_kitti_scan_ranges_slice(tmp_path: Path) -> None:
    """``scans.ranges_m[:k]`` (as for any ScanSequence) raised TypeError on the lazy KITTI scans."""
    rec = read_kitti(_kitti(tmp_path))
    first = rec.scans.ranges_m[:50]
    assert len(first) == 1 and first[0].dtype == np.float32


# ---------------------------------------------------------------------------- quoted tokens escaped

ESC_TOKEN = "1\x1b[2J\x7f"  # a number followed by a terminal escape sequence and DEL
ESC_SHOWN = r"'1\x1b[2J\x7f'"


@pytest.mark.parametrize(
    ("name", "text", "read"),
    [
        ("range.clf", flaser(ranges=f"1 {ESC_TOKEN} 3"), read_carmen),
        ("count.clf", f"FLASER {ESC_TOKEN} 1 2 3 1 2 0.5 1 2 0.5 1.0 host 1.0", read_carmen),
        ("stamp.clf", flaser(ipc=ESC_TOKEN), read_carmen),
        ("value.relations", f"1.0 2.0 {ESC_TOKEN} 0 0 0 0 0", read_relations),
        ("stamp.relations", f"1.0 {ESC_TOKEN} 0 0 0 0 0 0", read_relations),
        ("stamp.tum", f"{ESC_TOKEN} 0 0 0 0 0 0 1", read_tum),
        ("value.g2o", f"VERTEX_SE2 0 {ESC_TOKEN} 0 0", read_g2o),
        ("id.g2o", f"VERTEX_SE2 {ESC_TOKEN} 0 0 0", read_g2o),
        ("tag.g2o", "VERTEX\x1b[2J\x7f 0 0 0 0", read_g2o),
    ],
    ids=lambda v: v if isinstance(v, str) and "." in v and "\x1b" not in v else None,
)
def test_quoted_tokens_are_escaped(tmp_path: Path, name: str, text: str, read) -> None:
    """A token holding control characters is quoted escaped (it reached the terminal raw: ESC, DEL)."""
    path = _write(tmp_path / name, text + "\n")
    with pytest.raises(GpomError) as err:
        read(path)
    message = str(err.value)
    assert message.isprintable(), message
    assert ESC_SHOWN in message or r"VERTEX\x1b[2J\x7f" in message, message


def test_kitti_time_token_is_escaped(tmp_path: Path) -> None:
    folder = _kitti(tmp_path, times_txt=f"{ESC_TOKEN}\n")
    with pytest.raises(KittiError) as err:
        read_kitti(folder)
    assert str(err.value).isprintable() and ESC_SHOWN in str(err.value), str(err.value)


# ------------------------------------------------------------------------------------------- config


def test_config_not_utf8(tmp_path: Path) -> None:
    """Was UnicodeDecodeError."""
    path = _write(tmp_path / "c.yaml", b"input:\n  carmen_laser: \xff\xfe\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    _one_line(err, path, "not a UTF-8 text file")


def test_config_nested_too_deep(tmp_path: Path) -> None:
    path = _write(tmp_path / "deep.yaml", "[" * 100_000)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    _one_line(err, path)


def test_config_alias_bomb_is_not_expanded(tmp_path: Path) -> None:
    """The repr of a bad value built from nested YAML aliases (9**9 leaves) never finished."""
    text = 'x0: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
    for i in range(1, 9):
        text += f"x{i}: &{'abcdefghi'[i]} [" + ",".join([f"*{'abcdefghi'[i - 1]}"] * 9) + "]\n"
    path = _write(tmp_path / "bomb.yaml", text + "mapping:\n  resolution_m: *i\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    _one_line(err, path, "invalid value [[[")
    assert len(str(err.value)) < 500


@pytest.mark.parametrize(
    "text",
    ["input: {carmen_range_max_m: .inf}", "mapping: {resolution_m: .nan}", "scale: {pose_tolerance_m: .inf}"],
)
def test_config_non_finite_value(tmp_path: Path, text: str) -> None:
    """``carmen_range_max_m: .inf`` was accepted and failed later, in validation, naming no config."""
    path = _write(tmp_path / "c.yaml", text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    _one_line(err, path, "finite number")


def test_config_directory(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as err:
        load_config(tmp_path)
    _one_line(err, tmp_path, "is a directory")


def test_bad_command_line_value_is_blamed_on_the_option() -> None:
    """``run --resolution 0`` was blamed on pipeline/default.yaml."""
    with pytest.raises(ConfigError) as err:
        load_config(None, {"mapping": {"resolution_m": 0.0, "mapper": None}})
    message = str(err.value)
    assert message.startswith("--resolution 0.0: invalid value for 'mapping.resolution_m'"), message
    assert "default.yaml" not in message


def test_bad_file_value_is_still_blamed_on_the_file(tmp_path: Path) -> None:
    path = _write(tmp_path / "c.yaml", "mapping:\n  resolution_m: -1\n")
    with pytest.raises(ConfigError) as err:
        load_config(path, {"mapping": {"resolution_m": None, "mapper": "gpfol"}})
    _one_line(err, path, "invalid value -1 for 'mapping.resolution_m'")


BIG_DIGITS = "9" * 5000  # beyond Python's 4300-digit limit of int(str)


@pytest.mark.parametrize(
    ("text", "part"),
    [
        ("mapping: {resolution_m: !!float abc}", "line 1, column 25"),
        ("scale: {workers: !!int 1.5}", "line 1, column 18"),
        (f"scale: {{workers: {BIG_DIGITS}}}", "line 1, column 18"),
        (f"scale: {{workers: !!int 1:{BIG_DIGITS}}}", "line 1"),
        (f"scale: {{workers: !!float 1:{BIG_DIGITS}}}", "finite number"),
        (f"input:\n  ? {BIG_DIGITS}\n  : 1\n", "line 2, column 5"),
        ("input: {scan_topic: !!timestamp 2001-02-29}", "line 1, column 21"),
        ("input: {scan_topic: !!timestamp 2001-13-45}", "line 1"),
        ("input: {scan_topic: !!timestamp x}", "line 1, column 21: cannot read timestamp 'x'"),
        ("input: {scan_topic: !!timestamp 2001-02-28}", "invalid value datetime.date(2001, 2, 28)"),
        ("input: {scan_topic: !!timestamp '2001-12-14 21:59:43 +99'}", "line 1"),
        ("input: {scan_topic: !!binary //79}", "invalid value b'\\xff\\xfe\\xfd'"),
        ("input: {scan_topic: !!set {a: null}}", "'input.scan_topic'"),
        ("scale: {workers: !!float 1e99999}", "finite number"),
        (f"scale: {{workers: !!int 0x{'f' * 5000}}}", "invalid value <an integer of 6021 digits>"),
        (f"scale:\n  ? !!int 0x{'f' * 5000}\n  : 1\n", "invalid value <an integer of 6021 digits>"),
        ('mapping: {"\\e[31m\\0": 1}', r"unknown configuration key 'mapping.\x1b[31m\x00'"),
        ('mapping: {mapper: "gp\\e[2J\\npol"}', r"invalid value 'gp\x1b[2J\npol'"),
    ],
    ids=[
        "float-abc",
        "int-1.5",
        "int-5000-digits",
        "sexagesimal-int-5000-digits",
        "sexagesimal-float-5000-digits",
        "key-5000-digits",
        "timestamp-feb-29",
        "timestamp-month-13",
        "timestamp-not-a-date",
        "timestamp-valid-date-for-a-string",
        "timestamp-tz-99",
        "binary-not-utf8",
        "set",
        "float-overflow",
        "hex-int-6021-digits",
        "hex-int-key",
        "control-chars-in-key",
        "control-chars-in-value",
    ],
)
def test_config_values_yaml_cannot_construct_are_one_line(tmp_path: Path, text: str, part: str) -> None:
    """Tags and scalars that PyYAML's constructors refuse with a ValueError (was a traceback), or build into
    values whose repr fails (integers beyond 4300 digits) or spans lines: one printable ConfigError line."""
    path = _write(tmp_path / "c.yaml", text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    _one_line(err, path, part)
    assert str(err.value).isprintable() and len(str(err.value)) < 400, str(err.value)


@pytest.mark.parametrize("value", ["2001-02-28", "2001-02-29", "2001-13-45", "2001-12-14t21:59:43.10-05:00"])
def test_config_date_like_plain_values_stay_strings(tmp_path: Path, value: str) -> None:
    """YAML 1.1 reads a plain ``2001-02-28`` as a date (and ``2001-02-29`` as a ValueError): the configuration
    loader resolves no implicit timestamps, so a topic named like a date is that string."""
    cfg = load_config(_write(tmp_path / "c.yaml", f"input:\n  scan_topic: {value}\n"))
    assert cfg.input.scan_topic == value
    assert load_config(_write(tmp_path / "resolved.yaml", config_to_yaml(cfg))) == cfg  # a run's config.yaml


def test_every_error_here_is_a_gpom_error() -> None:
    for cls in (CarmenError, KittiError, RelationsError, TrajectoryFormatError, ConfigError):
        assert issubclass(cls, GpomError)


def test_keyframe_match_stamps_near_int64_limit(tmp_path: Path) -> None:
    """Logger stamps near the int64 limit wrapped around in the stamp window (no stamp match found)."""
    from datasets.keyframe_match import match_keyframe_scans

    far = "9223372036.850000"
    raw = _write(
        tmp_path / "raw.clf", flaser("1.0", logger="1.0") + "\n" + flaser("1.1", "4 5 6", logger=far) + "\n"
    )
    kf = _write(tmp_path / "kf.gfs.log", flaser("1.1", "4 5 6", logger=far) + "\n")
    result = match_keyframe_scans(read_carmen(kf), read_carmen(raw))
    assert result.indices.tolist() == [1] and result.methods.tolist() == ["stamp"]


# ------------------------------------------------------------------------------ placeholder stamps

PLACEHOLDER = ["-0.445999", "-0.913", "-1.343", "-1.82"] + ["4.29497e+09"] * 6  # infinite-corridor's


def test_corrected_log_with_placeholder_stamps_is_stamped_by_line_order(tmp_path: Path) -> None:
    """Stamps that no re-stamping can order within the usable years: a corrected log takes line order."""
    text = "".join(flaser(s) + "\n" + f"ODOM 1 2 0.5 0 0 0 {s} host {s}\n" for s in PLACEHOLDER)
    rec = read_carmen(_write(tmp_path / "x-corrected.log", text))
    validate_recording(rec)
    assert rec.meta["stamps_by_line_order"] and rec.meta["restamped"]["laser"] == len(PLACEHOLDER)
    np.testing.assert_array_equal(rec.scans.stamps_ns, np.arange(1, 20, 2) * 100_000_000)  # lines 1, 3, ...
    np.testing.assert_array_equal(rec.odometry.stamps_ns, np.arange(2, 21, 2) * 100_000_000)


def test_raw_log_with_placeholder_stamps_is_an_error(tmp_path: Path) -> None:
    path = _write(tmp_path / "x.clf", "".join(flaser(s) + "\n" for s in PLACEHOLDER))
    with pytest.raises(CarmenError) as err:
        read_carmen(path, InputConfig(carmen_stamp_jitter_s=1e300))
    _one_line(err, path, "cannot be put in order")


def test_infinite_corridor_reads(data_dir: Path) -> None:
    from datasets.registry import open_dataset

    rec = open_dataset(data_dir / "radish-corrected" / "infinite-corridor-corrected.log.gz")
    assert len(rec.scans) == 1941 and rec.meta["stamps_by_line_order"]
