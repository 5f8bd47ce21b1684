"""KITTI Velodyne frames: lazy clouds and scans, stamps from times files, Velodyne-frame reference poses."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from datasets import open_dataset
from datasets.cloud import cloud_to_scan
from datasets.config import InputConfig
from datasets.errors import DatasetError
from datasets.kitti import read_kitti
from tests.conftest import data_file


@pytest.fixture(scope="module")
def kitti_dir() -> Path:
    return data_file("kitti00")


def test_folder_of_frames(kitti_dir: Path) -> None:
    rec = open_dataset(kitti_dir)
    assert rec.format == "kitti" and len(rec.clouds) == 6 and len(rec.scans) == 6
    # stamps from times_KITTI00_0-5.txt, exactly: "1.037359e-01" -> 103735900 ns
    assert rec.clouds.stamps_ns.tolist() == [
        0,
        103_735_900,
        207_338_100,
        311_075_200,
        414_691_700,
        518_430_200,
    ]
    np.testing.assert_array_equal(rec.scans.stamps_ns, rec.clouds.stamps_ns)
    cloud = rec.clouds[0]
    raw = np.fromfile(kitti_dir / "000000.bin", dtype=np.float32).reshape(-1, 4)
    assert cloud.points_xyz_m.shape == (raw.shape[0], 3) and 120_000 < raw.shape[0] < 130_000
    assert cloud.points_xyz_m.dtype == np.float32 and cloud.intensity.dtype == np.float32
    np.testing.assert_array_equal(cloud.points_xyz_m, raw[:, :3])
    np.testing.assert_array_equal(cloud.intensity, raw[:, 3])
    assert cloud.frame_id == "velodyne" and cloud.stamp_ns == 0
    for i in range(6):
        assert 120_000 < rec.clouds[i].points_xyz_m.shape[0] < 130_000


def test_scans_are_the_height_band_of_each_cloud(kitti_dir: Path) -> None:
    cfg = InputConfig(cloud_scan_beams=360, cloud_range_max_m=60.0)
    rec = read_kitti(kitti_dir, cfg)
    scan = rec.scans[3]
    expected, angles = cloud_to_scan(rec.clouds[3].points_xyz_m, cfg.cloud_height_band_m, 360, 60.0)
    np.testing.assert_array_equal(scan.ranges_m, expected)
    np.testing.assert_array_equal(scan.angles_rad, angles)
    assert scan.range_max_m == 60.0 and rec.scans.beam_counts().tolist() == [360] * 6
    # an urban street: most bearings see something within 60 m
    assert np.isfinite(scan.ranges_m).mean() > 0.5
    ranges, _ = rec.scans.packed()
    assert ranges.shape == (6, 360)
    assert len(rec.scans.subset([5, 0])) == 2


def test_reference_in_velodyne_frame(kitti_dir: Path) -> None:
    rec = open_dataset(kitti_dir)
    se3 = rec.meta["reference_poses_se3"]
    assert se3.shape == (6, 4, 4)
    # camera frame: z forward; after the change of frame the car drives along the Velodyne x axis
    cam = np.loadtxt(kitti_dir / "poses_gt_KITTI00_0-5.txt").reshape(-1, 3, 4)
    assert cam[5, 2, 3] == pytest.approx(4.291335)
    xy_yaw = rec.reference.poses_xytheta
    np.testing.assert_allclose(xy_yaw[0], [0.0, 0.0, 0.0], atol=1e-3)
    assert xy_yaw[5, 0] == pytest.approx(4.29, abs=0.05)  # ~8.3 m/s forward over 0.52 s
    assert abs(xy_yaw[5, 1]) < 0.3 and abs(xy_yaw[5, 2]) < 0.02
    # a change of frame keeps the distance driven (the car barely turns in 6 frames)
    driven_cam = np.linalg.norm(cam[5, :, 3] - cam[0, :, 3])
    assert np.linalg.norm(se3[5, :3, 3] - se3[0, :3, 3]) == pytest.approx(driven_cam, abs=0.02)
    # T_velo = inv(Tr) @ T_cam @ Tr, with Tr from calib.txt
    tr_line = next(
        line for line in (kitti_dir / "calib.txt").read_text().splitlines() if line.startswith("Tr:")
    )
    tr = np.eye(4)
    tr[:3] = np.array(tr_line.split()[1:], float).reshape(3, 4)
    t_cam = np.eye(4)
    t_cam[:3] = cam[4]
    np.testing.assert_allclose(se3[4], np.linalg.inv(tr) @ t_cam @ tr, atol=1e-12)
    np.testing.assert_array_equal(rec.reference.stamps_ns, rec.scans.stamps_ns)


def test_single_frame_uses_its_index(kitti_dir: Path) -> None:
    rec = open_dataset(kitti_dir / "000002.bin")
    assert len(rec.scans) == 1 and rec.scans.stamps_ns.tolist() == [207_338_100]
    full = open_dataset(kitti_dir)
    np.testing.assert_array_equal(rec.meta["reference_poses_se3"][0], full.meta["reference_poses_se3"][2])


def test_nothing_is_read_until_asked(tmp_path: Path, kitti_dir: Path) -> None:
    """A long sequence costs its stamps: frames are opened only when a cloud or scan is requested."""
    for k in range(3):
        shutil.copy(kitti_dir / "000000.bin", tmp_path / f"{k:06d}.bin")
    rec = open_dataset(tmp_path)
    (tmp_path / "000001.bin").unlink()  # gone after reading: only a request for it may fail
    assert rec.scans.stamps_ns.tolist() == [0, 100_000_000, 200_000_000]  # 10 Hz without a times file
    assert rec.reference is None
    assert rec.scans[2].num_beams == 720
    with pytest.raises(DatasetError, match=r"000001\.bin: no such file or directory"):
        rec.scans[1]


def _copy_folder(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for name in (
        "000000.bin",
        "000001.bin",
        "calib.txt",
        "poses_gt_KITTI00_0-5.txt",
        "times_KITTI00_0-5.txt",
    ):
        shutil.copy(src / name, dst / name)
    return dst


def test_bad_inputs(tmp_path: Path, kitti_dir: Path) -> None:
    folder = _copy_folder(kitti_dir, tmp_path / "seq")
    (folder / "times_KITTI00_0-5.txt").write_text("0.0\n0.1x\n")
    with pytest.raises(DatasetError) as info:
        open_dataset(folder)
    assert str(info.value) == f"{folder / 'times_KITTI00_0-5.txt'}: line 2: '0.1x' is not a time in seconds"

    (folder / "times_KITTI00_0-5.txt").write_text("0.2\n0.1\n")
    with pytest.raises(DatasetError) as info:
        open_dataset(folder)
    assert (
        str(info.value)
        == f"{folder / 'times_KITTI00_0-5.txt'}: timestamps go backwards: frame 1 is not after frame 0"
    )

    (folder / "times_KITTI00_0-5.txt").write_text("0.0\n")
    with pytest.raises(DatasetError) as info:
        open_dataset(folder)
    assert str(info.value) == f"{folder / 'times_KITTI00_0-5.txt'}: 1 times lines, but frame 1 needs line 2"

    (folder / "times_KITTI00_0-5.txt").unlink()
    (folder / "poses_gt_KITTI00_0-5.txt").write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(DatasetError) as info:
        open_dataset(folder)
    assert str(info.value) == (
        f"{folder / 'poses_gt_KITTI00_0-5.txt'}: line 1: expected 12 numbers (a row-major 3x4 pose), found 11"
    )
    (folder / "poses_gt_KITTI00_0-5.txt").unlink()

    (folder / "000001.bin").write_bytes(b"\x00" * 10)
    rec = open_dataset(folder)
    with pytest.raises(DatasetError) as info:
        rec.clouds[1]
    assert str(info.value) == (
        f"{folder / '000001.bin'}: not a KITTI Velodyne frame (10 bytes is not a positive multiple of 16)"
    )
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError):
        open_dataset(empty)
    with pytest.raises(DatasetError, match="no KITTI frames"):
        read_kitti(empty)


def test_frames_are_ordered_and_checked_by_their_numbers(tmp_path: Path, kitti_dir: Path) -> None:
    """Unpadded numbers read in number order (9 before 10); a frame not named by a number among numbered
    ones, or two names of one number, is named in the error (it was 'frame 5 is not after frame 5')."""
    for name in ("9.bin", "10.bin"):
        shutil.copy(kitti_dir / "000000.bin", tmp_path / name)
    rec = read_kitti(tmp_path)
    assert rec.meta["frames"] == ["9.bin", "10.bin"] and rec.meta["frame_index"].tolist() == [9, 10]
    shutil.copy(kitti_dir / "000001.bin", tmp_path / "frame3.bin")
    with pytest.raises(DatasetError, match=r"frame3\.bin: not named by a frame number like the other"):
        read_kitti(tmp_path)
    (tmp_path / "frame3.bin").rename(tmp_path / "009.bin")
    with pytest.raises(DatasetError, match=r"9\.bin: frame 9 is also 009\.bin$"):
        read_kitti(tmp_path)
