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


# ------------------------------------------------------------------------------------- widened beams
def fan(ranges_m: np.ndarray, free_length_m: float = 12.0):
    """One 180-deg scan of len(ranges_m) beams from the origin, heading +x (one beam: straight ahead)."""
    angles = np.linspace(-np.pi / 2, np.pi / 2, len(ranges_m)) if len(ranges_m) > 1 else np.zeros(1)
    return beams_from_scans(
        [ranges_m], [angles], 0.0, 34.0, np.zeros((1, 3)), no_return_free_length_m=free_length_m
    )


def cell_polar(g: OccupancyGrid) -> tuple[np.ndarray, np.ndarray]:
    """Distance (m) and bearing (rad) of every cell centre from the origin, (H, W) each."""
    h, w = g.log_odds.shape
    x = g.origin_xy_m[0] + (np.arange(w) + 0.5) * g.resolution_m
    y = g.origin_xy_m[1] + (np.arange(h) + 0.5) * g.resolution_m
    xx, yy = np.meshgrid(x, y)
    return np.hypot(xx, yy), np.arctan2(yy, xx)


def test_a_widened_beam_is_a_cone_updated_once_per_cell() -> None:
    g = OccupancyGrid.build(fan(np.array([10.0])), 0.25, (-2.0, -6.0, 13.0, 6.0), beam_width_deg=20.0)
    d, bearing = cell_polar(g)
    L = g.log_odds
    # every cell holds the prior, one free update or one occupied update: each cell is updated once
    free, occ = L < 0, L > 0
    np.testing.assert_allclose(L[free], logit(0.4), rtol=1e-6)
    np.testing.assert_allclose(L[occ], logit(0.7), rtol=1e-6)
    assert g.cell_updates == free.sum() + occ.sum()
    # free cells fill the 20-deg sector up to the range, minus half a cell
    inside = (np.abs(bearing) < np.deg2rad(10.0) - 0.03) & (d > 1.0) & (d < 10.0 - 0.125 - 0.02)
    assert free[inside].all()
    assert free.sum() == pytest.approx(np.deg2rad(20.0) / 2 * 9.875**2 / 0.25**2, rel=0.06)
    # the occupied arc at 10 m spans the cone's width (plus the endpoint's own cell, whose centre may lie up
    # to half a diagonal away); nothing is touched outside the cone or behind the arc
    assert np.all(np.abs(d[occ] - 10.0) <= 0.25 / np.sqrt(2))
    assert np.ptp(bearing[occ]) == pytest.approx(np.deg2rad(20.0), abs=np.deg2rad(2.5))
    outside = (np.abs(bearing) > np.deg2rad(10.0)) & (d * np.sin(np.abs(bearing) - np.deg2rad(10.0)) > 0.36)
    assert np.all(L[outside] == 0) and np.all(L[d > 10.2] == 0)


def test_a_narrow_cone_still_covers_its_ray_and_a_no_return_cone_only_frees() -> None:
    g = OccupancyGrid.build(fan(np.array([5.0])), 0.1, (0.0, -0.95, 6.0, 1.05), beam_width_deg=0.01)
    L = g.log_odds  # the beam runs along y = 0, through the centres of row 9
    assert np.all(L[9, :49] < 0) and L[9, 50] > 0  # the ray's cells, then its endpoint
    assert np.all(np.delete(L, 9, axis=0) == 0) and np.all(L[9, 51:] == 0)
    none = OccupancyGrid.build(fan(np.array([np.inf])), 0.25, (-1.0, -4.0, 14.0, 4.0), beam_width_deg=20.0)
    d, _ = cell_polar(none)
    assert none.log_odds.max() == 0
    assert (none.log_odds < 0).sum() == pytest.approx(np.deg2rad(20.0) / 2 * 12.0**2 / 0.25**2, rel=0.06)
    assert np.all(none.log_odds[d > 12.0] == 0)


def test_cones_of_the_beam_spacing_fill_the_fan_that_rays_leave_mostly_unknown() -> None:
    """A 17-beam scan inside a ring wall 10 m away: rays free a small part of the half disc, cones as wide as
    the beam spacing (11.25 deg) free nearly all of it -- the paper's reason to widen the beams."""
    beams = fan(np.full(17, 10.0))
    bounds = (-11.0, -11.0, 11.0, 11.0)
    rays = OccupancyGrid.build(beams, 0.25, bounds)
    cones = OccupancyGrid.build(beams, 0.25, bounds, beam_width_deg=180.0 / 16)
    d, bearing = cell_polar(rays)
    half_disc = (np.abs(bearing) < np.pi / 2 - 0.05) & (d > 0.5) & (d < 9.5)
    assert (rays.log_odds[half_disc] < 0).mean() < 0.35
    assert (cones.log_odds[half_disc] < 0).mean() > 0.99
    wall = (np.abs(bearing) < np.pi / 2 - 0.05) & (np.abs(d - 10.0) < 0.1)
    assert (cones.log_odds[wall] > 0).mean() > 0.95 and (rays.log_odds[wall] > 0).mean() < 0.2


def test_from_config_and_bad_width() -> None:
    from mapping.config import GridBaselineConfig

    beams = fan(np.full(17, 10.0))
    cfg = GridBaselineConfig(resolution_m=0.25, beam_width_deg=11.25, p_occupied=0.8)
    a = OccupancyGrid.from_config(beams, cfg, (-11.0, -11.0, 11.0, 11.0))
    b = OccupancyGrid.build(beams, 0.25, (-11.0, -11.0, 11.0, 11.0), 0.8, 0.4, 0.97, 11.25)
    np.testing.assert_array_equal(a.log_odds, b.log_odds)
    assert a.resolution_m == 0.25 and a.log_odds.max() == pytest.approx(logit(0.8), rel=1e-6)
    with pytest.raises(ValueError, match="beam_width_deg"):
        OccupancyGrid.build(beams, 0.25, beam_width_deg=-1.0)
