"""The shared SE(2) helpers of ``datasets.se2``: hand-worked cases, group identities and broadcasting."""

from __future__ import annotations

import numpy as np
import pytest

from datasets import se2
from datasets.types import wrap_angle_rad
from slam import geometry

PI = np.pi


def _random_poses(n: int, seed: int, angle_span: float = PI) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3)) * [20.0, 20.0, 1.0]
    p[:, 2] = rng.uniform(-angle_span, angle_span, n)
    return p


def _same_angle(a, b, atol: float = 1e-12) -> None:
    np.testing.assert_allclose(se2.wrap_angle(np.asarray(a) - np.asarray(b)), 0.0, atol=atol)


@pytest.mark.parametrize(
    ("theta", "wrapped"),
    [(0.0, 0.0), (PI, -PI), (-PI, -PI), (1.5 * PI, -0.5 * PI), (-1.5 * PI, 0.5 * PI), (7.0, 7.0 - 2 * PI)],
)
def test_wrap_angle_hand_cases(theta: float, wrapped: float) -> None:
    assert float(se2.wrap_angle(theta)) == pytest.approx(wrapped, abs=1e-12)


def test_wrap_angle_range_and_idempotence() -> None:
    theta = np.concatenate([np.random.default_rng(0).uniform(-100.0, 100.0, 10_000), PI * np.arange(-6, 7)])
    w = se2.wrap_angle(theta)
    assert np.all(w >= -PI) and np.all(w < PI)
    np.testing.assert_allclose(np.cos(w), np.cos(theta), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(theta), atol=1e-12)
    np.testing.assert_allclose(se2.wrap_angle(w), w, atol=1e-15, rtol=0)


def test_compose_inverse_between_hand_cases() -> None:
    a = np.array([1.0, 2.0, PI / 2])  # at (1, 2), facing +y
    d = np.array([1.0, 0.0, PI / 2])  # one metre ahead, turned left
    np.testing.assert_allclose(se2.compose(a, d), [1.0, 3.0, -PI], atol=1e-12)
    np.testing.assert_allclose(se2.inverse(np.array([1.0, 0.0, PI / 2])), [0.0, 1.0, -PI / 2], atol=1e-12)
    # (3, 2) seen from a pose at (1, 2) facing +y is 2 m to its right
    np.testing.assert_allclose(se2.between(a, np.array([3.0, 2.0, 0.0])), [0.0, -2.0, -PI / 2], atol=1e-12)


def test_compose_with_inverse_is_identity() -> None:
    a = _random_poses(500, seed=1, angle_span=10.0)
    for ident in (se2.compose(a, se2.inverse(a)), se2.compose(se2.inverse(a), a)):
        np.testing.assert_allclose(ident[:, :2], 0.0, atol=1e-12)
        _same_angle(ident[:, 2], 0.0)


def test_between_undoes_compose() -> None:
    a, b = _random_poses(500, seed=2, angle_span=10.0), _random_poses(500, seed=3)
    got = se2.between(a, se2.compose(a, b))
    np.testing.assert_allclose(got[:, :2], b[:, :2], atol=1e-12)
    _same_angle(got[:, 2], b[:, 2])
    back = se2.compose(a, se2.between(a, b))
    np.testing.assert_allclose(back[:, :2], b[:, :2], atol=1e-12)
    _same_angle(back[:, 2], b[:, 2])


def test_headings_come_out_wrapped() -> None:
    a, b = _random_poses(200, seed=4, angle_span=30.0), _random_poses(200, seed=5, angle_span=30.0)
    for out in (se2.compose(a, b), se2.inverse(a), se2.between(a, b)):
        assert np.all(out[:, 2] >= -PI) and np.all(out[:, 2] < PI)


def test_transform_points_matches_a_rotation_matrix() -> None:
    poses = _random_poses(50, seed=6, angle_span=10.0)
    pts = np.random.default_rng(7).normal(size=(40, 2)) * 5.0

    def explicit(pose, p):
        c, s = np.cos(pose[2]), np.sin(pose[2])
        return p @ np.array([[c, -s], [s, c]]).T + pose[:2]

    np.testing.assert_allclose(se2.transform_points(poses[0], pts), explicit(poses[0], pts), atol=1e-12)
    np.testing.assert_allclose(
        se2.transform_points(poses, pts[0]), [explicit(p, pts[0]) for p in poses], atol=1e-12
    )
    np.testing.assert_allclose(
        se2.transform_points(poses[:40], pts),
        [explicit(p, q) for p, q in zip(poses[:40], pts, strict=True)],
        atol=1e-12,
    )
    every = se2.transform_points(poses[:, None], pts[None])
    assert every.shape == (50, 40, 2)
    np.testing.assert_allclose(every[9], explicit(poses[9], pts), atol=1e-12)


def test_transform_points_is_the_position_of_compose_bit_for_bit() -> None:
    a, d = _random_poses(300, seed=8), _random_poses(300, seed=9)
    assert np.array_equal(se2.transform_points(a, d[:, :2]), se2.compose(a, d)[:, :2])


def test_compose_broadcasts_one_pose_over_many() -> None:
    a, d = _random_poses(1, seed=10)[0], _random_poses(30, seed=11)
    assert np.array_equal(se2.compose(a, d), se2.compose(np.broadcast_to(a, d.shape), d))
    assert se2.compose(a, d[0]).shape == (3,)


def test_older_names_are_the_shared_helpers() -> None:
    assert geometry.wrap is se2.wrap_angle and wrap_angle_rad is se2.wrap_angle
    assert geometry.compose is se2.compose
    assert geometry.inverse is se2.inverse
    assert geometry.between is se2.between


def test_path_length_sums_the_steps() -> None:
    path_length_m = se2.path_length_m
    xy = np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 4.0], [3.0, 1.0]])
    np.testing.assert_allclose(path_length_m(xy), [0.0, 5.0, 5.0, 8.0])
    assert path_length_m(np.zeros((1, 2))).tolist() == [0.0]
    assert path_length_m(np.zeros((0, 2))).shape == (0,)
