"""The PLS link fitted on held-out beams: the probability of space far from the data, learnt from the data.

The paper fits the link ``p = Phi((alpha mu + beta) / sqrt(1 + alpha^2 var))`` (eqs. 10-12, R&W eq. 6.42) by
leave-one-out on the training points themselves. Every one of them lies on the data, where the variance is
small, so the fit says nothing about queries whose neighbourhoods are far: there ``mu -> 0`` and
``var -> sigma_f^2`` (the prior), and ``p`` lands wherever ``beta / sqrt(1 + alpha^2 sigma_f^2)`` happens to
put it (~0.5; above the walls the map did see, on the buildings where a fifth to a third of the hold-out
protocol's test points lie in unobserved cells).

Here the link is fitted as a classifier is calibrated: on predictions for data the map has not seen. Blocks of
scans are held out of the mapped scans (:func:`inner_holdout`); a map built from the rest predicts ``mu,
var`` along the held-out beams (their endpoints occupied, points along their free segments free:
:func:`beam_test_points`, the labels of the hold-out protocol of SPEC section 6); alpha and beta maximise the
likelihood of those labels (:func:`mapping.pls.fit_pls`). Held-out beams reach space the rest never saw as
often as a new scan does, so far, high-variance queries take part in the fit in their real proportion, and
the level the map gives unseen space (``GPParams.unseen_probability``) is the one the data support.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from mapping.beams import Beams
from mapping.pls import fit_pls

FloatArray = NDArray[np.float64]


class _Prediction(Protocol):
    mean: FloatArray
    variance: FloatArray


class _Map(Protocol):
    def query(self, points_xy_m: FloatArray, sort: bool = ...) -> _Prediction: ...


def inner_holdout(scan_ids: NDArray, fraction: float = 0.1, block: int = 10, seed: int = 0) -> NDArray:
    """The scan ids (ascending) held out of ``scan_ids``: ``round(fraction * n / block)`` (at least one)
    blocks of ``block`` consecutive scans, at random starts from ``numpy.random.default_rng(seed)`` that do
    not overlap; none when there are fewer than ``2 * block`` scans."""
    ids = np.unique(np.asarray(scan_ids, dtype=np.int64))
    n = ids.size
    if n < 2 * block:
        return np.zeros(0, dtype=np.int64)
    blocks = max(1, round(fraction * n / block))
    rng = np.random.default_rng(seed)
    taken = np.zeros(n, dtype=bool)
    for _ in range(50 * blocks):
        if blocks == 0:
            break
        start = int(rng.integers(0, n - block + 1))
        if taken[start : start + block].any():
            continue
        taken[start : start + block] = True
        blocks -= 1
    return ids[taken]


def beam_test_points(
    beams: Beams, free_per_m: float = 0.5, max_points: int = 20_000, seed: int = 0
) -> tuple[FloatArray, FloatArray]:
    """Labelled points along ``beams``: every return's endpoint (+1) and ``max(1, int(free_per_m * L))``
    points uniformly along each beam's free part of length ``L`` (-1), as the hold-out protocol draws them;
    at most ``max_points`` (a uniform subset, endpoints and free points alike). Returns (P, 2) points and
    (P,) labels."""
    rng = np.random.default_rng(seed)
    occ = beams.ends_xy_m[beams.is_hit]
    seg = beams.free_ends_xy_m - beams.origins_xy_m
    length = np.hypot(seg[:, 0], seg[:, 1])
    ok = length > 0
    counts = np.maximum(1, (free_per_m * length[ok]).astype(np.int64))
    which = np.repeat(np.nonzero(ok)[0], counts)
    t = rng.uniform(0.0, 1.0, which.size)
    free = beams.origins_xy_m[which] + t[:, None] * seg[which]
    points = np.concatenate([occ, free])
    labels = np.concatenate([np.ones(len(occ)), -np.ones(len(free))])
    if points.shape[0] > max_points:
        keep = np.sort(rng.choice(points.shape[0], max_points, replace=False))
        points, labels = points[keep], labels[keep]
    return points, labels


def holdout_link(
    beams: Beams,
    build_map: Callable[[Beams], _Map],
    fraction: float = 0.1,
    block: int = 10,
    seed: int = 0,
) -> tuple[float, float, float | None, dict[str, Any]] | None:
    """The PLS link (alpha, beta and the mean's cap, :func:`mapping.pls.fit_pls`) fitted on predictions for
    held-out beams (module docstring).

    ``build_map(beams)`` builds the map of the remaining beams (the same mapper, hyperparameters and
    sensor model as the real map); :func:`inner_holdout` chooses the held-out scans
    (``fraction``, ``block``, ``seed``) and :func:`beam_test_points` their labelled points. Returns alpha,
    beta, the cap and what was used (``held_out_scans``, ``points``, ``occupied_points``), or None when the
    beams have too few scans to hold any out or the held-out points lack one of the two labels."""
    held = inner_holdout(beams.scan_index, fraction, block, seed)
    if held.size == 0:
        return None
    out = np.isin(beams.scan_index, held)
    points, labels = beam_test_points(beams.subset(out), seed=seed)
    if not (labels > 0).any() or not (labels < 0).any() or out.all():
        return None
    prediction = build_map(beams.subset(~out)).query(points, sort=True)
    alpha, beta, mean_cap = fit_pls(prediction.mean, prediction.variance, labels)
    used = {
        "held_out_scans": int(held.size),
        "points": int(labels.size),
        "occupied_points": int((labels > 0).sum()),
    }
    return alpha, beta, mean_cap, used
