"""SE(2) helpers on ``(x, y, theta)`` rows, vectorised over leading axes.

Conventions: a pose ``p = (x, y, theta)`` maps body-frame points to the world, ``w = R(theta) b + t``.
``between(a, b)`` is the pose of ``b`` in the frame of ``a`` (``a^-1 * b``); ``compose(a, d)`` is ``a * d``.
Covariances in the *body* frame of a pose are GTSAM's ``Pose2`` tangent-space convention (perturbation on the
right, ``p * Exp(xi)``, order (x, y, theta)); world-frame covariances (SPEC section 2) are obtained with
:func:`rotate_cov_to_world`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

# the basic operations live on the ground floor (shared with the readers, the simulation and mapping)
from datasets import se2
from datasets.se2 import between as between
from datasets.se2 import compose as compose
from datasets.se2 import inverse as inverse
from datasets.se2 import path_length_m as path_length_m
from datasets.se2 import rot3 as rot3
from datasets.se2 import wrap_angle as wrap

FloatArray = NDArray[np.float64]


def chain(start: FloatArray, increments: FloatArray) -> FloatArray:
    """(N+1, 3) poses ``start, start*d0, start*d0*d1, ...`` from (N, 3) increments."""
    out = np.empty((increments.shape[0] + 1, 3))
    out[0] = start
    for i in range(increments.shape[0]):
        out[i + 1] = compose(out[i], increments[i])
    return out


def logmap(d: FloatArray) -> FloatArray:
    """(..., 3) SE(2) logarithm ``(v_x, v_y, omega)`` of poses (GTSAM ``Pose2.Logmap``)."""
    d = np.asarray(d, dtype=np.float64)
    w = wrap(d[..., 2])
    half = 0.5 * w
    small = np.abs(w) < 1e-10
    # V^-1 = (w/2) [[cot(w/2), 1], [-1, cot(w/2)]] ... written with a safe limit at w -> 0
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.where(small, 1.0, half / np.tan(np.where(small, 1.0, half)))
    x = k * d[..., 0] + half * d[..., 1]
    y = -half * d[..., 0] + k * d[..., 1]
    return np.stack([x, y, w], axis=-1)


def transform_points(pose: FloatArray, points_xy: FloatArray) -> FloatArray:
    """(P, 2) body-frame points mapped to the world by one pose (3,).

    A matrix product, which rounds differently from :func:`datasets.se2.transform_points`; kept so that
    scan matching, and so SLAM trajectories, stay bit for bit what they were.
    """
    c, s = np.cos(pose[2]), np.sin(pose[2])
    rot = np.array([[c, -s], [s, c]])
    return points_xy @ rot.T + pose[:2]


def transform_points_each(poses_xytheta: FloatArray, point_xy: FloatArray) -> FloatArray:
    """(N, 2) one body-frame point (2,) mapped to the world by each of (N, 3) poses."""
    return se2.transform_points(poses_xytheta, np.asarray(point_xy, dtype=np.float64)[:2])


def rotate_cov_to_world(poses_xytheta: FloatArray, cov_body: FloatArray) -> FloatArray:
    """World-frame (x, y, theta) covariances ``R S R^T`` of body-frame ones (SPEC section 2), (..., 3, 3)."""
    r = rot3(np.asarray(poses_xytheta)[..., 2])
    return r @ cov_body @ np.swapaxes(r, -1, -2)


def rotate_cov_to_body(poses_xytheta: FloatArray, cov_world: FloatArray) -> FloatArray:
    """Inverse of :func:`rotate_cov_to_world`."""
    r = rot3(np.asarray(poses_xytheta)[..., 2])
    return np.swapaxes(r, -1, -2) @ cov_world @ r


def adjoint(d: FloatArray) -> FloatArray:
    """(..., 3, 3) adjoint of SE(2) poses (GTSAM ``Pose2.AdjointMap``): ``Ad(d) xi`` moves a tangent vector
    at ``d``'s child frame into its parent frame, ``d * Exp(xi) = Exp(Ad(d) xi) * d``."""
    d = np.asarray(d, dtype=np.float64)
    c, s = np.cos(d[..., 2]), np.sin(d[..., 2])
    out = np.zeros((*d.shape[:-1], 3, 3))
    out[..., 0, 0] = c
    out[..., 0, 1] = -s
    out[..., 0, 2] = d[..., 1]
    out[..., 1, 0] = s
    out[..., 1, 1] = c
    out[..., 1, 2] = -d[..., 0]
    out[..., 2, 2] = 1.0
    return out


def compose_cov_body(cov_a: FloatArray, d: FloatArray, cov_d: FloatArray) -> FloatArray:
    """Body-frame covariance of ``a * d`` (first order, independent ``a`` and ``d``).

    ``cov_a`` is the body-frame covariance of ``a``, ``cov_d`` that of the increment ``d`` in its own child
    frame. With right perturbations, ``a Exp(ea) d Exp(ed) = a d Exp(Ad(d^-1) ea + ed)``.
    """
    j = adjoint(inverse(d))
    return j @ cov_a @ np.swapaxes(j, -1, -2) + cov_d


def propagate_chain_cov_body(
    increments: FloatArray, cov_increments: FloatArray, cov0: FloatArray
) -> FloatArray:
    """(N+1, 3, 3) body-frame covariances along an odometry chain (first-order propagation).

    ``increments`` (N, 3) and their child-frame covariances ``cov_increments`` (N, 3, 3); ``cov0`` the
    body-frame covariance of the first pose. This equals the marginals of a pose graph holding only the
    chain (checked against GTSAM in the tests).
    """
    n = increments.shape[0]
    out = np.empty((n + 1, 3, 3))
    out[0] = cov0
    for i in range(n):
        out[i + 1] = compose_cov_body(out[i], increments[i], cov_increments[i])
    return out
