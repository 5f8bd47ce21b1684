"""The paper's dataset I comparison (section 4.1.1, Table 1) on the calibrated ``street`` world, seed 0.

Paper: GP occupancy map AUC 0.9948 (FP rate 0.026 at a TP rate of 0.95), occupancy grid with widened beams at
0.25 m AUC 0.8938 (FP rate 0.1913). The world is calibrated on the grid (see ``street_world``); the GP was
measured afterwards. Scored on a 0.25 m ground-truth raster (288,000 cells) to keep the test fast: the AUCs
match those on the 0.1 m raster of ``evaluate map`` to within 0.0005.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from datasets.simulation import make_world
from mapping.build import MapBuilder
from mapping.evaluation import raster_cell_centres
from mapping.grid import OccupancyGrid
from mapping.metrics import roc_auc, roc_curve
from pipeline.config import load_config
from pipeline.evaluate_map import make_beams, reference_laser_poses
from tests.conftest import REPO

STREET_CONFIG = REPO / "mapping" / "configs" / "street.yaml"


def fp_rate_at(scores: np.ndarray, labels: np.ndarray, tp_rate: float = 0.95) -> float:
    fpr, tpr, _ = roc_curve(scores, labels)
    return float(np.interp(tp_rate, tpr, fpr))


@pytest.fixture(scope="module")
def street() -> dict[str, tuple[float, float]]:
    """(AUC, FP rate at TP 0.95) of GPFOL, the widened grid and the narrow grid."""
    cfg = load_config(STREET_CONFIG).mapping
    run = make_world("street", 0, resolution_m=0.25)
    rec, gt = run.recording, run.ground_truth
    beams = make_beams(rec, reference_laser_poses(rec, Path("street")), np.arange(len(rec.scans)), cfg)
    labels = gt.occupancy.astype(bool).ravel()
    centres = raster_cell_centres(gt.occupancy.shape, np.asarray(gt.origin_xy_m, np.float64), gt.resolution_m)
    builder = MapBuilder.from_config(cfg, "gpfol")
    gp = builder.gp_map(beams, builder.fit(beams))
    scores = {
        "gpfol": gp.query(centres, sort=False).probability,
        "grid": OccupancyGrid.from_config(beams, cfg.grid, gt.bounds_xy_m).query(centres),
        "narrow": OccupancyGrid.from_config(
            beams, cfg.grid.model_copy(update={"beam_width_deg": 0.0}), gt.bounds_xy_m
        ).query(centres),
    }
    return {k: (roc_auc(p, labels), fp_rate_at(p, labels)) for k, p in scores.items()}


def test_the_config_is_the_papers_grid() -> None:
    grid = load_config(STREET_CONFIG).mapping.grid
    assert grid.resolution_m == 0.25 and grid.beam_width_deg == pytest.approx(180.0 / 16)


def test_the_widened_grid_scores_like_the_papers_grid(street) -> None:
    auc, fp = street["grid"]
    assert auc == pytest.approx(0.8938, abs=0.01)  # measured 0.8918
    assert fp == pytest.approx(0.1913, abs=0.03)  # measured 0.183
    # without widening most of the map stays at the prior: "large portions of the map will remain unaltered"
    narrow_auc, narrow_fp = street["narrow"]
    assert 0.6 < narrow_auc < 0.7 and narrow_fp > 0.6  # measured 0.658, 0.648


def test_gpfol_beats_the_grid_as_in_table_one(street) -> None:
    auc, fp = street["gpfol"]
    # the bar; measured 0.9903 here, 0.9902 at 0.1 m; the paper: 0.9948. Seeds 0-4 at 0.1 m:
    # 0.986-0.994, mean 0.991. With the training problems' free margin equal to the map's (0.15 m) it was
    # 0.97-0.98; with 0.5 m for both 0.9837 (see mapping/configs/noise_free_simulation.yaml)
    assert auc > 0.99
    assert fp < 0.07  # measured 0.055 (0.077 before); the paper: 0.026
    assert auc > street["grid"][0] + 0.08
