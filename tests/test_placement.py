"""The placement uncertainty layer (mapping/placement.py): the world covariances propagated to the cells."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.beams import beams_from_scans
from mapping.exports import MapLayers, read_layers_npz, write_layers_npz
from mapping.placement import placement_sigma_m, with_placement

ANGLES = np.linspace(-np.pi / 2, np.pi / 2, 91)
GRID = dict(origin_xy_m=(-12.0, -12.0), resolution_m=0.1, shape=(240, 240))


def scans(ranges_m: list[float], poses_xytheta: list[list[float]]):
    """Scans of 91 beams over 180 deg, each scan at one range."""
    return beams_from_scans(
        [np.full(ANGLES.size, r) for r in ranges_m],
        [ANGLES] * len(ranges_m),
        0.1,
        30.0,
        np.asarray(poses_xytheta, dtype=np.float64),
    )


def cell(x_m: float, y_m: float) -> tuple[int, int]:
    """(row, column) of the grid cell holding (x, y)."""
    return int((y_m - GRID["origin_xy_m"][1]) // 0.1), int((x_m - GRID["origin_xy_m"][0]) // 0.1)


def test_a_position_covariance_places_every_observed_cell_alike() -> None:
    beams = scans([5.0], [[0.0, 0.0, 0.0]])
    sigma = placement_sigma_m(beams, np.diag([0.09, 0.04, 0.0])[None], **GRID)
    seen = np.isfinite(sigma)
    # the most uncertain direction: x, 0.3 m, wherever a beam passed or ended
    np.testing.assert_allclose(sigma[seen], 0.3, rtol=1e-6)
    assert np.isfinite(sigma[cell(0.05, 0.05)]) and np.isfinite(sigma[cell(4.97, 0.05)])  # origin, endpoint
    assert np.isnan(sigma[cell(6.0, 0.05)]) and np.isnan(sigma[cell(-3.0, 0.05)])  # beyond, behind
    assert 0.05 < seen.mean() < 0.5


def test_a_heading_uncertainty_grows_with_the_range() -> None:
    beams = scans([8.0], [[0.0, 0.0, 0.0]])
    sigma_rad = 0.01
    sigma = placement_sigma_m(beams, np.diag([0.0, 0.0, sigma_rad**2])[None], **GRID)
    along = sigma[cell(0.0, 0.05)[0], cell(0.05, 0.0)[1] : cell(7.95, 0.0)[1] + 1]  # the beam along +x
    assert np.all(np.isfinite(along)) and np.all(np.diff(along) >= 0)
    # the point at d metres moves d sigma_theta sideways (the exact UT, small angles)
    assert sigma[cell(7.97, 0.05)] == pytest.approx(8.0 * sigma_rad, rel=0.01)
    assert sigma[cell(4.05, 0.05)] == pytest.approx(4.05 * sigma_rad, rel=0.03)


def test_a_cell_takes_its_best_placed_observer() -> None:
    # two scans from one pose: the sharp one sees 4 m, the uncertain one 9 m
    beams = scans([4.0, 9.0], [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    cov = np.stack([np.diag([0.01, 0.01, 0.0]), np.diag([0.25, 0.25, 0.0])])
    sigma = placement_sigma_m(beams, cov, **GRID)
    assert sigma[cell(2.0, 0.05)] == pytest.approx(0.1, rel=1e-6)  # seen by both
    assert sigma[cell(6.0, 0.05)] == pytest.approx(0.5, rel=1e-6)  # by the uncertain one alone
    # without covariances there is nothing to add
    layers = MapLayers(*(np.zeros(GRID["shape"], np.float32),) * 3, 0.1, GRID["origin_xy_m"])
    assert with_placement(layers, beams, None) is layers
    assert with_placement(layers, beams, cov).placement_sigma_m == pytest.approx(sigma, nan_ok=True)


def test_the_layer_round_trips_through_layers_npz(tmp_path) -> None:
    beams = scans([5.0], [[0.0, 0.0, 0.3]])
    zeros = np.zeros(GRID["shape"], np.float32)
    plain = MapLayers(zeros, zeros, zeros, 0.1, GRID["origin_xy_m"])
    placed = with_placement(plain, beams, np.diag([0.01, 0.02, 1e-4])[None])
    back = read_layers_npz(write_layers_npz(tmp_path / "placed.npz", placed))
    assert back.placement_sigma_m.dtype == np.float32
    np.testing.assert_array_equal(back.placement_sigma_m, placed.placement_sigma_m)
    assert read_layers_npz(write_layers_npz(tmp_path / "plain.npz", plain)).placement_sigma_m is None
