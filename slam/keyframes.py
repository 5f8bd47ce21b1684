"""Keyframe selection by travelled distance and rotation, and the odometry factors between keyframes."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slam import geometry as se2

FloatArray = NDArray[np.float64]


def select_keyframes(poses_xytheta: FloatArray, distance_m: float, rotation_rad: float) -> NDArray[np.int64]:
    """Indices of keyframes: the first scan, then each scan after which the path length or the accumulated
    absolute rotation since the previous keyframe reaches ``distance_m`` or ``rotation_rad``."""
    poses = np.asarray(poses_xytheta, dtype=np.float64)
    n = poses.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    step_d = np.hypot(*np.diff(poses[:, :2], axis=0).T) if n > 1 else np.zeros(0)
    step_r = np.abs(se2.wrap(np.diff(poses[:, 2]))) if n > 1 else np.zeros(0)
    keys = [0]
    acc_d = 0.0
    acc_r = 0.0
    for i in range(1, n):
        acc_d += step_d[i - 1]
        acc_r += step_r[i - 1]
        if acc_d >= distance_m or acc_r >= rotation_rad:
            keys.append(i)
            acc_d = 0.0
            acc_r = 0.0
    return np.asarray(keys, dtype=np.int64)


def keyframe_of_scan(keyframe_scans: NDArray[np.int64], n_scans: int) -> NDArray[np.int64]:
    """(N,) index (into the sorted ``keyframe_scans``) of the last keyframe at or before each scan; scans
    before the first keyframe belong to it."""
    owner = np.searchsorted(keyframe_scans, np.arange(n_scans), side="right") - 1
    return np.clip(owner, 0, len(keyframe_scans) - 1)


def keyframe_offsets(
    keyframe_scans: NDArray[np.int64], scan_poses_xytheta: FloatArray
) -> tuple[NDArray[np.int64], FloatArray]:
    """Each scan's keyframe (:func:`keyframe_of_scan`, (N,)) and its (N, 3) pose in that keyframe's frame,
    both taken from the (N, 3) scan poses (the odometry in a run: rigid between keyframes)."""
    owner = keyframe_of_scan(keyframe_scans, len(scan_poses_xytheta))
    return owner, se2.between(scan_poses_xytheta[keyframe_scans[owner]], scan_poses_xytheta)


def scan_poses_from_keyframes(
    keyframe_poses_xytheta: FloatArray, keyframe_scans: NDArray[np.int64], scan_poses_xytheta: FloatArray
) -> FloatArray:
    """(N, 3) scan poses after the keyframes moved to ``keyframe_poses_xytheta`` (K, 3): each scan keeps its
    offset from its keyframe in the (N, 3) ``scan_poses_xytheta`` (how the pose graph's estimate reaches
    every scan)."""
    owner, offset = keyframe_offsets(keyframe_scans, scan_poses_xytheta)
    return se2.compose(np.asarray(keyframe_poses_xytheta, dtype=np.float64)[owner], offset)


def relative_cov_body(
    pose_a: FloatArray, cov_a_world: FloatArray, pose_b: FloatArray, cov_b_world: FloatArray, scale: float
) -> FloatArray:
    """Child-frame covariance of ``between(a, b)`` when ``a`` and ``b`` were registered independently
    against the same map with world-frame covariances ``cov_a_world``, ``cov_b_world``; inflated by
    ``scale``. ``eps_ab = eps_b - Ad(between(a, b)^-1) eps_a`` (body-frame perturbations)."""
    z = se2.between(pose_a, pose_b)
    ca = se2.rotate_cov_to_body(pose_a, cov_a_world)
    cb = se2.rotate_cov_to_body(pose_b, cov_b_world)
    return scale * se2.compose_cov_body(ca, z, cb)
