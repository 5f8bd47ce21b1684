"""Training data of the sensor model: beams in the world frame, no-returns, dropped ranges, margins."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.beams import beams_from_scans, compose_laser_poses


def test_endpoints_in_the_world_frame_with_mounting() -> None:
    ranges = [np.array([2.0, 1.0])]
    angles = [np.array([0.0, math.pi / 2])]
    pose = np.array([[1.0, 2.0, math.pi / 2]])
    mount = np.array([0.5, 0.0, 0.0])  # laser 0.5 m ahead of the base
    b = beams_from_scans(ranges, angles, 0.1, 10.0, pose, mount)
    np.testing.assert_allclose(b.origins_xy_m, [[1.0, 2.5], [1.0, 2.5]], atol=1e-12)
    np.testing.assert_allclose(b.ends_xy_m, [[1.0, 4.5], [0.0, 2.5]], atol=1e-12)
    assert b.is_hit.tolist() == [True, True]
    np.testing.assert_allclose(compose_laser_poses(pose, mount), [[1.0, 2.5, math.pi / 2]], atol=1e-12)


def test_no_returns_dropped_ranges_and_free_margin() -> None:
    ranges = [np.array([np.inf, np.nan, 10.0, 12.0, 0.05, 3.0])]
    angles = [np.zeros(6)]
    b = beams_from_scans(
        ranges, angles, 0.1, 10.0, np.zeros((1, 3)), no_return_free_length_m=4.0, free_margin_m=0.2
    )
    # inf, NaN, 10 (= range_max) and 12 are no-returns (free 4 m, no endpoint); 0.05 < range_min is dropped
    assert len(b) == 5
    assert b.is_hit.tolist() == [False, False, False, False, True]
    assert b.beam_index.tolist() == [0, 1, 2, 3, 5]
    np.testing.assert_allclose(b.ends_xy_m[:4, 0], 4.0)
    np.testing.assert_allclose(b.free_ends_xy_m[:4, 0], 4.0)  # no margin without an endpoint
    np.testing.assert_allclose(b.ends_xy_m[4], [3.0, 0.0])
    np.testing.assert_allclose(b.free_ends_xy_m[4], [2.8, 0.0])
    np.testing.assert_allclose(b.hit_xy_m, [[3.0, 0.0]])


def test_no_return_length_defaults_to_range_max_and_zero_drops() -> None:
    ranges = [np.array([np.inf, 1.0])]
    angles = [np.zeros(2)]
    b = beams_from_scans(ranges, angles, 0.0, 8.0, np.zeros((1, 3)))
    np.testing.assert_allclose(b.ends_xy_m[0], [8.0, 0.0])
    b0 = beams_from_scans(ranges, angles, 0.0, 8.0, np.zeros((1, 3)), no_return_free_length_m=0.0)
    assert len(b0) == 1 and b0.is_hit.all()


def test_scan_indices_and_selection() -> None:
    ranges = [np.array([1.0, 2.0])] * 3
    angles = [np.zeros(2)] * 3
    b = beams_from_scans(ranges, angles, 0.0, 8.0, np.zeros((3, 3)), scan_indices=[5, 7, 9])
    assert b.scan_index.tolist() == [5, 5, 7, 7, 9, 9]
    assert len(b.select_scans([7])) == 2
    with pytest.raises(ValueError, match="3 scans but 2 poses"):
        beams_from_scans(ranges, angles, 0.0, 8.0, np.zeros((2, 3)))


def test_with_free_margin_equals_building_with_that_margin() -> None:
    rng = np.random.default_rng(3)
    ranges = [np.r_[rng.uniform(0.2, 9.0, 40), np.inf, 0.3]]
    angles = [np.linspace(-1.5, 1.5, 42)]
    pose = np.array([[1.0, -2.0, 0.4]])
    kw = {"no_return_free_length_m": 4.0}
    narrow = beams_from_scans(ranges, angles, 0.1, 10.0, pose, free_margin_m=0.2, **kw)
    wide = beams_from_scans(ranges, angles, 0.1, 10.0, pose, free_margin_m=0.5, **kw)
    again = narrow.with_free_margin(0.5)
    np.testing.assert_allclose(again.free_ends_xy_m, wide.free_ends_xy_m, atol=1e-12)
    np.testing.assert_array_equal(again.ends_xy_m, narrow.ends_xy_m)  # endpoints and the rest unchanged
    assert not np.allclose(narrow.free_ends_xy_m[narrow.is_hit], wide.free_ends_xy_m[wide.is_hit])
    # the 0.3 m return has no free part left with 0.5 m; the no-return keeps its whole 4 m
    np.testing.assert_allclose(again.free_ends_xy_m[-1], again.origins_xy_m[-1], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(again.free_ends_xy_m[-2] - again.origins_xy_m[-2]), 4.0)
