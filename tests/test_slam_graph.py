"""The pose graph, GTSAM-test style: a small square loop, optimised, with its marginals asserted."""

from __future__ import annotations

import gtsam
import numpy as np

from slam import geometry as se2
from slam.config import GraphConfig
from slam.graph import EdgeTable, PoseGraph, edge_errors2
from slam.system import variance_factor

ODO_COV = np.diag([0.2**2, 0.2**2, 0.1**2])  # the noise of GTSAM's Pose2SLAMExample
PRIOR_COV = np.diag([0.3**2, 0.3**2, 0.1**2])
SQUARE = np.array([[0, 0, 0], [2, 0, np.pi / 2], [2, 2, np.pi], [0, 2, -np.pi / 2], [0, 0, 0]], dtype=float)


def _square_graph(with_closure: bool, initial: np.ndarray) -> PoseGraph:
    g = PoseGraph()
    for p in initial:
        g.add_pose(p)
    g.add_prior(0, SQUARE[0], PRIOR_COV)
    for i in range(4):
        g.add_between("odometry", i, i + 1, np.array([2.0, 0.0, np.pi / 2]), ODO_COV)
    if with_closure:
        g.add_between("loop", 4, 1, np.array([2.0, 0.0, np.pi / 2]), ODO_COV)
    g.update()
    return g


def _perturbed() -> np.ndarray:
    # GTSAM's example initial estimate
    return np.array(
        [[0.5, 0.0, 0.2], [2.3, 0.1, -0.2], [4.1, 0.1, np.pi / 2], [4.0, 2.0, np.pi], [2.1, 2.1, -np.pi / 2]]
    )


def test_square_loop_optimises_to_the_square() -> None:
    g = _square_graph(True, _perturbed())
    est = g.optimize_batch()
    np.testing.assert_allclose(est[:, :2], SQUARE[:, :2], atol=1e-6)
    np.testing.assert_allclose(se2.wrap(est[:, 2] - SQUARE[:, 2]), 0.0, atol=1e-6)


def test_marginals_symmetric_positive_definite_and_shrinking_after_closure() -> None:
    open_chain = _square_graph(False, SQUARE)
    open_chain.optimize_batch()
    before = open_chain.marginals_body()
    closed = _square_graph(True, SQUARE)
    closed.optimize_batch()
    after = closed.marginals_body()
    for cov in np.concatenate([before, after]):
        np.testing.assert_allclose(cov, cov.T, atol=1e-12)
        assert np.all(np.linalg.eigvalsh(cov) > 0)
    # the first pose is held by its prior in both graphs
    np.testing.assert_allclose(before[0], after[0], rtol=1e-6, atol=1e-12)
    # every later pose is better known once the loop is closed, the last one most of all
    for k in range(1, 5):
        assert np.all(np.linalg.eigvalsh(before[k] - after[k]) > -1e-12), k
        assert np.trace(after[k]) < np.trace(before[k])
    assert np.trace(after[4]) < 0.6 * np.trace(before[4])
    # GTSAM's own Marginals on the same graph agree (the wrapper adds nothing)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(
        gtsam.PriorFactorPose2(0, gtsam.Pose2(0, 0, 0), gtsam.noiseModel.Gaussian.Covariance(PRIOR_COV))
    )
    noise = gtsam.noiseModel.Gaussian.Covariance(ODO_COV)
    for i, j in ((0, 1), (1, 2), (2, 3), (3, 4), (4, 1)):
        graph.add(gtsam.BetweenFactorPose2(i, j, gtsam.Pose2(2, 0, np.pi / 2), noise))
    values = gtsam.Values()
    for k, p in enumerate(SQUARE):
        values.insert(k, gtsam.Pose2(*p))
    m = gtsam.Marginals(graph, values)
    np.testing.assert_allclose(after[3], m.marginalCovariance(3), rtol=1e-6, atol=1e-12)


def test_edge_errors_match_gtsam_factor_errors() -> None:
    g = _square_graph(True, _perturbed())
    est = _perturbed()
    values = gtsam.Values()
    for k, p in enumerate(est):
        values.insert(k, gtsam.Pose2(*p))
    ours = edge_errors2(est, g.edges)
    theirs = [2.0 * g.graph.at(i).error(values) for i in range(g.graph.size())]
    np.testing.assert_allclose(ours, theirs, rtol=1e-9)


def test_edge_table_grown_edge_by_edge_equals_one_built_at_once() -> None:
    """The graph's table is appended to as edges arrive (the loop search reads it after every closure): it
    must give every edge the error the edges give on their own, to the last bit, and follow new edges."""
    g = _square_graph(False, _perturbed())
    est = _perturbed()
    first = g.edge_table.errors2(est)  # 5 edges: prior and odometry
    assert first.shape == (5,)
    g.add_between("loop", 4, 1, np.array([2.0, 0.0, np.pi / 2]), ODO_COV * 3.0)
    g.add_between("loop", 3, 0, np.array([2.1, 0.1, np.pi / 2]), ODO_COV, "cauchy", 2.0)
    grown = g.edge_table.errors2(est)
    whole = EdgeTable(g.edges).errors2(est)
    one_by_one = np.concatenate([EdgeTable([e]).errors2(est) for e in g.edges])
    np.testing.assert_array_equal(grown, whole)
    np.testing.assert_array_equal(grown, one_by_one)
    np.testing.assert_array_equal(grown[:5], first)
    np.testing.assert_array_equal(g.edge_table.is_loop, [False] * 5 + [True, True])
    # and the variance factor reads the table as it reads the edge list
    cfg = GraphConfig(variance_factor_min_loops=1)
    s_table, inl_table = variance_factor(est, g.edge_table, 1.0, cfg)
    s_list, inl_list = variance_factor(est, list(g.edges), 1.0, cfg)
    assert s_table == s_list and s_table > 1.0
    np.testing.assert_array_equal(inl_table, inl_list)


def _corridor_loop(n: int, false_closure: str | None) -> tuple[np.ndarray, np.ndarray]:
    """A 4 x (n/4) square track with noisy odometry, true closures, and optionally one false closure."""
    rng = np.random.default_rng(1)
    side = n // 4
    inc_true = np.tile([1.0, 0.0, 0.0], (n, 1))
    inc_true[side - 1 :: side, 2] = np.pi / 2
    truth = se2.chain(np.zeros(3), inc_true)
    cov = np.diag([0.02**2, 0.02**2, 0.01**2])
    g = PoseGraph()
    g.add_pose(truth[0])
    g.add_prior(0, truth[0], np.diag([1e-6, 1e-6, 1e-8]))
    pose = truth[0]
    for i in range(n):
        z = se2.compose(inc_true[i], rng.multivariate_normal(np.zeros(3), cov))
        pose = se2.compose(pose, z)
        g.add_pose(pose)
        g.add_between("odometry", i, i + 1, z, cov)
    for j, k in ((0, n), (0, n - 1), (1, n), (1, n - 1)):
        g.add_between("loop", j, k, se2.between(truth[j], truth[k]), cov, robust="cauchy")
    if false_closure is not None:
        g.add_between("loop", side, 3 * side, np.array([0.0, 0.0, 0.0]), cov, robust=false_closure)
    g.update()
    return g.optimize_batch(), truth


def test_a_false_closure_does_not_wreck_a_robust_graph() -> None:
    clean, truth = _corridor_loop(40, None)
    robust, _ = _corridor_loop(40, "cauchy")
    plain, _ = _corridor_loop(40, "none")
    err = {
        name: np.max(np.hypot(*(est[:, :2] - truth[:, :2]).T))
        for name, est in (("clean", clean), ("robust", robust), ("plain", plain))
    }
    assert err["clean"] < 0.3
    assert err["robust"] < err["clean"] + 0.1  # the Cauchy loss ignores the false closure ...
    assert err["plain"] > 2.0  # ... which pulls two opposite sides of the square together without it


def test_variance_factor_recovers_a_common_noise_scale() -> None:
    rng = np.random.default_rng(5)
    truth = se2.chain(np.zeros(3), np.tile([0.5, 0.0, 0.05], (300, 1)))
    stated = np.diag([0.01**2, 0.01**2, 0.005**2])
    real_scale = 9.0  # the real noise is 3x the stated sigma
    g = PoseGraph()
    for p in truth:
        g.add_pose(p)
    g.add_prior(0, truth[0], np.diag([1e-8, 1e-8, 1e-10]))
    for i in range(300):
        z = se2.compose(
            se2.between(truth[i], truth[i + 1]), rng.multivariate_normal(np.zeros(3), stated * real_scale)
        )
        g.add_between("odometry", i, i + 1, z, stated)
    for _ in range(150):
        i, j = sorted(rng.choice(301, 2, replace=False))
        z = se2.compose(
            se2.between(truth[i], truth[j]), rng.multivariate_normal(np.zeros(3), stated * real_scale)
        )
        g.add_between("loop", int(i), int(j), z, stated)
    g.update()
    est = g.optimize_batch()
    scale, inliers = variance_factor(est, g.edges, 1.0, GraphConfig())
    assert 0.8 * real_scale < scale < 1.2 * real_scale
    assert inliers.mean() > 0.95


def test_a_loose_factor_between_tight_ones_falls_back_to_qr_instead_of_raising() -> None:
    """GTSAM's Cholesky refuses a chain whose factor information spans ~7 orders of magnitude (a wheel
    fallback's loose factor among millimetre registrations: fhw, acapulco, orebro raised
    IndeterminateSystemException); the graph switches to QR and still solves, with the loose factor's
    uncertainty in the marginals."""
    g = PoseGraph()
    g.add_pose(np.zeros(3))
    g.add_prior(0, np.zeros(3), np.diag([1e-6, 1e-6, 1e-8]))
    for k in range(1, 40):
        g.add_pose(np.array([0.5 * k, 0.0, 0.0]))
        cov = np.diag([1e-7, 1e-7, 1e-8]) if k != 20 else np.diag([4.0, 4.0, 1.0])
        g.add_between("odometry", k - 1, k, np.array([0.5, 0.0, 0.0]), cov)
        g.update()
    assert g.factorization == "QR"
    # the relative covariances work on the QR graph too: across the loose factor metres, past it millimetres
    rel = g.relative_covs_body([19, 21], 39)
    assert rel[0, 0, 0] > 1.0 > 1e-4 > rel[1, 0, 0]
    est = g.optimize_batch()
    np.testing.assert_allclose(est[-1], [19.5, 0.0, 0.0], atol=1e-6)
    marg = g.marginals_body()
    assert np.all(np.linalg.eigvalsh(marg) > 0)
    assert marg[19, 0, 0] < 1e-4 < 1.0 < marg[20, 0, 0]  # the loose factor's 2 m shows after it


def _chain(prior_cov: np.ndarray, closure_cov: np.ndarray | None) -> tuple[PoseGraph, np.ndarray, np.ndarray]:
    """A curved six-step chain (increments of different noise), optionally one exact closure 1 -> 5."""
    inc = np.array([[1.0, 0.1, 0.3], [0.8, -0.2, 0.5], [1.2, 0.0, -0.4], [0.5, 0.3, 0.9], [1.0, 0.0, 0.2]])
    covs = np.stack([np.diag([0.05 * (i + 1), 0.03, 0.01 * (i + 1)]) ** 2 for i in range(len(inc))])
    poses = se2.chain(np.array([2.0, -1.0, 0.4]), inc)
    g = PoseGraph()
    for p in poses:
        g.add_pose(p)
    g.add_prior(0, poses[0], prior_cov)
    for i in range(len(inc)):
        g.add_between("odometry", i, i + 1, inc[i], covs[i])
    if closure_cov is not None:
        g.add_between("loop", 1, 5, se2.between(poses[1], poses[5]), closure_cov)
    g.update()
    return g, inc, covs


def test_relative_covariance_is_the_chain_between_the_two_keyframes() -> None:
    """Without a loop, the uncertainty of the relative pose 1 -> 4 is that of the odometry between them
    (compounded in 4's frame), whatever the prior on the first pose; the sum of the two marginals, which
    ignores their correlation, is larger."""
    tight, inc, covs = _chain(np.diag([1e-6, 1e-6, 1e-8]) ** 2, None)
    loose, _, _ = _chain(np.diag([5.0, 5.0, 1.0]) ** 2, None)
    # the chain 1 -> 4 anchored exactly at 1: its last marginal is the relative covariance
    anchored = PoseGraph()
    poses = se2.chain(np.zeros(3), inc[1:4])
    for p in poses:
        anchored.add_pose(p)
    anchored.add_prior(0, poses[0], np.diag([1e-9, 1e-9, 1e-11]) ** 2)
    for i in range(3):
        anchored.add_between("odometry", i, i + 1, inc[1 + i], covs[1 + i])
    anchored.update()
    expected = anchored.marginal_body(3)
    for g in (tight, loose):
        np.testing.assert_allclose(g.relative_covs_body([1], 4)[0], expected, rtol=1e-5, atol=1e-12)
    summed = se2.rotate_cov_to_body(
        loose.estimate_of(4),
        se2.rotate_cov_to_world(loose.estimate_of(1), loose.marginal_body(1))
        + se2.rotate_cov_to_world(loose.estimate_of(4), loose.marginal_body(4)),
    )
    assert np.linalg.eigvalsh(summed - expected).min() > 0


def test_relative_covariance_fuses_a_closure_with_the_chain() -> None:
    """A closure 1 -> 5 with covariance C and the chain's P measure the same relative pose (5's frame):
    the joint marginal gives (P^-1 + C^-1)^-1."""
    closure = np.diag([0.02, 0.04, 0.005]) ** 2
    open_chain, _, _ = _chain(np.diag([5.0, 5.0, 1.0]) ** 2, None)
    closed, _, _ = _chain(np.diag([5.0, 5.0, 1.0]) ** 2, closure)
    p = open_chain.relative_covs_body([1], 5)[0]
    fused = np.linalg.inv(np.linalg.inv(p) + np.linalg.inv(closure))
    np.testing.assert_allclose(closed.relative_covs_body([1, 3], 5)[0], fused, rtol=1e-5, atol=1e-12)
    # one joint marginal for several keyframes gives each pair what a call of its own gives
    np.testing.assert_allclose(
        closed.relative_covs_body([1, 3], 5)[1], closed.relative_covs_body([3], 5)[0], rtol=1e-9, atol=1e-15
    )


def test_one_keyframes_estimate_equals_its_row_of_the_whole_estimate() -> None:
    """An incremental update leaves the whole estimate to be computed when read; one keyframe's pose, read
    before it, is the same value to the bit, through a closure and a relinearisation too."""
    g = PoseGraph()
    g.add_pose(SQUARE[0])
    g.add_prior(0, SQUARE[0], PRIOR_COV)
    for i, p in enumerate(_perturbed()[1:], start=1):
        g.add_pose(p)
        g.add_between("odometry", i - 1, i, np.array([2.0, 0.0, np.pi / 2]), ODO_COV)
        g.update()
        one = [g.estimate_of(k) for k in range(i + 1)]
        np.testing.assert_array_equal(np.stack(one), g.estimate())
    g.add_between("loop", 4, 1, np.array([2.0, 0.0, np.pi / 2]), ODO_COV)
    g.update(extra_iterations=1)
    last = g.estimate_of(4)
    np.testing.assert_array_equal(last, g.estimate()[4])
    assert np.allclose(g.optimize_batch()[4], SQUARE[4], atol=1e-6)
