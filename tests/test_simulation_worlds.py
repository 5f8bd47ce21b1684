"""The three simulated worlds in memory: faithful to the paper's datasets I and II, and a loop for SLAM."""

from __future__ import annotations

import numpy as np
import pytest

from datasets.errors import DatasetError
from datasets.se2 import compose
from datasets.simulation import SimulatedRun, World, cast_rays, make_world, rasterize
from datasets.simulation.geometry import polygon_area_m2


@pytest.fixture(scope="module")
def street() -> SimulatedRun:
    return make_world("street", 0)


@pytest.fixture(scope="module")
def two() -> SimulatedRun:
    return make_world("two-platform", 0)


@pytest.fixture(scope="module")
def loop() -> SimulatedRun:
    return make_world("loop", 0)


def laser_poses(run: SimulatedRun) -> np.ndarray:
    scans = run.recording.scans
    mounts = np.stack([run.platforms[i].laser_in_base_xytheta for i in scans.source_index])
    return compose(run.true_poses.poses_xytheta, mounts)


def distance_to_occupied_cells(run: SimulatedRun, points: np.ndarray, radius_cells: int) -> np.ndarray:
    """(N,) True where an occupied cell lies within ``radius_cells`` of each point's cell."""
    gt = run.ground_truth
    rc = gt.cell_of(points)
    h, w = gt.occupancy.shape
    near = np.zeros(len(points), dtype=bool)
    for di in range(-radius_cells, radius_cells + 1):
        for dj in range(-radius_cells, radius_cells + 1):
            r = np.clip(rc[:, 0] + di, 0, h - 1)
            c = np.clip(rc[:, 1] + dj, 0, w - 1)
            near |= gt.occupancy[r, c] == 1
    return near


def check_common(run: SimulatedRun) -> None:
    """Invariants of every world: poses in free space, returns on surfaces, raster geometry, metadata."""
    rec, gt = run.recording, run.ground_truth
    scans = rec.scans
    assert scans is not None and rec.reference is not None
    assert len(rec.reference) == len(scans)
    np.testing.assert_array_equal(rec.reference.stamps_ns, scans.stamps_ns)
    assert np.all(np.diff(scans.stamps_ns) >= 0)
    # the raster covers the scene at its resolution
    xmin, ymin, xmax, ymax = run.world.bounds_xy_m
    assert gt.occupancy.shape == (
        round((ymax - ymin) / gt.resolution_m),
        round((xmax - xmin) / gt.resolution_m),
    )
    assert gt.occupancy.dtype == np.uint8 and set(np.unique(gt.occupancy)) <= {0, 1}
    # every robot pose and laser is in free space, clear of obstacles
    poses = rec.reference.poses_xytheta
    assert not gt.occupied_at(poses[:, :2]).any()
    assert not distance_to_occupied_cells(run, laser_poses(run)[:, :2], 2).any()
    # each return lies on a surface (an occupied cell next to it) with free space in front of it: the ray
    # caster and the raster agree
    lp = laser_poses(run)
    ends, befores = [], []
    n_seen = n_returns = 0
    for k in range(len(scans)):
        r = scans.ranges_m[k].astype(np.float64)
        ok = np.isfinite(r) & (r > 0)
        a = scans.angles_rad[k].astype(np.float64)[ok] + lp[k, 2]
        d = np.stack([np.cos(a), np.sin(a)], axis=1)
        exact = cast_rays(lp[k, :2], a, run.world.edges())
        seen = np.isfinite(exact)  # (a noisy bearing may hit what the nominal beam misses)
        n_seen += int(seen.sum())
        n_returns += len(seen)
        ends.append(lp[k, :2] + d[seen] * exact[seen, None])
        befores.append(lp[k, :2] + d[seen] * (exact[seen, None] - 0.3))
    assert n_seen >= 0.95 * n_returns
    ends, befores = np.concatenate(ends), np.concatenate(befores)
    assert distance_to_occupied_cells(run, ends, 1).all()
    assert (~gt.occupied_at(befores)).mean() > 0.97
    # ground-truth metadata names every scan source with its noise
    assert [s.name for s in gt.sources] == scans.sources
    assert gt.world == run.name and gt.seed == run.seed


def test_unknown_world_is_a_clear_error() -> None:
    with pytest.raises(DatasetError, match="unknown simulated world 'moon'"):
        make_world("moon")


# ---------------------------------------------------------------------------------------------- street
def test_street_matches_the_papers_dataset_one(street: SimulatedRun) -> None:
    check_common(street)
    scans = street.recording.scans
    assert len(scans) == 28
    assert set(scans.beam_counts()) == {17}
    assert sum(scans.beam_counts()) == 476  # "a sensor reading database of just 476 entries"
    angles = scans.angles_rad[0].astype(np.float64)
    assert angles[0] == pytest.approx(-np.pi / 2, abs=1e-6) and angles[-1] == pytest.approx(
        np.pi / 2, abs=1e-6
    )
    assert np.all(scans.range_max_m == 34.0)
    assert street.world.area_m2 == pytest.approx(18_000, rel=0.05)
    # the beams are centred on the direction of travel
    poses = street.true_poses.poses_xytheta
    travel = np.arctan2(*np.diff(poses[:, :2], axis=0).T[::-1])
    assert np.abs(np.angle(np.exp(1j * (travel - poses[:-1, 2])))).max() < np.deg2rad(25)
    # negligible noise; returns, and no-returns written as +inf
    src = street.ground_truth.sources[0]
    assert src.range_variance_m2 <= 1e-4 and src.bearing_variance_rad2 <= 1e-6
    r = np.stack(scans.ranges_m)
    assert np.isinf(r).any() and np.isfinite(r).mean() > 0.5
    # the robot drives the main street, then turns into a side street
    assert np.ptp(poses[:, 0]) > 100 and np.ptp(poses[:, 1]) > 30
    # odometry = the known poses
    np.testing.assert_allclose(street.recording.odometry.poses_xytheta, poses)


def test_street_has_buildings_cars_and_vans_of_the_right_size(street: SimulatedRun) -> None:
    kinds = street.world.kinds
    assert kinds.count("building") >= 20
    n_cars, n_vans = kinds.count("car"), kinds.count("van")
    assert n_cars >= 10 and n_vans >= 2 and 15 <= n_cars + n_vans <= 40  # "a number of parked cars and vans"
    for kind, (length, width) in (("car", (4.5, 1.8)), ("van", (5.5, 2.1))):
        for p in street.world.select(kind):
            sides = np.hypot(*np.diff(np.vstack([p, p[:1]]), axis=0).T)
            assert max(sides) == pytest.approx(length, rel=0.05)
            assert min(sides) == pytest.approx(width, rel=0.05)
    # parked vehicles stand in the street, not in buildings
    buildings = World(
        "b",
        tuple(street.world.select("building")),
        ("b",) * kinds.count("building"),
        street.world.bounds_xy_m,
    )
    occ, origin = rasterize(buildings, 0.1)
    vehicles = [p for p, k in zip(street.world.polygons, kinds, strict=True) if k in ("car", "van")]
    gt_b = street.ground_truth.__class__(occ, 0.1, origin, "b")
    assert not gt_b.occupied_at(np.array([p.mean(axis=0) for p in vehicles])).any()
    # the raster's occupied area matches the polygons' (buildings do not overlap)
    area = sum(polygon_area_m2(p) for p in street.world.polygons)
    assert street.ground_truth.occupancy.sum() * 0.01 == pytest.approx(area, rel=0.01)


def free_cells_in_view(run: SimulatedRun, rays_per_scan: int = 1801) -> float:
    """Fraction of the free cells in view of some scan: in line of sight of its pose, within its range and
    its 180-deg fan (every bearing, not only the 17 beams)."""
    gt = run.ground_truth
    centres = gt.cell_centers_xy_m().reshape(-1, 2)
    free = gt.occupancy.ravel() == 0
    pts = centres[free]
    seen = np.zeros(len(pts), dtype=bool)
    range_max = float(run.recording.scans.range_max_m[0])
    edges = run.world.edges()
    for pose in laser_poses(run):
        rel = np.linspace(-np.pi / 2, np.pi / 2, rays_per_scan)
        reach = np.minimum(cast_rays(pose[:2], pose[2] + rel, edges), range_max)
        d = pts - pose[:2]
        dist = np.hypot(d[:, 0], d[:, 1])
        bearing = np.angle(np.exp(1j * (np.arctan2(d[:, 1], d[:, 0]) - pose[2])))
        k = np.clip(
            np.round((bearing + np.pi / 2) / np.pi * (rays_per_scan - 1)).astype(int), 0, rays_per_scan - 1
        )
        seen |= (np.abs(bearing) <= np.pi / 2) & (dist <= reach[k])
    return float(seen.mean())


def test_street_free_space_is_mostly_in_view_but_not_all() -> None:
    """The calibration of the street world (its docstring): about 80 % of the free space in view, as the
    paper's widened-beam grid implies, and unexplored roadways left."""
    run = make_world("street", 0, resolution_m=0.5)
    assert 0.72 < free_cells_in_view(run) < 0.86


def test_worlds_are_deterministic_per_seed() -> None:
    a, b, c = make_world("street", 3), make_world("street", 3), make_world("street", 4)
    for x, y in zip(a.recording.scans.ranges_m, b.recording.scans.ranges_m, strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.ground_truth.occupancy, b.ground_truth.occupancy)
    # another seed parks other cars (and draws other noise); the buildings stay
    assert not np.array_equal(a.ground_truth.occupancy, c.ground_truth.occupancy)
    assert [p.tolist() for p in a.world.select("building")] == [
        p.tolist() for p in c.world.select("building")
    ]


def test_any_raster_resolution(street: SimulatedRun) -> None:
    coarse = make_world("street", 0, resolution_m=0.5)
    assert coarse.ground_truth.occupancy.shape == (200, 360)
    assert coarse.ground_truth.occupancy.mean() == pytest.approx(
        street.ground_truth.occupancy.mean(), abs=0.01
    )


# ---------------------------------------------------------------------------------------- two-platform
def coverage(run: SimulatedRun, source: int, cell_m: float = 1.0) -> np.ndarray:
    """(H, W) bool: cells of ``cell_m`` crossed by a beam (free part or return) of platform ``source``."""
    scans = run.recording.scans
    xmin, ymin, xmax, ymax = run.world.bounds_xy_m
    seen = np.zeros((int((ymax - ymin) / cell_m), int((xmax - xmin) / cell_m)), dtype=bool)
    lp = laser_poses(run)
    for k in np.flatnonzero(scans.source_index == source):
        r = scans.ranges_m[k].astype(np.float64)
        length = np.where(np.isfinite(r), r, scans.range_max_m[k])
        a = scans.angles_rad[k].astype(np.float64) + lp[k, 2]
        t = np.linspace(0, 1, 60)[None, :] * length[:, None]
        x = lp[k, 0] + np.cos(a)[:, None] * t
        y = lp[k, 1] + np.sin(a)[:, None] * t
        i = np.clip(((y - ymin) / cell_m).astype(int), 0, seen.shape[0] - 1)
        j = np.clip(((x - xmin) / cell_m).astype(int), 0, seen.shape[1] - 1)
        seen[i, j] = True
    return seen


def test_two_platform_follows_table_two(two: SimulatedRun) -> None:
    check_common(two)
    scans = two.recording.scans
    assert scans.sources == ["/platform_1/scan", "/platform_2/scan"]
    spec = {  # Table 2: speed m/s, scans/s, range m, range variance m2, bearing variance deg2
        0: (0.5, 0.5, 20.0, 0.0, 0.0),
        1: (4.0, 4.0, 8.0, 0.8, 0.5),
    }
    for i, (speed, rate, range_m, rvar, bvar_deg2) in spec.items():
        idx = np.flatnonzero(scans.source_index == i)
        assert len(idx) > 100
        dt_s = np.diff(scans.stamps_ns[idx]) * 1e-9
        np.testing.assert_allclose(dt_s, 1.0 / rate, atol=1e-9)
        poses = two.true_poses.poses_xytheta[idx]
        v = np.hypot(*np.diff(poses[:, :2], axis=0).T) / dt_s
        assert np.median(v) == pytest.approx(speed, rel=0.02)
        assert np.all(scans.range_max_m[idx] == range_m)
        src = two.ground_truth.sources[i]
        assert src.range_variance_m2 == pytest.approx(rvar, abs=1e-4)
        assert np.rad2deg(np.sqrt(src.bearing_variance_rad2)) ** 2 == pytest.approx(bvar_deg2, abs=1e-6)
        # each platform has its own (exact) odometry, written to <ns>/odom
        odo = two.recording.meta["odometry_by_source"][scans.sources[i]]
        np.testing.assert_allclose(odo.poses_xytheta, poses)
    assert two.recording.odometry is None


def test_two_platform_has_parts_seen_by_platform_two_only_and_by_neither(two: SimulatedRun) -> None:
    seen1, seen2 = coverage(two, 0), coverage(two, 1)
    h, w = seen1.shape
    left = np.s_[:, : w // 2]
    upper_right = np.s_[h // 2 :, w // 2 :]
    lower_right = np.s_[: h // 2, int(w * 0.65) :]
    # the left part is scanned by both platforms
    assert (seen1[left] & seen2[left]).mean() > 0.15
    # in the upper right, platform II scans what platform I does not
    only2 = seen2[upper_right] & ~seen1[upper_right]
    assert only2.mean() > 0.1
    assert (seen1[upper_right] & ~seen2[upper_right]).mean() < 0.02
    # the lower right corner: neither
    assert (seen1 | seen2)[lower_right].mean() < 0.02


def test_platform_two_is_noisy_and_platform_one_is_not(two: SimulatedRun) -> None:
    scans = two.recording.scans
    lp = laser_poses(two)
    for i, (lo, hi) in ((0, (0.0, 0.02)), (1, (0.7, 1.0))):
        errs = []
        for k in np.flatnonzero(scans.source_index == i):
            r = scans.ranges_m[k].astype(np.float64)
            exact = cast_rays(lp[k, :2], scans.angles_rad[k].astype(np.float64) + lp[k, 2], two.world.edges())
            ok = np.isfinite(r) & (r > 0) & (exact < 0.6 * scans.range_max_m[k])
            errs.append(r[ok] - exact[ok])
        std = np.std(np.concatenate(errs))
        assert lo <= std <= hi, (i, std)


# ------------------------------------------------------------------------------------------------ loop
def test_loop_is_long_dense_and_revisits_its_start(loop: SimulatedRun) -> None:
    check_common(loop)
    scans = loop.recording.scans
    assert 300 <= len(scans) <= 1000
    assert set(scans.beam_counts()) == {360}
    angles = scans.angles_rad[0].astype(np.float64)
    assert np.diff(angles).mean() * 360 == pytest.approx(2 * np.pi, rel=1e-6)
    assert np.all(scans.range_max_m == 30.0)
    dense = loop.platforms[0].truth_dense.poses_xytheta
    length = np.hypot(*np.diff(dense[:, :2], axis=0).T).sum()
    assert 200 <= length <= 400
    np.testing.assert_allclose(dense[0], [0.0, 0.0, 0.0], atol=1e-9)  # starts at the origin, heading +x
    # the end of the run drives again through the start: loop-closure opportunities
    poses = loop.true_poses.poses_xytheta
    first, last = poses[: len(poses) // 10], poses[-len(poses) // 20 :]
    gaps = np.hypot(*(last[:, None, :2] - first[None, :, :2]).transpose(2, 0, 1)).min(axis=1)
    assert np.median(gaps) < 0.5
    # structure for scan matching: most beams return
    r = np.stack(scans.ranges_m)
    assert np.isfinite(r).mean() > 0.7
    kinds = set(loop.world.kinds)
    assert {"wall", "pillar", "furniture", "column", "glass"} <= kinds
    # the glazed facade is in the ground truth but returns nothing: no end point lies on it
    glass = loop.world.select("glass")
    gx0, gy0 = np.min(np.concatenate(glass), axis=0)
    gx1, gy1 = np.max(np.concatenate(glass), axis=0)
    assert loop.ground_truth.occupied_at(np.array([[(gx0 + gx1) / 2, (gy0 + gy1) / 2]])).all()
    lp = laser_poses(loop)
    hits = []
    for k in range(0, len(scans), 10):
        r = scans.ranges_m[k].astype(np.float64)
        ok = np.isfinite(r)
        a = scans.angles_rad[k].astype(np.float64)[ok] + lp[k, 2]
        hits.append(lp[k, :2] + r[ok, None] * np.stack([np.cos(a), np.sin(a)], axis=1))
    hits = np.concatenate(hits)
    on_glass = (hits[:, 0] > gx0 + 1) & (hits[:, 0] < gx1 - 1) & (np.abs(hits[:, 1] - (gy0 + gy1) / 2) < 0.3)
    assert not on_glass.any()
    np.testing.assert_allclose(loop.recording.laser_in_base_xytheta, [0.15, 0.0, 0.0])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_loop_odometry_drifts_by_metres(seed: int) -> None:
    run = make_world("loop", seed)
    platform = run.platforms[0]
    odo, truth = platform.odometry, platform.truth_dense
    np.testing.assert_array_equal(odo.stamps_ns, truth.stamps_ns)
    assert np.diff(odo.stamps_ns).max() == 50_000_000  # 20 Hz
    np.testing.assert_allclose(odo.poses_xytheta[0], truth.poses_xytheta[0])
    end_error = np.hypot(*(odo.poses_xytheta[-1, :2] - truth.poses_xytheta[-1, :2]))
    assert end_error > 1.0
    # realistic: locally the odometry is good (1 m of travel: a few cm of error)
    rel_o = odo.poses_xytheta[20:, :2] - odo.poses_xytheta[:-20, :2]
    rel_t = truth.poses_xytheta[20:, :2] - truth.poses_xytheta[:-20, :2]
    assert np.median(np.abs(np.hypot(*rel_o.T) - np.hypot(*rel_t.T))) < 0.03
    noise = run.ground_truth.odometry_noise
    assert noise["distance_scale_error"] > 0 and noise["yaw_bias_rad_per_m"] > 0
