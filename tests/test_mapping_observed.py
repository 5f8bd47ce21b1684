"""Observed cells: which test points lie in a cell some training beam touched, and the split of
the map protocols' AUCs by it (hand-made beams, random beams against an exact segment-box test, the Intel
hold-out of seed 0, a simulated world's raster)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from datasets.registry import open_dataset
from mapping.beams import Beams, compose_laser_poses
from mapping.build import MapBuilder
from mapping.config import MappingConfig
from mapping.evaluation import (
    HIT_COUNT_EDGES,
    NEAREST_HIT_EDGES_M,
    RANGE_EDGES_M,
    auc_by_bins,
    hits_within,
    holdout_block_scans,
    holdout_split,
    holdout_test_points,
    is_carmen_180,
    nearest_hit_m,
    observed_points,
    raster_cell_centres,
)
from mapping.metrics import roc_auc
from mapping.train import GPParams
from pipeline.evaluate_map import (
    breakdown_table,
    evaluate_ground_truth,
    evaluate_holdout,
    make_beams,
    reference_base_poses,
)
from pipeline.progress import Progress
from tests.conftest import data_file

FAST = {"train": {"anneal_evaluations": 40, "lbfgs_iterations": 40, "problems": 48}}


def make_test_beams(origins, ends, free_ends, is_hit) -> Beams:
    """Beams (M of them) from (M, 2) origins, ends and free ends and (M,) hit flags."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 2)
    e = np.asarray(ends, dtype=np.float64).reshape(-1, 2)
    d = e - o
    m = o.shape[0]
    return Beams(
        origins_xy_m=o,
        ends_xy_m=e,
        free_ends_xy_m=np.asarray(free_ends, dtype=np.float64).reshape(-1, 2),
        is_hit=np.asarray(is_hit, dtype=bool),
        ranges_m=np.hypot(d[:, 0], d[:, 1]),
        bearings_rad=np.zeros(m),
        scan_index=np.arange(m, dtype=np.int32),
        beam_index=np.zeros(m, dtype=np.int32),
        source_index=np.zeros(m, dtype=np.int32),
        laser_theta_rad=np.arctan2(d[:, 1], d[:, 0]),
    )


def centre(ix: int, iy: int, res: float = 1.0) -> list[float]:
    return [(ix + 0.5) * res, (iy + 0.5) * res]


def test_hand_made_beams_observe_the_cells_they_cross_and_their_endpoints_cell() -> None:
    """1 m cells from (0, 0). A return along row 0 whose free part stops in cell (2, 0), its endpoint in
    (3, 0); a no-return beam up column 0; a diagonal no-return beam through (0,0) (1,0) (1,1) (2,1); a return
    with a free part of length 0 from cell (5, 5), endpoint in (6, 5)."""
    beams = make_test_beams(
        origins=[[0.5, 0.5], [0.5, 0.5], [0.5, 0.5], [5.5, 5.5]],
        ends=[[3.5, 0.5], [0.5, 2.5], [2.5, 1.5], [6.2, 5.5]],
        free_ends=[[2.9, 0.5], [0.5, 2.5], [2.5, 1.5], [5.5, 5.5]],
        is_hit=[True, False, False, True],
    )
    seen = [(0, 0), (1, 0), (2, 0), (3, 0), (0, 1), (0, 2), (1, 1), (2, 1), (6, 5)]
    unseen = [(4, 0), (0, 3), (2, 2), (1, 2), (5, 5), (7, 5), (9, 9), (-3, -4)]
    cells = seen + unseen
    pts = np.array([centre(*c) for c in cells])
    got = observed_points(beams, pts, 1.0, anchor_xy_m=(0.0, 0.0))
    assert got.tolist() == [True] * len(seen) + [False] * len(unseen)
    # the diagonal beam: (2, 0) lies below it, (0, 1) above (only the vertical beam observes (0, 1))
    diag = beams.subset(np.array([2]))
    assert observed_points(
        diag, np.array([centre(2, 0), centre(0, 1), centre(1, 1)]), 1.0, (0, 0)
    ).tolist() == [
        False,
        False,
        True,
    ]
    # any point of a cell counts as the cell, not only its centre
    assert observed_points(
        beams, np.array([[3.01, 0.99], [3.99, 0.01], [4.01, 0.5]]), 1.0, (0, 0)
    ).tolist() == [
        True,
        True,
        False,
    ]
    # far test points only widen the lattice; no beams or no points: nothing observed
    assert observed_points(beams, np.zeros((0, 2)), 1.0).shape == (0,)
    assert not observed_points(beams.subset(np.zeros(4, dtype=bool)), pts, 1.0).any()
    with pytest.raises(ValueError, match="finite"):
        observed_points(beams, np.array([[np.nan, 0.0]]), 1.0)


def _segment_meets_box(p: np.ndarray, q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Does the segment p-q meet the box [lo, hi] (Liang-Barsky)?"""
    t0, t1 = 0.0, 1.0
    d = q - p
    for k in range(2):
        if d[k] == 0.0:
            if not lo[k] <= p[k] <= hi[k]:
                return False
            continue
        a, b = (lo[k] - p[k]) / d[k], (hi[k] - p[k]) / d[k]
        t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
        if t0 > t1:
            return False
    return True


def test_random_beams_agree_with_an_exact_segment_box_test() -> None:
    """Random beams (returns with a free margin, no-returns) in a 6 m box, cells of 0.5 m: a cell is observed
    exactly when a free segment meets it or an endpoint lies in it."""
    rng = np.random.default_rng(3)
    m = 40
    o = rng.uniform(0.3, 5.7, (m, 2))
    e = rng.uniform(0.3, 5.7, (m, 2))
    hit = rng.random(m) < 0.6
    length = np.hypot(*(e - o).T)
    free_len = np.where(hit, np.maximum(length - 0.4, 0.0), length)
    f = o + (free_len / length)[:, None] * (e - o)
    beams = make_test_beams(o, e, f, hit)
    res = 0.5
    pts = raster_cell_centres((14, 14), np.array([-0.5, -0.5]), res)
    got = observed_points(beams, pts, res, anchor_xy_m=(0.0, 0.0))
    expected = np.zeros(pts.shape[0], dtype=bool)
    for j, c in enumerate(pts):
        lo, hi = c - res / 2, c + res / 2
        for i in range(m):
            if hit[i] and np.all(np.floor(e[i] / res) == np.floor(c / res)):
                expected[j] = True
            elif free_len[i] > 0 and _segment_meets_box(o[i], f[i], lo, hi):
                expected[j] = True
    assert 0 < expected.sum() < expected.size
    np.testing.assert_array_equal(got, expected)
    # the default lattice is the grid baseline's: its cells the beams updated are the observed ones
    grid = MapBuilder.from_config(MappingConfig()).grid(beams.subset(~hit))
    touched = grid.log_odds != 0
    centres = raster_cell_centres(touched.shape, grid.origin_xy_m, grid.resolution_m)
    no_return = observed_points(beams.subset(~hit), centres, grid.resolution_m)
    np.testing.assert_array_equal(no_return, touched.ravel())


@pytest.fixture(scope="module")
def intel_seed0():
    """Intel (corrected poses), hold-out seed 0: the evaluated row, and the protocol's points, labels and
    training beams recomputed with the protocol functions."""
    path = data_file("intel/intel.gfs.log")
    rec = open_dataset(path)
    base = reference_base_poses(rec, path)
    cfg = MappingConfig(**FAST)
    row = evaluate_holdout(rec, base, [0], cfg, Progress(), breakdown=True)["per_seed"][0]
    n = len(rec.scans)
    held = holdout_split(n, 0, block=holdout_block_scans(n))
    train = np.setdiff1d(np.arange(n), held)
    carmen = all(is_carmen_180(a) for a in rec.scans.angles_rad[:10])
    laser = compose_laser_poses(base, rec.laser_in_base_xytheta)
    pts, labels, dist = holdout_test_points(
        rec.scans.ranges_m, rec.scans.angles_rad, laser, held, 0, carmen, with_ranges=True
    )
    return row, pts, labels, make_beams(rec, base, train, cfg), cfg, dist


def test_intel_holdout_split_by_observed_cells(intel_seed0) -> None:
    row, pts, labels, beams, cfg, _ = intel_seed0
    assert row["test_points"] == labels.size and row["occupied_test_points"] == labels.sum()
    observed = observed_points(beams, pts, cfg.resolution_m)
    assert row["observed_test_points"] == observed.sum() and row["observed_cell_m"] == cfg.resolution_m
    share = row["unobserved_share"]
    assert 0 < share < 1 and share == pytest.approx(np.mean(~observed), abs=0)
    assert share < 0.1  # held-out blocks of a lab mapped twice over: most test points lie in seen cells

    # the AUC over the observed points is computed from exactly those points
    p_grid = MapBuilder.from_config(cfg).grid(beams).query(pts)
    assert row["auc_grid"] == pytest.approx(roc_auc(p_grid, labels), abs=1e-12)
    assert row["auc_observed_grid"] == pytest.approx(roc_auc(p_grid[observed], labels[observed]), abs=1e-12)
    assert row["auc_unobserved_grid"] == pytest.approx(
        roc_auc(p_grid[~observed], labels[~observed]), abs=1e-12
    )
    params = GPParams.from_dict(row["gpfol_params"])
    p_gp = MapBuilder.from_config(cfg, "gpfol").gp_map(beams, params).query(pts, sort=True).probability
    assert row["auc_gpfol"] == pytest.approx(roc_auc(p_gp, labels), abs=1e-9)
    assert row["auc_observed_gpfol"] == pytest.approx(roc_auc(p_gp[observed], labels[observed]), abs=1e-9)
    unobserved_labels = labels[~observed].astype(bool)
    assert row["unobserved_occupied_test_points"] == unobserved_labels.sum()
    assert row["unobserved_free_test_points"] == (~unobserved_labels).sum()
    p_unobserved = p_grid[~observed]
    wrong = np.where(
        unobserved_labels, p_unobserved <= cfg.free_threshold, p_unobserved >= cfg.occupied_threshold
    )
    assert row["wrong_unobserved_grid"] == pytest.approx(wrong.mean(), abs=1e-12)
    for mapper in ("gppol", "gpfol", "grid"):
        assert 0.5 < row[f"auc_observed_{mapper}"] <= 1
        # unobserved cells are where the maps know least
        assert row[f"auc_observed_{mapper}"] > row[f"auc_unobserved_{mapper}"]
        assert 0 <= row[f"wrong_unobserved_{mapper}"] < 0.5


def test_intel_holdout_breakdown_by_range_and_nearby_endpoints(intel_seed0) -> None:
    """``breakdown``: each AUC over the test points of each distance bin and of each bin of mapped endpoints
    within 1 m, recomputed here from the protocol's points and the grid's probabilities."""
    row, pts, labels, beams, cfg, dist = intel_seed0
    p_grid = MapBuilder.from_config(cfg).grid(beams).query(pts)
    hits = beams.ends_xy_m[beams.is_hit]
    near = (np.hypot(*(pts[:, None, :] - hits[None, ::7, :]).transpose(2, 0, 1)) <= 1.0).any(axis=1)
    counts = hits_within(hits, pts)
    assert np.all(counts[near] >= 1)  # a subsample of the endpoints within 1 m: the count sees them too
    assert dist.max() <= 40.0 and row["by_range_m_grid"][-1]["to"] == 40.0  # the protocol's longest beam
    nearest = nearest_hit_m(hits, pts)
    assert np.all((nearest <= 1.0) == (counts >= 1))
    cases = (
        ("range_m", RANGE_EDGES_M, dist),
        ("hits_1m", HIT_COUNT_EDGES, counts),
        ("nearest_hit_m", NEAREST_HIT_EDGES_M, nearest),
    )
    for key, edges, values in cases:
        for mapper in ("gppol", "gpfol", "grid"):
            bins = row[f"by_{key}_{mapper}"]
            assert len(bins) == len(edges) - 1
            assert sum(b["test_points"] for b in bins) == labels.size
            assert sum(b["occupied"] for b in bins) == labels.sum()
        expected = auc_by_bins(p_grid, labels, values, edges)
        assert [b["test_points"] for b in row[f"by_{key}_grid"]] == [b["test_points"] for b in expected]
        for got, want in zip(row[f"by_{key}_grid"], expected, strict=True):
            assert (got["auc"] is None) == (want["auc"] is None)
            if want["auc"] is not None:
                assert got["auc"] == pytest.approx(want["auc"], abs=1e-12)
            assert got["auc_lost_occupied"] == pytest.approx(want["auc_lost_occupied"], abs=1e-12)
        for mapper in ("gppol", "gpfol", "grid"):  # the whole AUC's shortfall, split over the bins
            bins = row[f"by_{key}_{mapper}"]
            assert sum(b["auc_lost_free"] for b in bins) == pytest.approx(1 - row[f"auc_{mapper}"], abs=1e-9)
    # walls are where the mapped returns are: occupied test points crowd the densest bin, not the emptiest
    emptiest, densest = row["by_hits_1m_gppol"][0], row["by_hits_1m_gppol"][-1]
    assert densest["occupied"] / densest["test_points"] > 0.3 > emptiest["occupied"] / emptiest["test_points"]
    # a GP map loses most of its AUC next to the mapped returns, where walls and free space meet, not
    # metres from them
    lost = [b["auc_lost_occupied"] + b["auc_lost_free"] for b in row["by_nearest_hit_m_gppol"]]
    assert sum(lost[:3]) > sum(lost[4:])
    table = breakdown_table([row])
    bins = len(RANGE_EDGES_M) - 1 + len(HIT_COUNT_EDGES) - 1 + len(NEAREST_HIT_EDGES_M) - 1
    assert len(table) == 2 * bins  # per bin its AUC and its part of the shortfall
    near_lost = table["AUC lost (occupied + free) gppol / gpfol / grid, nearest mapped endpoint 0-0.05 m"]
    occ_lost, free_lost = (row["by_nearest_hit_m_gppol"][0][f"auc_lost_{k}"] for k in ("occupied", "free"))
    assert near_lost.startswith(f"{occ_lost:.4f} + {free_lost:.4f} / ")
    assert table["AUC gppol / gpfol / grid, nearest mapped endpoint >= 1 m"]
    first = row["by_range_m_gppol"][0]
    near_cell = table["AUC gppol / gpfol / grid, distance from the laser 0-2 m"]
    assert near_cell.startswith(f"{first['auc']:.4f} / ")
    hit_rows = [k.split("within 1 m ")[1] for k in table if k.startswith("AUC gppol") and "within 1 m" in k]
    assert hit_rows == ["0", "1-4", "5-19", "20-99", ">= 100"]  # counts: the integers of each bin
    assert breakdown_table([{k: v for k, v in row.items() if not k.startswith("by_")}]) == {}


def test_ground_truth_protocol_splits_the_raster_cells(tmp_path) -> None:
    """On a simulated world every (sampled) raster cell is a test point, its cell is the raster's own."""
    from datasets.simulation import load_ground_truth, simulate

    bag = tmp_path / "street.bag"
    simulate("street", bag, seed=0)
    gt = load_ground_truth(Path(str(bag) + ".gt.npz"))
    rec = open_dataset(bag)
    base = np.asarray(rec.reference.poses_xytheta)
    cfg = MappingConfig(**FAST)
    out = evaluate_ground_truth(rec, base, gt, bag, cfg, Progress(), every=10)
    row = out["per_seed"][0]
    centres = gt.cell_centers_xy_m()[::10, ::10].reshape(-1, 2)
    labels = np.asarray(gt.occupancy).astype(bool)[::10, ::10].ravel()
    beams = make_beams(rec, base, np.arange(len(rec.scans)), cfg)
    observed = observed_points(beams, centres, gt.resolution_m, gt.origin_xy_m)
    assert row["observed_cell_m"] == gt.resolution_m
    assert row["observed_test_points"] == observed.sum() and 0 < row["unobserved_share"] < 1
    p_grid = MapBuilder.from_config(cfg).grid(beams, gt.bounds_xy_m).query(centres)
    assert row["auc_observed_grid"] == pytest.approx(roc_auc(p_grid[observed], labels[observed]), abs=1e-12)


def test_breakdown_is_of_the_holdout_protocol_only(tmp_path) -> None:
    """A simulated world is scored on its raster: ``--breakdown`` says it does not apply, adds no keys."""
    from datasets.simulation import simulate
    from pipeline.evaluate_map import evaluate_map

    bag = tmp_path / "street.bag"
    simulate("street", bag, seed=0)
    result = evaluate_map(bag, breakdown=True)
    assert result["protocol"] == "ground_truth"
    assert result["table"]["AUC by distance / endpoints nearby"] == "- (hold-out protocol only)"
    assert not [k for k in result["per_seed"][0] if k.startswith("by_")]


def test_suite_rows_carry_the_split_and_the_table_shows_it(intel_seed0) -> None:
    """The suite's map result (as ``evaluate map``) has the means; its table one compact column."""
    from pipeline.evaluate_suite import _map_result, table_row

    row = intel_seed0[0]
    result = _map_result({"per_seed": [row]}, "holdout", [0], "reference", "none (exact reference poses)")
    assert result["auc_observed"] == {k: row[f"auc_observed_{k}"] for k in ("gppol", "gpfol", "grid")}
    assert result["unobserved_share"] == row["unobserved_share"]
    assert result["per_seed"][0]["auc_unobserved_gppol"] == row["auc_unobserved_gppol"]
    # each mapper's learnt log marginal likelihood per point stays in the trimmed rows (the full parameter
    # dumps go): it is what compares kernels on one recording
    for mapper in ("gppol", "gpfol"):
        lml = result["per_seed"][0][f"{mapper}_lml_per_point"]
        assert lml == row[f"{mapper}_params"]["info"]["lml_per_point"] and np.isfinite(lml)
        assert f"{mapper}_params" not in result["per_seed"][0]
    cells = table_row({"name": "intel", "maps": {"reference_poses": result, "slam_poses": result}})
    share = 100 * row["unobserved_share"]
    assert cells["AUC observed GPPOL / unobserved"] == f"{row['auc_observed_gppol']:.4f} / {share:.1f} %"
    assert table_row({"name": "x", "maps": None})["AUC observed GPPOL / unobserved"] == "-"
