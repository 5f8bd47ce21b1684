"""The 3D path: KISS-ICP odometry on the six KITTI frames, the Pose3 graph (a small loop: marginals SPD and
shrinking after the closure), world-frame marginals, and the SE(2) projection of poses and covariances."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from datasets.registry import open_dataset
from slam.config import SlamConfig
from slam.graph3d import (
    PoseGraph3,
    body_to_world_cov,
    pose3,
    project_cov_se2,
    project_pose_se2,
    world_to_body_cov,
)
from slam.system import SlamResult, run_slam_recording
from slam.system3d import verify_closure
from tests.conftest import data_file


def rot_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    return gtsam.Rot3.Ypr(yaw, pitch, roll).matrix()


def se3(r: np.ndarray, t) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = t
    return out


def test_se2_projection_of_a_level_pose_is_the_xy_yaw_block() -> None:
    t = se3(rot_zyx(0.7, 0.0, 0.0), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(project_pose_se2(t), [1.0, 2.0, 0.7])
    cov = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])  # (x, y, z, rx, ry, rz) world
    cov[0, 5] = cov[5, 0] = 0.5
    np.testing.assert_allclose(project_cov_se2(t, cov), [[1.0, 0.0, 0.5], [0.0, 2.0, 0.0], [0.5, 0.0, 6.0]])


def test_se2_projection_of_a_pitched_pose_by_hand() -> None:
    # yaw 0, pitch 0.3: R20 = -sin(0.3), R00 = cos(0.3), R10 = 0, so d yaw = d rz + tan(0.3) d rx
    p = 0.3
    t = se3(rot_zyx(0.0, p, 0.0), [0.0, 0.0, 0.0])
    cov = np.diag([0.01, 0.02, 0.5, 0.04, 0.05, 0.06])
    want_yaw_var = 0.06 + np.tan(p) ** 2 * 0.04
    got = project_cov_se2(t, cov)
    np.testing.assert_allclose(got, np.diag([0.01, 0.02, want_yaw_var]), atol=1e-12)
    # and numerically: perturb the world rotation by small rx, the yaw moves by tan(pitch) rx
    eps = 1e-6
    r2 = gtsam.Rot3.Rodrigues(eps, 0.0, 0.0).matrix() @ t[:3, :3]
    dyaw = project_pose_se2(se3(r2, [0, 0, 0]))[2] - project_pose_se2(t)[2]
    assert dyaw / eps == pytest.approx(np.tan(p), rel=1e-4)


def test_world_and_body_covariances_round_trip() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 6))
    cov = a @ a.T + np.eye(6)
    t = se3(rot_zyx(0.4, -0.2, 0.1), [1.0, -2.0, 0.5])
    np.testing.assert_allclose(world_to_body_cov(t, body_to_world_cov(t, cov)), cov, atol=1e-12)
    # body (omega, v) -> world (x, y, z, rx, ry, rz): a pure body-x translation variance lands on R e_x
    body = np.zeros((6, 6))
    body[3, 3] = 1.0
    w = body_to_world_cov(t, body)
    ex = t[:3, 0]
    np.testing.assert_allclose(w[:3, :3], np.outer(ex, ex), atol=1e-12)


def small_loop(closed: bool):
    """A square of 4 x 10 m driven once (16 steps of 2.5 m), a little up and down; odometry noise known."""
    g = PoseGraph3()
    poses = [np.eye(4)]
    step_cov = np.diag([1e-4, 1e-4, 4e-4, 1e-3, 1e-3, 1e-3])  # (omega, v)
    g.add_pose(poses[0])
    g.add_prior(0, poses[0], np.eye(6) * 1e-8)
    for k in range(16):
        turn = np.pi / 2 if k % 4 == 3 else 0.0
        rel = se3(rot_zyx(turn, 0.01 * (-1) ** k, 0.0), [2.5, 0.0, 0.05 * (-1) ** k])
        poses.append(poses[-1] @ rel)
        g.add_pose(poses[-1] @ se3(np.eye(3), [0.01 * k, 0.0, 0.0]))  # a drifting initial guess
        g.add_between("odometry", k, k + 1, rel, step_cov)
    if closed:
        g.add_between("loop", 0, 16, np.linalg.inv(poses[0]) @ poses[16], step_cov, robust="cauchy")
    est = g.optimize()
    return g, est, np.stack(poses)


def test_pose3_loop_marginals_are_spd_and_shrink_after_the_closure() -> None:
    g_open, est_open, truth = small_loop(False)
    g_closed, est_closed, _ = small_loop(True)
    for est in (est_open, est_closed):
        np.testing.assert_allclose(est[:, :3, 3], truth[:, :3, 3], atol=1e-6)
    m_open, m_closed = g_open.marginals_world(), g_closed.marginals_world()
    assert m_open.shape == (17, 6, 6)
    for m in (m_open[1:], m_closed[1:]):
        np.testing.assert_allclose(m, np.swapaxes(m, 1, 2), atol=1e-12)
        assert np.all(np.linalg.eigvalsh(m) > 0)
    tr_open = np.trace(m_open[:, :3, :3], axis1=1, axis2=2)
    tr_closed = np.trace(m_closed[:, :3, :3], axis1=1, axis2=2)
    assert np.all(tr_closed[1:] <= tr_open[1:] + 1e-12)
    assert tr_closed[16] < 0.05 * tr_open[16]  # the end of the loop is tied back to the start
    assert tr_closed[8] < 0.5 * tr_open[8]


@pytest.fixture(scope="module")
def kitti() -> tuple:
    rec = open_dataset(data_file("kitti00"))
    return rec, run_slam_recording(rec, SlamConfig())


def test_kitti_kiss_icp_odometry_against_the_reference(kitti) -> None:
    rec, result = kitti
    assert isinstance(result, SlamResult)
    n = len(rec.clouds)
    assert result.poses_after_se3.shape == (n, 4, 4) and result.cov_after_se3.shape == (n, 6, 6)
    assert result.poses_after_xytheta.shape == (n, 3) and result.cov_after_xytheta.shape == (n, 3, 3)
    assert np.all(np.linalg.eigvalsh(result.cov_after_xytheta[1:]) > 0)
    np.testing.assert_allclose(result.poses_after_xytheta, project_pose_se2(result.poses_after_se3))
    ref = rec.meta["reference_poses_se3"]
    est = result.poses_before_se3
    step_est = np.linalg.norm(np.diff(est[:, :3, 3], axis=0), axis=1)
    step_ref = np.linalg.norm(np.diff(ref[:, :3, 3], axis=0), axis=1)
    # measured: KISS-ICP 0.69-0.74 m per frame, the poses file 0.86 m per frame: the frames and the
    # poses disagree (pairwise ICP started AT the reference increment converges to the same ~0.7 m, below)
    assert np.all((step_est > 0.6) & (step_est < 0.8))
    np.testing.assert_allclose(step_ref, 0.86, atol=0.01)
    # straight ahead in both, heading within 3 degrees of the reference
    yaw_err = result.poses_before_xytheta[:, 2] - rec.reference.poses_xytheta[:, 2]
    assert np.all(np.abs(yaw_err) < np.deg2rad(3.0))


def test_kitti_pairwise_icp_from_the_reference_agrees_with_kiss_icp(kitti) -> None:
    rec, result = kitti
    from kiss_icp.voxelization import voxel_down_sample

    ref = rec.meta["reference_poses_se3"]
    est = result.poses_before_se3
    cfg = SlamConfig().cloud
    for i in (1, 3, 5):
        target = voxel_down_sample(rec.clouds[i - 1].points_xyz_m.astype(np.float64), 0.5)
        query = voxel_down_sample(rec.clouds[i].points_xyz_m.astype(np.float64), 1.5)
        guess = np.linalg.inv(ref[i - 1]) @ ref[i]
        found, cov, frac, rms = verify_closure(query, target, guess, cfg, 1.0)
        kiss_step = np.linalg.inv(est[i - 1]) @ est[i]
        assert frac > 0.8 and rms < 0.3
        assert np.linalg.norm(found[:3, 3] - kiss_step[:3, 3]) < 0.1  # frame-to-frame vs frame-to-map
        assert np.linalg.norm(found[:3, 3] - guess[:3, 3]) > 0.1  # ... and both differ from the poses file
        assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_pose3_helper_orthonormalises() -> None:
    t = se3(rot_zyx(0.3, 0.0, 0.0), [1.0, 0.0, 0.0])
    t[:3, :3] *= 1.0 + 1e-9
    np.testing.assert_allclose(pose3(t).matrix(), se3(rot_zyx(0.3, 0.0, 0.0), [1.0, 0.0, 0.0]), atol=1e-8)


def test_cli_evaluate_slam_on_a_kitti_folder_uses_its_own_poses() -> None:
    import json
    import subprocess
    import sys

    from tests.conftest import REPO

    folder = str(data_file("kitti00"))
    done = subprocess.run(
        [sys.executable, "run.py", "evaluate", "slam", folder, "--reference", folder, "--json"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["reference"]["matched_scans"] == 6 and out["slam"]["scans"] == 6
    # measured: 0.239 m, the frames / poses-file disagreement (about 0.17 m per frame) of the tests above
    assert 0.1 < out["ate_rmse_m"]["after"] < 0.4
