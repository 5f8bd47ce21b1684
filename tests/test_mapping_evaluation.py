"""The hold-out protocol of SPEC section 6, exactly as written."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from mapping.beams import beams_from_scans
from mapping.evaluation import (
    HIT_COUNT_EDGES,
    NEAREST_HIT_EDGES_M,
    auc_by_bins,
    ground_truth_auc_over,
    hits_within,
    holdout_split,
    holdout_test_points,
    is_carmen_180,
    nearest_hit_m,
    observed_cells,
    pass_masks,
    raster_cell_centres,
    rendered_ground_truth_auc,
)
from mapping.exports import MapLayers
from mapping.metrics import auc_shortfall_per_point, roc_auc


def test_split_is_deterministic_block_structured_and_disjoint() -> None:
    a = holdout_split(910, 3)
    assert a == holdout_split(910, 3)
    assert a != holdout_split(910, 4)
    assert len(a) == int(910 * 0.1 / 40) * 40 == 80
    assert len(set(a)) == len(a) and a == sorted(a)
    assert all(0 <= i < 910 for i in a)
    # runs of consecutive indices are whole blocks of 40
    runs = np.split(np.asarray(a), np.flatnonzero(np.diff(a) != 1) + 1)
    assert all(len(r) % 40 == 0 for r in runs)


def test_split_follows_the_written_rule() -> None:
    """Re-derive the split with the SPEC's words for several seeds and sizes."""
    for n, seed in [(910, 0), (910, 1), (2000, 7), (4000, 2)]:
        rng = random.Random(seed)
        blocks = int(n * 0.1 / 40)
        held: list[int] = []
        while len(held) < blocks * 40:
            start = rng.randint(0, n - 40)
            if start in held or start + 40 in held:
                continue
            held.extend(range(start, start + 40))
        assert holdout_split(n, seed) == sorted(held)
        assert len(holdout_split(n, seed)) == blocks * 40


def test_too_few_scans_hold_out_nothing() -> None:
    assert holdout_split(399, 0) == []


def test_test_points_hand_count_and_labels() -> None:
    """Two held-out scans of 4 beams; ranges 0.5 (1 free point), 4.0 (2), 41 (skipped), 9.9 (4), inf, NaN."""
    ranges = [np.array([0.5, 4.0, 41.0, 9.9]), np.array([np.inf, 3.0, np.nan, 40.0]), np.array([1.0] * 4)]
    angles = [np.linspace(-np.pi / 2, np.pi / 2 * 0.5, 4)] * 3
    poses = np.array([[1.0, 2.0, 0.3], [0.0, 0.0, 0.0], [5.0, 5.0, 1.0]])
    pts, labels = holdout_test_points(ranges, angles, poses, [0, 1], seed=5, carmen_180=True)
    # scan 0: 0.5 -> 1 + 1, 4.0 -> 1 + 2, 41 skipped, 9.9 -> 1 + 4 ; scan 1: 3.0 -> 1 + 1, 40.0 -> 1 + 20
    assert labels.size == 2 + 3 + 5 + 2 + 21
    assert labels.sum() == 5
    # the first point is the endpoint of beam 0 of scan 0 at theta - pi/2 + 0 * pi / 4
    a = 0.3 - math.pi / 2
    np.testing.assert_allclose(pts[0], [1.0 + 0.5 * math.cos(a), 2.0 + 0.5 * math.sin(a)], atol=1e-12)
    assert labels[0] and not labels[1]
    # the free point of beam 0 uses the first uniform draw of Random(seed + 1)
    d = random.Random(6).uniform(0, max(0.0, 0.5 - 0.1))
    np.testing.assert_allclose(pts[1], [1.0 + d * math.cos(a), 2.0 + d * math.sin(a)], atol=1e-12)
    # free points lie on the beam before the endpoint
    again, _ = holdout_test_points(ranges, angles, poses, [0, 1], seed=5, carmen_180=True)
    np.testing.assert_array_equal(pts, again)


def test_test_points_with_their_distance_from_the_laser() -> None:
    """``with_ranges`` changes nothing else and gives each point's distance from its scan's laser."""
    ranges = [np.array([0.5, 4.0, 41.0, 9.9]), np.array([np.inf, 3.0, np.nan, 40.0])]
    angles = [np.linspace(-np.pi / 2, np.pi / 4, 4)] * 2
    poses = np.array([[1.0, 2.0, 0.3], [-3.0, 0.5, 2.0]])
    pts, labels = holdout_test_points(ranges, angles, poses, [0, 1], seed=2, carmen_180=True)
    pts2, labels2, dist = holdout_test_points(ranges, angles, poses, [0, 1], 2, True, with_ranges=True)
    np.testing.assert_array_equal(pts, pts2)
    np.testing.assert_array_equal(labels, labels2)
    # scan 0 gives the first 10 points (1 + 1, 1 + 2, 1 + 4), scan 1 the rest
    origin = np.where(np.arange(labels.size)[:, None] < 10, poses[0, :2], poses[1, :2])
    np.testing.assert_allclose(dist, np.hypot(*(pts - origin).T), atol=1e-9)
    np.testing.assert_array_equal(dist[labels], [0.5, 4.0, 9.9, 3.0, 40.0])
    assert np.all(dist[~labels] <= np.repeat(dist[labels], [1, 2, 4, 1, 20]))


def test_auc_by_bins_counts_and_scores_each_bin() -> None:
    rng = np.random.default_rng(0)
    labels = rng.random(400) < 0.3
    p = np.clip(labels * 0.4 + rng.random(400) * 0.6, 0, 1)
    values = rng.uniform(0, 10, 400)
    values[:5] = 10.0  # the last bin is closed: these count
    values[labels] = np.where(values[labels] < 2, 3.0, values[labels])  # no occupied point below 2
    rows = auc_by_bins(p, labels, values, (0.0, 2.0, 5.0, 10.0))
    assert [r["from"] for r in rows] == [0.0, 2.0, 5.0] and [r["to"] for r in rows] == [2.0, 5.0, 10.0]
    assert sum(r["test_points"] for r in rows) == 400 and sum(r["occupied"] for r in rows) == labels.sum()
    assert rows[0]["auc"] is None and rows[0]["p_occupied"] is None  # one label only
    assert rows[0]["p_free"] == pytest.approx(p[values < 2].mean())
    m = values >= 5
    assert rows[2]["auc"] == pytest.approx(roc_auc(p[m], labels[m]))
    assert rows[2]["p_occupied"] == pytest.approx(p[m & labels].mean())
    # an open-ended last bin is written without infinity (JSON has none)
    open_rows = auc_by_bins(p, labels, values, (0.0, 5.0, math.inf))
    assert open_rows[-1]["to"] is None and open_rows[-1]["test_points"] == np.sum(values >= 5)
    assert HIT_COUNT_EDGES[-1] == math.inf and NEAREST_HIT_EDGES_M[-1] == math.inf
    # the whole AUC's shortfall, split over the bins: each label's parts add up to 1 - AUC
    lost = 1 - roc_auc(p, labels)
    assert sum(r["auc_lost_occupied"] for r in rows) == pytest.approx(lost, abs=1e-12)
    assert sum(r["auc_lost_free"] for r in rows) == pytest.approx(lost, abs=1e-12)
    assert rows[0]["auc_lost_occupied"] == 0.0 and rows[0]["auc_lost_free"] > 0  # free points only there
    one_label = auc_by_bins(p[~labels], labels[~labels], values[~labels], (0.0, 5.0, 10.0))
    assert one_label[0]["auc_lost_free"] is None and one_label[0]["auc"] is None
    # the shares ranked once by the caller give the same rows
    shares = auc_shortfall_per_point(p, labels)
    assert auc_by_bins(p, labels, values, (0.0, 2.0, 5.0, 10.0), shortfall=shares) == rows


def test_nearest_hit_m_is_the_distance_to_the_nearest_endpoint() -> None:
    rng = np.random.default_rng(2)
    hits = rng.uniform(0, 5, (300, 2))
    pts = rng.uniform(-1, 6, (200, 2))
    d = np.hypot(*(pts[:, None, :] - hits[None, :, :]).transpose(2, 0, 1))
    np.testing.assert_allclose(nearest_hit_m(hits, pts), d.min(axis=1), atol=1e-12)
    assert np.all(np.isinf(nearest_hit_m(np.zeros((0, 2)), pts)))


def test_hits_within_counts_like_brute_force() -> None:
    rng = np.random.default_rng(1)
    hits = rng.uniform(0, 5, (300, 2))
    pts = rng.uniform(-1, 6, (200, 2))
    d = np.hypot(*(pts[:, None, :] - hits[None, :, :]).transpose(2, 0, 1))
    np.testing.assert_array_equal(hits_within(hits, pts, 0.7), (d <= 0.7).sum(axis=1))
    np.testing.assert_array_equal(hits_within(np.zeros((0, 2)), pts), np.zeros(200, dtype=np.int64))


def test_test_points_use_the_scans_own_angles_when_not_carmen() -> None:
    ranges = [np.array([2.0])]
    angles = [np.array([0.25])]
    pts, labels = holdout_test_points(ranges, angles, np.array([[0.0, 0.0, 0.5]]), [0], 0, carmen_180=False)
    np.testing.assert_allclose(pts[0], [2 * math.cos(0.75), 2 * math.sin(0.75)], atol=1e-12)
    assert labels.tolist() == [True, False]


def test_carmen_convention_detection() -> None:
    n = 180
    assert is_carmen_180((-np.pi / 2 + np.arange(n) * np.pi / n).astype(np.float32))
    assert not is_carmen_180(np.linspace(-np.pi / 2, np.pi / 2, n))


def test_raster_cell_centres() -> None:
    c = raster_cell_centres((2, 3), np.array([10.0, 20.0]), 0.5)
    assert c.shape == (6, 2)
    np.testing.assert_allclose(c[0], [10.25, 20.25])
    np.testing.assert_allclose(c[4], [10.75, 20.75])  # row 1, column 1
    assert c[:, 0].max() == pytest.approx(11.25)


def _field(xy: np.ndarray) -> np.ndarray:
    """A smooth p(occ)-like field, distinct at every cell of the rasters below."""
    return 0.5 + 0.4 * np.sin(1.3 * xy[:, 0] + 0.01) * np.cos(0.7 * xy[:, 1] - 0.2)


def _rendered(origin: tuple[float, float], shape: tuple[int, int], res: float) -> MapLayers:
    p = _field(raster_cell_centres(shape, np.asarray(origin), res)).reshape(shape).astype(np.float32)
    return MapLayers(p, np.zeros_like(p), np.ones_like(p), res, origin)


def test_rendered_ground_truth_auc_reads_shared_cells_and_queries_the_rest() -> None:
    """A raster on the map's lattice, half inside it: the inside cells are read from the float32 layer, the
    others queried (and only those); the AUC is the AUC of exactly those values."""
    res = 0.1
    occupancy = (np.arange(12 * 20).reshape(12, 20) % 7 == 0).astype(np.uint8)
    gt_origin = np.array([1.0, -0.5])
    rendered = _rendered((0.3, -1.2), (10, 15), res)  # covers GT columns 0..7, rows 0..2
    asked: list[np.ndarray] = []

    def query(xy: np.ndarray) -> np.ndarray:
        asked.append(xy)
        return _field(xy)

    auc = rendered_ground_truth_auc(rendered, occupancy, gt_origin, res, query)
    centres = raster_cell_centres(occupancy.shape, gt_origin, res)
    inside = (centres[:, 0] < 0.3 + 15 * res) & (centres[:, 1] < -1.2 + 10 * res)
    assert inside.sum() == 8 * 3
    assert len(asked) == 1 and asked[0].shape == ((~inside).sum(), 2)
    expected = _field(centres)
    expected[inside] = expected[inside].astype(np.float32)
    assert auc == roc_auc(expected, occupancy.astype(bool).ravel())


def test_rendered_ground_truth_auc_off_the_lattice_queries_every_cell() -> None:
    res = 0.1
    occupancy = (np.arange(6 * 9).reshape(6, 9) % 4 == 0).astype(np.uint8)
    gt_origin = np.array([0.0, 0.0])
    rendered = _rendered((-0.55, -0.55), (30, 30), res)  # half a cell off the raster's lattice
    auc = rendered_ground_truth_auc(rendered, occupancy, gt_origin, res, _field)
    centres = raster_cell_centres(occupancy.shape, gt_origin, res)
    assert auc == roc_auc(_field(centres), occupancy.astype(bool).ravel())
    # a map covering the whole raster on its lattice: nothing is queried
    on_lattice = _rendered((-0.5, -0.5), (30, 30), res)

    def refuse(xy: np.ndarray) -> np.ndarray:
        raise AssertionError("queried although every cell was rendered")

    assert rendered_ground_truth_auc(on_lattice, occupancy, gt_origin, res, refuse) == roc_auc(
        _field(centres).astype(np.float32), occupancy.astype(bool).ravel()
    )


def test_pass_masks_tell_a_second_pass_from_one_long_look() -> None:
    # a robot looks along +x from (0, 0), drives 8 m along the x axis (scans every 0.5 m, still one pass: no
    # cell goes unobserved over more than 10 m of travel), leaves for 30 m and looks again from (0, 0)
    angles = np.linspace(-0.5, 0.5, 21)
    xs = np.arange(0.0, 8.01, 0.5)
    poses = [[x, 0.0, 0.0] for x in xs] + [[0.0, 0.0, 0.0]]
    path_m = np.concatenate([xs, [xs[-1] + 30.0]])
    beams = beams_from_scans(
        [np.full(21, 3.0)] * len(poses), [angles] * len(poses), 0.1, 30.0, np.array(poses)
    )
    shape, origin, res = (40, 160), np.array([-2.0, -2.0]), 0.1
    observed, revisited = pass_masks(beams, path_m, 10.0, shape, origin, res)
    bounds = (origin[0], origin[1], origin[0] + 160 * res, origin[1] + 40 * res)
    np.testing.assert_array_equal(observed, observed_cells(beams, bounds, res))  # the same cells as the grid
    # the last scan's cells are revisited; the far end, seen only from x >= 3.5, is not
    last_scan = pass_masks(
        beams.subset(beams.scan_index == len(poses) - 1), path_m, 10.0, shape, origin, res
    )[0]
    assert revisited[last_scan].mean() > 0.95
    assert not revisited[:, int((9.0 - origin[0]) / res)].any()
    assert not pass_masks(beams, path_m, 40.0, shape, origin, res)[1].any()  # a gap of 30 m < 40 m: one pass


def test_ground_truth_auc_over_named_cells() -> None:
    occ = np.zeros((4, 5), np.uint8)
    occ[:, 4] = 1
    p = np.tile(np.array([0.1, 0.2, 0.9, 0.3, 0.8], np.float32), (4, 1))
    layers = MapLayers(p, p, p, 0.5, (0.0, 0.0))
    right = np.zeros((4, 5), bool)
    right[:, 2:] = True
    out = ground_truth_auc_over(
        layers,
        occ,
        np.zeros(2),
        0.5,
        {"all": np.ones((4, 5), bool), "right": right, "free": ~right & (occ == 0)},
    )
    assert out["all"] == pytest.approx(roc_auc(p.ravel(), occ.ravel().astype(bool)))
    assert out["right"] == pytest.approx(0.5)  # 0.8 occupied against 0.9 and 0.3 free
    assert out["free"] is None  # one label only
