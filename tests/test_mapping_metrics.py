"""ROC / AUC against the brute-force pairwise definition."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.metrics import fpr_at_tpr, roc_auc, roc_curve


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
