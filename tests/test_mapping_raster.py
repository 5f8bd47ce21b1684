"""The compiled grid helpers shared by the neighbour indexes and the occupancy-grid baseline: the cell walk
along a segment (mapping.raster) and the ring search of the k-NN (mapping.index), against brute force."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.index import _segment_cells, rings_next, rings_start
from mapping.raster import (
    GridGeometry,
    point_cell,
    segment_cells,
    segment_walk,
    squared_distances_cells,
    walk_next,
    within_distance,
)

GRID = GridGeometry.of(-1.3, 0.7, 0.37, 23, 17)


def walked_cells(grid: GridGeometry, p0, p1, clamp: bool = False) -> list[tuple[int, int]]:
    """The cells of the walk from p0 to p1: its ``steps`` cells, then the end cell (as the baseline's ray)."""
    w, ex, ey, steps = segment_walk(grid, p0[0], p0[1], p1[0], p1[1], clamp)
    cells = []
    for _ in range(steps):
        cells.append((w.ix, w.iy))
        w = walk_next(w)
    assert (w.ix, w.iy) == (ex, ey)  # the walk ends in the end point's cell
    return [*cells, (ex, ey)]


def sampled_cells(grid: GridGeometry, p0, p1, per_cell: int = 20_000) -> list[tuple[int, int]]:
    """Brute force: the distinct cells of points densely spaced along the segment, in order."""
    n = max(2, int(np.hypot(*(np.subtract(p1, p0))) / grid.cell * per_cell))
    t = np.linspace(0.0, 1.0, n)
    xy = np.asarray(p0) + t[:, None] * (np.asarray(p1) - np.asarray(p0))
    ij = np.floor((xy - [grid.x0, grid.y0]) / grid.cell).astype(np.int64)
    keep = np.r_[True, np.any(ij[1:] != ij[:-1], axis=1)]
    return [(int(i), int(j)) for i, j in ij[keep]]


def random_segments(n: int, seed: int, lo: float, hi: float) -> np.ndarray:
    return np.random.default_rng(seed).uniform(lo, hi, (n, 4))


def test_the_cell_walk_visits_the_cells_of_a_supersampled_segment_in_order() -> None:
    # segments anywhere (partly or wholly outside the grid: the baseline's walk is not clamped)
    for s in random_segments(300, 0, -4.0, 10.0):
        p0, p1 = s[:2], s[2:]
        assert walked_cells(GRID, p0, p1) == sampled_cells(GRID, p0, p1)


@pytest.mark.parametrize(
    "p0, p1", [((0.1, 1.0), (0.1, 5.0)), ((3.0, 2.0), (-1.0, 2.0)), ((2.0, 2.0), (2.0, 2.0))]
)
def test_axis_parallel_and_degenerate_walks(p0, p1) -> None:
    assert walked_cells(GRID, p0, p1) == sampled_cells(GRID, p0, p1)


def test_segment_cells_lists_the_walks_cells_inside_the_grid() -> None:
    out = np.empty((GRID.nx + GRID.ny, 2), np.int64)  # the bound it documents
    inside_some = 0
    for s in random_segments(300, 1, -8.0, 14.0):  # many cross the grid's border or miss it
        p0, p1 = s[:2], s[2:]
        want = [c for c in sampled_cells(GRID, p0, p1) if 0 <= c[0] < GRID.nx and 0 <= c[1] < GRID.ny]
        n = segment_cells(GRID, p0[0], p0[1], p1[0], p1[1], out)
        assert [tuple(int(v) for v in row) for row in out[:n]] == want
        inside_some += n > 0
    assert 0 < inside_some < 300
    assert point_cell(GRID, -1.3 + 0.37 * 2.5, 0.7 - 0.1) == (2, -1)


def test_the_segment_index_lists_the_cells_each_segment_crosses() -> None:
    # segments inside the grid: the index's walk (ends clamped into the grid) lists the same cells, as ids
    lo = np.array([GRID.x0, GRID.y0]) + 1e-3
    hi = lo + np.array([GRID.nx, GRID.ny]) * GRID.cell - 2e-3
    rng = np.random.default_rng(1)
    p0 = rng.uniform(lo, hi, (200, 2))
    p1 = rng.uniform(lo, hi, (200, 2))
    counts, cells = _segment_cells(p0, p1, GRID)
    offsets = np.r_[0, np.cumsum(counts)]
    for i in range(200):
        expected = [ix * GRID.ny + iy for ix, iy in sampled_cells(GRID, p0[i], p1[i])]
        assert cells[offsets[i] : offsets[i + 1]].tolist() == expected


@pytest.mark.parametrize("q", [(3.1, 2.2), (-1.3, 0.7), (7.2, 6.9), (-5.0, 3.0), (20.0, -9.0), (2.0, 40.0)])
def test_the_ring_search_visits_every_cell_once_ring_by_ring(q) -> None:
    """Never full, the search visits every cell of the grid once, by growing Chebyshev distance from the
    query's cell, inside the grid or not."""
    gx, gy = (q[0] - GRID.x0) / GRID.cell, (q[1] - GRID.y0) / GRID.cell
    cx, cy = int(np.floor(gx)), int(np.floor(gy))
    rings = rings_start(GRID, gx, gy)
    seen = []
    while not rings.done:
        assert 0 <= rings.ix < GRID.nx and 0 <= rings.iy < GRID.ny
        assert max(abs(rings.ix - cx), abs(rings.iy - cy)) == rings.r
        seen.append((rings.ix, rings.iy))
        rings = rings_next(GRID, rings, False, 0.0)
    assert len(seen) == len(set(seen)) == GRID.nx * GRID.ny
    r = [max(abs(ix - cx), abs(iy - cy)) for ix, iy in seen]
    assert r == sorted(r)


def test_the_ring_search_stops_once_the_kth_distance_lies_within_the_rings_searched() -> None:
    gx, gy = 10.4, 8.5  # 0.4 and 0.5 cells from the query cell's lower sides
    cell = GRID.cell
    # after ring r, every unseen item is at least (r + 0.4) cells away
    for kth_cells, last_ring in ((0.3, 0), (0.41, 1), (1.39, 1), (1.41, 2), (4.2, 4)):
        rings = rings_start(GRID, gx, gy)
        last = rings.r
        while not rings.done:
            last = rings.r
            rings = rings_next(GRID, rings, True, (kth_cells * cell) ** 2)
        assert last == last_ring, kth_cells


def test_within_distance_equals_scipys_distance_transform() -> None:
    """The compiled distance transform against ``scipy.ndimage.distance_transform_edt`` on random masks
    (sparse and dense, single rows and columns): the squared distances exactly, and the thresholded mask at
    radii on and between the integer distances."""
    from scipy import ndimage

    rng = np.random.default_rng(0)
    cases = (((50, 70), 0.02), ((300, 200), 0.001), ((1, 50), 0.1), ((40, 1), 0.1), ((90, 90), 0.3))
    for shape, density in cases:
        marked = rng.random(shape) < density
        marked[rng.integers(shape[0]), rng.integers(shape[1])] = True
        distance = ndimage.distance_transform_edt(~marked)
        np.testing.assert_array_equal(np.sqrt(squared_distances_cells(marked)), distance)
        for radius in (0.0, 1.0, 1.5, math.sqrt(8.0), 3.3, 7.0, 40.0):
            np.testing.assert_array_equal(within_distance(marked, radius), distance <= radius)
    empty = np.zeros((5, 6), dtype=bool)
    assert not within_distance(empty, 3.0).any() and not within_distance(empty, np.inf).any()
    assert within_distance(~empty, np.inf).all() and not within_distance(~empty, -1.0).any()
