"""ROS bag readers on the real bags of ../shared/data (read in place) and round trips of them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from datasets import open_dataset
from datasets.errors import TopicError
from datasets.rosbag import write_recording
from datasets.types import beam_angles_rad
from tests.conftest import data_file

DEMO_FIXED = "lsm-demo/demo_index_fixed.bag"
DEMO_DAMAGED = "lsm-demo/demo.bag"
JACKAL = "jackal/test2.bag"


def assert_same_scans(a, b) -> None:
    assert len(a) == len(b)
    for x, y in zip(a.ranges_m, b.ranges_m, strict=True):
        np.testing.assert_array_equal(x.view(np.uint32), y.view(np.uint32))
    for x, y in zip(a.angles_rad, b.angles_rad, strict=True):
        np.testing.assert_array_equal(x.view(np.uint32), y.view(np.uint32))
    np.testing.assert_array_equal(a.stamps_ns, b.stamps_ns)
    np.testing.assert_array_equal(a.range_min_m, b.range_min_m)
    np.testing.assert_array_equal(a.range_max_m, b.range_max_m)
    assert a.frame_ids == b.frame_ids


def test_old_definition_bag_reads_360_scans_of_681_beams() -> None:
    rec = open_dataset(data_file(DEMO_FIXED))
    scans = rec.scans
    assert len(scans) == 360
    assert set(scans.beam_counts().tolist()) == {681}
    assert np.all(np.diff(scans.stamps_ns) > 0)
    assert scans.stamps_ns[0] == 1_282_836_370_970_876_375  # header stamp, not bag time
    # angle_min / angle_increment of the first message, as stored, through the canonical construction
    expected = beam_angles_rad(-2.0862138271331787, 0.006135923322290182, 681)
    np.testing.assert_array_equal(scans[0].angles_rad, expected)
    assert scans.angles_rad[359] is scans.angles_rad[0]  # one shared array for identical parameters
    assert scans[0].range_max_m == pytest.approx(5.6, abs=1e-6) and scans.frame_ids[0] == "/laser"
    assert rec.odometry is None and rec.reference is None and rec.meta["notes"] == []


def test_old_definition_needs_the_fallback() -> None:
    """Plain rosbags cannot decode this bag from its embedded definition (roslib/Header)."""
    from rosbags.highlevel import AnyReader, AnyReaderError

    with pytest.raises(AnyReaderError, match="std_msgs/msg/Header"):
        AnyReader([data_file(DEMO_FIXED)]).open()


def test_damaged_index_bag_gives_exactly_the_scans_of_the_fixed_file() -> None:
    damaged = open_dataset(data_file(DEMO_DAMAGED))
    fixed = open_dataset(data_file(DEMO_FIXED))
    assert_same_scans(damaged.scans, fixed.scans)
    notes = damaged.meta["notes"]
    assert notes[0].startswith("damaged index bypassed by scanning the chunks")
    assert notes[1:] == [
        "index record at byte 792650 declares 5560 bytes for 278 entries; used 3336",
        "index record at byte 1027986 declares 1640 bytes for 82 entries; used 984",
    ]


def test_strict_reader_rejects_the_damaged_bag() -> None:
    """The fallback is needed: rosbags' own reader fails on demo.bag's index."""
    from rosbags.rosbag1 import Reader

    with pytest.raises(AssertionError):
        Reader(data_file(DEMO_DAMAGED)).open()


def test_jackal_odometry_only() -> None:
    path = data_file(JACKAL)
    rec = open_dataset(path, scan_topic="none")
    assert rec.scans is None
    assert len(rec.odometry) == 3060
    assert rec.meta["odom_topic"] == "/jackal_velocity_controller/odom"
    assert rec.odometry.frame_id == "odom"
    assert np.all(np.diff(rec.odometry.stamps_ns) >= 0)
    assert rec.odometry.covariances_xytheta is not None  # the controller publishes a pose covariance
    with pytest.raises(TopicError) as err:
        open_dataset(path)
    assert str(err.value) == (
        f"{path}: no sensor_msgs/LaserScan or PointCloud2 topic; topics: /imu/data (sensor_msgs/msg/Imu), "
        "/jackal_velocity_controller/odom (nav_msgs/msg/Odometry) "
        "(scan topic 'none' reads the bag without scans)"
    )


@pytest.mark.parametrize("name", ["demo.bag", "demo.mcap", "demo"])
def test_real_scans_round_trip(tmp_path: Path, name: str) -> None:
    rec = open_dataset(data_file(DEMO_DAMAGED))
    write_recording(rec, tmp_path / name)
    assert_same_scans(open_dataset(tmp_path / name).scans, rec.scans)


def test_jackal_odometry_round_trip(tmp_path: Path) -> None:
    rec = open_dataset(data_file(JACKAL), scan_topic="none")
    write_recording(rec, tmp_path / "odo.mcap")
    back = open_dataset(tmp_path / "odo.mcap", scan_topic="none")
    np.testing.assert_array_equal(back.odometry.stamps_ns, rec.odometry.stamps_ns)
    np.testing.assert_allclose(back.odometry.poses_xytheta, rec.odometry.poses_xytheta, atol=1e-9, rtol=0)
    np.testing.assert_allclose(
        back.odometry.covariances_xytheta, rec.odometry.covariances_xytheta, rtol=1e-12
    )
