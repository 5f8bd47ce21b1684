"""``convert`` (pipeline.convert and ``run.py convert``): good conversions, and bad input as one line, exit 1,
nothing left behind."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from datasets import open_dataset
from datasets.rosbag import open_bag_writer, write_recording
from pipeline.convert import convert_recording
from tests.conftest import REPO, data_file
from tests.test_rosbag import T0, synthetic_recording
from tests.test_rosbag_real import DEMO_DAMAGED, DEMO_FIXED, assert_same_scans


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "run.py", *args], cwd=REPO, capture_output=True, text=True, timeout=600
    )


def assert_fails(result: subprocess.CompletedProcess, message: str) -> None:
    assert result.returncode == 1, result.stderr
    assert result.stderr == f"error: {message}\n"
    assert result.stdout == ""


def test_cli_converts_the_damaged_demo_bag(tmp_path: Path) -> None:
    out = tmp_path / "demo.mcap"
    result = run_cli("convert", str(data_file(DEMO_DAMAGED)), str(out))
    assert result.returncode == 0, result.stderr
    assert result.stdout == f"wrote {out}: 360 scans, 0 odometry messages, 0 reference poses\n"
    assert_same_scans(open_dataset(out).scans, open_dataset(data_file(DEMO_FIXED)).scans)
    assert [p.name for p in tmp_path.iterdir()] == ["demo.mcap"]


def test_cli_missing_and_unknown_inputs(tmp_path: Path) -> None:
    missing = tmp_path / "nothing.bag"
    assert_fails(
        run_cli("convert", str(missing), str(tmp_path / "o.bag")), f"{missing}: no such file or directory"
    )
    text = tmp_path / "notes.txt"
    text.write_text("not a recording\n")
    assert_fails(
        run_cli("convert", str(text), str(tmp_path / "o.bag")),
        f"{text}: unknown format (expected a ROS1 .bag, a ROS2 bag folder / .mcap / .db3, "
        "a CARMEN .clf / .log (optionally .gz / .bz2), or KITTI .bin frames)",
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_cli_truncated_bag(tmp_path: Path) -> None:
    good = tmp_path / "good.bag"
    write_recording(synthetic_recording(n=20), good)
    data = good.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[:30_000])
    at = data.index(b"index_pos=") + len(b"index_pos=")
    index_pos = int.from_bytes(data[at : at + 8], "little")
    assert_fails(
        run_cli("convert", str(cut), str(tmp_path / "o.mcap")),
        f"{cut}: truncated ROS1 bag (30000 bytes, but its index starts at byte {index_pos})",
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.bag", "good.bag"]


def _two_scan_topics_bag(path: Path, negative: bool = False) -> Path:
    with open_bag_writer(path) as w:
        laser = w.types["sensor_msgs/msg/LaserScan"]
        for topic in ("/front/scan", "/rear/scan"):
            for i in range(3):
                ranges = np.array([1.0, -2.0 if negative and i == 2 else 2.0], np.float32)
                msg = laser(
                    header=w.header(T0 + i, "laser"),
                    angle_min=0.0,
                    angle_max=0.1,
                    angle_increment=0.1,
                    time_increment=0.0,
                    scan_time=0.0,
                    range_min=0.0,
                    range_max=10.0,
                    ranges=ranges,
                    intensities=np.zeros(0, np.float32),
                )
                w.write(topic, "sensor_msgs/msg/LaserScan", T0 + i, msg)
    return path


def test_cli_topic_errors(tmp_path: Path) -> None:
    bag = _two_scan_topics_bag(tmp_path / "two.bag")
    out = tmp_path / "o.bag"
    assert_fails(
        run_cli("convert", str(bag), str(out)),
        f"{bag}: several scan topics (/front/scan, /rear/scan); choose one with --scan-topic "
        "(or 'all' for every LaserScan topic)",
    )
    assert_fails(
        run_cli("convert", str(bag), str(out), "--scan-topic", "/scan"),
        f"{bag}: no scan topic /scan; topics: /front/scan (sensor_msgs/msg/LaserScan), "
        "/rear/scan (sensor_msgs/msg/LaserScan)",
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["two.bag"]


def test_cli_negative_range(tmp_path: Path) -> None:
    bag = _two_scan_topics_bag(tmp_path / "neg.mcap", negative=True)
    assert_fails(
        run_cli("convert", str(bag), str(tmp_path / "o"), "--scan-topic", "/rear/scan"),
        f"{bag}: topic /rear/scan: message 2 (stamp {T0 + 2} ns) has 1 negative ranges (beam 1: -2.0 m)",
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["neg.mcap"]


def test_cli_refuses_an_existing_output(tmp_path: Path) -> None:
    out = tmp_path / "o.bag"
    out.write_bytes(b"precious")
    assert_fails(
        run_cli("convert", str(data_file(DEMO_FIXED)), str(out)),
        f"{out}: exists already; not overwriting it (remove it or choose another name)",
    )
    assert out.read_bytes() == b"precious"


def test_convert_recording_all_platforms(tmp_path: Path) -> None:
    bag = _two_scan_topics_bag(tmp_path / "two.bag")
    report = convert_recording(bag, tmp_path / "all.mcap", scan_topic="all")
    assert (
        report["scans"] == 6 and report["topics"]["/front/scan"] == 3 and report["topics"]["/rear/scan"] == 3
    )
    back = open_dataset(tmp_path / "all.mcap", scan_topic="all")
    assert back.scans.sources == ["/front/scan", "/rear/scan"]
    assert back.scans.source_index.tolist() == [0, 1, 0, 1, 0, 1]


# -- CARMEN -> bag on the real Intel log.
@pytest.mark.slow
@pytest.mark.parametrize("name", ["intel.bag", "intel.mcap"])
def test_carmen_intel_round_trip(tmp_path: Path, name: str) -> None:
    source = data_file("intel/intel.clf.bz2")
    rec = open_dataset(source)
    out = tmp_path / name
    result = run_cli("convert", str(source), str(out))
    assert result.returncode == 0, result.stderr
    back = open_dataset(out)
    assert len(back.scans) == len(rec.scans) == 13_631
    assert_same_scans(back.scans, rec.scans)
    for a, b in (
        (back.odometry, rec.odometry),
        (back.scan_poses, rec.scan_poses),
        (back.reference, rec.reference),
    ):
        if b is None:
            assert a is None
            continue
        np.testing.assert_array_equal(a.stamps_ns, b.stamps_ns)
        np.testing.assert_allclose(a.poses_xytheta[:, :2], b.poses_xytheta[:, :2], atol=1e-9, rtol=0)
        d = np.angle(np.exp(1j * (a.poses_xytheta[:, 2] - b.poses_xytheta[:, 2])))
        np.testing.assert_allclose(d, 0.0, atol=1e-9)


@pytest.mark.parametrize("suffix", [".db3", ".mcap", ".bag"])
def test_cli_output_over_the_file_size_limit(tmp_path: Path, suffix: str) -> None:
    """A bag that the file-size limit (as a full disk) stops mid-way: one line naming the output, exit 1,
    nothing left behind (a .db3 bag's SQLite storage raises its own error type)."""
    resource = pytest.importorskip("resource")
    out = tmp_path / f"demo{suffix}"
    limit = 200_000  # bytes; the demo bag's 360 scans of 681 beams take about 1 MB

    def limited() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    result = subprocess.run(
        [sys.executable, "run.py", "-q", "convert", str(data_file(DEMO_FIXED)), str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        preexec_fn=limited,
    )
    assert result.returncode == 1, result.stderr
    assert result.stderr.startswith(f"error: {out}: cannot write the bag ("), result.stderr
    assert result.stderr.count("\n") == 1, result.stderr
    assert list(tmp_path.iterdir()) == []
