"""Free margins that grow where a beam grazes its surface: delta(r) / sin(gamma), the floor, the
fallbacks, and the paths that rebuild free segments (train margin, subsets, GPPOL's free points)."""

from __future__ import annotations

import math

import numpy as np

from datasets.types import ScanSequence
from mapping.beams import beams_from_scan_sequence, beams_from_scans, free_lengths_m, grazing_margins_m
from mapping.build import MapBuilder
from mapping.config import MappingConfig
from mapping.gppol import GaussianInputs, SensorNoise, input_moments
from mapping.tiling.support import concat_beams

ORIGIN = np.zeros((1, 3))


def _free_len(b) -> np.ndarray:
    return np.hypot(*(b.free_ends_xy_m - b.origins_xy_m).T)


def _wall_y(y_m: float, angles_rad: np.ndarray) -> list[np.ndarray]:
    """Ranges from the origin to the wall y = ``y_m`` along ``angles_rad`` (heading 0)."""
    return [y_m / np.sin(angles_rad)]


def test_head_on_wall_keeps_the_floor_margin() -> None:
    a = np.deg2rad(np.arange(-3.0, 3.5, 0.5))
    r = [5.0 / np.cos(a)]  # the wall x = 5, seen head-on by the middle beam
    b = beams_from_scans(r, [a], 0.1, 20.0, ORIGIN, free_margin_m=0.1, free_band_m=0.05)
    mid = len(a) // 2
    assert abs(b.grazing_margin_m[mid] - 0.05) < 1e-9  # delta / sin(90 deg)
    np.testing.assert_allclose(_free_len(b)[mid], 5.0 - 0.1, atol=1e-12)  # the floor wins
    assert b.grazing_margin_m[0] == 0 and b.grazing_margin_m[-1] == 0  # one neighbour only: plain margin


def test_grazing_beam_stops_delta_over_sin_gamma_short() -> None:
    gamma = np.deg2rad(10.0)
    a = gamma + np.deg2rad([-0.5, 0.0, 0.5])
    r = _wall_y(1.0, a)  # the wall y = 1: every beam meets it at its own angle a
    band, per_m = 0.05, 0.01
    b = beams_from_scans(
        r, [a], 0.1, 20.0, ORIGIN, free_margin_m=0.1, free_band_m=band, free_band_per_m=per_m
    )
    expected = (band + per_m * r[0][1]) / math.sin(gamma)
    assert 0.1 < expected < 2.0
    np.testing.assert_allclose(b.grazing_margin_m[1], expected, rtol=1e-9)
    np.testing.assert_allclose(_free_len(b)[1], r[0][1] - expected, rtol=1e-9)
    # every point of the free part lies at least delta from the wall, the free end exactly delta
    np.testing.assert_allclose(1.0 - b.free_ends_xy_m[1, 1], band + per_m * r[0][1], rtol=1e-9)
    # the cap bounds it
    capped = beams_from_scans(
        r, [a], 0.1, 20.0, ORIGIN, free_margin_m=0.1, free_band_m=band, free_margin_max_m=0.2
    )
    np.testing.assert_allclose(capped.grazing_margin_m[1], 0.2)


def test_depth_edges_corners_and_thin_objects_fall_back() -> None:
    a = np.deg2rad([-1.0, 0.0, 1.0])
    kw = {"free_margin_m": 0.1, "free_band_m": 0.5}
    # a post at 2 m in front of a wall at 8 m: both neighbours behind it
    post = beams_from_scans([np.array([8.0, 2.0, 8.0])], [a], 0.1, 20.0, ORIGIN, **kw)
    # the end of a near wall: one neighbour on it, the other on a far wall (steps of 3.5 cm and 6 m)
    edge = beams_from_scans([np.array([2.0, 2.0, 8.0])], [a], 0.1, 20.0, ORIGIN, **kw)
    # a no-return or a dropped beam beside it: no neighbour there
    gap = beams_from_scans([np.array([2.0, 2.0, np.inf, 2.0])], [np.r_[a, 0.03]], 0.1, 20.0, ORIGIN, **kw)
    short = beams_from_scans([np.array([2.0, 2.0, 0.01])], [a], 0.1, 20.0, ORIGIN, **kw)
    for b in (post, edge, short):
        assert b.grazing_margin_m[1] == 0
        np.testing.assert_allclose(_free_len(b)[1], 2.0 - 0.1, atol=1e-12)
    assert np.all(gap.grazing_margin_m == 0)
    # a corner: the steps to its neighbours turn by 90 degrees
    corner = np.array([[1.0, 0.1], [1.0, 0.0], [1.1, 0.0]])
    u = corner / np.linalg.norm(corner, axis=1)[:, None]
    g = grazing_margins_m(corner, u, np.linalg.norm(corner, axis=1), np.ones(3, bool), np.zeros(3), 0.5)
    assert g[1] == 0


def test_never_negative_never_beyond_the_start_and_off_without_a_band() -> None:
    a = np.deg2rad([0.4, 0.5, 0.6])  # a beam nearly along the wall y = 0.5
    r = _wall_y(0.5, a)
    b = beams_from_scans(r, [a], 0.1, 200.0, ORIGIN, free_band_m=1.0, free_margin_max_m=None)
    assert b.grazing_margin_m[1] == r[0][1]  # capped at the beam's length
    np.testing.assert_allclose(b.free_ends_xy_m[1], b.origins_xy_m[1], atol=1e-12)
    assert np.all(_free_len(b) >= 0)
    # both bands 0: the plain margin, bit for bit
    plain = beams_from_scans(r, [a], 0.1, 200.0, ORIGIN, free_margin_m=0.1)
    off = beams_from_scans(r, [a], 0.1, 200.0, ORIGIN, free_margin_m=0.1, free_margin_max_m=0.5)
    assert np.all(off.grazing_margin_m == 0)
    np.testing.assert_array_equal(off.free_ends_xy_m, plain.free_ends_xy_m)
    np.testing.assert_array_equal(_free_len(plain), free_lengths_m(plain.ranges_m, plain.is_hit, 0.1))


def _room_scans(n_scans: int = 3):
    """Scans from inside a 31 m x 2.5 m corridor (walls at x = -1, 30 and y = -1, 1.5), with a no-return."""
    rng = np.random.default_rng(1)
    ranges, angles = [], []
    poses = np.column_stack(
        [rng.uniform(0, 2, n_scans), rng.uniform(0, 0.5, n_scans), rng.uniform(-0.3, 0.3, n_scans)]
    )
    for x, y, th in poses:
        a = np.linspace(-math.pi / 2, math.pi / 2, 181)
        d = np.stack([np.cos(th + a), np.sin(th + a)])
        with np.errstate(divide="ignore"):
            tx = np.where(d[0] > 0, (30 - x) / d[0], (-1 - x) / d[0])
            ty = np.where(d[1] > 0, (1.5 - y) / d[1], (-1 - y) / d[1])
        r = np.minimum(tx, ty)
        r[40] = np.inf
        ranges.append(r)
        angles.append(a)
    return ranges, angles, poses


def test_train_margin_subsets_and_gppol_free_points_follow_the_grazing_margin() -> None:
    ranges, angles, poses = _room_scans()
    kw = {"no_return_free_length_m": 2.0, "free_band_m": 0.05, "free_band_per_m": 0.01}
    narrow = beams_from_scans(ranges, angles, 0.1, 20.0, poses, free_margin_m=0.1, **kw)
    wide = beams_from_scans(ranges, angles, 0.1, 20.0, poses, free_margin_m=0.5, **kw)
    assert (narrow.grazing_margin_m > 0.5).any() and (narrow.grazing_margin_m[narrow.is_hit] < 0.1).any()
    again = narrow.with_free_margin(0.5)
    np.testing.assert_allclose(again.free_ends_xy_m, wide.free_ends_xy_m, atol=1e-12)
    back = again.with_free_margin(0.1)
    np.testing.assert_allclose(back.free_ends_xy_m, narrow.free_ends_xy_m, atol=1e-12)
    # subsets and joins carry the per-beam margin
    sub = narrow.select_scans([1])
    np.testing.assert_array_equal(sub.grazing_margin_m, narrow.grazing_margin_m[narrow.scan_index == 1])
    joined = concat_beams(narrow.select_scans([0]), narrow.select_scans([1, 2]))
    np.testing.assert_array_equal(joined.grazing_margin_m, narrow.grazing_margin_m)
    # the configuration reaches the beams the pipeline makes
    seq = ScanSequence(ranges, angles, np.arange(3), 0.1, 20.0)
    cfg = MappingConfig(free_space={"margin_m": 0.1, "band_m": 0.05, "band_per_m": 0.01, "margin_max_m": 2.0})
    made = MapBuilder.from_config(cfg).beams(seq, poses, np.zeros(3))
    direct = beams_from_scan_sequence(
        seq, poses, None, 2.0, 0.1, free_band_m=0.05, free_band_per_m=0.01, free_margin_max_m=2.0
    )
    np.testing.assert_array_equal(made.free_ends_xy_m, direct.free_ends_xy_m)
    assert (made.grazing_margin_m > 0.1).any()
    # GPPOL's free points run along each beam up to the same free length
    moments = input_moments(narrow, None, [SensorNoise(0.0, 0.0)])  # exact means
    hit_beam = np.flatnonzero(narrow.is_hit)
    _, seg = GaussianInputs(moments).core_arrays(narrow, hit_beam)
    free_len = seg[:, 13]  # the column the core reads the free length from (mapping.core._gaussian_inputs)
    np.testing.assert_allclose(free_len, _free_len(narrow), atol=1e-12)
    free_end = moments.mean_at(free_len[None, :], np.arange(len(narrow))[None, :])[0]
    np.testing.assert_allclose(free_end, narrow.free_ends_xy_m, atol=1e-9)
