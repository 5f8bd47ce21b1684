"""Planar rigid motions (SE(2)) on ``(x, y, theta)`` rows, vectorised over leading axes.

A pose ``p = (x, y, theta)`` (m, m, rad) is a frame given in a parent frame (usually the world): it maps a
point ``b`` given in its own (body) frame to ``w = R(theta) b + (x, y)`` in the parent frame. Poses are
``(..., 3)`` float arrays, points ``(..., 2)``; leading axes broadcast against each other like numpy
operands, so one pose ``(3,)`` can act on ``(N, 3)`` poses or ``(P, 2)`` points and ``(N, 3)`` poses pair
up row by row with ``(N, 3)`` or ``(N, 2)`` arrays.

Every stage (readers, simulation, SLAM, mapping) uses these so the same operation gives the same bits
everywhere; the arithmetic is written out term by term (no matrix products) and its order is part of the
contract: results must not change by a rounding when callers switch to these helpers. Numba-compiled code
keeps its own inline copies.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def wrap_angle(theta_rad: NDArray | float) -> NDArray | float:
    """Angles (any shape, rad) wrapped to [-pi, pi) as ``(theta + pi) mod 2 pi - pi``.

    Returns a numpy array (0-d for a scalar input). Already wrapped angles may move by a rounding.
    """
    return (np.asarray(theta_rad) + np.pi) % (2.0 * np.pi) - np.pi


def compose(a: FloatArray, d: FloatArray) -> FloatArray:
    """``a * d``: (..., 3) poses ``d`` given in the frame of (..., 3) poses ``a``, expressed in ``a``'s parent
    frame (x, y in m, theta in rad wrapped to [-pi, pi))."""
    a = np.asarray(a, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * d[..., 0] - s * d[..., 1]
    y = a[..., 1] + s * d[..., 0] + c * d[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + d[..., 2])], axis=-1)


def inverse(a: FloatArray) -> FloatArray:
    """``a^-1``: for (..., 3) poses ``a`` of a frame in its parent, the (..., 3) poses of the parent in that
    frame (theta wrapped to [-pi, pi))."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -(c * a[..., 0] + s * a[..., 1])
    y = -(-s * a[..., 0] + c * a[..., 1])
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def between(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a^-1 * b``: (..., 3) poses ``b`` seen from the frame of (..., 3) poses ``a`` (both given in the same
    parent frame; theta wrapped to [-pi, pi)). ``compose(a, between(a, b))`` is ``b`` up to rounding."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1)


def rot3(theta_rad: NDArray | float) -> FloatArray:
    """(..., 3, 3) ``blockdiag(R(theta), 1)``: maps body-frame (x, y, theta) vectors to the world frame."""
    th = np.asarray(theta_rad, dtype=np.float64)
    out = np.zeros((*th.shape, 3, 3))
    c, s = np.cos(th), np.sin(th)
    out[..., 0, 0] = c
    out[..., 0, 1] = -s
    out[..., 1, 0] = s
    out[..., 1, 1] = c
    out[..., 2, 2] = 1.0
    return out


def transform_points(poses: FloatArray, points_xy: FloatArray) -> FloatArray:
    """(..., 2) parent-frame positions of (..., 2) points given in the frames of (..., 3) poses.

    The position part of :func:`compose` (``x + cos(theta) px - sin(theta) py``, same rounding), without a
    heading. Shapes broadcast: one pose (3,) and points (P, 2), poses (N, 3) and one point (2,), or row by
    row; for every pose with every point pass ``poses[:, None]`` and ``points[None]``.
    """
    p = np.asarray(poses, dtype=np.float64)
    q = np.asarray(points_xy, dtype=np.float64)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    x = p[..., 0] + c * q[..., 0] - s * q[..., 1]
    y = p[..., 1] + s * q[..., 0] + c * q[..., 1]
    return np.stack([x, y], axis=-1)


def path_length_m(xy_m: FloatArray) -> FloatArray:
    """(N,) distance travelled (m) along the (N, 2) positions up to each one, 0 at the first (the cumulative
    length of the straight steps between them)."""
    xy = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
    if xy.shape[0] == 0:
        return np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
