"""SE(3) for 3D inputs: the GTSAM ``Pose3`` pose graph, its marginals in the world frame, and the SE(2)
projection (x, y, yaw) of poses and covariances for the 2D mapper.

Conventions. Poses are (4, 4) homogeneous matrices ``poses_se3`` (body to world). GTSAM's ``Pose3`` tangent
is ``xi = (omega, v)`` (rotation first) with the right perturbation ``T' = T Exp(xi)``, so its marginals
are in the body frame. This module's world-frame 6x6 covariances are in the order
``(x, y, z, rx, ry, rz)``: the world-frame translation and the world-frame small rotation ``delta`` with
``R' = Exp(delta) R``; to first order ``dt_world = R v`` and ``delta = R omega``.

Projection to SE(2): ``yaw = atan2(R10, R00)``; marginalising z, roll and pitch of a Gaussian is dropping
their rows and columns after the linear map ``J`` from (x, y, z, rx, ry, rz) to (x, y, yaw), with
``d yaw = delta_z - R20 (R00 delta_x + R10 delta_y) / (R00^2 + R10^2)`` (exactly ``delta_z`` for a
level pose).
"""

from __future__ import annotations

import gtsam
import numpy as np
from numpy.typing import NDArray

from slam.graph import _robust

FloatArray = NDArray[np.float64]


def pose3(t_se3: FloatArray) -> gtsam.Pose3:
    """A GTSAM ``Pose3`` from a (4, 4) matrix (its rotation re-orthonormalised)."""
    t = np.asarray(t_se3, dtype=np.float64)
    u, _, vt = np.linalg.svd(t[:3, :3])
    r = u @ vt
    if np.linalg.det(r) < 0:
        r = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return gtsam.Pose3(gtsam.Rot3(r), np.asarray(t[:3, 3], dtype=np.float64))


def body_to_world_cov(t_se3: FloatArray, cov_body: FloatArray) -> FloatArray:
    """(6, 6) world-frame ``(x, y, z, rx, ry, rz)`` covariance from a GTSAM body-frame ``(omega, v)`` one."""
    r = np.asarray(t_se3, dtype=np.float64)[:3, :3]
    m = np.zeros((6, 6))
    m[:3, 3:] = r  # world translation from v
    m[3:, :3] = r  # world rotation from omega
    return m @ np.asarray(cov_body, dtype=np.float64) @ m.T


def world_to_body_cov(t_se3: FloatArray, cov_world: FloatArray) -> FloatArray:
    """Inverse of :func:`body_to_world_cov`."""
    r = np.asarray(t_se3, dtype=np.float64)[:3, :3]
    m = np.zeros((6, 6))
    m[:3, 3:] = r.T
    m[3:, :3] = r.T
    return m @ np.asarray(cov_world, dtype=np.float64) @ m.T


def project_pose_se2(t_se3: FloatArray) -> FloatArray:
    """(..., 3) ``(x, y, yaw)`` of (..., 4, 4) poses."""
    t = np.asarray(t_se3, dtype=np.float64)
    yaw = np.arctan2(t[..., 1, 0], t[..., 0, 0])
    return np.stack([t[..., 0, 3], t[..., 1, 3], yaw], axis=-1)


def projection_jacobian(t_se3: FloatArray) -> FloatArray:
    """(3, 6) d(x, y, yaw) / d(x, y, z, rx, ry, rz) at the pose (see the module docstring)."""
    r = np.asarray(t_se3, dtype=np.float64)[:3, :3]
    c2 = r[0, 0] ** 2 + r[1, 0] ** 2
    j = np.zeros((3, 6))
    j[0, 0] = 1.0
    j[1, 1] = 1.0
    j[2, 3] = -r[2, 0] * r[0, 0] / c2
    j[2, 4] = -r[2, 0] * r[1, 0] / c2
    j[2, 5] = 1.0
    return j


def project_cov_se2(t_se3: FloatArray, cov_world: FloatArray) -> FloatArray:
    """(3, 3) world-frame ``(x, y, yaw)`` covariance of a pose with (6, 6) world-frame covariance."""
    j = projection_jacobian(t_se3)
    out = j @ np.asarray(cov_world, dtype=np.float64) @ j.T
    return 0.5 * (out + out.T)


def relative_se3(a_se3: FloatArray, b_se3: FloatArray) -> FloatArray:
    """(4, 4) ``a^-1 b``."""
    return np.linalg.inv(np.asarray(a_se3, dtype=np.float64)) @ np.asarray(b_se3, dtype=np.float64)


class PoseGraph3:
    """A ``Pose3`` pose graph (keys 0..K-1), batch Levenberg-Marquardt and marginals.

    Factor covariances are (6, 6) in GTSAM's tangent order ``(omega, v)`` of the child frame of the measured
    relative pose (``BetweenFactorPose3``).
    """

    def __init__(self) -> None:
        self.graph = gtsam.NonlinearFactorGraph()
        self.values = gtsam.Values()
        self.kinds: list[str] = []
        self.count = 0

    def add_pose(self, t_se3: FloatArray) -> int:
        self.values.insert(self.count, pose3(t_se3))
        self.count += 1
        return self.count - 1

    def add_prior(self, key: int, t_se3: FloatArray, cov: FloatArray) -> None:
        noise = gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=np.float64))
        self.graph.add(gtsam.PriorFactorPose3(key, pose3(t_se3), noise))
        self.kinds.append("prior")

    def add_between(
        self,
        kind: str,
        key_from: int,
        key_to: int,
        relative: FloatArray,
        cov: FloatArray,
        robust: str = "none",
        robust_width: float = 1.0,
    ) -> None:
        base = gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=np.float64))
        noise = _robust(robust, robust_width, base)
        self.graph.add(gtsam.BetweenFactorPose3(key_from, key_to, pose3(relative), noise))
        self.kinds.append(kind)

    def optimize(self, max_iterations: int = 100) -> FloatArray:
        """Optimise in place; returns the (K, 4, 4) estimate."""
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        self.values = gtsam.LevenbergMarquardtOptimizer(self.graph, self.values, params).optimize()
        return self.estimate()

    def estimate(self) -> FloatArray:
        return np.stack([self.values.atPose3(k).matrix() for k in range(self.count)])

    def marginals_body(self) -> FloatArray:
        """(K, 6, 6) GTSAM body-frame ``(omega, v)`` marginal covariances."""
        m = gtsam.Marginals(self.graph, self.values)
        return np.stack([m.marginalCovariance(k) for k in range(self.count)])

    def marginals_world(self) -> FloatArray:
        """(K, 6, 6) world-frame ``(x, y, z, rx, ry, rz)`` marginals."""
        est = self.estimate()
        return np.stack([body_to_world_cov(t, c) for t, c in zip(est, self.marginals_body(), strict=True)])
