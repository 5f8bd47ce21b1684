"""The PLS link fitted on held-out scans: the split, the labelled points, the fit, and on a real
log that it predicts an independent hold-out split better than the leave-one-out link."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy import special

from datasets import open_dataset
from mapping.beams import beams_from_scans
from mapping.build import MapBuilder
from mapping.calibration import beam_test_points, holdout_link, inner_holdout
from mapping.config import MappingConfig
from mapping.kernels import make_kernel
from mapping.pls import capped_mean
from mapping.train import GPParams
from tests.conftest import data_file


def test_inner_holdout_takes_whole_blocks() -> None:
    ids = np.arange(500) * 3  # ids need not be consecutive integers
    held = inner_holdout(ids, fraction=0.1, block=10, seed=4)
    assert held.size == 50 and np.all(np.diff(held) > 0) and np.isin(held, ids).all()
    pos = np.searchsorted(ids, held)
    # five runs of ten consecutive scans
    runs = np.split(pos, np.flatnonzero(np.diff(pos) > 1) + 1)
    assert sum(len(r) for r in runs) == 50 and all(len(r) % 10 == 0 for r in runs)
    assert inner_holdout(np.arange(19), block=10).size == 0  # fewer than two blocks: none
    assert inner_holdout(np.arange(30), fraction=0.01, block=10).size == 10  # at least one block


def test_beam_test_points_label_ends_and_free_segments() -> None:
    a = np.linspace(-0.5, 0.5, 5)
    ranges = [np.array([4.0, 4.0, np.inf, 4.0, 0.01])]
    kw = {"no_return_free_length_m": 2.0, "free_margin_m": 0.1}
    b = beams_from_scans(ranges, [a], 0.1, 10.0, np.zeros((1, 3)), **kw)
    pts, y = beam_test_points(b, free_per_m=1.0)
    assert (y > 0).sum() == 3  # the three returns; the no-return and the dropped beam have no endpoint
    # free points: int(1 * L) per free segment (3.9 m for returns, 2 m for the no-return)
    assert (y < 0).sum() == 3 * 3 + 2
    occ = pts[y > 0]
    np.testing.assert_allclose(np.hypot(*occ.T), 4.0)
    free = pts[y < 0]
    assert np.all(np.hypot(*free.T) <= 3.9 + 1e-12)
    few, y_few = beam_test_points(b, free_per_m=1.0, max_points=4)
    assert few.shape == (4, 2) and y_few.shape == (4,)


def test_unseen_probability_is_the_link_at_the_prior() -> None:
    se = make_kernel("se", {"sigma_f": 0.5, "length_scale": 0.3})  # k(x, x) = 0.25
    assert GPParams(se, 0.25, 3.0, 0.0).unseen_probability == pytest.approx(0.5)
    p = GPParams(se, 0.25, 2.0, -1.0).unseen_probability
    assert p == pytest.approx(special.ndtr(-1.0 / np.sqrt(1 + 4 * (0.25 + 0.25))))
    assert GPParams(se, 0.25, 2.0, -1.0).to_dict()["unseen_probability"] == p


@dataclass
class _Pred:
    mean: np.ndarray
    variance: np.ndarray


class _DistanceMap:
    """A stand-in map: mean +1 within 0.05 m of a wall at x = 5, -1 elsewhere (free segments stop 0.1 m
    short of it), variance 0.01."""

    def __init__(self, beams) -> None:
        self.n_beams = beams.origins_xy_m.shape[0]

    def query(self, points, sort=True):
        x = points[:, 0]
        mean = np.where(np.abs(x - 5.0) < 0.05, 1.0, -1.0)
        var = np.full(x.shape, 0.01)
        return _Pred(mean, var)


def test_holdout_link_fits_on_held_out_beams_only() -> None:
    n = 60
    a = np.linspace(-0.3, 0.3, 7)
    poses = np.column_stack([np.zeros(n), np.linspace(-1, 1, n), np.zeros(n)])
    ranges = [5.0 / np.cos(a) for _ in range(n)]
    b = beams_from_scans(ranges, [a] * n, 0.1, 20.0, poses, free_margin_m=0.1)
    seen = []

    def build(rest):
        seen.append(np.unique(rest.scan_index))
        return _DistanceMap(rest)

    alpha, beta, mean_cap, used = holdout_link(b, build, fraction=0.2, block=5, seed=1)
    held = inner_holdout(b.scan_index, 0.2, 5, 1)
    assert used["held_out_scans"] == held.size == 10
    assert not np.isin(seen[0], held).any() and seen[0].size == n - held.size  # the map never saw them
    # the stand-in separates the labels perfectly: a steep link, and the endpoint share of the points
    assert alpha > 5 and used["occupied_points"] == 10 * 7
    assert mean_cap is None or mean_cap >= 1.0  # the stand-in's labels are +-1 exactly
    p_wall = special.ndtr((alpha + beta) / np.sqrt(1 + alpha**2 * 0.01))
    p_free = special.ndtr((-alpha + beta) / np.sqrt(1 + alpha**2 * 0.01))
    assert p_wall > 0.99 and p_free < 0.01
    assert holdout_link(b.select_scans(np.arange(9)), build) is None  # too few scans to hold any out


def _log_lik(params, mean: np.ndarray, var: np.ndarray, y: np.ndarray) -> float:
    m = capped_mean(mean, params.mean_cap)
    return float(
        np.mean(special.log_ndtr(y * (params.alpha * m + params.beta) / np.sqrt(1 + params.alpha**2 * var)))
    )


@pytest.mark.slow
def test_holdout_link_predicts_unseen_scans_better_than_loo_on_a_real_log() -> None:
    """Seattle (241 scans, 2 % of the protocol's test points unobserved): the link fitted on held-out scans of
    the first 200 scans scores the last 41 scans' beams (never mapped, never used in a fit) better than the
    leave-one-out link of the same hyperparameters."""
    rec = open_dataset(data_file("radish-corrected/seattle-corrected.log.gz"))
    poses = np.asarray(rec.reference.poses_xytheta)
    loo_cfg = MappingConfig(mapper="gpfol")
    hold_cfg = MappingConfig(mapper="gpfol", pls={"link": "holdout"})
    loo_builder, hold_builder = MapBuilder.from_config(loo_cfg), MapBuilder.from_config(hold_cfg)
    train = loo_builder.beams(rec.scans, poses, rec.laser_in_base_xytheta, np.arange(200))
    test = loo_builder.beams(rec.scans, poses, rec.laser_in_base_xytheta, np.arange(200, len(rec.scans)))
    loo = loo_builder.fit(train)
    hold = hold_builder.fit(train)
    assert loo.kernel.as_dict() == hold.kernel.as_dict()  # the same hyperparameters, another link
    assert hold.info["pls"]["fit"] == "holdout" and hold.info["pls"]["held_out_scans"] == 20
    assert hold.info["pls"]["loo"] == {"alpha": loo.alpha, "beta": loo.beta, "mean_cap": loo.mean_cap}
    assert 0 < hold.unseen_probability < 1 and 0 < loo.unseen_probability < 1
    pts, y = beam_test_points(test, seed=3)
    pred = loo_builder.gp_map(train, loo).query(pts)
    ll_loo = _log_lik(loo, pred.mean, pred.variance, y)
    ll_hold = _log_lik(hold, pred.mean, pred.variance, y)
    assert ll_hold > ll_loo, (ll_hold, ll_loo)
