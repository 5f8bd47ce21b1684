"""ROS1 / ROS2 bag reading and writing on synthetic recordings (written with rosbags' writer in tmp_path)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from datasets import open_dataset
from datasets.errors import DatasetError, TopicError, UnknownFormatError
from datasets.ros.reader import cloud_points
from datasets.rosbag import (
    angle_parameters,
    open_bag_writer,
    read_bag,
    standard_typestore,
    write_messages,
    write_recording,
)
from datasets.types import Recording, ScanSequence, Trajectory, beam_angles_rad, wrap_angle_rad

T0 = 1_600_000_000_123_456_789
MS = 1_000_000
LAYOUTS = ["out.bag", "out.mcap", "out"]  # ROS1 file, ROS2 single MCAP file, ROS2 folder


def synthetic_recording(n: int = 40, seed: int = 0, sources: tuple[str, ...] = ("laser",)) -> Recording:
    """Scans with awkward angles, inf / NaN no-returns, odometry (with covariance), reference, scan poses."""
    rng = np.random.default_rng(seed)
    stamps = T0 + np.arange(n, dtype=np.int64) * 100_000_000 + rng.integers(0, 999, n)
    # an increment that is not a "nice" float32, with a start angle that is not float32-exact
    angles = beam_angles_rad(-2.0862138271331787, 0.006135923322290182, 681)
    ranges = [rng.uniform(0.02, 5.6, 681).astype(np.float32) for _ in range(n)]
    ranges[1][0] = np.inf
    ranges[2][3] = np.nan
    ranges[3][4] = -np.inf  # REP 117: too close
    k = len(sources)
    odo_stamps = np.sort(T0 + rng.integers(0, n * 100_000_000, 3 * n))
    odo_stamps = np.unique(odo_stamps)
    m = len(odo_stamps)
    cov = np.einsum("nij,nkj->nik", *(2 * [rng.normal(size=(m, 3, 3))]))
    odometry = Trajectory(
        odo_stamps, np.c_[rng.normal(size=(m, 2)) * 10, rng.uniform(-np.pi, np.pi, m)], "odom", cov
    )
    ref = np.c_[rng.normal(size=(n, 2)) * 10, rng.uniform(-np.pi, np.pi, n)]
    scans = ScanSequence(
        ranges,
        [angles] * n,
        stamps,
        0.02,
        5.6,
        "laser" if k == 1 else [f"laser{i % k}" for i in range(n)],
        np.arange(n, dtype=np.int32) % k,
        sources,
    )
    return Recording(
        source=Path("synthetic"),
        format="synthetic",
        scans=scans,
        odometry=odometry,
        scan_poses=Trajectory(stamps, ref[::-1].copy(), "odom"),
        reference=Trajectory(stamps, ref, "map"),
        laser_in_base_xytheta=np.array([0.12, -0.03, 0.25]),
    )


def assert_poses_equal(a: np.ndarray, b: np.ndarray, atol: float = 1e-9) -> None:
    np.testing.assert_allclose(a[:, :2], b[:, :2], atol=atol, rtol=0)
    np.testing.assert_allclose(wrap_angle_rad(a[:, 2] - b[:, 2]), 0.0, atol=atol)


def assert_same_recording(back: Recording, rec: Recording) -> None:
    assert back.scans is not None and rec.scans is not None
    assert len(back.scans) == len(rec.scans)
    for r_back, r in zip(back.scans.ranges_m, rec.scans.ranges_m, strict=True):
        assert r_back.dtype == np.float32
        np.testing.assert_array_equal(r_back.view(np.uint32), r.view(np.uint32))  # bit for bit, NaN too
    for a_back, a in zip(back.scans.angles_rad, rec.scans.angles_rad, strict=True):
        np.testing.assert_array_equal(a_back.view(np.uint32), a.view(np.uint32))
    np.testing.assert_array_equal(back.scans.stamps_ns, rec.scans.stamps_ns)
    np.testing.assert_array_equal(back.scans.range_max_m, rec.scans.range_max_m.astype(np.float32))
    np.testing.assert_array_equal(back.odometry.stamps_ns, rec.odometry.stamps_ns)
    assert_poses_equal(back.odometry.poses_xytheta, rec.odometry.poses_xytheta)
    np.testing.assert_allclose(
        back.odometry.covariances_xytheta, rec.odometry.covariances_xytheta, atol=1e-12
    )
    np.testing.assert_array_equal(back.reference.stamps_ns, rec.reference.stamps_ns)
    assert_poses_equal(back.reference.poses_xytheta, rec.reference.poses_xytheta)
    assert_poses_equal(back.scan_poses.poses_xytheta, rec.scan_poses.poses_xytheta)
    np.testing.assert_allclose(back.laser_in_base_xytheta, rec.laser_in_base_xytheta, atol=1e-12)


@pytest.mark.parametrize("name", [*LAYOUTS, "out.db3"])
def test_round_trip(tmp_path: Path, name: str) -> None:
    rec = synthetic_recording()
    counts = write_recording(rec, tmp_path / name)
    assert counts == {"/tf_static": 1, "/scan": 40, "/ground_truth/pose": 40, "/scan_pose": 40, "/odom": 120}
    back = open_dataset(tmp_path / name)
    assert back.format == ("ros1" if name.endswith(".bag") else "ros2")
    assert back.meta["scan_topics"] == ["/scan"] and back.meta["odom_topic"] == "/odom"
    assert back.meta["reference_topic"] == "/ground_truth/pose"
    assert_same_recording(back, rec)
    # only the output is left: no temporary folder, and .mcap / .db3 are single files
    assert [p.name for p in tmp_path.iterdir()] == [name]
    assert (tmp_path / name).is_dir() == (name == "out")


def test_mcap_file_is_a_self_contained_ros2_bag(tmp_path: Path) -> None:
    from rosbags.interfaces import QosDurability
    from rosbags.rosbag2 import Reader

    write_recording(synthetic_recording(n=5), tmp_path / "x.mcap")
    with Reader(tmp_path / "x.mcap") as reader:
        topics = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        tf_static = next(c for c in reader.connections if c.topic == "/tf_static")
    assert topics["/scan"] == ("sensor_msgs/msg/LaserScan", 5)
    assert topics["/odom"][0] == "nav_msgs/msg/Odometry"
    assert [q.durability for q in tf_static.ext.offered_qos_profiles] == [QosDurability.TRANSIENT_LOCAL]


def test_tf_static_is_latched_in_ros1(tmp_path: Path) -> None:
    from rosbags.rosbag1 import Reader

    write_recording(synthetic_recording(n=5), tmp_path / "x.bag")
    with Reader(tmp_path / "x.bag") as reader:
        latching = {c.topic: c.ext.latching for c in reader.connections}
    assert latching["/tf_static"] == 1 and latching["/scan"] is None


def test_several_sources_round_trip(tmp_path: Path) -> None:
    rec = synthetic_recording(n=30, sources=("/r0/scan", "/r1/scan"))
    counts = write_recording(rec, tmp_path / "two.bag")
    assert counts["/r0/scan"] == 15 and counts["/r1/scan"] == 15
    assert counts["/r0/ground_truth/pose"] == 15 and counts["/r1/ground_truth/pose"] == 15
    with pytest.raises(TopicError) as err:
        open_dataset(tmp_path / "two.bag")
    assert str(err.value) == (
        f"{tmp_path / 'two.bag'}: several scan topics (/r0/scan, /r1/scan); choose one with --scan-topic "
        "(or 'all' for every LaserScan topic)"
    )
    back = open_dataset(tmp_path / "two.bag", scan_topic="all")
    assert back.scans.sources == ["/r0/scan", "/r1/scan"]
    np.testing.assert_array_equal(back.scans.source_index, rec.scans.source_index)
    assert back.meta["reference_topics"] == {
        "/r0/scan": "/r0/ground_truth/pose",
        "/r1/scan": "/r1/ground_truth/pose",
    }
    assert_same_recording(back, rec)
    # one platform alone: its own namespace's ground truth, at its own scans
    one = open_dataset(tmp_path / "two.bag", scan_topic="/r1/scan")
    assert one.meta["reference_topic"] == "/r1/ground_truth/pose"
    assert_poses_equal(one.reference.poses_xytheta, rec.reference.poses_xytheta[1::2])


def test_global_ground_truth_serves_every_namespace(tmp_path: Path) -> None:
    with open_bag_writer(tmp_path / "g.bag") as w:
        laser = w.types["sensor_msgs/msg/LaserScan"]
        for ns in ("/a", "/b"):
            for i in range(3):
                msg = laser(
                    header=w.header(T0 + MS * i, "laser"),
                    angle_min=0.0,
                    angle_max=0.2,
                    angle_increment=0.1,
                    time_increment=0.0,
                    scan_time=0.0,
                    range_min=0.0,
                    range_max=10.0,
                    ranges=np.ones(3, np.float32),
                    intensities=np.zeros(0, np.float32),
                )
                w.write(f"{ns}/scan", "sensor_msgs/msg/LaserScan", T0 + MS * i, msg)
        pose = w.types["geometry_msgs/msg/PoseStamped"]
        from datasets.ros.typestores import pose_msg

        for i in range(3):
            w.write(
                "/ground_truth",
                "geometry_msgs/msg/PoseStamped",
                T0 + MS * i,
                pose(header=w.header(T0 + MS * i, "map"), pose=pose_msg(w.typestore, i, 0.0, 0.0)),
            )
    back = open_dataset(tmp_path / "g.bag", scan_topic="all")
    assert back.meta["reference_topics"] == {"/a/scan": "/ground_truth", "/b/scan": "/ground_truth"}
    np.testing.assert_allclose(back.reference.poses_xytheta[:, 0], [0, 0, 1, 1, 2, 2])
    assert back.meta["scans_outside_pose_topics"] == {"/ground_truth": 0}
    one = open_dataset(tmp_path / "g.bag", scan_topic="/a/scan", reference_topic="/ground_truth")
    assert one.meta["reference_topic"] == "/ground_truth"


@pytest.mark.parametrize(
    ("a_min", "a_inc", "n"),
    [
        (-np.pi / 2, np.pi / 180, 180),
        (-2.0862138271331787, 0.006135923322290182, 681),
        (-np.pi, 2 * np.pi / 720, 720),
        (0.3, 1e-7, 5),
        (1.0, 0.0, 1),
    ],
)
def test_angle_parameters_reproduce_angles_bit_for_bit(a_min: float, a_inc: float, n: int) -> None:
    angles = beam_angles_rad(a_min, a_inc, n)
    a0, inc = angle_parameters(angles)
    assert a0 == float(np.float32(a0)) and inc == float(np.float32(inc))
    np.testing.assert_array_equal(beam_angles_rad(a0, inc, n).view(np.uint32), angles.view(np.uint32))


def test_angle_parameters_reject_non_uniform_angles() -> None:
    angles = beam_angles_rad(0.0, 0.01, 100)
    angles[50] += np.float32(1e-3)
    with pytest.raises(DatasetError, match="a sensor_msgs/LaserScan cannot hold them"):
        angle_parameters(angles)


def test_writer_refuses_non_uniform_angles_before_writing(tmp_path: Path) -> None:
    rec = synthetic_recording(n=4)
    bad = rec.scans.angles_rad[0].copy()
    bad[10] = 0.0
    scans = ScanSequence(
        rec.scans.ranges_m, [rec.scans.angles_rad[0], bad, bad, bad], rec.scans.stamps_ns, 0.0, 5.6
    )
    with pytest.raises(DatasetError, match=r"^synthetic: scan 1: beam angles are not"):
        write_recording(Recording(Path("synthetic"), "x", scans=scans), tmp_path / "o.bag")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["out.bag", "out.mcap", "out"])
def test_writer_refuses_to_overwrite(tmp_path: Path, name: str) -> None:
    target = tmp_path / name
    target.mkdir() if name == "out" else target.write_bytes(b"keep")
    with pytest.raises(DatasetError) as err:
        write_recording(synthetic_recording(n=4), target)
    assert (
        str(err.value) == f"{target}: exists already; not overwriting it (remove it or choose another name)"
    )
    assert target.is_dir() if name == "out" else target.read_bytes() == b"keep"


def test_writer_unknown_suffix(tmp_path: Path) -> None:
    with pytest.raises(UnknownFormatError, match=r"unknown bag format '\.txt'"):
        write_recording(synthetic_recording(n=4), tmp_path / "o.txt")


@pytest.mark.parametrize("name", LAYOUTS)
def test_failed_write_leaves_nothing(tmp_path: Path, name: str) -> None:
    with pytest.raises(RuntimeError, match="boom"), open_bag_writer(tmp_path / name) as w:
        w.write("/odom", "nav_msgs/msg/Odometry", T0, _odometry(w))
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def _odometry(w):
    from datasets.ros.writer import _odometry_msg

    return _odometry_msg(w, Trajectory(np.array([T0]), np.zeros((1, 3))), 0, "base_link")


# -- topic choice and bad content -----------------------------------------------------------------------


def _scan_bag(path: Path, scans: list[tuple[int, np.ndarray]], topic: str = "/scan", extra_topics=()) -> Path:
    """A bag with LaserScans ``(stamp_ns, ranges)`` on ``topic`` plus one scan on each of ``extra_topics``."""
    with open_bag_writer(path) as w:
        laser = w.types["sensor_msgs/msg/LaserScan"]
        for t in (topic, *extra_topics):
            for stamp, ranges in scans if t == topic else scans[:1]:
                r = np.asarray(ranges, np.float32)
                msg = laser(
                    header=w.header(stamp, "laser"),
                    angle_min=-0.5,
                    angle_max=0.5,
                    angle_increment=1.0 / max(len(r) - 1, 1),
                    time_increment=0.0,
                    scan_time=0.0,
                    range_min=0.0,
                    range_max=10.0,
                    ranges=r,
                    intensities=np.zeros(0, np.float32),
                )
                w.write(t, "sensor_msgs/msg/LaserScan", stamp, msg)
        w.write("/odom", "nav_msgs/msg/Odometry", T0, _odometry(w))
    return path


@pytest.mark.parametrize("name", ["b.bag", "b.mcap"])
def test_inf_and_nan_ranges_are_no_returns_and_accepted(tmp_path: Path, name: str) -> None:
    path = _scan_bag(tmp_path / name, [(T0, [1.0, np.inf, np.nan, -np.inf]), (T0 + 1, [2.0, 2.0, 2.0, 2.0])])
    back = open_dataset(path)
    assert len(back.scans) == 2
    assert back.scans[0].hit_mask().tolist() == [True, False, False, False]
    assert np.isposinf(back.scans[0].ranges_m[1]) and np.isnan(back.scans[0].ranges_m[2])
    # a reading at the declared range_max (10 m) is no return either, and the meta says which rule
    path = _scan_bag(tmp_path / ("c" + name), [(T0, [1.0, 10.0, 9.99]), (T0 + 1, [2.0, 2.0, 2.0])])
    back = open_dataset(path)
    assert back.scans[0].hit_mask().tolist() == [True, False, True]
    assert back.meta["no_return"]["range_m"] == 10.0 and "range_max" in back.meta["no_return"]["rule"]


@pytest.mark.parametrize("name", ["b.bag", "b.mcap"])
def test_negative_range_is_an_error_naming_the_message(tmp_path: Path, name: str) -> None:
    path = _scan_bag(tmp_path / name, [(T0, [1.0, 1.0, 1.0]), (T0 + 5, [1.0, -0.5, 1.0])])
    with pytest.raises(DatasetError) as err:
        open_dataset(path)
    assert (
        str(err.value)
        == f"{path}: topic /scan: message 1 (stamp {T0 + 5} ns) has 1 negative ranges (beam 1: -0.5 m)"
    )


def test_empty_scan_is_an_error(tmp_path: Path) -> None:
    path = _scan_bag(tmp_path / "e.bag", [(T0, [1.0]), (T0 + 7, [])])
    with pytest.raises(DatasetError) as err:
        open_dataset(path)
    assert str(err.value) == f"{path}: topic /scan: message 1 (stamp {T0 + 7} ns) is an empty scan"


def test_stamps_going_backwards_are_an_error(tmp_path: Path) -> None:
    # bag times in order, header stamps going back at message 2
    path = tmp_path / "back.bag"
    with open_bag_writer(path) as w:
        laser = w.types["sensor_msgs/msg/LaserScan"]
        for i, stamp in enumerate([T0, T0 + 100, T0 + 50]):
            msg = laser(
                header=w.header(stamp, "laser"),
                angle_min=0.0,
                angle_max=0.1,
                angle_increment=0.1,
                time_increment=0.0,
                scan_time=0.0,
                range_min=0.0,
                range_max=10.0,
                ranges=np.ones(2, np.float32),
                intensities=np.zeros(0, np.float32),
            )
            w.write("/scan", "sensor_msgs/msg/LaserScan", T0 + 1000 * i, msg)
    with pytest.raises(DatasetError) as err:
        open_dataset(path)
    assert str(err.value) == (
        f"{path}: topic /scan: header stamp goes backwards at message 2 ({T0 + 50} ns after {T0 + 100} ns)"
    )


def test_topic_errors_list_what_exists(tmp_path: Path) -> None:
    path = _scan_bag(tmp_path / "t.bag", [(T0, [1.0, 2.0])], extra_topics=("/front/scan",))
    with pytest.raises(TopicError) as err:
        open_dataset(path)
    assert str(err.value) == (
        f"{path}: several scan topics (/front/scan, /scan); choose one with --scan-topic "
        "(or 'all' for every LaserScan topic)"
    )
    with pytest.raises(TopicError) as err:
        open_dataset(path, scan_topic="/rear/scan")
    assert str(err.value) == (
        f"{path}: no scan topic /rear/scan; topics: /front/scan (sensor_msgs/msg/LaserScan), "
        "/odom (nav_msgs/msg/Odometry), /scan (sensor_msgs/msg/LaserScan)"
    )
    with pytest.raises(TopicError) as err:
        open_dataset(path, scan_topic="/odom")
    assert str(err.value) == (
        f"{path}: scan topic /odom is nav_msgs/msg/Odometry, not sensor_msgs/msg/LaserScan or "
        "sensor_msgs/msg/PointCloud2"
    )
    with pytest.raises(TopicError, match=r"no odometry topic /wheels; topics: /front/scan"):
        open_dataset(path, scan_topic="/scan", odom_topic="/wheels")
    assert len(open_dataset(path, scan_topic="/front/scan").scans) == 1


def test_scans_outside_the_ground_truth_span_are_counted(tmp_path: Path) -> None:
    from datasets.ros.typestores import pose_msg

    gt = tmp_path / "gt.bag"
    with open_bag_writer(gt) as w:
        laser = w.types["sensor_msgs/msg/LaserScan"]
        for stamp in T0 + MS * np.arange(5):
            msg = laser(
                header=w.header(int(stamp), "laser"),
                angle_min=0.0,
                angle_max=0.1,
                angle_increment=0.1,
                time_increment=0.0,
                scan_time=0.0,
                range_min=0.0,
                range_max=10.0,
                ranges=np.ones(2, np.float32),
                intensities=np.zeros(0, np.float32),
            )
            w.write("/scan", "sensor_msgs/msg/LaserScan", int(stamp), msg)
        for i in (1, 2):  # ground truth covers scans 1..2 only
            stamp = T0 + MS * i
            msg = w.types["geometry_msgs/msg/PoseStamped"](
                header=w.header(stamp, "map"), pose=pose_msg(w.typestore, float(i), 0.0, 0.0)
            )
            w.write("/ground_truth", "geometry_msgs/msg/PoseStamped", stamp, msg)
    back = open_dataset(gt)
    assert back.meta["scans_outside_pose_topics"] == {"/ground_truth": 3}
    np.testing.assert_allclose(back.reference.poses_xytheta[:, 0], [1, 1, 2, 2, 2])


def test_no_scan_topic_error_and_odometry_only_reading(tmp_path: Path) -> None:
    path = tmp_path / "odo.mcap"
    with open_bag_writer(path) as w:
        w.write("/odom", "nav_msgs/msg/Odometry", T0, _odometry(w))
    with pytest.raises(TopicError) as err:
        open_dataset(path)
    assert str(err.value) == (
        f"{path}: no sensor_msgs/LaserScan or PointCloud2 topic; topics: /odom (nav_msgs/msg/Odometry) "
        "(scan topic 'none' reads the bag without scans)"
    )
    rec = open_dataset(path, scan_topic="none")
    assert rec.scans is None and len(rec.odometry) == 1


def test_truncated_ros1_bag(tmp_path: Path) -> None:
    good = tmp_path / "good.bag"
    write_recording(synthetic_recording(n=20), good)
    data = good.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: len(data) * 2 // 3])
    at = data.index(b"index_pos=") + len(b"index_pos=")
    index_pos = int.from_bytes(data[at : at + 8], "little")
    with pytest.raises(DatasetError) as err:
        open_dataset(cut)
    assert str(err.value) == (
        f"{cut}: truncated ROS1 bag ({len(data) * 2 // 3} bytes, but its index starts at byte {index_pos})"
    )


def test_truncated_mcap(tmp_path: Path) -> None:
    good = tmp_path / "good.mcap"
    write_recording(synthetic_recording(n=20), good)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[:5000])
    with pytest.raises(DatasetError, match=rf"^{cut}: corrupt or unreadable ROS2 bag \(") as err:
        open_dataset(cut)
    assert "\n" not in str(err.value)


def test_not_a_bag(tmp_path: Path) -> None:
    path = tmp_path / "text.bag"
    path.write_text("hello\n")
    with pytest.raises(DatasetError) as err:
        open_dataset(path)
    assert str(err.value).startswith(f"{path}: corrupt ROS1 bag (not a ROS1 v2.0 bag (bad magic line)")


# -- tf --------------------------------------------------------------------------------------------------


def test_tf_chain_through_an_intermediate_frame(tmp_path: Path) -> None:
    path = tmp_path / "tf.bag"
    with open_bag_writer(path) as w:
        from datasets.ros.writer import _transform_stamped

        tfs = [
            _transform_stamped(w, T0, "base_link", "mast", np.array([1.0, 0.0, np.pi / 2])),
            _transform_stamped(w, T0, "mast", "laser", np.array([0.5, 0.0, 0.1])),
        ]
        w.write("/tf_static", "tf2_msgs/msg/TFMessage", T0, w.types["tf2_msgs/msg/TFMessage"](transforms=tfs))
        laser = w.types["sensor_msgs/msg/LaserScan"]
        msg = laser(
            header=w.header(T0, "/laser"),
            angle_min=0.0,
            angle_max=0.1,
            angle_increment=0.1,
            time_increment=0.0,
            scan_time=0.0,
            range_min=0.0,
            range_max=10.0,
            ranges=np.ones(2, np.float32),
            intensities=np.zeros(0, np.float32),
        )
        w.write("/scan", "sensor_msgs/msg/LaserScan", T0, msg)
    rec = open_dataset(path)
    np.testing.assert_allclose(rec.laser_in_base_xytheta, [1.0, 0.5, np.pi / 2 + 0.1], atol=1e-12)


# -- point clouds ----------------------------------------------------------------------------------------


def _cloud_msg(w, stamp: int, pts: np.ndarray, big_endian: bool, f64: bool, pad: int, height: int = 1):
    """A PointCloud2 with an (x, y, z, intensity) layout of the given endianness / width and row padding."""
    t = w.types
    e = ">" if big_endian else "<"
    ft = f"{e}f8" if f64 else f"{e}f4"
    dtype = np.dtype(
        {
            "names": ["intensity", "x", "y", "z"],
            "formats": [f"{e}u2", ft, ft, ft],
            "offsets": [0, 4, 4 + 8 * f64 + 4 * (not f64), 4 + 2 * (8 * f64 + 4 * (not f64))],
            "itemsize": 4 + 3 * (8 if f64 else 4) + 3,
        }
    )
    arr = np.zeros(len(pts), dtype)
    arr["x"], arr["y"], arr["z"] = pts.T
    arr["intensity"] = np.arange(len(pts))
    width = len(pts) // height
    row = arr.tobytes()
    rows = [
        row[i * width * dtype.itemsize : (i + 1) * width * dtype.itemsize] + b"\xee" * pad
        for i in range(height)
    ]
    pf = t["sensor_msgs/msg/PointField"]
    fields = [
        pf(name="intensity", offset=0, datatype=4, count=1),
        pf(name="x", offset=dtype.fields["x"][1], datatype=8 if f64 else 7, count=1),
        pf(name="y", offset=dtype.fields["y"][1], datatype=8 if f64 else 7, count=1),
        pf(name="z", offset=dtype.fields["z"][1], datatype=8 if f64 else 7, count=1),
    ]
    return t["sensor_msgs/msg/PointCloud2"](
        header=w.header(stamp, "lidar"),
        height=height,
        width=width,
        fields=fields,
        is_bigendian=big_endian,
        point_step=dtype.itemsize,
        row_step=width * dtype.itemsize + pad,
        data=np.frombuffer(b"".join(rows), np.uint8),
        is_dense=False,
    )


@pytest.mark.parametrize(
    ("big_endian", "f64", "pad", "height"), [(False, False, 0, 1), (True, False, 5, 2), (True, True, 3, 4)]
)
def test_point_cloud_layouts(tmp_path: Path, big_endian: bool, f64: bool, pad: int, height: int) -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform(-20, 20, (400, 3)).astype(np.float32)
    pts[:, 2] = rng.uniform(-0.2, 0.2, 400)
    pts[7] = np.nan  # dropped
    path = tmp_path / "cloud.mcap"
    with open_bag_writer(path) as w:
        for i in range(3):
            w.write(
                "/points",
                "sensor_msgs/msg/PointCloud2",
                T0 + i,
                _cloud_msg(w, T0 + i, pts + i, big_endian, f64, pad, height),
            )
    rec = open_dataset(path, cloud_scan_beams=360)
    assert rec.clouds is not None and len(rec.clouds) == 3 and len(rec.scans) == 3
    keep = np.isfinite(pts).all(axis=1)
    cloud = rec.clouds[2]
    np.testing.assert_array_equal(cloud.points_xyz_m, (pts + 2)[keep])
    np.testing.assert_array_equal(cloud.intensity, np.arange(400)[keep])
    assert cloud.stamp_ns == T0 + 2 and cloud.frame_id == "lidar"
    from datasets.cloud import cloud_to_scan

    r, a = cloud_to_scan((pts + 1)[keep], (-0.25, 0.25), 360, 80.0)
    np.testing.assert_array_equal(rec.scans.ranges_m[1], r)
    np.testing.assert_array_equal(rec.scans.angles_rad[1], a)


def test_point_cloud_without_z_is_an_error() -> None:
    store = standard_typestore("ros2")
    pf = store.types["sensor_msgs/msg/PointField"]
    msg = store.types["sensor_msgs/msg/PointCloud2"](
        header=None,
        height=1,
        width=1,
        fields=[pf(name="x", offset=0, datatype=7, count=1)],
        is_bigendian=False,
        point_step=4,
        row_step=4,
        data=np.zeros(4, np.uint8),
        is_dense=True,
    )
    with pytest.raises(DatasetError, match=r"^here: point cloud without field\(s\) y, z$"):
        cloud_points(msg, "here")


# -- arbitrary messages: OccupancyGrid and GridMap -------------------------------------------------------


def _grid_messages(kind: str) -> tuple[list, np.ndarray, np.ndarray]:
    store = standard_typestore(kind)
    from datasets.ros.typestores import header_msg, pose_msg, time_msg

    t = store.types
    occupancy = np.arange(12, dtype=np.int8).reshape(3, 4) * 8
    layer = np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4)
    origin = pose_msg(store, -1.5, 2.0, 0.0)
    grid = t["nav_msgs/msg/OccupancyGrid"](
        header=header_msg(store, kind, T0, "map"),
        info=t["nav_msgs/msg/MapMetaData"](
            map_load_time=time_msg(store, T0), resolution=0.05, width=4, height=3, origin=origin
        ),
        data=occupancy.reshape(-1),
    )
    dims = [
        t["std_msgs/msg/MultiArrayDimension"](label="column_index", size=4, stride=12),
        t["std_msgs/msg/MultiArrayDimension"](label="row_index", size=3, stride=3),
    ]
    array = t["std_msgs/msg/Float32MultiArray"](
        layout=t["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0), data=layer.T.reshape(-1)
    )
    info = dict(resolution=0.05, length_x=0.2, length_y=0.15, pose=pose_msg(store, 0.5, -0.25, 0.0))
    if kind == "ros1":
        grid_info = t["grid_map_msgs/msg/GridMapInfo"](header=header_msg(store, kind, T0, "map"), **info)
        gridmap = t["grid_map_msgs/msg/GridMap"](
            info=grid_info,
            layers=["variance"],
            basic_layers=[],
            data=[array],
            outer_start_index=0,
            inner_start_index=0,
        )
    else:
        gridmap = t["grid_map_msgs/msg/GridMap"](
            header=header_msg(store, kind, T0, "map"),
            info=t["grid_map_msgs/msg/GridMapInfo"](**info),
            layers=["variance"],
            basic_layers=[],
            data=[array],
            outer_start_index=0,
            inner_start_index=0,
        )
    msgs = [
        ("/map", "nav_msgs/msg/OccupancyGrid", T0, grid),
        ("/grid_map", "grid_map_msgs/msg/GridMap", T0, gridmap),
    ]
    return msgs, occupancy, layer


@pytest.mark.parametrize("name", ["maps.bag", "maps.mcap"])
def test_occupancy_grid_and_grid_map_round_trip(tmp_path: Path, name: str) -> None:
    from datasets.ros.bag import open_bag

    kind = "ros1" if name.endswith(".bag") else "ros2"
    msgs, occupancy, layer = _grid_messages(kind)
    assert write_messages(tmp_path / name, msgs) == {"/map": 1, "/grid_map": 1}
    with open_bag(tmp_path / name, kind) as bag:
        assert {t.name: t.msgtype for t in bag.topics.values()} == {
            "/map": "nav_msgs/msg/OccupancyGrid",
            "/grid_map": "grid_map_msgs/msg/GridMap",
        }
        got = {topic: msg for topic, _, msg in bag.messages(["/map", "/grid_map"])}
        # decoded with the definition embedded in the bag (grid_map_msgs is not standard in rosbags)
    grid = got["/map"]
    assert (grid.info.width, grid.info.height, grid.info.resolution) == (4, 3, np.float32(0.05))
    assert (grid.info.origin.position.x, grid.info.origin.position.y) == (-1.5, 2.0)
    np.testing.assert_array_equal(grid.data.reshape(3, 4), occupancy)
    gm = got["/grid_map"]
    assert gm.layers == ["variance"]
    assert (gm.info.resolution, gm.info.length_x, gm.info.length_y) == (0.05, 0.2, 0.15)
    assert (gm.info.pose.position.x, gm.info.pose.position.y) == (0.5, -0.25)
    assert [d.size for d in gm.data[0].layout.dim] == [4, 3]
    np.testing.assert_array_equal(gm.data[0].data.reshape(4, 3).T, layer)
    frame = gm.info.header.frame_id if kind == "ros1" else gm.header.frame_id
    assert frame == "map"


def test_grid_map_is_decoded_from_the_embedded_definition(tmp_path: Path) -> None:
    """A reader without grid_map_msgs in its store decodes the GridMap from the bag's own definition."""
    from rosbags.highlevel import AnyReader

    msgs, _, layer = _grid_messages("ros1")
    write_messages(tmp_path / "m.bag", msgs)
    with AnyReader([tmp_path / "m.bag"]) as reader:
        conn = next(c for c in reader.connections if c.topic == "/grid_map")
        msg = reader.deserialize(next(reader.messages([conn]))[2], conn.msgtype)
    np.testing.assert_array_equal(msg.data[0].data.reshape(4, 3).T, layer)


def test_read_bag_rejects_a_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"no such file"):
        read_bag(tmp_path / "missing.bag", __import__("datasets.config").config.InputConfig(), "ros1")
