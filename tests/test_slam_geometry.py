"""SE(2) helpers against GTSAM's Pose2, and first-order covariance propagation against GTSAM marginals."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from slam import geometry as se2
from slam.graph import chain_graph_marginals


def _random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3)) * [3.0, 3.0, 1.0]
    p[:, 2] = rng.uniform(-np.pi, np.pi, n)
    return p


def test_compose_between_inverse_match_gtsam() -> None:
    a, b = _random_poses(2)
    ga, gb = gtsam.Pose2(*a), gtsam.Pose2(*b)
    c = ga.compose(gb)
    np.testing.assert_allclose(se2.compose(a, b), [c.x(), c.y(), c.theta()], atol=1e-12)
    d = ga.between(gb)
    np.testing.assert_allclose(se2.between(a, b), [d.x(), d.y(), d.theta()], atol=1e-12)
    i = ga.inverse()
    np.testing.assert_allclose(se2.inverse(a), [i.x(), i.y(), i.theta()], atol=1e-12)
    np.testing.assert_allclose(se2.compose(a, se2.between(a, b)), b, atol=1e-12)


def test_logmap_and_adjoint_match_gtsam() -> None:
    for p in _random_poses(20, seed=3):
        np.testing.assert_allclose(se2.logmap(p), gtsam.Pose2.Logmap(gtsam.Pose2(*p)), atol=1e-10)
        np.testing.assert_allclose(se2.adjoint(p), gtsam.Pose2(*p).AdjointMap(), atol=1e-12)
    np.testing.assert_allclose(se2.logmap(np.array([1.0, 2.0, 0.0])), [1.0, 2.0, 0.0])


def test_world_rotation_of_a_body_covariance() -> None:
    # a pose heading +y (theta = 90 deg) that is uncertain along its own x axis is uncertain along world y
    body = np.diag([0.04, 0.0001, 0.01])
    world = se2.rotate_cov_to_world(np.array([5.0, 1.0, np.pi / 2]), body)
    np.testing.assert_allclose(world, np.diag([0.0001, 0.04, 0.01]), atol=1e-12)
    np.testing.assert_allclose(
        se2.rotate_cov_to_body(np.array([5.0, 1.0, np.pi / 2]), world), body, atol=1e-12
    )


def test_chain_propagation_equals_gtsam_marginals() -> None:
    rng = np.random.default_rng(7)
    n = 30
    inc = np.column_stack([rng.uniform(0.2, 1.0, n), rng.normal(0, 0.05, n), rng.normal(0, 0.3, n)])
    covs = np.stack([np.diag(rng.uniform(0.5, 2.0, 3) * [1e-4, 1e-4, 1e-5]) for _ in range(n)])
    covs[:, 0, 2] = covs[:, 2, 0] = 1e-6
    cov0 = np.diag([1e-6, 1e-6, 1e-8])
    ours = se2.propagate_chain_cov_body(inc, covs, cov0)
    ref = chain_graph_marginals(inc, covs, np.array([1.0, -2.0, 0.3]), cov0)
    np.testing.assert_allclose(ours, ref, rtol=1e-6, atol=1e-12)
    # and the uncertainty grows along the chain
    assert np.all(np.diff(np.trace(ours, axis1=1, axis2=2)) > 0)


@pytest.mark.parametrize("theta", [0.0, 1.0, -2.5])
def test_wrap(theta: float) -> None:
    for k in (-2, 0, 3):
        assert se2.wrap(theta + 2 * np.pi * k) == pytest.approx(se2.wrap(theta))
    assert -np.pi <= se2.wrap(np.pi) < np.pi
