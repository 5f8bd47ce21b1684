"""Scan-to-submap odometry on real and simulated scans: drift against the corrected Intel log, both
registrations (point-to-line and KISS-ICP's core), wheel-less operation, fallbacks and keyframes."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.carmen import match_scans
from datasets.registry import open_dataset
from datasets.simulation import make_world
from slam import geometry as se2
from slam import metrics, odometry
from slam.config import OdometryConfig
from slam.keyframes import keyframe_of_scan, select_keyframes
from slam.odometry import (
    FALLBACK,
    MATCHED,
    MAX_MATCH_SPACING_M,
    TOO_FEW_POINTS,
    _refine,
    match_subset,
    run_odometry,
    scans_points_base,
)
from slam.scan_matching import PointGrid, scan_normals
from slam.system import wheel_poses_at_scans
from tests.conftest import data_file

PREFIX = 1500  # scans of intel.clf (about 5 minutes, 55 m of travel, two rooms and a corridor)


@pytest.fixture(scope="module")
def intel_prefix() -> tuple:
    raw = open_dataset(data_file("intel/intel.clf.bz2"))
    gfs = open_dataset(data_file("intel/intel.gfs.log"))
    idx = match_scans(gfs, raw)
    keep = idx < PREFIX
    sc = raw.scans
    cfg = OdometryConfig()
    pts = scans_points_base(sc, raw.laser_in_base_xytheta, cfg, PREFIX)
    return pts, raw.scan_poses.poses_xytheta[:PREFIX], idx[keep], gfs.reference.poses_xytheta[keep]


@pytest.mark.parametrize("matcher", ["point_to_line", "kiss_icp"])
def test_intel_prefix_drift_against_the_corrected_log(intel_prefix, matcher: str) -> None:
    pts, wheel, idx, ref = intel_prefix
    odo = run_odometry(pts, wheel, OdometryConfig(matcher=matcher))
    assert odo.status_counts()["matched"] == PREFIX - 1
    est = odo.poses_xytheta[idx]
    rel = metrics.relation_errors(est[:-1], est[1:], se2.between(ref[:-1], ref[1:])).as_dict()
    ate = metrics.ate_rmse(est, ref)
    ate_wheel = metrics.ate_rmse(wheel[idx], ref)
    # measured (point_to_line / kiss_icp): ATE 0.184 / 0.238 m, relations 0.030 / 0.029 m and
    # 0.38 / 0.38 deg; the wheels alone: ATE 8.1 m
    assert ate < 0.3 and ate_wheel > 10 * ate
    assert rel["trans_mean_m"] < 0.04 and rel["rot_mean_deg"] < 0.6
    assert np.all(np.linalg.eigvalsh(odo.cov_xytheta[1:]) > 0)


def test_odometry_on_the_loop_world_with_and_without_wheels() -> None:
    rec = make_world("loop", 0).recording
    cfg = OdometryConfig()
    sc = rec.scans
    pts = scans_points_base(sc, rec.laser_in_base_xytheta, cfg)
    truth = rec.reference.poses_xytheta
    wheel = wheel_poses_at_scans(rec.odometry, sc.stamps_ns)
    with_wheels = run_odometry(pts, wheel, cfg)
    without = run_odometry(pts, None, cfg)
    # the stretch of the glazed gallery scored here (world x 30..90 m; the glass spans -10..90 m) is
    # degenerate along its axis where no end wall is in range: there the chain follows its
    # prediction (the wheels' 2 % scale error, ~1 m over 60 m) and its covariance says so (sd ~6 cm per
    # scan along the gallery, ~1 mm across it and ~7 mm along elsewhere); measured 0.29 m ATE with
    # wheels, 0.16 m with a constant-velocity prediction (the true speed is constant), 1.23 m wheels alone
    gallery = (truth[:, 0] > 30) & (truth[:, 0] < 90) & (np.abs(truth[:, 1]) < 3)
    step_err = se2.between(with_wheels.poses_xytheta[:-1], with_wheels.poses_xytheta[1:]) - se2.between(
        truth[:-1], truth[1:]
    )
    assert 0.6 < step_err[gallery[1:], 0].sum() < 1.4  # along the gallery: mostly the wheels' drift
    assert abs(step_err[gallery[1:], 1].sum()) < 0.1  # across it: the scans
    sd_along = np.sqrt(with_wheels.cov_xytheta[:, 0, 0])
    assert sd_along[gallery].mean() > 5 * sd_along[~gallery].mean()
    assert metrics.ate_rmse(wheel, truth) > 2 * metrics.ate_rmse(with_wheels.poses_xytheta, truth)
    # a constant-velocity prediction is enough at 0.5 m per scan in this world (starts at the origin)
    assert metrics.ate_rmse(without.poses_xytheta, truth) < 0.3
    assert without.status_counts()["matched"] == len(sc) - 1
    np.testing.assert_allclose(without.poses_xytheta[0], 0.0)


def test_scans_without_enough_points_fall_back_to_the_wheels() -> None:
    rng = np.random.default_rng(0)
    ang = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    room = np.stack([6 * np.cos(ang), 4 * np.sin(ang)], axis=1)  # an elliptic room around the origin
    wheel = np.column_stack([np.linspace(0, 1, 6), np.zeros(6), np.zeros(6)])
    pts = [room - wheel[i, :2] + rng.normal(0, 0.005, room.shape) for i in range(6)]
    pts[3] = pts[3][:5]  # a scan with 5 returns
    odo = run_odometry(pts, wheel, OdometryConfig())
    assert odo.status[3] == TOO_FEW_POINTS
    np.testing.assert_allclose(odo.poses_xytheta[3], se2.compose(odo.poses_xytheta[2], wheel[3] - wheel[2]))
    assert np.trace(odo.cov_xytheta[3]) > np.trace(odo.cov_xytheta[2])  # wheel uncertainty accumulates
    assert odo.status[4] == MATCHED
    # a wheel increment that the scans contradict by far more than the gate is rejected
    bad = wheel.copy()
    bad[4:, 0] += 2.0
    odo2 = run_odometry(pts, bad, OdometryConfig(search_window_m=0.1))
    assert FALLBACK in odo2.status or np.hypot(*(odo2.poses_xytheta[4, :2] - wheel[4, :2])) < 0.05


def test_keyframes_by_distance_and_rotation() -> None:
    poses = np.zeros((40, 3))
    poses[:20, 0] = np.arange(20) * 0.1  # 1.9 m straight
    poses[20:, 0] = 1.9
    poses[20:, 2] = np.arange(1, 21) * 0.1  # then 2 rad on the spot
    kf = select_keyframes(poses, 0.45, 0.45)  # steps of 0.1 do not sum to exactly 0.5
    # every 5 steps of 0.1 m, then (0.4 m since scan 15 not being enough) every 5 turns of 0.1 rad
    np.testing.assert_array_equal(kf, [0, 5, 10, 15, 24, 29, 34, 39])
    owner = keyframe_of_scan(kf, 40)
    assert owner[0] == 0 and owner[4] == 0 and owner[5] == 1 and owner[23] == 3 and owner[39] == 7


def test_degenerate_directions_keep_the_prediction_and_its_uncertainty() -> None:
    from slam.odometry import remap_degenerate

    pred = np.array([10.0, 2.0, 0.3])
    found = np.array([10.25, 2.01, 0.302])
    # a corridor along world x: the scan fixes y and the heading, x only through a few weak points
    h = np.array([[0.5, 0.0, 0.0], [0.0, 300.0, 5.0], [0.0, 5.0, 900.0]])
    pose, info = remap_degenerate(pred, found, h, 0.02)
    np.testing.assert_allclose(pose, [10.0, 2.01, 0.302])  # x from the prediction, y and theta matched
    np.testing.assert_allclose(info[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(info[1:, 1:], h[1:, 1:])
    # a well-conditioned match is kept as it is
    pose, info = remap_degenerate(pred, found, np.diag([200.0, 300.0, 900.0]), 0.02)
    np.testing.assert_array_equal(pose, found)
    # rotated corridor: the degenerate direction is the corridor's axis, whatever it is
    c, s = np.cos(0.7), np.sin(0.7)
    r = np.array([[c, -s], [s, c]])
    h2 = np.zeros((3, 3))
    h2[:2, :2] = r @ np.diag([0.1, 300.0]) @ r.T
    h2[2, 2] = 900.0
    pose, info = remap_degenerate(pred, pred + np.array([0.2 * c, 0.2 * s, 0.0]), h2, 0.02)
    np.testing.assert_allclose(pose, pred, atol=1e-12)
    assert np.abs(info[:2, :2] @ np.array([c, s])).max() < 1e-9


def test_scans_alone_register_a_sparse_real_log() -> None:
    """seattle's corrected log without its wheel odometry: 241 scans about a metre and up to 1.4 rad apart.
    The wide branch-and-bound search with a constant-velocity motion prior registers every scan; measured
    ATE 0.06 m over 190 m."""
    rec = open_dataset(data_file("radish-corrected/seattle-corrected.log.gz"))
    cfg = OdometryConfig()
    sc = rec.scans
    pts = scans_points_base(sc, rec.laser_in_base_xytheta, cfg)
    odo = run_odometry(pts, None, cfg)
    assert odo.status_counts()["matched"] == len(sc) - 1
    truth = rec.reference.poses_xytheta
    assert metrics.ate_rmse(odo.poses_xytheta, truth) < 0.15
    step = se2.between(
        se2.between(truth[:-1], truth[1:]), se2.between(odo.poses_xytheta[:-1], odo.poses_xytheta[1:])
    )
    assert np.abs(step[:, 2]).max() < np.radians(3)  # no turn registered the wrong way


def test_a_run_of_rejected_registrations_restarts_the_submaps() -> None:
    """The robot walks out of its submap while every registration is rejected (here: scans of a second
    room that the wheels say is elsewhere): after submap_restart_fallbacks rejections the submaps start
    afresh at the wheel pose and the following scans register again."""
    rng = np.random.default_rng(1)
    ang = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    room_a = np.stack([6 * np.cos(ang), 4 * np.sin(ang)], axis=1)
    room_b = np.stack([3 * np.cos(ang) + 1.0, 5 * np.sin(ang) ** 3], axis=1)  # another shape
    n = 20
    wheel = np.column_stack([np.linspace(0, 1.9, n), np.zeros(n), np.zeros(n)])
    pts = [
        (room_a if i < 8 else room_b) - wheel[i, :2] + rng.normal(0, 0.003, room_a.shape) for i in range(n)
    ]
    odo = run_odometry(pts, wheel, OdometryConfig(submap_restart_fallbacks=3))
    assert np.all(odo.status[8:11] == FALLBACK)  # room b does not match room a's submap
    assert odo.submap_restarts == 1
    assert np.all(odo.status[11:] == MATCHED)  # matched against the new submap
    stuck = run_odometry(pts, wheel, OdometryConfig(submap_restart_fallbacks=100))
    assert np.all(stuck.status[8:] == FALLBACK) and stuck.submap_restarts == 0


def test_a_gap_in_the_wheel_records_is_a_step_without_wheels() -> None:
    """A NaN wheel pose (no wheel records into that scan) must not become a zero-motion prediction: the
    steps into and out of it are searched as without wheels, so a 0.6 m step across the gap is found."""
    rng = np.random.default_rng(1)
    ang = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    room = np.stack([6 * np.cos(ang), 4 * np.sin(ang) + 0.5 * np.cos(3 * ang)], axis=1)
    truth = np.column_stack([0.3 * np.arange(8), np.zeros(8), np.zeros(8)])
    truth[4:, 0] += 0.3  # the step into scan 4 is twice as long
    pts = [room - truth[i, :2] + rng.normal(0, 0.005, room.shape) for i in range(8)]
    wheel = truth.copy()
    wheel[4] = np.nan
    odo = run_odometry(pts, wheel, OdometryConfig())
    assert odo.status_counts()["matched"] == 7
    step = se2.between(odo.poses_xytheta[:-1], odo.poses_xytheta[1:]) - se2.between(truth[:-1], truth[1:])
    assert np.abs(step[:, :2]).max() < 0.03
    # with the gap read as "no motion" the wheels' zero step would be kept (the window is 0.1 m)
    zero = truth.copy()
    zero[4:, 0] -= 0.6
    odo_zero = run_odometry(pts, zero, OdometryConfig())
    assert np.abs(se2.between(odo_zero.poses_xytheta[3], odo_zero.poses_xytheta[4])[0] - 0.6) > 0.1


def test_wheels_turned_wrong_by_more_than_the_window_are_searched_again() -> None:
    """A keyframe step whose wheel rotation is 15 deg wrong (belgioioso's wheels err so between keyframes):
    the window around the wheels cannot reach the truth, the retry over +-0.5 rad finds it. Without the
    retry the step keeps the wheels' heading."""
    rng = np.random.default_rng(2)
    ang = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    room = np.stack([6 * np.cos(ang), 4 * np.sin(ang) + 0.5 * np.cos(3 * ang)], axis=1)
    truth = np.column_stack([0.3 * np.arange(8), np.zeros(8), np.zeros(8)])

    def seen_from(pose: np.ndarray) -> np.ndarray:  # the room in the base frame at ``pose``
        return se2.transform_points(se2.inverse(pose), room) + rng.normal(0, 0.005, room.shape)

    pts = [seen_from(truth[i]) for i in range(8)]
    wheel = truth.copy()
    wheel[5:, 2] += np.radians(15.0)  # the wheels turn 15 deg between scans 4 and 5
    odo = run_odometry(pts, wheel, OdometryConfig())
    assert odo.retries >= 1
    assert odo.status_counts()["matched"] == 7
    assert abs(np.degrees(se2.between(truth[4], odo.poses_xytheta[5])[2])) < 0.5
    plain = run_odometry(pts, wheel, OdometryConfig(retry_window_rad=0.0))
    assert plain.retries == 0
    assert abs(np.degrees(se2.between(truth[4], plain.poses_xytheta[5])[2])) > 5.0


@pytest.fixture(scope="module")
def fr079_scans() -> tuple:
    """fr079.clf's first 400 scans (360 beams at 0.5 deg), base frame, with the logged odometry."""
    rec = open_dataset(data_file("fr079/fr079.clf.bz2"))
    pts = scans_points_base(rec.scans, rec.laser_in_base_xytheta, OdometryConfig(), 400)
    return pts, rec.scan_poses.poses_xytheta[:400]


def test_a_dense_scan_is_thinned_evenly_along_itself(fr079_scans) -> None:
    pts, _ = fr079_scans
    counts = []
    for scan in pts[::40]:
        idx = match_subset(scan, 200)
        assert scan.shape[0] > 200 and 200 <= idx.size < scan.shape[0]
        assert np.all(np.diff(idx) > 0)  # beam order
        gap = np.hypot(*np.diff(scan[idx], axis=0).T)
        spacing = gap.min()
        assert spacing <= MAX_MATCH_SPACING_M + 1e-12
        # every dropped point lies within the spacing of the last point kept before it
        last = np.maximum.accumulate(
            np.where(np.isin(np.arange(scan.shape[0]), idx), np.arange(scan.shape[0]), 0)
        )
        dropped = np.setdiff1d(np.arange(scan.shape[0]), idx)
        assert np.all(np.hypot(*(scan[dropped] - scan[last[dropped]]).T) < spacing + 1e-9)
        counts.append(idx.size)
    assert max(counts) < 240  # about the target: the widest spacing that keeps 200
    # a scan of no more points than the target, or a target of 0, keeps every point
    np.testing.assert_array_equal(match_subset(pts[0][:150], 200), np.arange(150))
    np.testing.assert_array_equal(match_subset(pts[0], 0), np.arange(pts[0].shape[0]))
    # points farther apart than the widest spacing are all kept
    ring = 100.0 * np.stack([np.cos(np.arange(300) * 0.02), np.sin(np.arange(300) * 0.02)], axis=1)
    np.testing.assert_array_equal(match_subset(ring, 200), np.arange(300))


def test_each_kept_point_counts_for_the_points_it_stands_for(fr079_scans) -> None:
    """The refinement of a thinned scan with weight w has the optimum and information of w copies of each
    kept point: the information of a dense scan is not lost by thinning it."""
    pts, wheel = fr079_scans
    cfg = OdometryConfig()
    grid = PointGrid.around(wheel[0, :2], 40.0, radius_m=cfg.max_correspondence_m, sigma_m=cfg.resolution_m)
    rot = se2.rot3(wheel[0, 2])[:2, :2]
    grid.insert(pts[0] @ rot.T + wheel[0, :2], scan_normals(pts[0]) @ rot.T)
    scan = pts[10][match_subset(pts[10], 120)]
    prior = np.diag([100.0, 100.0, 400.0])
    start = wheel[10] + np.array([0.03, -0.02, 0.01])
    thinned = _refine(grid, scan, start, wheel[10], prior, None, cfg, True, 3.0)
    copies = _refine(grid, np.repeat(scan, 3, axis=0), start, wheel[10], prior, None, cfg, True)
    np.testing.assert_allclose(thinned[1], copies[1], atol=1e-9)
    np.testing.assert_allclose(thinned[2], copies[2], rtol=1e-9)
    plain = _refine(grid, scan, start, wheel[10], prior, None, cfg, True)
    assert np.trace(plain[2]) < 0.5 * np.trace(thinned[2])  # the weight is not ignored


@pytest.fixture(scope="module")
def demo_scans() -> list[np.ndarray]:
    """lsm-demo's 360 scans (681 beams at 10 Hz, no wheel odometry), base frame."""
    rec = open_dataset(data_file("lsm-demo/demo_index_fixed.bag"))
    return scans_points_base(rec.scans, rec.laser_in_base_xytheta, OdometryConfig())


def _recording_windows(monkeypatch) -> dict[int, list[tuple[float, float]]]:
    """Every search window (m, rad) run_odometry asks for, by scan index."""
    windows: dict[int, list[tuple[float, float]]] = {}
    current = [-1]
    real_search, real_register = odometry.search_window, odometry._Odometer.register

    def search(target, pts, center, window_m, window_rad, *args, **kwargs):
        windows.setdefault(current[0], []).append((window_m, window_rad))
        return real_search(target, pts, center, window_m, window_rad, *args, **kwargs)

    def register(self, i, pts, motion):
        current[0] = i
        return real_register(self, i, pts, motion)

    monkeypatch.setattr(odometry, "search_window", search)
    monkeypatch.setattr(odometry._Odometer, "register", register)
    return windows


def test_dense_scans_without_wheels_search_the_window_the_model_errors_call_for(
    demo_scans, monkeypatch
) -> None:
    """A 10 Hz scanner without wheels: once ten dense steps are registered, each search spans three times
    the RMS error of the constant-velocity guess (at least search_window_*), not the whole dense window,
    and finds the same poses: the best pose lay inside the smaller window all along."""
    cfg = OdometryConfig()
    windows = _recording_windows(monkeypatch)
    adaptive = run_odometry(demo_scans, None, cfg)
    first = [ws[0] for ws in windows.values()]
    compact = [w for w in first if w[0] < cfg.no_wheels_dense_window_m]
    assert len(compact) > 0.9 * len(demo_scans)
    assert all(w == (cfg.search_window_m, cfg.search_window_rad) for w in compact)  # the floor: 10 Hz
    assert sum(len(ws) > 1 for ws in windows.values()) < 0.05 * len(demo_scans)  # few searched again
    monkeypatch.setattr(odometry, "MODEL_MIN_STEPS", 10**9)  # never adapt: the dense window every time
    windows.clear()
    fixed = run_odometry(demo_scans, None, cfg)
    assert not [w for ws in windows.values() for w in ws if w[0] < cfg.no_wheels_dense_window_m]
    np.testing.assert_array_equal(adaptive.poses_xytheta, fixed.poses_xytheta)
    np.testing.assert_array_equal(adaptive.status, fixed.status)


def test_a_jump_beyond_the_adapted_window_is_searched_in_the_dense_window(demo_scans, monkeypatch) -> None:
    """Twenty scans dropped (2 s, 0.6 m of travel): the guess of the step across the gap errs by more
    than the adapted window covers, so that step is searched again in the whole dense window and lands
    where the unbroken sequence puts the scan."""
    cfg = OdometryConfig()
    whole = run_odometry(demo_scans, None, cfg)
    gap = list(range(250, 270))
    kept = [i for i in range(len(demo_scans)) if i not in gap]
    windows = _recording_windows(monkeypatch)
    broken = run_odometry([demo_scans[i] for i in kept], None, cfg)
    after = kept.index(270)
    # the step across the gap: a compact search, then the dense window
    assert windows[after] == [
        (cfg.search_window_m, cfg.search_window_rad),
        (cfg.no_wheels_dense_window_m, cfg.no_wheels_dense_window_rad),
    ]
    assert broken.status[after] == MATCHED
    err = se2.between(
        se2.between(whole.poses_xytheta[249], whole.poses_xytheta[270]),
        se2.between(broken.poses_xytheta[after - 1], broken.poses_xytheta[after]),
    )
    assert np.hypot(err[0], err[1]) < 0.03 and abs(np.degrees(err[2])) < 1.0


def test_dense_scans_without_wheels_register_thinned_like_with_wheels(demo_scans, monkeypatch) -> None:
    """Without wheels, once the steps are dense (the compact search), a 681-beam scan registers with about
    match_points of its points, as with wheels; the first scans (a wide search, the velocity unknown) with
    every point. Each step stays within a centimetre and a third of a degree of the registration with
    every point."""
    cfg = OdometryConfig()
    used: dict[int, int] = {}
    real_register = odometry._Odometer.register

    def register(self, i, pts, motion):
        used[i] = pts.shape[0]
        return real_register(self, i, pts, motion)

    monkeypatch.setattr(odometry._Odometer, "register", register)
    thinned = run_odometry(demo_scans, None, cfg)
    monkeypatch.setattr(odometry._Odometer, "register", real_register)
    every = run_odometry(demo_scans, None, cfg.model_copy(update={"match_points": 0}))
    assert [used[i] for i in (1, 2, 3)] == [demo_scans[i].shape[0] for i in (1, 2, 3)]
    fewer = [i for i in used if used[i] < demo_scans[i].shape[0]]
    assert len(fewer) > 0.95 * len(demo_scans)
    assert all(cfg.match_points <= used[i] <= 1.1 * cfg.match_points for i in fewer)
    assert np.all(thinned.status[1:] == MATCHED) and np.all(every.status[1:] == MATCHED)
    steps = se2.between(
        se2.between(every.poses_xytheta[:-1], every.poses_xytheta[1:]),
        se2.between(thinned.poses_xytheta[:-1], thinned.poses_xytheta[1:]),
    )
    assert np.hypot(steps[:, 0], steps[:, 1]).max() < 0.015
    assert np.degrees(np.abs(steps[:, 2])).max() < 0.4


def test_scans_outside_the_odometry_span_have_no_wheel_pose() -> None:
    """Odometry that covers only the middle of the recording: the scans before its first stamp and after
    its last (beyond the slack) get no wheel pose, not its end poses, so their steps are registered
    without wheels, and the odometry still follows the scans there."""
    from datasets.types import Trajectory

    rec = make_world("loop", 0).recording
    sc = rec.scans
    odo = rec.odometry
    keep = (odo.stamps_ns >= sc.stamps_ns[100]) & (odo.stamps_ns <= sc.stamps_ns[300])
    middle = Trajectory(odo.stamps_ns[keep], odo.poses_xytheta[keep], odo.frame_id)
    wheel = wheel_poses_at_scans(middle, sc.stamps_ns)
    assert np.all(np.isfinite(wheel[100:301]))
    assert np.all(np.isnan(wheel[:98])) and np.all(np.isnan(wheel[303:]))  # the next scan is in the slack
    pts = scans_points_base(sc, rec.laser_in_base_xytheta, OdometryConfig())
    result = run_odometry(pts, wheel, OdometryConfig())
    assert result.status_counts()["matched"] == len(sc) - 1
    truth = rec.reference.poses_xytheta
    late = slice(320, 400)  # registered without wheels, from a constant-velocity guess
    steps = se2.between(
        se2.between(truth[late][:-1], truth[late][1:]),
        se2.between(result.poses_xytheta[late][:-1], result.poses_xytheta[late][1:]),
    )
    assert np.hypot(steps[:, 0], steps[:, 1]).max() < 0.05


def test_sensor_reach_is_the_farthest_point_of_any_scan() -> None:
    pts = [np.array([[3.0, 4.0], [1.0, 0.0]]), np.zeros((0, 2)), np.array([[0.0, -5.5]])]
    assert odometry.sensor_reach_m(pts) == pytest.approx(5.5)
    assert odometry.sensor_reach_m([np.zeros((0, 2))]) == 0.0
    cfg = OdometryConfig()
    widest = odometry._Submaps(cfg, 1e6).cells
    assert widest == odometry._Submaps(cfg).cells == round(2 * (cfg.max_range_m + 5.0) / cfg.resolution_m)
    assert odometry._Submaps(cfg, 30.0).cells == widest  # twice 30 m reach beyond max_range_m
    for reach_m in (5.5, 5.52, 12.0):
        cells = odometry._Submaps(cfg, reach_m).cells
        # twice the reach plus 5 m each side (one more cell where needed to keep the widest grid's edges)
        side_m = 2 * (2 * reach_m + 5.0)
        assert side_m <= cells * cfg.resolution_m < side_m + 2 * cfg.resolution_m
        assert (widest - cells) % 2 == 0


def test_submaps_sized_by_the_sensor_reach_register_as_before(monkeypatch) -> None:
    """A 5.6 m Hokuyo (the lsm-demo bag, no wheels): grids sized by its reach, not by the configured
    60 m, are a fraction of the cells and give the same poses and covariances bit for bit."""
    rec = open_dataset(data_file("lsm-demo/demo_index_fixed.bag"))
    cfg = OdometryConfig()
    pts = scans_points_base(rec.scans, rec.laser_in_base_xytheta, cfg)
    reach_m = odometry.sensor_reach_m(pts)
    grids = []

    class Recorded(PointGrid):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            grids.append(self)

    monkeypatch.setattr(odometry, "PointGrid", Recorded)
    sized = run_odometry(pts, None, cfg)
    sized_cells = grids[0].shape[0]
    monkeypatch.setattr(odometry, "sensor_reach_m", lambda _pts: np.inf)  # the configured range alone
    wide = run_odometry(pts, None, cfg)
    assert sized_cells * cfg.resolution_m < 2 * (2 * reach_m + 5.0) + 2 * cfg.resolution_m
    assert grids[-1].shape[0] * cfg.resolution_m >= 2 * cfg.max_range_m
    assert reach_m < 6.0
    np.testing.assert_array_equal(sized.poses_xytheta, wide.poses_xytheta)
    np.testing.assert_array_equal(sized.cov_xytheta, wide.cov_xytheta)
    assert sized.status_counts()["matched"] == wide.status_counts()["matched"] > 300
