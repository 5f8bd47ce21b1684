"""The occupancy-grid baseline: inverse sensor model along traced rays."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.beams import beams_from_scans
from mapping.grid import OccupancyGrid, logit


def one_beam(range_m: float, angle: float = 0.0, range_max: float = 10.0):
    return beams_from_scans(
        [np.array([range_m])], [np.array([angle])], 0.0, range_max, np.array([[0.05, 0.05, 0.0]]),
        no_return_free_length_m=3.0,
    )  # fmt: skip


def test_a_beam_frees_its_cells_and_occupies_its_endpoint() -> None:
    g = OccupancyGrid.build(one_beam(2.0), 0.1, (0.0, 0.0, 4.0, 1.0))
    row = g.log_odds[0]
    np.testing.assert_allclose(row[:20], logit(0.4), rtol=1e-6)  # cells 0..19 crossed before x = 2.05
    assert row[20] == pytest.approx(logit(0.7), rel=1e-6)  # endpoint cell
    assert np.all(row[21:] == 0)  # nothing behind the endpoint
    assert g.cell_updates == 21
    p = g.query(np.array([[1.0, 0.05], [2.06, 0.05], [3.5, 0.05], [-5.0, 0.0]]))
    np.testing.assert_allclose(p, [0.4, 0.7, 0.5, 0.5], atol=1e-6)


def test_no_return_beam_only_frees() -> None:
    g = OccupancyGrid.build(one_beam(np.inf), 0.1, (0.0, 0.0, 4.0, 1.0))
    row = g.log_odds[0]
    assert np.all(row[:31] < 0) and np.all(row[31:] == 0)  # free up to 3.05 m, no endpoint


def test_log_odds_are_clamped_and_accumulate() -> None:
    beams = beams_from_scans(
        [np.array([1.0])] * 50, [np.array([0.0])] * 50, 0.0, 10.0, np.tile([0.05, 0.05, 0.0], (50, 1))
    )
    g = OccupancyGrid.build(beams, 0.1, (0.0, 0.0, 2.0, 1.0), p_clamp=0.9)
    assert g.log_odds[0, 10] == pytest.approx(logit(0.9), rel=1e-6)
    assert g.log_odds[0, 5] == pytest.approx(-logit(0.9), rel=1e-6)
    assert g.probability.shape == g.log_odds.shape


def test_diagonal_ray_visits_connected_cells() -> None:
    g = OccupancyGrid.build(one_beam(3.0, angle=np.pi / 4), 0.1, (0.0, 0.0, 3.0, 3.0))
    free = np.argwhere(g.log_odds < 0)
    steps = np.abs(np.diff(free[np.lexsort((free[:, 1], free[:, 0]))], axis=0)).sum(axis=1)
    assert len(free) >= 40 and np.all(steps <= 2)
