"""ROS reader hardening: LaserScan beam fans that disagree with themselves, and odometry outside the scans'
time span. Bags are written in ``tmp_path`` with rosbags' writers (builders of ``tests/test_bad_input_ros``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from datasets import open_dataset
from datasets.config import InputConfig
from datasets.errors import DatasetError
from datasets.ros.reader import read_ros1
from datasets.ros.typestores import BagKind
from datasets.types import beam_angles_rad
from pipeline.run import input_notes
from tests.conftest import data_file
from tests.test_bad_input_ros import (
    STEP_NS,
    T0,
    Message,
    odom_msg,
    scan_msg,
    standard_messages,
    tf_static_msg,
    write_bag,
)

DEMO_MIN, DEMO_INC, DEMO_BEAMS = -2.0862138271331787, 0.006135923322290182, 681  # lsm-demo/demo.bag
DEMO = {"angle_min": DEMO_MIN, "angle_increment": DEMO_INC, "beams": DEMO_BEAMS}


def _expect_error(path: Path, *parts: str, **topics: str) -> str:
    with pytest.raises(DatasetError) as err:
        open_dataset(path, **topics)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{path}: "), message
    for part in parts:
        assert part in message, message
    return message


# -- LaserScan beam fans -----------------------------------------------------------------------------------


def _scan(
    kind: BagKind, stamp: int, angle_min: float, angle_increment: float, beams: int, set_: dict | None = None
) -> Message:
    """A LaserScan of ``beams`` beams; ``set_`` overrides fields after the consistent ``angle_max``."""
    topic, msgtype, t, msg = scan_msg(
        kind,
        stamp,
        angle_min=angle_min,
        angle_increment=angle_increment,
        ranges=np.full(beams, 2.0, np.float32),
    )
    for name, value in (set_ or {}).items():
        setattr(msg, name, value)
    return topic, msgtype, t, msg


BAD_FANS = [
    # (fields of the second scan, what the error says)
    (dict(DEMO, angle_increment_=0.0), "zero angle_increment"),
    (dict(DEMO, angle_increment_=1e-30), "do not end at angle_max"),
    # mirrored: a negative increment while angle_min < angle_max
    (dict(DEMO, angle_increment_=-DEMO_INC), "do not end at angle_max"),
    # 681 beams of 0.1 rad span 68 rad, angle_max says 4.17 rad
    (dict(DEMO, angle_increment_=0.1), "do not end at angle_max"),
    # 681 ranges where angle_min .. angle_max holds 341
    (dict(DEMO, angle_max=0.0), "do not end at angle_max"),
    (dict(DEMO, angle_max=float("nan")), "non-finite angle_max"),
    # consistent, but 3 pi wide
    (dict(angle_min=-1.5 * np.pi, angle_increment=3 * np.pi / 300, beams=301), "more than a full turn"),
]


def _make_second(kind: BagKind, spec: dict) -> Message:
    spec = dict(spec)
    inc_after = spec.pop("angle_increment_", None)
    extra = {k: spec.pop(k) for k in ("angle_max",) if k in spec}
    if inc_after is not None:
        extra["angle_increment"] = inc_after
    return _scan(kind, T0 + STEP_NS, spec["angle_min"], spec["angle_increment"], spec["beams"], extra)


@pytest.mark.parametrize(("spec", "expected"), BAD_FANS)
def test_inconsistent_beam_fan_names_topic_and_message(tmp_path: Path, spec: dict, expected: str) -> None:
    def messages(kind: BagKind) -> list[Message]:
        out = standard_messages(kind, 3)
        out[3] = _make_second(kind, spec)
        return out

    path = write_bag("bag", tmp_path, messages)
    _expect_error(path, "topic /scan: message 1", expected, f"{spec['beams']} beams")


@pytest.mark.parametrize("layout", ["mcap", "db3"])
def test_zero_increment_refused_in_ros2_bags(tmp_path: Path, layout: str) -> None:
    def messages(kind: BagKind) -> list[Message]:
        out = standard_messages(kind, 3)
        out[3] = _scan(kind, T0 + STEP_NS, DEMO_MIN, DEMO_INC, DEMO_BEAMS, {"angle_increment": 0.0})
        return out

    _expect_error(write_bag(layout, tmp_path, messages), "topic /scan: message 1", "zero angle_increment")


GOOD_FANS = [
    # reversed and consistent (angle_min > angle_max, negative increment)
    dict(angle_min=-DEMO_MIN, angle_increment=-DEMO_INC, beams=DEMO_BEAMS),
    # off by one increment: n beams over angle_max - angle_min in n steps (angle_max one step beyond the last)
    dict(DEMO, angle_max=DEMO_MIN + DEMO_BEAMS * DEMO_INC),
    # ... or in n - 2 steps (angle_max one step short of the last beam)
    dict(DEMO, angle_max=DEMO_MIN + 679 * DEMO_INC),
    # a full turn: 360 beams of 1 degree from -pi, angle_max pi
    dict(angle_min=-np.pi, angle_increment=2 * np.pi / 360, beams=360, angle_max=np.pi),
    # one beam: no fan, the increment does not matter
    dict(angle_min=0.25, angle_increment=0.0, beams=1, angle_max=0.25),
]


@pytest.mark.parametrize("spec", GOOD_FANS)
def test_sound_beam_fans_are_read_as_before(tmp_path: Path, spec: dict) -> None:
    def messages(kind: BagKind) -> list[Message]:
        out = standard_messages(kind, 3)
        out[3] = _make_second(kind, spec)
        return out

    rec = open_dataset(write_bag("bag", tmp_path, messages))
    expected = beam_angles_rad(spec["angle_min"], spec["angle_increment"], spec["beams"])
    np.testing.assert_array_equal(rec.scans.angles_rad[1], expected)


def test_float32_rounding_of_angle_max_is_accepted(tmp_path: Path) -> None:
    """angle_max computed in float32 by a driver from float32 angle_min and increment."""
    end = float(np.float32(np.float32(DEMO_MIN) + np.float32(DEMO_BEAMS - 1) * np.float32(DEMO_INC)))
    spec = dict(DEMO, angle_max=end)

    def messages(kind: BagKind) -> list[Message]:
        out = standard_messages(kind, 3)
        out[3] = _make_second(kind, spec)
        return out

    rec = open_dataset(write_bag("mcap", tmp_path, messages))
    assert len(rec.scans) == 3


@pytest.mark.parametrize("name", ["demo.bag", "demo_index_fixed.bag"])
def test_real_demo_bag_fans_still_read(name: str) -> None:
    rec = read_ros1(data_file(f"lsm-demo/{name}"), InputConfig())
    assert len(rec.scans) == 360
    expected = beam_angles_rad(DEMO_MIN, DEMO_INC, DEMO_BEAMS)
    assert all(np.array_equal(a, expected) for a in rec.scans.angles_rad)


# -- odometry outside the scans' time span -----------------------------------------------------------------


def _odometry_bag(layout: str, where: Path, odom_stamps: list[int], n: int = 5) -> Path:
    def messages(kind: BagKind) -> list[Message]:
        out = [tf_static_msg(kind)]
        out += [scan_msg(kind, T0 + i * STEP_NS) for i in range(n)]
        out += [odom_msg(kind, s, x=0.1 * k) for k, s in enumerate(odom_stamps)]
        return out

    return write_bag(layout, where, messages)


@pytest.mark.parametrize("layout", ["bag", "mcap"])
def test_odometry_stamps_all_zero_are_an_error(tmp_path: Path, layout: str) -> None:
    path = _odometry_bag(layout, tmp_path, [0] * 5)
    msg = _expect_error(
        path,
        "odometry topic /odom spans [0.000, 0.000] s",
        f"scans span [{T0 / 1e9:.3f}, {(T0 + 4 * STEP_NS) / 1e9:.3f}] s",
        "no scan lies within the odometry's time span",
        "--odom-topic none",
    )
    assert "fix the header stamps" in msg


def test_odometry_after_the_scans_is_an_error_even_when_named(tmp_path: Path) -> None:
    late = T0 + 1000 * 10**9
    path = _odometry_bag("bag", tmp_path, [late + i * STEP_NS for i in range(5)])
    _expect_error(path, "odometry topic /odom", "no scan lies within", odom_topic="/odom")


def test_odometry_none_reads_the_scans_without_odometry(tmp_path: Path) -> None:
    path = _odometry_bag("bag", tmp_path, [0] * 5)
    rec = open_dataset(path, odom_topic="none")
    assert rec.odometry is None and rec.meta["odom_topic"] is None and len(rec.scans) == 5


def test_scans_outside_partial_odometry_are_counted(tmp_path: Path) -> None:
    # odometry over the first two scans only (plus 1 ns): scans 2..4 lie beyond it (slack 0.1 s = 1 step)
    path = _odometry_bag("bag", tmp_path, [T0 + 1, T0 + STEP_NS // 2, T0 + STEP_NS + 1], n=5)
    rec = open_dataset(path)
    assert rec.meta["scans_outside_odometry"] == {"/odom": 2}  # scan 2 is 0.1 s after the last: within slack
    # odometry matching the scans: none outside
    (tmp_path / "m").mkdir()
    path = _odometry_bag("mcap", tmp_path / "m", [T0 + i * STEP_NS + 1 for i in range(5)])
    assert open_dataset(path).meta["scans_outside_odometry"] == {"/odom": 0}


def _restamped(message: Message, stamp_ns: int, bag_time_ns: int) -> Message:
    """``message`` with header stamp ``stamp_ns``, recorded at bag time ``bag_time_ns``."""
    topic, msgtype, _, msg = message
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
    return topic, msgtype, bag_time_ns, msg


@pytest.mark.parametrize("layout", ["bag", "mcap"])
def test_header_stamps_all_equal_give_way_to_the_bags_times(tmp_path: Path, layout: str) -> None:
    """A driver that never sets its header stamps (all 0) leaves no time in them: the bag's receive times
    stamp that topic instead, so odometry still moves between scans; a topic with real stamps keeps them."""
    n = 6

    def messages(kind: BagKind) -> list[Message]:
        out = [tf_static_msg(kind)]
        out += [_restamped(scan_msg(kind, T0), 0, T0 + i * STEP_NS) for i in range(n)]
        out += [odom_msg(kind, T0 + i * STEP_NS + 1, x=0.1 * i) for i in range(n)]
        return out

    rec = open_dataset(write_bag(layout, tmp_path, messages))
    assert rec.meta["bag_time_topics"] == ["/scan"]
    assert input_notes(rec.meta) == ["header stamps of /scan all equal: stamped with the bag's receive times"]
    np.testing.assert_array_equal(rec.scans.stamps_ns, T0 + STEP_NS * np.arange(n))
    np.testing.assert_array_equal(rec.odometry.stamps_ns, T0 + STEP_NS * np.arange(n) + 1)
    assert np.ptp(rec.odometry.poses_xytheta[:, 0]) > 0.4

    # the odometry's headers unset too: both topics run on the bag's clock
    def unset_odometry(kind: BagKind) -> list[Message]:
        out = messages(kind)
        return [_restamped(m, 0, m[2]) if m[0] == "/odom" else m for m in out]

    (tmp_path / "b").mkdir()
    rec = open_dataset(write_bag(layout, tmp_path / "b", unset_odometry))
    assert sorted(rec.meta["bag_time_topics"]) == ["/odom", "/scan"]
    np.testing.assert_array_equal(rec.odometry.stamps_ns, T0 + STEP_NS * np.arange(n) + 1)
    assert rec.meta["scans_outside_odometry"] == {"/odom": 0}
