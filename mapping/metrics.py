"""Map metrics: the ROC curve and the area under it (paper section 4.1.1, Table 1), and the log loss.

AUC ranks: it asks whether occupied test points score above free ones, and ignores what the probabilities
say. The log loss (mean negative log-likelihood of the labels) is a proper scoring rule: it rewards a map
that is uncertain where it does not know and punishes one that is confidently wrong, which is what the map's
variance and the PLS link are for."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.stats import rankdata

FloatArray = NDArray[np.float64]


def _check(scores: NDArray, labels: NDArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    s = np.asarray(scores, dtype=np.float64).ravel()
    y = np.asarray(labels).ravel().astype(bool)
    if s.shape != y.shape:
        raise ValueError(f"{s.shape[0]} scores but {y.shape[0]} labels")
    if not np.all(np.isfinite(s)):
        raise ValueError("scores must be finite")
    if y.all() or not y.any():
        raise ValueError("ROC needs both positive and negative labels")
    return s, y


def roc_auc(scores: NDArray, labels: NDArray) -> float:
    """Area under the ROC curve of ``scores`` (higher = more likely positive) for boolean ``labels``:
    the probability that a random positive scores above a random negative, ties counting one half
    (Mann-Whitney U / (n_pos n_neg), computed from average ranks in O(n log n))."""
    s, y = _check(scores, labels)
    ranks = rankdata(s)  # average ranks for ties
    n_pos = int(y.sum())
    n_neg = y.size - n_pos
    u = ranks[y].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))


def auc_shortfall_per_point(scores: NDArray, labels: NDArray) -> FloatArray:
    """(T,) each point's part of ``1 - AUC`` (:func:`roc_auc`): an occupied point's is the share of the free
    points scoring at or above it (ties one half) over the number of occupied points, a free point's the
    share of occupied points at or below it over the number of free points. The occupied points' parts sum
    to ``1 - AUC``, and so do the free points'; summed over a subset (e.g. the test points at some
    distance from the map's returns), they say how much of the AUC's shortfall falls there, against every
    other point of the other label (an AUC within the subset only compares the subset's points)."""
    s, y = _check(scores, labels)
    ranks = rankdata(s)
    n_pos = int(y.sum())
    n_neg = y.size - n_pos
    out = np.empty(y.size)
    # among all points, an occupied point's average rank counts the free points below it (ties one half)
    # on top of its rank among the occupied points; likewise for a free point
    below = ranks[y] - rankdata(s[y])
    out[y] = (1.0 - below / n_neg) / n_pos
    above = n_pos - (ranks[~y] - rankdata(s[~y]))
    out[~y] = (1.0 - above / n_pos) / n_neg
    return out


def roc_curve(scores: NDArray, labels: NDArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """False- and true-positive rates at every distinct threshold (from +inf down), with the thresholds.

    Returns ``fpr``, ``tpr`` (both start at 0 and end at 1) and ``thresholds`` (``score >= threshold`` is
    called positive). The trapezoidal area under (fpr, tpr) equals :func:`roc_auc`."""
    s, y = _check(scores, labels)
    order = np.argsort(-s, kind="stable")
    s, y = s[order], y[order]
    last = np.r_[np.flatnonzero(np.diff(s)), s.size - 1]  # last index of every distinct score
    tp = np.cumsum(y)[last]
    fp = (last + 1) - tp
    tpr = np.r_[0.0, tp / y.sum()]
    fpr = np.r_[0.0, fp / (~y).sum()]
    thresholds = np.r_[np.inf, s[last]]
    return fpr, tpr, thresholds


def fpr_at_tpr(fpr: FloatArray, tpr: FloatArray, target_tpr: float = 0.95) -> float:
    """False-positive rate when the true-positive rate first reaches ``target_tpr`` (paper Table 1)."""
    i = int(np.searchsorted(tpr, target_tpr, side="left"))
    return float(fpr[min(i, fpr.size - 1)])


#: Probabilities are clipped to [LOG_LOSS_CLIP, 1 - LOG_LOSS_CLIP] in :func:`log_loss` (a map that says 0 or 1
#: would otherwise cost infinity for one wrong point).
LOG_LOSS_CLIP = 1e-3


def log_loss(probabilities: NDArray, labels: NDArray) -> float:
    """Mean negative log-likelihood (nats) of boolean ``labels`` under ``probabilities`` of the positive
    class, clipped to [1e-3, 1 - 1e-3]: 0.693 for a map that says 0.5 everywhere, lower is better."""
    p = np.asarray(probabilities, dtype=np.float64).ravel()
    y = np.asarray(labels).ravel().astype(bool)
    if p.shape != y.shape:
        raise ValueError(f"{p.shape[0]} probabilities but {y.shape[0]} labels")
    if p.size == 0 or not np.all(np.isfinite(p)):
        raise ValueError("log loss needs finite probabilities")
    p = np.clip(p, LOG_LOSS_CLIP, 1.0 - LOG_LOSS_CLIP)
    return float(-np.mean(np.where(y, np.log(p), np.log1p(-p))))
