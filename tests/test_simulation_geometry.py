"""Simulation maths: exact ray casting, ground-truth rasters, the laser and odometry models, paths."""

from __future__ import annotations

import re

import numpy as np
import pytest

from datasets.errors import DatasetError
from datasets.se2 import between as relative
from datasets.se2 import compose
from datasets.simulation import (
    GroundTruth,
    LaserSpec,
    NoiseSource,
    OdometryNoise,
    World,
    cast_rays,
    load_ground_truth,
    rasterize,
    save_ground_truth,
)
from datasets.simulation.geometry import box, polygon_area_m2, rectangle, regular_polygon, wall_with_gaps
from datasets.simulation.sensors import SmoothPath, drift_odometry, simulate_ranges

ROOM = World("room", (box(-2.0, -1.0, 3.0, 4.0),), ("wall",), (-5.0, -5.0, 5.0, 5.0))
BLOCK = World("block", (box(2.0, 2.0, 3.0, 3.0),), ("building",), (0.0, 0.0, 5.0, 5.0))


def cast1(world: World, x: float, y: float, angle_deg: float) -> float:
    return float(cast_rays(np.array([x, y]), np.array(np.deg2rad(angle_deg)), world.edges()))


# ------------------------------------------------------------------------------------------ ray casting
@pytest.mark.parametrize(
    ("angle_deg", "expected_m"),
    [(0.0, 3.0), (90.0, 4.0), (180.0, 2.0), (-90.0, 1.0)],
)
def test_ray_inside_a_square_room_hits_each_wall_exactly(angle_deg: float, expected_m: float) -> None:
    assert cast1(ROOM, 0.0, 0.0, angle_deg) == pytest.approx(expected_m, abs=1e-12)


def test_ray_inside_room_at_an_angle() -> None:
    # from (0, 0) at atan2(1, 3): reaches x = 3 at y = 1 -> distance sqrt(10)
    angle = np.rad2deg(np.arctan2(1.0, 3.0))
    assert cast1(ROOM, 0.0, 0.0, angle) == pytest.approx(np.sqrt(10.0), abs=1e-12)


def test_ray_aimed_at_a_corner_hits_the_corner() -> None:
    assert cast1(BLOCK, 0.0, 0.0, 45.0) == pytest.approx(2.0 * np.sqrt(2.0), abs=1e-12)
    # the room's inner corner (3, 4) from the origin
    angle = np.rad2deg(np.arctan2(4.0, 3.0))
    assert cast1(ROOM, 0.0, 0.0, angle) == pytest.approx(5.0, abs=1e-12)


def test_ray_grazing_an_edge_hits_at_first_contact_and_just_past_it_misses() -> None:
    # along the block's bottom edge (y = 2) and top edge (y = 3): first contact at x = 2
    assert cast1(BLOCK, 0.0, 2.0, 0.0) == pytest.approx(2.0, abs=1e-12)
    assert cast1(BLOCK, 0.0, 3.0, 0.0) == pytest.approx(2.0, abs=1e-12)
    # a hair above the top edge: nothing to hit
    assert cast1(BLOCK, 0.0, 3.0 + 1e-6, 0.0) == np.inf
    # collinear with an edge, starting on it: contact at distance 0
    assert cast1(BLOCK, 2.5, 2.0, 0.0) == pytest.approx(0.0, abs=1e-12)


def test_ray_missing_everything_is_inf() -> None:
    assert cast1(BLOCK, 0.0, 0.0, 180.0) == np.inf
    assert cast1(BLOCK, 0.0, 0.0, 10.0) == np.inf  # passes below the block
    assert cast1(World("empty", (), (), (0, 0, 1, 1)), 0.0, 0.0, 0.0) == np.inf


def test_ray_takes_the_nearest_of_several_hits() -> None:
    world = World("two", (box(2.0, -1.0, 3.0, 1.0), box(5.0, -1.0, 6.0, 1.0)), ("a", "b"), (0, -2, 7, 2))
    assert cast1(world, 0.0, 0.0, 0.0) == pytest.approx(2.0, abs=1e-12)
    assert cast1(world, 4.0, 0.0, 0.0) == pytest.approx(1.0, abs=1e-12)
    assert cast1(world, 4.0, 0.0, 180.0) == pytest.approx(1.0, abs=1e-12)


def test_ray_casting_matches_a_brute_force_reference() -> None:
    rng = np.random.default_rng(5)
    polys = tuple(
        rectangle(rng.uniform(-20, 20, 2), *rng.uniform(0.5, 6, 2), rng.uniform(-3, 3)) for _ in range(30)
    )
    world = World("random", polys, ("x",) * 30, (-25, -25, 25, 25))
    origins = rng.uniform(-25, 25, (200, 2))
    angles = rng.uniform(-np.pi, np.pi, 200)
    got = cast_rays(origins, angles, world.edges())
    for o, a, g in zip(origins, angles, got, strict=True):
        d = np.array([np.cos(a), np.sin(a)])
        best = np.inf
        for x0, y0, x1, y1 in world.edges():
            m = np.array([[d[0], x0 - x1], [d[1], y0 - y1]])
            if abs(np.linalg.det(m)) < 1e-14:
                continue
            t, u = np.linalg.solve(m, np.array([x0, y0]) - o)
            if t >= 0 and 0 <= u <= 1:
                best = min(best, t)
        assert g == pytest.approx(best, rel=1e-9, abs=1e-9)


def test_ray_casting_broadcasts_poses_against_beams() -> None:
    origins = np.zeros((4, 1, 2))
    angles = np.deg2rad(np.array([0.0, 90.0, 180.0, -90.0]))[None, :] + np.zeros((4, 1))
    out = cast_rays(origins, angles, ROOM.edges())
    assert out.shape == (4, 4)
    np.testing.assert_allclose(out, np.tile([3.0, 4.0, 2.0, 1.0], (4, 1)), atol=1e-12)


# ---------------------------------------------------------------------------------------------- raster
@pytest.mark.parametrize("resolution_m", [0.5, 0.2, 0.1, 0.05])
def test_raster_area_matches_polygon_area(resolution_m: float) -> None:
    polys = (
        rectangle((10.3, 7.1), 4.5, 1.8, 0.3),
        rectangle((4.0, 4.0), 5.5, 2.1, 1.2),
        regular_polygon((15.0, 15.0), 2.0, 12),
        np.array([[1.0, 12.0], [8.0, 12.0], [8.0, 19.0], [6.0, 19.0], [6.0, 14.0], [1.0, 14.0]]),  # an L
    )
    world = World("shapes", polys, ("x",) * len(polys), (0.0, 0.0, 20.0, 20.0))
    occ, origin = rasterize(world, resolution_m)
    assert occ.shape == (round(20 / resolution_m),) * 2
    np.testing.assert_array_equal(origin, [0.0, 0.0])
    area = sum(polygon_area_m2(p) for p in polys)
    perimeter = sum(np.hypot(*np.diff(np.vstack([p, p[:1]]), axis=0).T).sum() for p in polys)
    measured = occ.sum() * resolution_m**2
    # centre sampling: the error is bounded by half a cell along the perimeter, and is far smaller on average
    assert abs(measured - area) <= 0.5 * perimeter * resolution_m
    assert abs(measured - area) <= 0.05 * area if resolution_m <= 0.1 else True


def test_raster_convention_row_zero_is_lowest_y() -> None:
    world = World("corner", (box(0.0, 0.0, 1.0, 1.0),), ("x",), (0.0, 0.0, 4.0, 2.0))
    occ, origin = rasterize(world, 0.5)
    assert occ.shape == (4, 8)
    expected = np.zeros((4, 8), np.uint8)
    expected[:2, :2] = 1
    np.testing.assert_array_equal(occ, expected)
    gt = GroundTruth(occ, 0.5, origin, "corner")
    assert gt.occupied_at(np.array([[0.25, 0.25], [0.25, 1.75], [3.9, 0.1], [-1.0, 0.0]])).tolist() == [
        True,
        False,
        False,
        False,
    ]
    assert gt.bounds_xy_m == (0.0, 0.0, 4.0, 2.0)
    np.testing.assert_allclose(gt.cell_centers_xy_m()[1, 2], [1.25, 0.75])


def test_raster_rejects_bad_resolution() -> None:
    with pytest.raises(DatasetError, match="resolution"):
        rasterize(BLOCK, 0.0)


def test_ground_truth_round_trip_is_exact_and_byte_stable(tmp_path) -> None:
    occ, origin = rasterize(BLOCK, 0.1)
    gt = GroundTruth(
        occupancy=occ,
        resolution_m=0.1,
        origin_xy_m=origin,
        world="block",
        frame_id="map",
        seed=7,
        sources=(NoiseSource("/platform_1/scan", 1e-4, 0.0), NoiseSource("/platform_2/scan", 0.8, 1.5e-4)),
        odometry_noise={"distance_scale_error": 0.01},
        meta={"note": "test"},
    )
    a, b = tmp_path / "a.gt.npz", tmp_path / "b.gt.npz"
    save_ground_truth(gt, a)
    save_ground_truth(gt, b)
    assert a.read_bytes() == b.read_bytes()
    back = load_ground_truth(a)
    np.testing.assert_array_equal(back.occupancy, occ)
    assert back.occupancy.dtype == np.uint8
    assert back.resolution_m == 0.1 and back.world == "block" and back.seed == 7 and back.frame_id == "map"
    np.testing.assert_array_equal(back.origin_xy_m, origin)
    assert back.sources == gt.sources
    assert back.odometry_noise == {"distance_scale_error": 0.01}
    assert back.meta["note"] == "test"
    # plain numpy can read it without pickle
    with np.load(a, allow_pickle=False) as z:
        assert z["source_names"].tolist() == ["/platform_1/scan", "/platform_2/scan"]
        assert float(z["resolution_m"]) == 0.1


def test_load_ground_truth_errors_name_the_file(tmp_path) -> None:
    missing = tmp_path / "none.gt.npz"
    with pytest.raises(DatasetError, match=re.escape(f"{missing}: no such ground-truth file")):
        load_ground_truth(missing)
    bad = tmp_path / "bad.gt.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match=re.escape(f"{bad}: not a readable ground-truth .npz")):
        load_ground_truth(bad)
    partial = tmp_path / "partial.gt.npz"
    np.savez(partial, occupancy=np.zeros((2, 2), np.uint8))
    with pytest.raises(DatasetError, match="lacks resolution_m, origin_xy_m"):
        load_ground_truth(partial)


# --------------------------------------------------------------------------------------------- polygons
def test_wall_with_gaps_leaves_the_doors_open() -> None:
    pieces = wall_with_gaps((0.0, 0.0), (10.0, 0.0), [(2.0, 1.0), (6.0, 1.5)], thickness_m=0.2)
    assert len(pieces) == 3
    world = World("w", tuple(pieces), ("wall",) * 3, (-1, -1, 11, 1))
    # beams across the wall: blocked except through the doors
    xs = np.array([1.0, 2.5, 4.0, 6.75, 9.0])
    hits = cast_rays(np.stack([xs, np.full(5, -0.5)], axis=1), np.full(5, np.pi / 2), world.edges())
    np.testing.assert_allclose(hits, [0.4, np.inf, 0.4, np.inf, 0.4], atol=1e-12)
    # the outer ends are extended by half the thickness (corners close)
    assert min(p[:, 0].min() for p in pieces) == pytest.approx(-0.1)
    assert max(p[:, 0].max() for p in pieces) == pytest.approx(10.1)
    with pytest.raises(DatasetError, match="gap"):
        wall_with_gaps((0, 0), (3, 0), [(2.5, 1.0)])


# -------------------------------------------------------------------------------------------- sensors
def test_laser_no_returns_are_inf_and_short_ranges_are_zero() -> None:
    spec = LaserSpec.sweep("/scan", 3, 180.0, range_min_m=0.5, range_max_m=2.5)
    np.testing.assert_allclose(spec.angles_rad(), [-np.pi / 2, 0.0, np.pi / 2], atol=1e-7)
    # in the room, from (2.7, 0): +x wall at 0.3 m (below range_min), +y wall at 4 m (beyond range),
    # -y wall at 1 m
    ranges = simulate_ranges(ROOM.edges(), np.array([[2.7, 0.0, 0.0]]), spec, np.random.default_rng(0))
    assert ranges.dtype == np.float32
    np.testing.assert_allclose(ranges[0], [1.0, 0.0, np.inf], atol=1e-6)


def test_laser_noise_statistics_and_nominal_bearings() -> None:
    spec = LaserSpec.sweep(
        "/scan",
        181,
        180.0,
        range_min_m=0.0,
        range_max_m=100.0,
        range_variance_m2=0.8,
        bearing_variance_rad2=0.0,
    )
    poses = np.zeros((40, 3))
    ranges = simulate_ranges(ROOM.edges(), poses, spec, np.random.default_rng(1)).astype(np.float64)
    exact = cast_rays(np.zeros(2), spec.angles_rad().astype(np.float64), ROOM.edges())
    err = ranges - exact[None, :]
    ok = np.isfinite(err) & (ranges > 0)
    assert ok.mean() > 0.95
    assert np.var(err[ok]) == pytest.approx(0.8, rel=0.1)
    # bearing noise: the beam is cast off its nominal angle, reported at the nominal angle
    spec_b = LaserSpec("/scan", 1, 0.0, 0.0, 0.0, 100.0, bearing_variance_rad2=0.01)
    r = simulate_ranges(ROOM.edges(), np.zeros((2000, 3)), spec_b, np.random.default_rng(2)).astype(
        np.float64
    )
    # beam at 0 rad hits the x = 3 wall at 3 / cos(eps): never shorter than 3, mean ~ 3 (1 + var / 2)
    assert r.min() >= 3.0 - 1e-5
    assert r.mean() == pytest.approx(3.0 * (1 + 0.01 / 2), rel=2e-3)


def test_odometry_without_noise_is_exact_and_scale_error_stretches_it() -> None:
    path = SmoothPath([(0, 0), (10, 0), (10, 10)], corner_radius_m=2.0)
    truth = path.at(np.linspace(0, path.length_m, 400))
    exact = drift_odometry(truth, OdometryNoise(), np.random.default_rng(0))
    np.testing.assert_allclose(exact, truth, atol=1e-9)
    scaled = drift_odometry(truth, OdometryNoise(distance_scale_error=0.1), np.random.default_rng(0))
    steps = np.hypot(*np.diff(scaled[:, :2], axis=0).T).sum()
    assert steps == pytest.approx(1.1 * np.hypot(*np.diff(truth[:, :2], axis=0).T).sum(), rel=1e-9)
    biased = drift_odometry(truth, OdometryNoise(yaw_bias_rad_per_m=0.01), np.random.default_rng(0))
    travelled = np.hypot(*np.diff(truth[:, :2], axis=0).T).sum()
    heading_gain = np.unwrap(biased[:, 2])[-1] - np.unwrap(truth[:, 2])[-1]
    assert heading_gain == pytest.approx(0.01 * travelled, rel=1e-6)


def test_odometry_random_drift_grows_with_distance_not_rate() -> None:
    noise = OdometryNoise(translation_variance_m2_per_m=0.01)
    finals = {}
    for n in (50, 500):  # the same 10 m straight line in 50 or 500 odometry steps
        truth = np.stack([np.linspace(0, 10, n + 1), np.zeros(n + 1), np.zeros(n + 1)], axis=1)
        ends = [drift_odometry(truth, noise, np.random.default_rng(k))[-1, 0] for k in range(600)]
        finals[n] = np.var(ends)
    for var in finals.values():
        assert var == pytest.approx(0.01 * 10, rel=0.2)


def test_compose_and_relative_are_inverse() -> None:
    rng = np.random.default_rng(3)
    a = rng.uniform(-5, 5, (20, 3))
    b = rng.uniform(-5, 5, (20, 3))
    np.testing.assert_allclose(
        compose(a, relative(a, b)),
        np.concatenate([b[:, :2], (b[:, 2:] + np.pi) % (2 * np.pi) - np.pi], axis=1),
        atol=1e-12,
    )


def test_smooth_path_is_continuous_with_tangent_heading() -> None:
    path = SmoothPath([(0, 0), (10, 0), (10, 10), (0, 10)], corner_radius_m=2.0)
    # two quarter-circle corners of radius 2 replace 4 m of straight legs each
    assert path.length_m == pytest.approx(30 - 4 * 2 + 2 * np.pi, abs=1e-3)
    s = np.linspace(0, path.length_m, 3000)
    poses = path.at(s)
    steps = np.diff(poses[:, :2], axis=0)
    assert np.hypot(*steps.T).max() < 1.01 * path.length_m / 2999
    tangent = np.arctan2(steps[:, 1], steps[:, 0])
    diff = np.angle(np.exp(1j * (tangent - poses[:-1, 2])))
    assert np.abs(diff).max() < 0.01
    with pytest.raises(DatasetError):
        SmoothPath([(0, 0)], 1.0)
