"""ROC / AUC against the brute-force pairwise definition."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.metrics import auc_shortfall_per_point, fpr_at_tpr, roc_auc, roc_curve


def brute_auc(scores, labels) -> float:
    pos = scores[labels]
    neg = scores[~labels]
    diff = pos[:, None] - neg[None, :]
    return float(((diff > 0).sum() + 0.5 * (diff == 0).sum()) / diff.size)


@pytest.mark.parametrize("seed", range(5))
def test_auc_equals_pairwise_definition(seed: int) -> None:
    rng = np.random.default_rng(seed)
    labels = rng.random(300) < 0.4
    scores = np.round(rng.normal(size=300) + labels * rng.uniform(0, 2), 1)  # rounded: many ties
    assert roc_auc(scores, labels) == pytest.approx(brute_auc(scores, labels), abs=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_auc_shortfall_per_point_is_each_points_lost_pairs(seed: int) -> None:
    """Each point's part of 1 - AUC is its pairs with the other label that are ranked wrongly (ties one
    half) over all pairs; each label's parts sum to 1 - AUC."""
    rng = np.random.default_rng(seed)
    labels = rng.random(200) < 0.35
    scores = np.round(rng.normal(size=200) + labels * rng.uniform(0, 2), 1)  # many ties
    lost = auc_shortfall_per_point(scores, labels)
    pos, neg = scores[labels], scores[~labels]
    wrong = (pos[:, None] < neg[None, :]) + 0.5 * (pos[:, None] == neg[None, :])  # (P, N) lost pairs
    pairs = wrong.size
    np.testing.assert_allclose(lost[labels], wrong.sum(axis=1) / pairs, atol=1e-12)
    np.testing.assert_allclose(lost[~labels], wrong.sum(axis=0) / pairs, atol=1e-12)
    auc = roc_auc(scores, labels)
    assert lost[labels].sum() == pytest.approx(1 - auc, abs=1e-12)
    assert lost[~labels].sum() == pytest.approx(1 - auc, abs=1e-12)
    assert np.all(lost >= 0)
    # a perfect ranking loses nothing; one occupied point below every free point loses all its pairs
    perfect = auc_shortfall_per_point(np.r_[0.9, 0.8, 0.1, 0.2], np.array([True, True, False, False]))
    np.testing.assert_array_equal(perfect, 0.0)
    one = auc_shortfall_per_point(np.r_[0.9, 0.0, 0.1, 0.2], np.array([True, True, False, False]))
    np.testing.assert_allclose(one, [0.0, 0.5, 0.25, 0.25])
    with pytest.raises(ValueError):
        auc_shortfall_per_point(np.r_[0.1, 0.2], np.array([True, True]))


def test_curve_area_equals_auc_and_endpoints() -> None:
    rng = np.random.default_rng(9)
    labels = rng.random(500) < 0.3
    scores = np.round(rng.normal(size=500) + labels, 2)
    fpr, tpr, thr = roc_curve(scores, labels)
    assert (fpr[0], tpr[0], fpr[-1], tpr[-1]) == (0.0, 0.0, 1.0, 1.0)
    assert np.all(np.diff(fpr) >= 0) and np.all(np.diff(tpr) >= 0) and np.all(np.diff(thr) < 0)
    area = float(np.sum(np.diff(fpr) * (tpr[1:] + tpr[:-1]) / 2))
    assert area == pytest.approx(roc_auc(scores, labels), abs=1e-12)


def test_perfect_inverted_and_constant_scores() -> None:
    labels = np.array([0, 0, 1, 1], bool)
    assert roc_auc(np.array([0.1, 0.2, 0.8, 0.9]), labels) == 1.0
    assert roc_auc(np.array([0.9, 0.8, 0.2, 0.1]), labels) == 0.0
    assert roc_auc(np.full(4, 0.5), labels) == 0.5
    fpr, tpr, _ = roc_curve(np.array([0.1, 0.2, 0.8, 0.9]), labels)
    assert fpr_at_tpr(fpr, tpr, 0.95) == 0.0


def test_bad_inputs() -> None:
    with pytest.raises(ValueError, match="both positive and negative"):
        roc_auc(np.array([0.1, 0.2]), np.array([True, True]))
    with pytest.raises(ValueError, match="finite"):
        roc_auc(np.array([np.nan, 0.2]), np.array([True, False]))
    with pytest.raises(ValueError, match="labels"):
        roc_auc(np.array([0.1, 0.2, 0.3]), np.array([True, False]))
