"""The CARMEN reader on the real logs: counts, stamps, frames, and the beam-angle convention."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from datasets import open_dataset
from datasets.carmen import is_corrected_log, match_scans, read_carmen
from datasets.config import InputConfig
from datasets.types import Recording, beam_angles_rad
from tests.conftest import data_file


@pytest.fixture(scope="module")
def intel_clf() -> Recording:
    return open_dataset(data_file("intel/intel.clf.bz2"))


@pytest.fixture(scope="module")
def intel_gfs() -> Recording:
    return open_dataset(data_file("intel/intel.gfs.log"))


def test_intel_clf_counts_and_first_records(intel_clf: Recording) -> None:
    rec = intel_clf
    assert rec.format == "carmen"
    assert len(rec.scans) == 13_631
    assert set(rec.scans.beam_counts().tolist()) == {180}
    assert len(rec.odometry) == 26_915
    assert rec.meta["record_counts"] == {"PARAM": 2, "ODOM": 26_915, "FLASER": 13_631}
    assert rec.meta["ignored_records"] == {}
    assert rec.reference is None and not rec.meta["corrected"]
    np.testing.assert_array_equal(rec.laser_in_base_xytheta, [0.0, 0.0, 0.0])
    # first FLASER line: "FLASER 180 1.07 1.07 1.08 ... 976052857.337530 nohost 0.000246"
    first = rec.scans[0]
    assert first.ranges_m[:4].tolist() == pytest.approx([1.07, 1.07, 1.08, 1.08])
    assert first.ranges_m.dtype == np.float32
    assert rec.meta["ipc_stamps_ns"][0] == 976_052_857_337_530_000
    assert rec.meta["logger_stamps_ns"][0] == 246_000
    assert rec.meta["logger_stamps_ns"].dtype == np.int64
    assert rec.meta["logger_stamps_ns"].shape == (13_631,)
    # first ODOM line: "ODOM 0.000000 0.000000 -0.002458 ... 976052857.337284 nohost 0.000000"
    assert rec.odometry.stamps_ns[0] == 976_052_857_337_284_000
    np.testing.assert_array_equal(rec.odometry.poses_xytheta[0], [0.0, 0.0, -0.002458])


def test_intel_beams_angles_and_no_returns(intel_clf: Recording) -> None:
    scan = intel_clf.scans[100]
    np.testing.assert_array_equal(scan.angles_rad, beam_angles_rad(-np.pi / 2, np.pi / 180, 180))
    assert scan.range_max_m == 80.0 and scan.range_min_m == np.float32(0.05)  # float32 as in a bag
    ranges, _ = intel_clf.scans.packed()
    # no-return readings are logged as 81.83 m; every real return is far below the 80 m limit
    assert np.unique(ranges[ranges >= 80.0]).tolist() == [np.float32(81.83)]
    assert ranges[ranges < 80.0].max() < 40.0
    assert (ranges >= 80.0).sum() == 68_313


def test_intel_stamps_are_line_ordered_and_increasing(intel_clf: Recording) -> None:
    rec = intel_clf
    raw = rec.meta["ipc_stamps_ns"]
    stamps = rec.scans.stamps_ns
    assert np.all(np.diff(stamps) > 0) and np.all(np.diff(rec.odometry.stamps_ns) > 0)
    # intel.clf has 631 scans stamped before their predecessor in the file; those are re-stamped
    assert int(np.sum(np.diff(raw) < 0)) == 631
    changed = stamps != raw
    assert changed.sum() == rec.meta["restamped"]["laser"]
    assert rec.meta["restamped"] == {"laser": 787, "odometry": 1_250}  # figures quoted in the docstring
    # the other 94% keep their exact logged stamps
    np.testing.assert_array_equal(stamps[~changed], raw[~changed])
    # scan_poses share the scan stamps and are the FLASER poses (raw odometry in intel.clf)
    np.testing.assert_array_equal(rec.scan_poses.stamps_ns, stamps)
    np.testing.assert_array_equal(rec.scan_poses.poses_xytheta, rec.meta["laser_poses_xytheta"])


def test_intel_gfs_is_corrected_and_matches_clf_by_logger_stamp(
    intel_gfs: Recording, intel_clf: Recording
) -> None:
    gfs = intel_gfs
    assert is_corrected_log(gfs.source) and gfs.meta["corrected"]
    assert len(gfs.scans) == 910 and len(gfs.reference) == 910
    np.testing.assert_array_equal(gfs.reference.poses_xytheta, gfs.scan_poses.poses_xytheta)
    assert gfs.meta["ignored_records"] == {"NEFF": 910}
    assert gfs.meta["odometry_is_corrected"]
    # gfs stamps are the clf logger stamps rounded to 6 significant digits: every keyframe is a clf scan
    clf_logger = intel_clf.meta["logger_stamps_ns"]
    gfs_logger = gfs.meta["logger_stamps_ns"]
    index = match_scans(gfs, intel_clf)
    assert len(np.unique(index)) == 910
    assert np.abs(clf_logger[index] - gfs_logger).max() <= 5_000_000  # half a unit of 2683.77 s
    for j in range(0, 910, 7):
        np.testing.assert_array_equal(gfs.scans[j].ranges_m, intel_clf.scans[int(index[j])].ranges_m)
    # the nearest logger stamp alone picks another scan (a burst 1 ms apart) for many keyframes
    nearest = np.array([np.argmin(np.abs(clf_logger - t)) for t in gfs_logger])
    assert 0.1 < np.mean(nearest != index) < 0.3


def test_fr079_raw_log() -> None:
    rec = read_carmen(data_file("fr079/fr079.clf.bz2"), InputConfig())
    assert len(rec.scans) == 4_934 and set(rec.scans.beam_counts().tolist()) == {360}
    assert len(rec.odometry) == 8_951
    assert rec.reference is None
    assert rec.meta["params"]["robot_frontlaser_offset"] == "-0.04"
    # the laser sits 4 cm behind the base, as the PARAM record says
    np.testing.assert_allclose(rec.laser_in_base_xytheta, [-0.04, 0.0, 0.0], atol=1e-6)
    np.testing.assert_array_equal(rec.scans[0].angles_rad, beam_angles_rad(-np.pi / 2, np.pi / 360, 360))
    assert rec.meta["restamped"] == {"laser": 0, "odometry": 0}
    # scan_poses are base poses: laser pose = base (+) mounting
    base = rec.scan_poses.poses_xytheta
    c, s = np.cos(base[:, 2]), np.sin(base[:, 2])
    laser = rec.meta["laser_poses_xytheta"]
    np.testing.assert_allclose(laser[:, 0], base[:, 0] - 0.04 * c, atol=1e-5)
    np.testing.assert_allclose(laser[:, 1], base[:, 1] - 0.04 * s, atol=1e-5)


def test_fr079_corrected_log_with_unreliable_stamps_reads() -> None:
    path = data_file("fr079/freiburg-079-corrected.log.gz")
    rec = open_dataset(path)
    assert is_corrected_log(path)
    assert len(rec.scans) == 4_791 and len(rec.reference) == 4_791
    # its ODOM stamps are 0, 9e-67 or negative every other record: kept in line order, re-stamped
    assert rec.meta["restamped"]["odometry"] == 4_791
    assert np.all(np.diff(rec.odometry.stamps_ns) > 0)
    np.testing.assert_array_equal(rec.laser_in_base_xytheta, [0.0, 0.0, 0.0])


def test_laser_record_choice(intel_gfs: Recording) -> None:
    assert intel_gfs.meta["carmen_laser"] == "FLASER"
    rec = read_carmen(data_file("intel/intel.gfs.log"), InputConfig(carmen_laser="FLASER"))
    assert len(rec.scans) == 910


def test_is_corrected_log_by_name() -> None:
    assert is_corrected_log("a/intel.gfs.log")
    assert is_corrected_log("freiburg-079-corrected.log.gz")
    assert is_corrected_log("CSAIL-Corrected.clf")
    assert not is_corrected_log("intel.clf.bz2")
    assert not is_corrected_log("fr079.log")


# ------------------------------------------------------------------------------ beam-angle convention


def _endpoint_disagreement(rec: Recording, angles_rad: np.ndarray, pairs: np.ndarray) -> float:
    """Mean over scan pairs of the mean nearest-neighbour distance (clipped at 0.2 m) between endpoints."""
    ranges, _ = rec.scans.packed()
    poses = rec.reference.poses_xytheta
    scores = []
    for a, b in pairs:
        clouds = []
        for k in (a, b):
            hit = (ranges[k] > 0.05) & (ranges[k] < 8.0)
            bearing = angles_rad[hit] + poses[k, 2]
            r = ranges[k][hit]
            clouds.append(np.stack([poses[k, 0] + r * np.cos(bearing), poses[k, 1] + r * np.sin(bearing)], 1))
        d, _ = cKDTree(clouds[0]).query(clouds[1])
        scores.append(np.mean(np.minimum(d, 0.2)))
    return float(np.mean(scores))


def test_beam_angle_convention_on_corrected_intel(intel_gfs: Recording) -> None:
    """Nearby scans seen from headings 20-60 degrees apart must agree under the reader's angles.

    A wrong convention (mirrored, rotated by a beam or a few degrees) puts the same walls at different
    places in the two scans, which raises the endpoint disagreement.
    """
    rec = intel_gfs
    poses = rec.reference.poses_xytheta
    pairs = []
    for a, b in sorted(cKDTree(poses[:, :2]).query_pairs(1.0)):
        dtheta = abs((poses[a, 2] - poses[b, 2] + np.pi) % (2 * np.pi) - np.pi)
        if np.radians(20) < dtheta < np.radians(60) and abs(a - b) >= 3:
            pairs.append((a, b))
    pairs = np.array(pairs)
    assert len(pairs) > 300
    pairs = pairs[np.random.default_rng(0).choice(len(pairs), 300, replace=False)]

    reader = rec.scans[0].angles_rad.astype(np.float64)
    i = np.arange(180)
    good = _endpoint_disagreement(rec, reader, pairs)
    wrong = {
        "mirrored": np.pi / 2 - i * np.pi / 180,
        "one beam late": reader + np.pi / 180,
        "one beam early": reader - np.pi / 180,
        "3 degrees": reader + np.radians(3),
        "-3 degrees": reader - np.radians(3),
    }
    scores = {name: _endpoint_disagreement(rec, a, pairs) for name, a in wrong.items()}
    assert good < 0.09
    assert scores["mirrored"] > 2 * good
    for name in ("3 degrees", "-3 degrees"):
        assert scores[name] > 1.02 * good, (name, scores[name], good)
    for name in ("one beam late", "one beam early"):
        assert scores[name] > good, (name, scores[name], good)


# ------------------------------------------------------------------------- other laser record types


def _robotlaser1(ranges: list[float], remissions: list[float], ipc: str) -> str:
    robot = (1.0, 2.0, 0.5)
    laser = (1.0 + 0.2 * np.cos(0.5), 2.0 + 0.2 * np.sin(0.5), 0.5)  # 0.2 m ahead of the base
    fields = [
        "ROBOTLASER1", "0", "-1.5708", "3.14159", "0.0174533", "50.0", "0.01", "0",
        str(len(ranges)), *map(str, ranges), str(len(remissions)), *map(str, remissions),
        *(f"{v:.9f}" for v in laser), *map(str, robot), "0.1", "0.0", "0.5", "0.3", "1.0",
        ipc, "host", ipc,
    ]  # fmt: skip
    return " ".join(fields)


def test_robotlaser1_uses_its_own_geometry(tmp_path) -> None:
    path = tmp_path / "robot.clf"
    lines = [
        _robotlaser1([1.0, 2.0, 60.0], [0.5, 0.6], "10.5"),
        _robotlaser1([1.5, 2.5, 3.5], [], "10.7"),
        "FLASER 3 1 2 3 0 0 0 0 0 0 10.6 host 10.6",
    ]
    path.write_text("\n".join(lines) + "\n")
    rec = open_dataset(path)
    assert rec.meta["carmen_laser"] == "ROBOTLASER1"  # the most frequent laser record
    assert rec.meta["ignored_records"] == {"FLASER": 1}
    scan = rec.scans[0]
    np.testing.assert_array_equal(scan.angles_rad, beam_angles_rad(-1.5708, 0.0174533, 3))
    assert scan.range_max_m == 50.0
    assert scan.no_return_mask().tolist() == [False, False, True]
    assert rec.scans[1].ranges_m.tolist() == pytest.approx([1.5, 2.5, 3.5])
    np.testing.assert_allclose(rec.laser_in_base_xytheta, [0.2, 0.0, 0.0], atol=1e-8)
    np.testing.assert_allclose(rec.scan_poses.poses_xytheta[0], [1.0, 2.0, 0.5])
    assert rec.scans.stamps_ns.tolist() == [10_500_000_000, 10_700_000_000]
    flaser = open_dataset(path, carmen_laser="FLASER")
    assert len(flaser.scans) == 1 and flaser.scans[0].range_max_m == 80.0


def test_rlaser_records(tmp_path) -> None:
    path = tmp_path / "rear.log"
    path.write_text(
        "RLASER 4 1 2 3 4 0 0 3.14159 0 0 0 1.0 host 1.0\n"
        "FLASER 2 1 2 0 0 0 0 0 0 1.05 host 1.05\n"
        "RLASER 4 1 2 3 5 0 0 3.14159 0 0 0 1.2 host 1.2\n"
    )
    rec = open_dataset(path)
    assert rec.meta["carmen_laser"] == "RLASER" and rec.scans.sources == ["RLASER"]
    np.testing.assert_array_equal(rec.scans[1].angles_rad, beam_angles_rad(-np.pi / 2, np.pi / 4, 4))
    # the rear laser faces backwards: its mounting says so
    np.testing.assert_allclose(rec.laser_in_base_xytheta, [0.0, 0.0, 3.14159])
    assert rec.odometry is None


def _flaser(pose: np.ndarray, stamp: float) -> str:
    x, y, t = pose
    return f"FLASER 3 1 2 3 {x} {y} {t} {x} {y} {t} {stamp} host {stamp}\n"


def _odom(pose: np.ndarray, stamp: float) -> str:
    x, y, t = pose
    return f"ODOM {x} {y} {t} 0 0 0 {stamp} host {stamp}\n"


def test_a_corrected_logs_reanchored_odom_records_give_its_wheel_odometry(tmp_path) -> None:
    """GMapping's corrected logs re-anchor the ODOM stream at every scan (the first record repeats the
    scan's corrected pose, the next ones add the raw wheel motion): the wheel increments between scans are
    recovered exactly, a step without wheel records is NaN, and records that only repeat the poses give
    none."""
    from datasets.carmen import corrected_log_odometry
    from datasets.se2 import between, compose

    corrected = np.array(
        [[0.0, 0.0, 0.0], [1.0, 0.1, 0.2], [2.0, 0.5, 0.3], [2.5, 1.5, 1.2], [3.0, 2.0, 1.0]]
    )
    raw_inc = np.array([[0.9, 0.05, 0.25], [1.1, 0.0, 0.05], [0.0, 0.0, 0.0], [0.6, 0.1, -0.1]])
    lines, stamp = [], 1.0
    for k in range(5):
        lines.append(_flaser(corrected[k], stamp))
        if k == 4:
            break
        lines.append(_odom(corrected[k], stamp))  # the anchor
        if k != 2:  # interval 2 has no wheel records
            lines.append(_odom(compose(corrected[k], raw_inc[k] / 2), stamp + 0.5))
            lines.append(_odom(compose(corrected[k], raw_inc[k]), stamp + 0.9))
        stamp += 1.0
    path = tmp_path / "bldg-corrected.log"
    path.write_text("".join(lines))
    rec = open_dataset(path)
    traj, phrase = corrected_log_odometry(rec)
    assert "3 of 4 steps" in phrase and "1 without wheel records" in phrase
    np.testing.assert_array_equal(traj.stamps_ns, rec.scans.stamps_ns)
    poses = traj.poses_xytheta
    np.testing.assert_allclose(poses[0], 0.0)
    assert np.isnan(poses[3]).all() and np.isfinite(np.delete(poses, 3, axis=0)).all()
    inc = between(poses[:-1], poses[1:])
    np.testing.assert_allclose(inc[[0, 1]], raw_inc[[0, 1]], atol=1e-9)
    assert not np.allclose(inc[0], between(corrected[0], corrected[1]), atol=1e-3)  # not the corrected step
    # the chain goes on across the gap: scan 4 = scan 2 + the last known increment
    np.testing.assert_allclose(poses[4], compose(poses[2], raw_inc[3]), atol=1e-9)

    # ODOM records that only repeat the corrected poses carry no wheel motion
    path2 = tmp_path / "poses-corrected.log"
    path2.write_text("".join(_flaser(corrected[k], 1.0 + k) + _odom(corrected[k], 1.0 + k) for k in range(5)))
    none, phrase2 = corrected_log_odometry(open_dataset(path2))
    assert none is None and "0 of 4 steps" in phrase2


def test_radish_corrected_logs_wheel_odometry() -> None:
    """On the real logs: seattle's ODOM records hold wheel odometry (per-step differences from the
    corrected poses of a few centimetres, not zero; one step of 240 has no wheel records), orebro's only
    repeat the corrected poses."""
    from datasets.carmen import corrected_log_odometry
    from datasets.se2 import between

    rec = open_dataset(data_file("radish-corrected/seattle-corrected.log.gz"))
    traj, phrase = corrected_log_odometry(rec)
    assert "239 of 240 steps" in phrase
    wheel = traj.poses_xytheta
    ok = np.isfinite(wheel).all(axis=1)
    ok = ok[:-1] & ok[1:]
    ref = rec.reference.poses_xytheta
    d = between(between(ref[:-1], ref[1:])[ok], between(wheel[:-1], wheel[1:])[ok])
    err_m = np.hypot(d[:, 0], d[:, 1])
    assert 0.005 < np.median(err_m) < 0.05 and np.percentile(err_m, 95) < 0.1
    orebro = open_dataset(data_file("radish-corrected/orebro-corrected.log.gz"))
    assert corrected_log_odometry(orebro)[0] is None
