"""The branch-and-bound search's pyramids store only the part of the window that can score above 0 and reuse
their memory from one search to the next: the levels must equal max-pooling the whole window, and the search
must return exactly the pose (ties included) and score of the same search over a whole-window pyramid and
of scoring every candidate pose."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from slam.scan_matching import (
    PYRAMID_TILE_CELLS,
    PointGrid,
    ScorePyramid,
    _PyramidLayout,
    _reached_tiles,
    _rotated_cells,
    bnb_depth,
    branch_and_bound_search,
)


def reference_levels(
    grid: PointGrid, depth: int, pool: int, bounds_xy_m: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, float]:
    """``(levels (depth + 1, H, W), origin (2,), resolution)`` of the whole window of
    :meth:`ScorePyramid.of_grid`, by max-pooling every cell with numpy."""
    res = grid.resolution_m
    ox, oy = (float(v) for v in grid.origin_xy_m)
    gh, gw = grid.shape
    if bounds_xy_m is None:
        r0, c0, h, w = 0, 0, gh, gw
    else:
        c0 = math.floor((bounds_xy_m[0] - ox) / res)
        r0 = math.floor((bounds_xy_m[1] - oy) / res)
        w = math.ceil((bounds_xy_m[2] - ox) / res) + 1 - c0
        h = math.ceil((bounds_xy_m[3] - oy) / res) + 1 - r0
    h, w = -(-h // pool) * pool, -(-w // pool) * pool
    box = np.zeros((h, w), dtype=np.float32)
    for y in range(h):
        for x in range(w):
            if 0 <= r0 + y < gh and 0 <= c0 + x < gw:
                box[y, x] = grid.score[r0 + y, c0 + x]
    box = box.reshape(h // pool, pool, w // pool, pool).max(axis=(1, 3))
    pad = 1 << depth
    window = np.zeros((box.shape[0] + pad, box.shape[1] + pad), dtype=np.float32)
    window[pad:, pad:] = box
    levels = np.empty((depth + 1, *window.shape), dtype=np.float32)
    for d in range(depth + 1):
        k = 1 << d
        padded = np.zeros((window.shape[0] + k - 1, window.shape[1] + k - 1), dtype=np.float32)
        padded[: window.shape[0], : window.shape[1]] = window
        levels[d] = sliding_window_view(padded, (k, k)).max(axis=(2, 3))
    cres = res * pool
    return levels, np.array([ox + c0 * res - pad * cres, oy + r0 * res - pad * cres]), cres


def whole_window(pyramid: ScorePyramid, shape: tuple[int, ...]) -> np.ndarray:
    """The stored part of ``pyramid`` placed in a zero window of ``shape`` (depth + 1, H, W)."""
    r, c = pyramid.offset_rc
    d, h, w = pyramid.levels.shape
    assert r >= 0 and c >= 0 and r + h <= shape[1] and c + w <= shape[2] and d == shape[0]
    out = np.zeros(shape, dtype=np.float32)
    out[:, r : r + h, c : c + w] = pyramid.levels
    return out


def random_grid(rng: np.random.Generator, n_points: int) -> PointGrid:
    """A grid of random size and origin holding points in part of it (some outside it)."""
    h, w = (int(v) for v in rng.integers(20, 90, 2))
    grid = PointGrid(rng.uniform(-2.0, 2.0, 2), (h, w))
    lo = grid.origin_xy_m + rng.uniform(-0.5, 0.3 * w * 0.05, 2)
    pts = lo + rng.uniform(0.0, [0.5 * w * 0.05, 0.6 * h * 0.05], (n_points, 2))
    grid.insert(pts, np.zeros_like(pts))
    return grid


@pytest.mark.parametrize("seed", range(6))
def test_pyramid_levels_equal_max_pooling_the_whole_window(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for n_points in (0, 1, 25):
        grid = random_grid(rng, n_points)
        for depth in (0, 1, 3, 5):
            for pool in (1, 2, 3):
                bounds = None
                if rng.random() < 0.7:
                    corner = grid.origin_xy_m + rng.uniform(-1.5, 3.0, 2)
                    bounds = np.concatenate([corner, corner + rng.uniform(0.2, 4.0, 2)])
                ref, origin, res = reference_levels(grid, depth, pool, bounds)
                pyr = ScorePyramid.of_grid(grid, depth, pool, bounds)
                assert np.array_equal(whole_window(pyr, ref.shape), ref)
                assert np.array_equal(pyr.origin_xy_m, origin) and pyr.resolution_m == res
                # built in a reused buffer (too small, then large enough): the same levels
                for size in (1, ref.size + 7):
                    buf = np.full(size, np.nan, dtype=np.float32)
                    again = ScorePyramid.of_grid(grid, depth, pool, bounds, buf)
                    assert np.array_equal(again.levels, pyr.levels) and again.offset_rc == pyr.offset_rc


def lattice_grid(spacing_cells: int, extent_cells: int) -> PointGrid:
    """A grid whose points sit on cell centres ``spacing_cells`` apart: shifts by the spacing tie."""
    grid = PointGrid(np.zeros(2), (extent_cells, extent_cells))
    ij = np.arange(spacing_cells, extent_cells - spacing_cells, spacing_cells)
    pts = (np.stack(np.meshgrid(ij, ij), axis=-1).reshape(-1, 2) + 0.5) * grid.resolution_m
    grid.insert(pts, np.zeros_like(pts))
    return grid


def brute_force(
    grid: PointGrid, points: np.ndarray, center: np.ndarray, window_m: float, window_rad: float, step: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(poses (K, 3), totals (K,))`` of every candidate of :func:`branch_and_bound_search` (no prior):
    the summed level-0 scores, added point by point in float64 as the search does."""
    res = grid.resolution_m
    n_lin = max(math.ceil(window_m / res), 0)
    n_ang = max(math.ceil(window_rad / step), 0)
    r_max = float(np.max(np.hypot(points[:, 0], points[:, 1])))
    reach = r_max + window_m + 2 * res
    box = np.array([center[0] - reach, center[1] - reach, center[0] + reach, center[1] + reach])
    levels, origin, _ = reference_levels(grid, bnb_depth(window_m, res), 1, box)
    score = levels[0].astype(np.float64)
    h, w = score.shape
    offsets = np.arange(-n_lin, n_lin + 1)
    dy, dx = (v.ravel() for v in np.meshgrid(offsets, offsets, indexing="ij"))
    poses, totals = [], []
    for a in range(2 * n_ang + 1):
        th = center[2] + (a - n_ang) * step
        c, s = math.cos(th), math.sin(th)
        ix = np.array([math.floor((c * px - s * py + center[0] - origin[0]) / res) for px, py in points])
        iy = np.array([math.floor((s * px + c * py + center[1] - origin[1]) / res) for px, py in points])
        jx, jy = ix[None, :] + dx[:, None], iy[None, :] + dy[:, None]
        inside = (jx >= 0) & (jx < w) & (jy >= 0) & (jy < h)
        vals = np.where(inside, score[np.clip(jy, 0, h - 1), np.clip(jx, 0, w - 1)], 0.0)
        totals.append(np.cumsum(vals, axis=1)[:, -1])
        poses.append(np.stack([center[0] + dx * res, center[1] + dy * res, np.full(dx.size, th)], axis=1))
    return np.concatenate(poses), np.concatenate(totals)


@pytest.mark.parametrize("seed", range(4))
def test_search_returns_a_brute_force_optimum_and_breaks_ties_as_a_whole_window_pyramid(seed: int) -> None:
    rng = np.random.default_rng(seed)
    grid = lattice_grid(10, 120)
    center = np.array([3.0, 3.0, 0.0]) + np.append(rng.integers(-3, 4, 2) * grid.resolution_m, 0.0)
    # scan points on lattice cell centres around the centre (some beyond the map: no score)
    cells = rng.choice(np.arange(-40, 41, 10), size=(30, 2))
    points = (cells + 0.5) * grid.resolution_m + np.array([3.0, 3.0]) - center[:2]
    step = math.radians(0.5)
    window_m, window_rad = 0.8, 2 * step
    found = branch_and_bound_search(grid, points, center, window_m, window_rad, step)
    poses, totals = brute_force(grid, points, center, window_m, window_rad, step)
    best = totals.max()
    winners = poses[totals == best]
    assert len(winners) > 1  # the lattice ties
    assert any(np.array_equal(found.pose_xytheta, p) for p in winners)
    assert found.score == best / len(points)
    # the same traversal over the whole window: the same winner among the ties
    res = grid.resolution_m
    reach = float(np.max(np.hypot(points[:, 0], points[:, 1]))) + window_m + 2 * res
    box = np.array([center[0] - reach, center[1] - reach, center[0] + reach, center[1] + reach])
    levels, origin, cres = reference_levels(grid, bnb_depth(window_m, res), 1, box)
    whole = branch_and_bound_search(
        ScorePyramid(levels, origin, cres), points, center, window_m, window_rad, step
    )
    assert np.array_equal(whole.pose_xytheta, found.pose_xytheta) and whole.score == found.score


def test_search_with_a_motion_prior_matches_a_whole_window_pyramid_after_each_insertion() -> None:
    """Searches of one grid reuse its pyramid memory across windows of different sizes and insertions:
    each result equals the search over a whole-window pyramid of the grid as it is then."""
    rng = np.random.default_rng(7)
    grid = PointGrid(np.array([-1.0, -2.0]), (160, 150))
    walls = rng.uniform([0.0, -1.0], [6.0, 5.0], (4, 2, 2))
    step = math.radians(0.5)
    for i in range(6):
        a, b = walls[i % 4]
        t = rng.uniform(0.0, 1.0, (40, 1))
        pts = a + t * (b - a) + rng.normal(0.0, 0.02, (40, 2))
        grid.insert(pts, np.zeros_like(pts))
        center = np.array([2.5, 1.5, 0.1]) + rng.normal(0.0, [0.3, 0.3, 0.05])
        scan = se2_inverse_transform(center, grid.points_xy[rng.choice(len(grid), 60)])
        scan += rng.normal(0.0, 0.03, scan.shape)
        window_m = (0.3, 1.2, 0.6)[i % 3]
        kw = {"prior_sigma_xy_m": 0.5, "prior_sigma_theta_rad": 0.5, "prior_weight": 0.1}
        found = branch_and_bound_search(grid, scan, center, window_m, 0.2, step, **kw)
        res = grid.resolution_m
        reach = float(np.max(np.hypot(scan[:, 0], scan[:, 1]))) + window_m + 2 * res
        box = np.array([center[0] - reach, center[1] - reach, center[0] + reach, center[1] + reach])
        levels, origin, cres = reference_levels(grid, bnb_depth(window_m, res), 1, box)
        whole = branch_and_bound_search(
            ScorePyramid(levels, origin, cres), scan, center, window_m, 0.2, step, **kw
        )
        assert np.array_equal(whole.pose_xytheta, found.pose_xytheta) and whole.score == found.score
        assert found.score > 0.0


def se2_inverse_transform(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P, 2) world points in the frame of ``pose``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d = points - pose[:2]
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)


def walls_grid(rng: np.random.Generator) -> tuple[PointGrid, np.ndarray, np.ndarray]:
    """A 12 m x 12 m grid holding a few long walls (most of the box around a scan is empty), a scan (P, 2)
    of them and the pose (3,) near the middle it was taken from."""
    grid = PointGrid(np.array([-6.0, -6.0]), (240, 240))
    for _ in range(5):
        a, b = rng.uniform(-5.5, 5.5, (2, 2))
        t = rng.uniform(0.0, 1.0, (80, 1))
        pts = a + t * (b - a)
        grid.insert(pts, np.zeros_like(pts))
    center = np.append(rng.uniform(-0.5, 0.5, 2), rng.uniform(-0.3, 0.3))
    scan = se2_inverse_transform(center, grid.points_xy[rng.choice(len(grid), 70)])
    return grid, scan + rng.normal(0.0, 0.02, scan.shape), center


@pytest.mark.parametrize("seed", range(5))
def test_a_pyramid_built_for_one_search_holds_every_cell_the_search_reads(seed: int) -> None:
    """A search builds its pyramid only on the tiles its transformed points reach: every cell a node of the
    search can read (any rotation, any offset within the window) lies in a built tile, and the built
    tiles hold the whole pyramid's values on every level."""
    rng = np.random.default_rng(seed)
    grid, scan, _ = walls_grid(rng)
    window_m = float(rng.choice([0.2, 0.45, 1.0]))
    step = math.radians(0.5)
    n_ang = int(rng.integers(0, 8))
    res = grid.resolution_m
    n_lin = math.ceil(window_m / res)
    box = np.array([-7.0, -7.0, 7.0, 7.0])
    layout = _PyramidLayout.of_grid(grid, bnb_depth(window_m, res), 1, box)
    (x0, y0), (row0, col0) = layout.origin_xy_m, layout.offset_rc
    ixs, iys = _rotated_cells(scan, 0.0, 0.0, 0.0, n_ang, step, x0, y0, res, row0, col0)
    tile = max(PYRAMID_TILE_CELLS, 1 << layout.depth)
    tiles = _reached_tiles(ixs, iys, n_lin, layout.h, layout.w, tile)
    assert 0 < tiles.sum() < tiles.size  # the walls leave tiles out
    # every cell read: a rotated point's cell shifted by an offset within the window, inside the part
    offsets = np.arange(-n_lin, n_lin + 1)
    jy = (iys[:, :, None, None] + offsets[:, None]).ravel()
    jx = (ixs[:, :, None, None] + offsets[None, :]).ravel()
    inside = (jy >= 0) & (jy < layout.h) & (jx >= 0) & (jx < layout.w)
    assert tiles[jy[inside] // tile, jx[inside] // tile].all()
    lazy = layout.build(np.full((layout.depth + 1) * layout.h * layout.w, np.nan, np.float32), tiles, tile)
    whole = layout.build()
    cells = np.kron(tiles, np.ones((tile, tile), dtype=bool))[: layout.h, : layout.w]
    assert np.isnan(lazy.levels[:, ~cells]).any()  # not built: still the buffer's NaN
    assert np.array_equal(lazy.levels[:, cells], whole.levels[:, cells])


@pytest.mark.parametrize("seed", range(5))
def test_a_search_reads_no_cell_its_pyramid_left_unbuilt(seed: int) -> None:
    """The grid's pyramid memory filled with NaN first: the search returns exactly the whole-window
    search's pose and score (a NaN read would change them)."""
    rng = np.random.default_rng(100 + seed)
    grid, scan, true_pose = walls_grid(rng)
    center = true_pose + np.array([0.15, -0.2, 0.05])
    window_m, window_rad, step = 0.6, 0.1, math.radians(0.5)
    grid._pyramid_buffer = np.full(4_000_000, np.nan, dtype=np.float32)
    kw = {"prior_sigma_xy_m": 0.5, "prior_sigma_theta_rad": 0.5, "prior_weight": 0.05}
    found = branch_and_bound_search(grid, scan, center, window_m, window_rad, step, **kw)
    assert np.isnan(grid._pyramid_buffer).any()  # built in that memory, part of it left alone
    res = grid.resolution_m
    reach = float(np.max(np.hypot(scan[:, 0], scan[:, 1]))) + window_m + 2 * res
    box = np.array([center[0] - reach, center[1] - reach, center[0] + reach, center[1] + reach])
    levels, origin, cres = reference_levels(grid, bnb_depth(window_m, res), 1, box)
    whole = branch_and_bound_search(
        ScorePyramid(levels, origin, cres), scan, center, window_m, window_rad, step, **kw
    )
    assert np.isfinite(found.score) and found.score > 0.0
    assert np.array_equal(whole.pose_xytheta, found.pose_xytheta) and whole.score == found.score
