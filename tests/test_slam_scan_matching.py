"""The grid scan matcher on synthetic rooms: correlative search, point-to-line refinement, the information
of an alignment (a corridor constrains one direction only), normals and the free-space check."""

from __future__ import annotations

import numpy as np
import pytest

from slam import geometry as se2
from slam.odometry import search_window
from slam.scan_matching import (
    PointGrid,
    ScorePyramid,
    _csm,
    branch_and_bound_search,
    correlative_search,
    fitness,
    mark_free_space,
    overlap,
    refine_point_to_line,
    scan_normals,
    voxel_thin,
)

ROOM = [  # walls as segments (x0, y0, x1, y1): a 10 x 6 m room with a pillar and a notch
    (0, 0, 10, 0),
    (10, 0, 10, 6),
    (10, 6, 0, 6),
    (0, 6, 0, 0),
    (4, 2, 5, 2),
    (5, 2, 5, 3),
    (5, 3, 4, 3),
    (4, 3, 4, 2),
    (7, 6, 7, 4.5),
    (7, 4.5, 8, 4.5),
    (8, 4.5, 8, 6),
]
CORRIDOR = [(-50, 0, 50, 0), (-50, 2, 50, 2)]


def cast(pose: np.ndarray, walls: list, n: int = 360, max_range: float = 30.0) -> np.ndarray:
    """(P, 2) body-frame end points of ``n`` beams over 360 degrees (exact segment intersection)."""
    ang = np.linspace(-np.pi, np.pi, n, endpoint=False)
    d = np.stack([np.cos(ang + pose[2]), np.sin(ang + pose[2])], axis=1)
    best = np.full(n, np.inf)
    for x0, y0, x1, y1 in walls:
        e = np.array([x1 - x0, y1 - y0], dtype=float)
        w = np.array([x0, y0]) - pose[:2]
        den = d[:, 0] * (-e[1]) - d[:, 1] * (-e[0])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[0] * (-e[1]) - w[1] * (-e[0])) / den
            u = (d[:, 0] * w[1] - d[:, 1] * w[0]) / den
        ok = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
        best = np.where(ok & (t < best), t, best)
    hit = best < max_range
    return np.stack([best[hit] * np.cos(ang[hit]), best[hit] * np.sin(ang[hit])], axis=1)


def _map(pose: np.ndarray, walls: list) -> tuple[PointGrid, np.ndarray]:
    pts = cast(pose, walls)
    world = se2.transform_points(pose, pts)
    rot = se2.rot3(pose[2])[:2, :2]
    grid = PointGrid.from_points(world, scan_normals(pts) @ rot.T)
    return grid, world


def test_normals_of_a_straight_wall_are_perpendicular() -> None:
    x = np.linspace(-1, 1, 21)
    pts = np.stack([x, np.full_like(x, 2.0)], axis=1)
    n = scan_normals(pts)
    assert np.all(np.isfinite(n))
    np.testing.assert_allclose(np.abs(n[:, 1]), 1.0, atol=1e-9)
    lonely = scan_normals(np.array([[0.0, 0.0], [5.0, 0.0], [10.0, 3.0]]))
    assert np.all(np.isnan(lonely))


@pytest.mark.parametrize("offset", [(0.12, -0.08, 0.05), (-0.3, 0.25, -0.12)])
def test_search_and_refinement_recover_a_known_pose(offset: tuple) -> None:
    map_pose = np.array([3.0, 1.5, 0.2])
    grid, _ = _map(map_pose, ROOM)
    true_pose = se2.compose(map_pose, np.array(offset))
    scan = cast(true_pose, ROOM)
    found = correlative_search(grid, scan, map_pose, 0.4, 0.2, np.radians(0.25))
    assert found.score > 0.5
    al = refine_point_to_line(grid, scan, found.pose_xytheta)
    err = se2.between(true_pose, al.pose_xytheta)
    assert np.hypot(err[0], err[1]) < 0.01
    assert abs(err[2]) < np.radians(0.1)
    assert al.rms_m < 0.01
    # the information is symmetric positive definite: the room pins every direction
    eig = np.linalg.eigvalsh(al.hessian)
    assert np.all(eig > 0)
    # a start 2 m and 60 deg off is beyond the refinement's reach: that is what the search is for
    far = refine_point_to_line(grid, scan, se2.compose(true_pose, np.array([2.0, -1.5, 1.0])))
    assert np.hypot(*se2.between(true_pose, far.pose_xytheta)[:2]) > 0.1


def test_a_corridor_constrains_one_direction_and_the_prior_holds_the_other() -> None:
    pose = np.array([0.0, 1.0, 0.0])
    # a map seen from elsewhere (the scan itself would match exactly at its own pose), beyond its reach
    others = ([-10.0, 1.0, 0.0], [-3.3, 1.0, 0.0], [3.7, 1.0, 0.0], [10.0, 1.0, 0.0])
    world = np.concatenate([se2.transform_points(np.array(p), cast(np.array(p), CORRIDOR)) for p in others])
    grid = PointGrid.from_points(world, np.tile([0.0, 1.0], (len(world), 1)))
    scan = cast(pose, CORRIDOR)
    al = refine_point_to_line(grid, scan, pose)
    eig = np.linalg.eigvalsh(al.hessian[:2, :2])
    assert eig[0] < 1e-3 * eig[1]  # the corridor's axis is not observed
    # a wheel prior 0.3 m ahead along the axis is kept along the axis; across it the walls win
    prior = np.array([0.3, 1.05, 0.0])
    info = np.diag([1 / 0.05**2, 1 / 0.05**2, 1 / 0.02**2])
    al2 = refine_point_to_line(grid, scan, prior, prior_xytheta=prior, prior_information=info)
    assert al2.pose_xytheta[0] == pytest.approx(0.3, abs=0.01)
    assert al2.pose_xytheta[1] == pytest.approx(1.0, abs=0.005)


def test_free_space_check_separates_partial_overlap_from_a_wrong_alignment() -> None:
    map_pose = np.array([2.0, 1.5, 0.0])
    grid, world = _map(map_pose, ROOM)
    mark_free_space(grid, np.tile(map_pose[:2], (world.shape[0], 1)), world, 0.15)
    query_pose = np.array([6.0, 3.5, 1.0])
    scan = cast(query_pose, ROOM)
    hits, conflicts = overlap(grid, scan, query_pose)
    assert hits > 0.5 * scan.shape[0]
    assert conflicts <= 0.05 * (hits + conflicts)
    wrong = se2.compose(query_pose, np.array([0.0, 0.0, np.pi / 2]))
    hits_w, conflicts_w = overlap(grid, scan, wrong)
    assert conflicts_w > 0.3 * (hits_w + conflicts_w)
    # fitness counts the same hits over all points, and needs no free space
    assert fitness(grid, scan, query_pose) == hits / scan.shape[0]
    assert fitness(grid, scan, wrong) == hits_w / scan.shape[0] < 0.5


def test_grid_insert_and_reset() -> None:
    grid = PointGrid.around(np.zeros(2), 2.0, resolution_m=0.05)
    assert np.all(grid.nearest == -1)
    grid.insert(np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[1.0, 0.0], [0.0, 1.0]]))
    assert len(grid) == 2
    cell = ((np.array([1.0, 1.0]) - grid.origin_xy_m) / grid.resolution_m).astype(int)
    assert grid.nearest[cell[1], cell[0]] == 1
    assert grid.score[cell[1], cell[0]] > 0.5
    grid.reset(np.array([10.0, 10.0]))
    assert len(grid) == 0 and np.all(grid.nearest == -1) and np.all(grid.score == 0)


def test_grid_insertion_equals_a_cell_by_cell_reference() -> None:
    """Every cell holds the first of the nearest points within the radius (its distance stored in float32)
    and that distance's score, whether points come in one batch or in batches that revisit the same walls
    (whose rows the compiled insertion skips when no cell improves)."""
    rng = np.random.default_rng(5)
    wall = np.column_stack([np.linspace(-1.5, 1.5, 120), np.full(120, 0.3)])
    pts = np.concatenate([wall, wall + rng.normal(0, 0.01, wall.shape), rng.uniform(-2.2, 2.2, (60, 2))])
    nrm = np.tile([0.0, 1.0], (len(pts), 1))
    batched = PointGrid.around(np.zeros(2), 2.0, resolution_m=0.05, radius_m=0.3, sigma_m=0.05)
    for part in np.array_split(np.arange(len(pts)), 4):
        batched.insert(pts[part], nrm[part])
    ys, xs = np.mgrid[: batched.shape[0], : batched.shape[1]]
    centres = batched.origin_xy_m + (np.stack([xs, ys], axis=-1) + 0.5) * batched.resolution_m
    d2 = np.full(batched.shape, np.inf, np.float32)
    nearest = np.full(batched.shape, -1, np.int32)
    score = np.zeros(batched.shape, np.float32)
    for i, p in enumerate(pts):
        dd = np.sum((centres - p) ** 2, axis=-1)
        better = (dd <= 0.3**2) & (dd < d2)
        d2[better] = dd[better]
        nearest[better] = i
        score[better] = np.exp(-dd[better] / (2 * 0.05**2))
    np.testing.assert_array_equal(batched.nearest, nearest)
    np.testing.assert_array_equal(batched.score, score)
    np.testing.assert_array_equal(batched._d2, d2)


@pytest.mark.parametrize("spread_m", [0.5, 40.0])
def test_reset_empties_every_written_cell(spread_m: float) -> None:
    """A reset leaves the grid as a new one: dense points (the bounding box is cleared) and points spread far
    apart, some beyond the grid's edge (only the cells around them are), and a grid reused after it fills
    exactly as a new one does."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(-spread_m, spread_m, size=(300, 2))
    nrm = np.tile([1.0, 0.0], (300, 1))
    grid = PointGrid.around(np.zeros(2), 30.0, resolution_m=0.05)
    grid.insert(pts, nrm)
    assert np.any(grid.score > 0)
    grid.reset(np.array([1.0, -2.0]))
    assert np.all(grid.nearest == -1) and np.all(grid.score == 0) and np.all(np.isinf(grid._d2))
    grid.insert(pts[:100], nrm[:100])
    fresh = PointGrid(grid.origin_xy_m, grid.shape, 0.05)
    fresh.insert(pts[:100], nrm[:100])
    np.testing.assert_array_equal(grid.nearest, fresh.nearest)
    np.testing.assert_array_equal(grid.score, fresh.score)


def test_normals_face_the_sensor() -> None:
    x = np.linspace(-1, 1, 21)
    above = scan_normals(np.stack([x, np.full_like(x, 2.0)], axis=1))
    below = scan_normals(np.stack([x, np.full_like(x, -2.0)], axis=1))
    np.testing.assert_allclose(above[:, 1], -1.0, atol=1e-9)  # a wall at y = 2 faces the origin: -y
    np.testing.assert_allclose(below[:, 1], 1.0, atol=1e-9)
    # a metric radius gathers many beams of a dense scan, a beam window of 2 only 5 of them
    rng = np.random.default_rng(3)
    dense = np.stack([np.linspace(-1, 1, 401), 2.0 + rng.normal(0, 0.01, 401)], axis=1)
    tilt_narrow = np.abs(scan_normals(dense, 0.3, 2)[:, 0])
    tilt_wide = np.abs(scan_normals(dense, 0.3, 60)[:, 0])
    assert np.nanmedian(tilt_wide) < 0.2 * np.nanmedian(tilt_narrow)


def test_the_far_face_of_a_thin_wall_does_not_attract_a_scan() -> None:
    """A 0.2 m wall seen from the left in the map (face x = 1.0) and from the right in the scan (face
    x = 1.2): nearest-point matching drags the scan 0.2 m onto the wrong face; with the scan's normals
    (facing its sensor, opposite to the map's) those points find no partner and the pose stays put."""
    y = np.linspace(-1.0, 1.0, 81)
    floor_x = np.linspace(-1.0, 3.0, 161)
    floor = np.stack([floor_x, np.full_like(floor_x, -2.0)], axis=1)
    map_pts = np.concatenate([np.stack([np.full_like(y, 1.0), y], axis=1), floor])
    map_sensor = np.array([0.0, 0.0])
    grid = PointGrid.from_points(map_pts, scan_normals(map_pts - map_sensor))
    scan_sensor = np.array([2.0, 0.0])
    scan_pts = np.concatenate([np.stack([np.full_like(y, 1.2), y], axis=1), floor]) - scan_sensor
    nrm = scan_normals(scan_pts)
    pose = np.array([2.0, 0.0, 0.0])
    prior_info = np.diag([1.0, 1.0, 100.0])  # a weak prior at the true pose
    plain = refine_point_to_line(grid, scan_pts, pose, prior_xytheta=pose, prior_information=prior_info)
    checked = refine_point_to_line(
        grid, scan_pts, pose, prior_xytheta=pose, prior_information=prior_info, normals_xy=nrm
    )
    assert plain.pose_xytheta[0] < 2.0 - 0.15  # dragged onto the wrong face
    assert abs(checked.pose_xytheta[0] - 2.0) < 0.01
    assert checked.hessian[0, 0] < 1e-6 * checked.hessian[1, 1]  # the wall's points matched nothing


@pytest.mark.parametrize("trial", range(4))
def test_branch_and_bound_finds_the_exhaustive_optimum(trial: int) -> None:
    """Branch and bound is exact: the same best pose and score as scoring every pose of the window, from
    a grid's own pyramid and from a prebuilt one, at any pyramid depth."""
    rng = np.random.default_rng(trial)
    map_pose = np.array([3.0, 1.5, 0.2])
    grid, _ = _map(map_pose, ROOM)
    true_pose = se2.compose(map_pose, rng.uniform([-0.8, -0.8, -0.5], [0.8, 0.8, 0.5]))
    scan = cast(true_pose, ROOM, n=180)
    step = np.radians(0.5)
    n_lin, n_ang = 20, int(np.ceil(0.6 / step))
    best = _csm(grid.score, *grid.origin_xy_m, grid.resolution_m, scan, *map_pose, n_lin, 1, n_ang, step, 1)[
        0
    ]
    found = branch_and_bound_search(grid, scan, map_pose, 1.0, 0.6, step)
    np.testing.assert_allclose(found.pose_xytheta, best[1:], atol=1e-9)
    assert found.score == pytest.approx(best[0] / len(scan))
    for depth in (0, 3, 7):
        pyr = ScorePyramid.of_grid(grid, depth)
        again = branch_and_bound_search(pyr, scan, map_pose, 1.0, 0.6, step)
        np.testing.assert_allclose(again.pose_xytheta, best[1:], atol=1e-9)
    assert np.hypot(*se2.between(true_pose, found.pose_xytheta)[:2]) < 0.1
    # a score the window cannot reach prunes everything: no pose
    none = branch_and_bound_search(grid, scan, map_pose, 1.0, 0.6, step, min_score=0.99)
    assert none.score == 0.0 and np.array_equal(none.pose_xytheta, map_pose)


@pytest.mark.parametrize("trial", range(3))
def test_a_wide_heading_search_over_few_cells_is_exhaustive_and_exact(trial: int) -> None:
    """The odometry's retry (every heading within 0.5 rad, a translation window of two cells, no prior) is
    searched exhaustively instead of building a score pyramid over the scan's reach: the same lattice of
    poses, so the same best pose and score as branch and bound."""
    rng = np.random.default_rng(10 + trial)
    map_pose = np.array([3.0, 1.5, 0.2])
    grid, _ = _map(map_pose, ROOM)
    true_pose = se2.compose(map_pose, rng.uniform([-0.08, -0.08, -0.45], [0.08, 0.08, 0.45]))
    scan = cast(true_pose, ROOM, n=180)
    found = search_window(grid, scan, map_pose, 0.1, 0.5, 0.0044)
    assert grid._pyramid_buffer.size == 0  # no pyramid was built
    bnb = branch_and_bound_search(grid, scan, map_pose, 0.1, 0.5, 0.0044)  # step >= 0.25 deg: kept
    np.testing.assert_allclose(found.pose_xytheta, bnb.pose_xytheta, atol=1e-9)
    assert found.score == pytest.approx(bnb.score, rel=1e-12)
    assert abs(se2.between(true_pose, found.pose_xytheta)[2]) < np.radians(0.5)


def test_the_motion_prior_picks_the_pose_near_the_prediction_among_equal_matches() -> None:
    """In a featureless corridor every shift along it scores the same; the exhaustive search takes any of
    them, the prior-weighted search the one nearest the prediction."""
    pose = np.array([0.0, 1.0, 0.0])
    # a map seen from elsewhere (the scan itself would match exactly at its own pose), beyond its reach
    others = ([-10.0, 1.0, 0.0], [-3.3, 1.0, 0.0], [3.7, 1.0, 0.0], [10.0, 1.0, 0.0])
    world = np.concatenate([se2.transform_points(np.array(p), cast(np.array(p), CORRIDOR)) for p in others])
    grid = PointGrid.from_points(world, np.tile([0.0, 1.0], (len(world), 1)))
    scan = cast(pose, CORRIDOR)
    pred = np.array([0.4, 1.0, 0.0])  # 0.4 m along the axis from where the scan was taken
    found = branch_and_bound_search(
        grid,
        scan,
        pred,
        1.5,
        0.2,
        np.radians(0.5),
        prior_sigma_xy_m=0.5,
        prior_sigma_theta_rad=0.5,
        prior_weight=0.1,
    )
    assert abs(found.pose_xytheta[0] - 0.4) < 0.051 and abs(found.pose_xytheta[1] - 1.0) < 0.051


@pytest.mark.parametrize("n", [0, 1, 7, 5000, 120_000])
def test_voxel_thin_keeps_the_first_point_of_every_voxel(n: int) -> None:
    """Against the sorting definition (np.unique's first index per voxel), with repeated points and
    negative coordinates: the hash table must give the same points in the same order."""
    rng = np.random.default_rng(n)
    pts = rng.normal(scale=4.0, size=(n, 2)) - 3.0
    pts = np.concatenate([pts, pts[: n // 3] + 1e-4])  # near-duplicates, most in their originals' voxels
    got = voxel_thin(pts, 0.05)
    if len(pts) == 0:
        assert got.shape == (0,)
        return
    cells = np.floor(pts / 0.05).astype(np.int64)
    keys = [tuple(c) for c in cells]
    first: dict[tuple, int] = {}
    for i, key in enumerate(keys):
        first.setdefault(key, i)
    np.testing.assert_array_equal(got, sorted(first.values()))
