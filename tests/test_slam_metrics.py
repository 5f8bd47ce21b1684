"""SLAM metrics: ATE after SE(2) alignment, the relations error (checked by hand), NEES, stamp matching."""

from __future__ import annotations

import numpy as np
import pytest

from slam import geometry as se2
from slam import metrics


def test_relations_errors_by_hand() -> None:
    p1 = np.array([[1.0, 2.0, np.pi / 2], [0.0, 0.0, 0.0], [0.0, 0.0, np.pi]])
    p2 = np.array([[1.0, 4.0, np.pi / 2 + 0.1], [3.0, 4.0, 0.0], [-1.0, 0.0, -np.pi + 0.2]])
    # by hand: the estimated relative poses are (2, 0, 0.1), (3, 4, 0) and (1, 0, 0.2)
    np.testing.assert_allclose(se2.between(p1, p2), [[2, 0, 0.1], [3, 4, 0], [1, 0, 0.2]], atol=1e-12)
    relations = np.array([[2.1, 0.0, 0.05], [3.0, 4.0, 0.0], [1.0, 0.3, 0.2 - 2 * np.pi]])
    err = metrics.relation_errors(p1, p2, relations)
    np.testing.assert_allclose(err.trans_m, [0.1, 0.0, 0.3], atol=1e-12)
    np.testing.assert_allclose(err.rot_deg, [np.degrees(0.05), 0.0, 0.0], atol=1e-9)  # yaw wraps
    d = err.as_dict()
    assert d["count"] == 3
    assert d["trans_mean_m"] == pytest.approx(0.4 / 3)
    assert d["trans_std_m"] == pytest.approx(np.sqrt(0.1 / 3 - (0.4 / 3) ** 2))
    assert d["rot_mean_deg"] == pytest.approx(np.degrees(0.05) / 3)
    assert metrics.relation_errors(p1[:0], p2[:0], relations[:0]).as_dict()["trans_mean_m"] is None


def test_ate_is_invariant_to_a_rigid_motion_and_measures_the_rest() -> None:
    rng = np.random.default_rng(0)
    ref = np.column_stack([rng.uniform(-20, 20, 500), rng.uniform(-20, 20, 500), rng.uniform(-3, 3, 500)])
    moved = se2.compose(np.array([5.0, -3.0, 1.2]), ref)
    assert metrics.ate_rmse(moved, ref) == pytest.approx(0.0, abs=1e-9)
    # a known residual: +-0.1 m along x alternating (zero mean, no rotation to absorb) -> RMSE 0.1
    noisy = ref.copy()
    noisy[:, 0] += np.where(np.arange(500) % 2 == 0, 0.1, -0.1)
    moved_noisy = se2.compose(np.array([5.0, -3.0, 1.2]), noisy)
    assert metrics.ate_rmse(moved_noisy, ref) == pytest.approx(0.1, rel=0.02)
    with pytest.raises(ValueError, match="matched"):
        metrics.ate_rmse(ref[:3], ref[:4])


def test_nees_of_consistent_errors_averages_three() -> None:
    rng = np.random.default_rng(1)
    n = 4000
    truth = np.column_stack([rng.uniform(-5, 5, n), rng.uniform(-5, 5, n), rng.uniform(-3, 3, n)])
    a = rng.normal(size=(n, 3, 3)) * [0.1, 0.1, 0.02]
    cov = a @ np.swapaxes(a, 1, 2) + np.eye(3) * 1e-4
    err = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=(n, 3)))
    est = truth + err
    est[0] = truth[0]  # the anchor
    cov[0] = np.eye(3) * 1e-9
    values = metrics.nees(est, cov, truth)
    assert np.mean(values[1:]) == pytest.approx(3.0, rel=0.08)
    # errors twice as large as the covariance says: NEES about 12
    est2 = truth + 2 * err
    est2[0] = truth[0]
    values2 = metrics.nees(est2, cov, truth)
    assert np.mean(values2[1:]) == pytest.approx(12.0, rel=0.08)


def test_nees_anchors_the_reference_on_the_first_pose() -> None:
    truth = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    est = se2.compose(np.array([10.0, 5.0, 0.5]), truth)  # the same trajectory in another frame
    cov = np.tile(np.eye(3) * 1e-4, (3, 1, 1))
    np.testing.assert_allclose(metrics.nees(est, cov, truth), 0.0, atol=1e-12)


def test_index_at_stamps() -> None:
    stamps = np.array([0, 100, 200, 300], dtype=np.int64)
    q = np.array([-5, 49, 51, 160, 301, 400], dtype=np.int64)
    np.testing.assert_array_equal(metrics.index_at_stamps(stamps, q, 10), [0, -1, -1, -1, 3, -1])
    np.testing.assert_array_equal(metrics.index_at_stamps(stamps, q, 60), [0, 0, 1, 2, 3, -1])


def test_loop_closure_precision_and_recall() -> None:
    """An out-and-back corridor: keyframes 0-10 go out 10 m, 11-21 come back; every way back passes the
    way out. Two closures, one right and one 1 m off; revisits are the keyframes 20 m or more of travel
    after a keyframe within 2 m of them."""
    x = np.r_[np.arange(11.0), 10.0 - np.arange(1, 11.0)]
    ref = np.column_stack([x, np.zeros(21), np.r_[np.zeros(11), np.full(10, np.pi)]])
    path = np.arange(21.0)
    rel_true = se2.between(ref[[2, 1]], ref[[18, 19]])
    rel = rel_true.copy()
    rel[1, 0] += 1.0
    out = metrics.loop_closure_scores(ref, path, np.array([18, 19]), np.array([2, 1]), rel, 10.0)
    assert out["accepted"] == 2 and out["correct"] == 1 and out["precision"] == 0.5
    # revisits: keyframes 14..20 (x = 6..0, within 2 m of a keyframe 10 m or more of travel back);
    # covered: 16..20, within 2 m of travel of the correct closure's query keyframe 18
    assert out["revisit_keyframes"] == 7
    assert out["covered_revisits"] == 5 and out["recall"] == pytest.approx(5 / 7)
    none = metrics.loop_closure_scores(ref, path, np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3)), 10.0)
    assert none["precision"] is None and none["recall"] == 0.0


def test_loop_closures_judged_by_the_relations_that_join_their_places() -> None:
    """A loop of 40 scans (keyframes every 4th): the relations are exact, some a few scans off the
    keyframes (the odometry, here exact, bridges them), one stored in the reverse order. A closure is judged
    by the nearest relation within the bridge; a right one is correct, one 0.5 m or 3 deg off is wrong, and
    one no relation reaches is not judged."""
    ang = np.linspace(0.0, 2.0 * np.pi, 40, endpoint=False)
    truth = np.column_stack([5.0 * np.cos(ang), 5.0 * np.sin(ang), ang + np.pi / 2])
    keyframes = np.arange(0, 40, 4)
    pairs = np.array([[1, 37], [6, 30], [22, 9]])  # scans: near keyframes 0 / 9, 1 / 7, 2 / 6 (reversed)
    relations = se2.between(truth[pairs[:, 0]], truth[pairs[:, 1]])
    query, target = np.array([9, 7, 6, 8]), np.array([0, 1, 2, 3])
    closures = se2.between(truth[keyframes[target]], truth[keyframes[query]])
    closures[1, 1] += 0.5  # half a metre off
    closures[2, 2] += np.radians(3.0)  # three degrees off
    out = metrics.closures_against_relations(
        keyframes, truth, query, target, closures, (pairs[:, 0], pairs[:, 1]), relations, bridge_scans=3
    )
    assert out["judged"] == 3 and out["correct"] == 1 and out["precision"] == pytest.approx(1 / 3)
    by_query = {w["query_keyframe"]: w for w in out["wrong"]}
    assert sorted(by_query) == [6, 7]
    assert by_query[7]["error_m"] == pytest.approx(0.5) and by_query[7]["error_deg"] == pytest.approx(
        0.0, abs=1e-9
    )
    assert by_query[6]["error_deg"] == pytest.approx(3.0) and by_query[6]["error_m"] == pytest.approx(
        0.0, abs=1e-9
    )
    # a bridge of one scan reaches only the first relation (one scan from each keyframe)
    narrow = metrics.closures_against_relations(
        keyframes, truth, query, target, closures, (pairs[:, 0], pairs[:, 1]), relations, bridge_scans=1
    )
    assert narrow["judged"] == 1 and narrow["correct"] == 1
    none = metrics.closures_against_relations(
        keyframes,
        truth,
        np.zeros(0, int),
        np.zeros(0, int),
        np.zeros((0, 3)),
        (pairs[:, 0], pairs[:, 1]),
        relations,
    )
    assert none["judged"] == 0 and none["precision"] is None and none["wrong"] == []


def test_reference_noise_is_the_jitter_of_a_reference_against_a_smooth_odometry() -> None:
    """A straight drive, the odometry exact, the reference with 1 cm / 0.3 deg of white noise per pose:
    the estimate recovers that noise (the step differences carry two poses' noise each)."""
    rng = np.random.default_rng(4)
    n = 4000
    odo = np.column_stack([np.arange(n) * 0.05, np.zeros(n), np.zeros(n)])
    ref = odo + rng.normal(0.0, 1.0, (n, 3)) * [0.01, 0.01, np.radians(0.3)]
    sxy, sth = metrics.reference_noise_sigma(ref, odo)
    assert sxy == pytest.approx(0.01, rel=0.1)
    assert np.degrees(sth) == pytest.approx(0.3, rel=0.1)
    assert metrics.reference_noise_sigma(odo, odo) == (0.0, 0.0)


def test_the_scans_dispute_a_relation_that_is_wrong_and_back_one_that_is_right() -> None:
    """The loop of the test above in a 14 m square room, each scan the room's walls in its own frame. A
    closure 3 deg off an exact relation: wrong, and the relation's scans overlap more at the relation's pose
    (not disputed). An exact closure judged by a relation 3 deg off: wrong, but the scans overlap more at the
    closure's pose (disputed). Without scan points nothing is disputed or measured."""
    ang = np.linspace(0.0, 2.0 * np.pi, 40, endpoint=False)
    truth = np.column_stack([5.0 * np.cos(ang), 5.0 * np.sin(ang), ang + np.pi / 2])
    side = np.linspace(-7.0, 7.0, 281)
    walls = np.concatenate(
        [np.column_stack([side, np.full_like(side, c)]) for c in (-7.0, 7.0)]
        + [np.column_stack([np.full_like(side, c), side]) for c in (-7.0, 7.0)]
    )

    def scan_points(i: int) -> np.ndarray:
        return se2.transform_points(se2.inverse(truth[i]), walls)

    keyframes = np.arange(0, 40, 4)
    pairs = np.array([[1, 37], [6, 30]])  # near keyframes 0 / 9 and 1 / 7
    relations = se2.between(truth[pairs[:, 0]], truth[pairs[:, 1]])
    relations[1, 2] += np.radians(3.0)  # the second relation is wrong
    query, target = np.array([9, 7]), np.array([0, 1])
    closures = se2.between(truth[keyframes[target]], truth[keyframes[query]])
    closures[0, 2] += np.radians(3.0)  # the first closure is wrong
    args = (keyframes, truth, query, target, closures, (pairs[:, 0], pairs[:, 1]), relations)
    out = metrics.closures_against_relations(*args, bridge_scans=3, scan_points=scan_points)
    assert out["judged"] == 2 and out["correct"] == 0 and out["disputed"] == 1
    by_query = {w["query_keyframe"]: w for w in out["wrong"]}
    assert not by_query[9]["disputed"] and by_query[9]["overlap_at_relation"] == pytest.approx(1.0)
    assert by_query[9]["overlap_at_closure"] < 0.5
    assert by_query[7]["disputed"] and by_query[7]["overlap_at_closure"] == pytest.approx(1.0)
    assert by_query[7]["overlap_at_relation"] < 0.5
    plain = metrics.closures_against_relations(*args, bridge_scans=3)
    assert plain["disputed"] is None and all("disputed" not in w for w in plain["wrong"])


def test_scan_overlap_counts_query_points_near_the_target() -> None:
    """Half of the query's points land on the target's at the right pose; none 1 m off; an empty scan
    overlaps nothing."""
    target = np.column_stack([np.linspace(0.0, 1.0, 11), np.zeros(11)])
    query = np.vstack([target, target + np.array([0.0, 3.0])])
    assert metrics.scan_overlap(target, query, np.zeros(3)) == pytest.approx(0.5)
    assert metrics.scan_overlap(target, query, np.array([0.0, 1.0, 0.0])) == 0.0
    assert metrics.scan_overlap(target, np.zeros((0, 2)), np.zeros(3)) == 0.0
