"""Uniform-grid spatial indexes for occupied endpoints and free beam segments, with compiled k-NN search.

The paper stores training data in a kd-tree (section 3.7); a uniform grid does the same job faster for 2D
laser maps: each cell lists the items it holds (endpoints) or the segments crossing it (beams), in CSR form
(``cell_start`` (C+1,), ``items`` (E,)). A k-NN query walks square rings of cells around the query and
stops when the k-th best distance is below the distance to the next ring, so results are exact.

Compiled code takes an index as named tuples (:class:`CellIndex`, and the data with it: :class:`PointSet`,
:class:`SegmentSet`); :class:`GridIndex` is the Python-side index that builds them. Numba's parallel loops
pass only one level of tuples into their bodies, so a parallel caller hands them in flat
(:func:`flat_points` / :func:`points_of`, :func:`flat_segments` / :func:`segments_of`). The searches and
their non-inlined helpers allocate nothing and are compiled without reference counting (``_nrt=False``,
see :mod:`mapping.core`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mapping.raster import GridGeometry, in_grid, segment_walk, walk_next

FloatArray = NDArray[np.float64]


class CellIndex(NamedTuple):
    """A grid index for compiled code: cell ``c = ix * grid.ny + iy`` lists
    ``items[cell_start[c]:cell_start[c + 1]]``; ``most`` is the largest number of items in one cell (the
    size of per-cell scratch buffers)."""

    grid: GridGeometry
    cell_start: NDArray[np.int64]
    items: NDArray[np.int32]
    most: int


class PointSet(NamedTuple):
    """Points for :func:`knn_points`: ``xy`` (P, 2) sorted by cell of ``index`` (whose items are then
    ``0..P-1``)."""

    xy: FloatArray
    index: CellIndex


class SegmentSet(NamedTuple):
    """Segments for :func:`knn_segments`: ``seg`` (M, 5), one per row, (start x, start y, d x, d y,
    1 / |d|^2); ``entries`` (5, E) float32 copies of them per entry of ``index`` (start relative to the
    entry's cell centre, see :func:`segment_entry_copies`)."""

    seg: FloatArray
    entries: NDArray[np.float32]
    index: CellIndex


@dataclass(frozen=True)
class GridIndex:
    """Items binned in a uniform grid of ``shape`` = (nx, ny) cells of ``cell_m``, lower-left ``origin_xy_m``.

    Cell ``(ix, iy)`` has id ``ix * ny + iy`` and holds ``items[cell_start[id]:cell_start[id + 1]]``.
    """

    origin_xy_m: FloatArray
    cell_m: float
    shape: tuple[int, int]
    cell_start: NDArray[np.int64]
    items: NDArray[np.int32]

    @property
    def mean_items_per_occupied_cell(self) -> float:
        counts = np.diff(self.cell_start)
        nonzero = counts[counts > 0]
        return float(nonzero.mean()) if nonzero.size else 0.0

    @property
    def geometry(self) -> GridGeometry:
        """The grid's corner, cell and size."""
        o = self.origin_xy_m
        return GridGeometry.of(o[0], o[1], self.cell_m, self.shape[0], self.shape[1])

    @cached_property
    def packed(self) -> CellIndex:
        """The index for compiled code (computed once)."""
        most = int(np.diff(self.cell_start).max()) if self.cell_start.size > 1 else 0
        return CellIndex(self.geometry, self.cell_start, self.items, most)


def _grid_geometry(points_xy_m: FloatArray, cell_m: float) -> tuple[FloatArray, tuple[int, int]]:
    if points_xy_m.shape[0] == 0:
        return np.zeros(2), (1, 1)
    lo = points_xy_m.min(axis=0) - 1e-6
    hi = points_xy_m.max(axis=0) + 1e-6
    shape = np.maximum(np.ceil((hi - lo) / cell_m).astype(np.int64), 1)
    return lo, (int(shape[0]), int(shape[1]))


def build_point_index(points_xy_m: FloatArray, cell_m: float) -> GridIndex:
    """Index of (P, 2) points in cells of ``cell_m``."""
    pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    origin, (nx, ny) = _grid_geometry(pts, cell_m)
    if pts.shape[0] == 0:
        return GridIndex(origin, cell_m, (nx, ny), np.zeros(nx * ny + 1, np.int64), np.zeros(0, np.int32))
    ij = np.floor((pts - origin) / cell_m).astype(np.int64)
    ij[:, 0] = np.clip(ij[:, 0], 0, nx - 1)
    ij[:, 1] = np.clip(ij[:, 1], 0, ny - 1)
    cell = ij[:, 0] * ny + ij[:, 1]
    start, order = _by_cell(cell, nx * ny)
    return GridIndex(origin, cell_m, (nx, ny), start, order.astype(np.int32))


def _by_cell(cells: NDArray[np.int64], n_cells: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The (n_cells + 1,) start of each cell's entries and the (E,) entries ordered by cell, each cell's in
    their order in ``cells`` (E,): ``np.argsort(cells, kind="stable")``, by counting (a big building's
    index has millions of entries)."""
    per_cell = np.bincount(cells, minlength=n_cells)
    start = np.zeros(n_cells + 1, np.int64)
    np.cumsum(per_cell, out=start[1:])
    order = np.empty(cells.size, np.int64)
    _place_by_cell(cells, start, order)
    return start, order


@nb.njit(cache=True, error_model="numpy")
def _place_by_cell(cells, start, order):
    """Counting sort's placing pass: entry ``e`` goes to the next free slot of its cell."""
    nxt = start[:-1].copy()
    for e in range(cells.size):
        c = cells[e]
        order[nxt[c]] = e
        nxt[c] += 1


@nb.njit(cache=True, error_model="numpy")
def _traverse(x0, y0, x1, y1, grid, out_cells, fill):
    """Number of cells of ``grid`` the segment (x0, y0)-(x1, y1) crosses, its ends clamped into the grid
    (the walk stops where it would leave it); writes their ids to ``out_cells`` when ``fill``."""
    w, ex, ey, steps = segment_walk(grid, x0, y0, x1, y1, True)
    n = 0
    while True:
        if fill:
            out_cells[n] = w.ix * grid.ny + w.iy
        n += 1
        if (w.ix == ex and w.iy == ey) or n > steps:
            break
        w = walk_next(w)
        if not in_grid(grid, w.ix, w.iy):
            break
    return n


@nb.njit(cache=True, error_model="numpy")
def _segment_cells(p0, p1, grid):
    """Cells crossed by the (M, 2)-(M, 2) segments: (M,) counts and the cell ids, segment after segment."""
    m = p0.shape[0]
    counts = np.empty(m, np.int64)
    dummy = np.empty(1, np.int64)
    for i in range(m):
        counts[i] = _traverse(p0[i, 0], p0[i, 1], p1[i, 0], p1[i, 1], grid, dummy, False)
    offs = np.zeros(m + 1, np.int64)
    for i in range(m):
        offs[i + 1] = offs[i] + counts[i]
    cells = np.empty(offs[m], np.int64)
    for i in range(m):
        _traverse(p0[i, 0], p0[i, 1], p1[i, 0], p1[i, 1], grid, cells[offs[i] : offs[i + 1]], True)
    return counts, cells


def segment_entry_copies(index: GridIndex, seg: FloatArray) -> NDArray[np.float32]:
    """(5, E) float32 copies of the (M, 5) segments ``seg`` for every entry of a segment ``index``, in entry
    order, with the start relative to the centre of the entry's cell (for :func:`knn_segments`)."""
    out = np.empty((5, index.items.size), np.float32)
    _entry_copies(
        index.cell_start,
        index.items,
        np.ascontiguousarray(seg, dtype=np.float64),
        float(index.origin_xy_m[0]),
        float(index.origin_xy_m[1]),
        float(index.cell_m),
        int(index.shape[1]),
        out,
    )
    return out


@nb.njit(cache=True, error_model="numpy")
def _entry_copies(cell_start, items, seg, x0, y0, cell_m, ny, out):
    """Fill ``out`` (5, E) for :func:`segment_entry_copies`: a compiled walk over the cells (numpy's per-entry
    cell ids, divisions and gathers cost a big building's map seconds)."""
    for c in range(cell_start.size - 1):
        centre_x = x0 + (c // ny + 0.5) * cell_m
        centre_y = y0 + (c % ny + 0.5) * cell_m
        for e in range(cell_start[c], cell_start[c + 1]):
            s = items[e]
            out[0, e] = seg[s, 0] - centre_x
            out[1, e] = seg[s, 1] - centre_y
            for k in range(2, 5):
                out[k, e] = seg[s, k]


def build_segment_index(starts_xy_m: FloatArray, ends_xy_m: FloatArray, cell_m: float) -> GridIndex:
    """Index of (M, 2)-(M, 2) segments: every cell lists the segments crossing it."""
    p0 = np.ascontiguousarray(starts_xy_m, dtype=np.float64).reshape(-1, 2)
    p1 = np.ascontiguousarray(ends_xy_m, dtype=np.float64).reshape(-1, 2)
    origin, (nx, ny) = _grid_geometry(np.concatenate([p0, p1]), cell_m)
    if p0.shape[0] == 0:
        return GridIndex(origin, cell_m, (nx, ny), np.zeros(nx * ny + 1, np.int64), np.zeros(0, np.int32))
    counts, cells = _segment_cells(p0, p1, GridGeometry.of(origin[0], origin[1], cell_m, nx, ny))
    seg = np.repeat(np.arange(p0.shape[0], dtype=np.int32), counts)
    start, order = _by_cell(cells, nx * ny)
    return GridIndex(origin, cell_m, (nx, ny), start, seg[order])


# ---------------------------------------------------------------------------------------------------------
# Flat forms of the index tuples, for parallel loops (module docstring).


@nb.njit(cache=True, error_model="numpy", inline="always")
def flat_points(points):
    """A :class:`PointSet` as a flat tuple of arrays and scalars."""
    c = points.index
    g = c.grid
    return (points.xy, c.cell_start, c.items, c.most, g.x0, g.y0, g.cell, g.nx, g.ny)


@nb.njit(cache=True, error_model="numpy", inline="always")
def points_of(f):
    """The :class:`PointSet` of :func:`flat_points`."""
    return PointSet(f[0], CellIndex(GridGeometry(f[4], f[5], f[6], f[7], f[8]), f[1], f[2], f[3]))


@nb.njit(cache=True, error_model="numpy", inline="always")
def flat_segments(segments):
    """A :class:`SegmentSet` as a flat tuple of arrays and scalars."""
    c = segments.index
    g = c.grid
    return (segments.seg, segments.entries, c.cell_start, c.items, c.most, g.x0, g.y0, g.cell, g.nx, g.ny)


@nb.njit(cache=True, error_model="numpy", inline="always")
def segments_of(f):
    """The :class:`SegmentSet` of :func:`flat_segments`."""
    return SegmentSet(f[0], f[1], CellIndex(GridGeometry(f[5], f[6], f[7], f[8], f[9]), f[2], f[3], f[4]))


# ---------------------------------------------------------------------------------------------------------
# Compiled k-NN. Results are kept sorted by squared distance in (k,) buffers; the return value is the count.


@nb.njit(cache=True, error_model="numpy", inline="always")
def _insert(best_d2, best_id, best_t, count, k, d2, idx, t):
    """Insert (d2, idx, t) into the sorted top-k buffers; returns the new count."""
    if count == k:
        if d2 >= best_d2[k - 1]:
            return count
        j = k - 1
    else:
        j = count
        count += 1
    while j > 0 and best_d2[j - 1] > d2:
        best_d2[j] = best_d2[j - 1]
        best_id[j] = best_id[j - 1]
        best_t[j] = best_t[j - 1]
        j -= 1
    best_d2[j] = d2
    best_id[j] = idx
    best_t[j] = t
    return count


@nb.njit(cache=True, error_model="numpy", inline="always")
def _rank_place(d2s, n, w, best_d2, best_id, idx):
    """Write ``d2s[w]`` and ``idx`` at the rank of entry w among ``d2s[:n]`` (ties in entry order)."""
    d = d2s[w]
    r = 0
    for v in range(n):
        dv = d2s[v]
        r += (dv < d) | ((dv == d) & (v < w))
    best_d2[r] = d
    best_id[r] = idx
    return r


@nb.njit(cache=True, error_model="numpy", inline="always")
def _rank_sort(best_d2, best_id, best_t, m):
    """Sort the m entries (d2, id, t) of the buffers by d2, stably (as inserting them one by one in their
    order would): ranks first (branch-free), then the permutation in place, cycle by cycle; ids are
    non-negative int32 values, the rank is kept above them meanwhile."""
    low = (1 << 32) - 1
    placed = 1 << 62
    for w in range(m):
        d = best_d2[w]
        r = 0
        for v in range(m):
            dv = best_d2[v]
            r += (dv < d) | ((dv == d) & (v < w))
        best_id[w] |= r << 32
    for p in range(m):
        cur = best_id[p]
        if cur >= placed:
            continue
        d = best_d2[p]
        t = best_t[p]
        while True:
            r = cur >> 32
            nd = best_d2[r]
            nt = best_t[r]
            nxt = best_id[r]
            best_d2[r] = d
            best_t[r] = t
            best_id[r] = (cur & low) | placed
            if r == p:
                break
            d = nd
            t = nt
            cur = nxt
    for p in range(m):
        best_id[p] &= low


@nb.njit(cache=True, error_model="numpy", inline="always")
def _listed(ids, count, i):
    for j in range(count):
        if ids[j] == i:
            return True
    return False


@nb.njit(cache=True, error_model="numpy", inline="always")
def _cell_d2(gx, gy, ix, iy):
    """Squared distance (in cell units) from grid point (gx, gy) to cell (ix, iy)."""
    ddx = max(max(ix - gx, gx - (ix + 1)), 0.0)
    ddy = max(max(iy - gy, gy - (iy + 1)), 0.0)
    return ddx * ddx + ddy * ddy


@nb.njit(cache=True, error_model="numpy", inline="always")
def _square(gx, gy, radius, nx, ny):
    """Cell ranges (inclusive) of the square of half-side ``radius`` (cells) around (gx, gy), in the grid."""
    return (
        max(math.floor(gx - radius), 0),
        min(math.floor(gx + radius), nx - 1),
        max(math.floor(gy - radius), 0),
        min(math.floor(gy + radius), ny - 1),
    )


# ---------------------------------------------------------------------------------------------------------
# The ring search of a cold start (no warm candidates, or fewer than k): square rings of cells of growing
# radius r around the query's cell (cx, cy), ring r being the cells at Chebyshev distance r from it, in the
# grid only. After each ring the search stops once the k-th distance found lies within the block of rings
# searched (every unseen item is then farther), or when the rings have left the grid. A caller steps a
# :class:`Rings` cursor: :func:`rings_start`, then :func:`rings_next` after each cell it visits.


class Rings(NamedTuple):
    """A ring search at cell (ix, iy) of ring ``r`` around (cx, cy); the query is (gx, gy) in cell units,
    rings beyond ``rmax`` lie outside the grid; ``done`` once the search may stop."""

    gx: float
    gy: float
    cx: int
    cy: int
    rmax: int
    r: int
    ix: int
    iy: int
    done: bool


@nb.njit(cache=True, error_model="numpy", inline="always")
def _ring_step(cx, cy, r, ix, iy):
    """The cell after (ix, iy) on ring r, column by column (a side column whole, others top and bottom)."""
    if ix == cx - r or ix == cx + r:
        iy += 1
    else:
        iy += 2 * r
    if iy > cy + r:
        ix += 1
        iy = cy - r
    return ix, iy


@nb.njit(cache=True, error_model="numpy", inline="always")
def _ring_seek(grid, gx, gy, cx, cy, rmax, r, ix, iy, full, kth_d2):
    """From cell (ix, iy) of ring r on, the first cell in the grid; past the end of a ring, the next ring,
    unless the search may stop (``full``: k items found, the k-th at squared distance ``kth_d2``)."""
    while True:
        x_hi = min(cx + r, grid.nx - 1)
        while ix <= x_hi:
            if 0 <= iy < grid.ny:
                return Rings(gx, gy, cx, cy, rmax, r, ix, iy, False)
            ix, iy = _ring_step(cx, cy, r, ix, iy)
        if r >= rmax:
            break
        if full:
            # distance from the query to the outside of the (2r+1)^2 block of cells
            b = min(
                min(gx - (cx - r), (cx + r + 1) - gx),
                min(gy - (cy - r), (cy + r + 1) - gy),
            )
            b *= grid.cell
            if b > 0 and b * b >= kth_d2:
                break
        r += 1
        ix = max(cx - r, 0)
        iy = cy - r
    return Rings(gx, gy, cx, cy, rmax, r, ix, iy, True)


@nb.njit(cache=True, error_model="numpy", inline="always")
def rings_start(grid, gx, gy):
    """The first cell of a ring search around (gx, gy) (cell units) in ``grid``."""
    cx = math.floor(gx)
    cy = math.floor(gy)
    # rings beyond this radius lie entirely outside the grid
    rmax = max(max(cx, grid.nx - 1 - cx), max(cy, grid.ny - 1 - cy))
    return _ring_seek(grid, gx, gy, cx, cy, rmax, 0, max(cx, 0), cy, False, 0.0)


@nb.njit(cache=True, error_model="numpy", inline="always")
def rings_next(grid, rings, full, kth_d2):
    """The cell after the current one, with the search's state after visiting it (``full``: k items found,
    the k-th at squared distance ``kth_d2``)."""
    ix, iy = _ring_step(rings.cx, rings.cy, rings.r, rings.ix, rings.iy)
    return _ring_seek(grid, rings.gx, rings.gy, rings.cx, rings.cy, rings.rmax, rings.r, ix, iy, full, kth_d2)


# ---------------------------------------------------------------------------------------------------------
# Endpoints.


@nb.njit(cache=True, error_model="numpy", inline="always")
def _point_cell(qx, qy, pts, cell_start, k, best_d2, best_id, best_t, buf, c, count, check_dup):
    """Offer the points of cell ``c`` to the top-k buffers (distances first, in one vectorised pass)."""
    start = cell_start[c]
    end = cell_start[c + 1]
    if end > start:
        _cell_point_d2(qx, qy, pts, start, end, buf)
        for i in range(start, end):
            d2 = buf[i - start]
            if count < k or d2 < best_d2[k - 1]:
                if check_dup and _listed(best_id, count, i):
                    continue
                count = _insert(best_d2, best_id, best_t, count, k, d2, i, 0.0)
    return count


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def knn_points(qx, qy, points, k, best_d2, best_id, best_t, warm, n_warm, buf):
    """The k points of ``points`` (a :class:`PointSet`) nearest (qx, qy): writes sorted squared distances
    and indices into ``points.xy``; returns how many were found. ``warm[:n_warm]`` are distinct candidate
    indices tried first (e.g. the neighbours of the previous, nearby query): they only make the search
    faster, never change its result. ``buf`` (``points.index.most`` long) receives each cell's distances."""
    count = 0
    pts = points.xy
    if k == 0 or pts.shape[0] == 0:
        return 0
    if n_warm <= k:
        # the warm candidates in order of distance (stably, as inserting them one by one would): by rank,
        # with their distances in ``best_t`` meanwhile (branch-free, unlike insertion)
        for w in range(n_warm):
            i = warm[w]
            dx = pts[i, 0] - qx
            dy = pts[i, 1] - qy
            best_t[w] = dx * dx + dy * dy
        for w in range(n_warm):
            _rank_place(best_t, n_warm, w, best_d2, best_id, warm[w])
        count = n_warm
        for w in range(n_warm):
            best_t[w] = 0.0
    else:
        for w in range(n_warm):
            i = warm[w]
            dx = pts[i, 0] - qx
            dy = pts[i, 1] - qy
            count = _insert(best_d2, best_id, best_t, count, k, dx * dx + dy * dy, i, 0.0)
    cell_start = points.index.cell_start
    grid = points.index.grid
    cell = grid.cell
    ny = grid.ny
    gx = (qx - grid.x0) / cell
    gy = (qy - grid.y0) / cell
    if count == k:
        # warm start: every better point lies within the current k-th distance; scan that square of cells.
        # A point is listed in one cell only, so only the warm points can be offered twice: they are masked
        # out of their cell's distances (a warm point no longer listed is beyond the k-th distance anyway).
        lo_x, hi_x, lo_y, hi_y = _square(gx, gy, math.sqrt(best_d2[k - 1]) / cell, grid.nx, ny)
        for ix in range(lo_x, hi_x + 1):
            for iy in range(lo_y, hi_y + 1):
                if _cell_d2(gx, gy, ix, iy) * cell * cell < best_d2[k - 1]:
                    c = ix * ny + iy
                    start = cell_start[c]
                    end = cell_start[c + 1]
                    if end > start:
                        _cell_point_d2(qx, qy, pts, start, end, buf)
                        for w in range(n_warm):
                            j = warm[w] - start
                            if 0 <= j < end - start:
                                buf[j] = np.inf
                        kth = best_d2[k - 1]
                        for i in range(start, end):
                            d2 = buf[i - start]
                            if d2 < kth:
                                count = _insert(best_d2, best_id, best_t, count, k, d2, i, 0.0)
                                kth = best_d2[k - 1]
        return count
    rings = rings_start(grid, gx, gy)
    while not rings.done:
        ix = rings.ix
        iy = rings.iy
        if count < k or _cell_d2(gx, gy, ix, iy) * cell * cell < best_d2[k - 1]:
            count = _point_cell(
                qx, qy, pts, cell_start, k, best_d2, best_id, best_t, buf, ix * ny + iy, count, n_warm > 0
            )
        rings = rings_next(grid, rings, count == k, best_d2[k - 1])
    return count


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
def _cell_point_d2(qx, qy, pts, start, end, buf):
    """Squared distances from (qx, qy) to ``pts[start:end]`` into ``buf`` (vectorised)."""
    for i in range(start, end):
        dx = pts[i, 0] - qx
        dy = pts[i, 1] - qy
        buf[i - start] = dx * dx + dy * dy


# ---------------------------------------------------------------------------------------------------------
# Free segments.


@nb.njit(cache=True, error_model="numpy", inline="always")
def _segment_cell(
    qx, qy, seg, entries, cell_start, items, grid, k, best_d2, best_id, best_t, buf, cand, ix, iy, count,
    check_dup,
):  # fmt: skip
    """Offer the segments of cell (ix, iy) to the top-k buffers (float32 screen, exact float64 check)."""
    c = ix * grid.ny + iy
    start = cell_start[c]
    end = cell_start[c + 1]
    if start == end:
        return count
    ccx = grid.x0 + (ix + 0.5) * grid.cell
    ccy = grid.y0 + (iy + 0.5) * grid.cell
    _cell_segment_d2(np.float32(qx - ccx), np.float32(qy - ccy), entries, start, end, buf)
    lim2 = _screen_limit(best_d2, count, k)
    cell_lim2 = np.inf
    n = end - start
    if n > 4 * k and lim2 < np.inf:
        cell_lim2 = _dense_cell_limit(buf, n, lim2, k)
        lim2 = min(lim2, cell_lim2)
    return _offer_screened(
        qx, qy, seg, items, start, end, k, best_d2, best_id, best_t, buf, cand, count, check_dup, lim2,
        cell_lim2,
    )  # fmt: skip


@nb.njit(cache=True, error_model="numpy", inline="always")
def _dense_cell_limit(buf, n, lim2, k):
    """A screening limit for a dense cell whose ``n`` float32 squared distances are in ``buf``, from the
    limit ``lim2``: halve the radius while k of its segments (distinct: a segment is listed once per cell)
    still screen within it; the k-th distance is then at most that radius plus the float32 error (0.1 mm),
    and a segment screening beyond it plus another 0.1 mm cannot be among the k nearest (infinity when the
    first halving already keeps fewer than k). The halving stops at 0.1 mm: below it the limit no longer
    tightens, and k segments at distance 0 (a query at a scan's origin) would keep it halving for ever."""
    cell_lim2 = np.inf
    within2 = np.float32(lim2 * 0.25)
    while within2 >= 1e-8 and _count_within(buf, n, within2) >= k:
        r = math.sqrt(within2) + 2e-4
        cell_lim2 = r * r
        within2 = np.float32(within2 * 0.25)
    return cell_lim2


@nb.njit(cache=True, error_model="numpy", inline="always")
def _offer_screened(
    qx, qy, seg, items, start, end, k, best_d2, best_id, best_t, buf, cand, count, check_dup, lim2, cell_lim2
):  # fmt: skip
    """Offer the entries ``start:end`` whose screened distance (``buf``) is within ``lim2`` to the top-k
    buffers, exactly (float64); the limit follows the k-th distance, capped at ``cell_lim2``.

    With a finite limit the candidates are listed first (``cand[0]``, entry numbers held exactly as float64
    so that one scratch array serves), then evaluated in one pass of independent iterations (``cand[1]``,
    ``cand[2]``: d2, t), so that the loads of their rows of ``seg``, scattered over the map's beams and
    mostly cache misses, overlap; then offered in entry order. A
    candidate the running limit would have skipped is beyond the k-th distance by then (the screen is
    conservative) and is not kept either way: the result is that of offering one by one."""
    if lim2 == np.inf:  # a cold start: the limit falls as the first k are found
        for e in range(start, end):
            if buf[e - start] > lim2:
                continue
            i = items[e]
            d2, t = _segment_d2(qx, qy, seg, i)
            if count < k or d2 < best_d2[k - 1]:
                if check_dup and _listed(best_id, count, i):
                    continue
                count = _insert(best_d2, best_id, best_t, count, k, d2, i, t)
                lim2 = min(_screen_limit(best_d2, count, k), cell_lim2)
        return count
    nc = 0
    for e in range(start, end):  # branch-free listing
        cand[0, nc] = e
        nc += buf[e - start] <= lim2
    for c in range(nc):
        d2, t = _segment_d2(qx, qy, seg, items[int(cand[0, c])])
        cand[1, c] = d2
        cand[2, c] = t
    for c in range(nc):
        d2 = cand[1, c]
        if count < k or d2 < best_d2[k - 1]:
            i = items[int(cand[0, c])]
            if check_dup and _listed(best_id, count, i):
                continue
            count = _insert(best_d2, best_id, best_t, count, k, d2, i, cand[2, c])
    return count


@nb.njit(cache=True, error_model="numpy", inline="always")
def _screen_limit(best_d2, count, k):
    """Float32 screening bound: (current k-th distance + 0.1 mm)^2, or infinity while fewer than k."""
    if count < k:
        return np.inf
    lim = math.sqrt(best_d2[k - 1]) + 1e-4
    return lim * lim


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
def _count_within(buf, n, lim2):
    """How many of ``buf[:n]`` are at most ``lim2`` (vectorised)."""
    c = 0
    for e in range(n):
        c += buf[e] <= lim2
    return c


@nb.njit(cache=True, error_model="numpy", _nrt=False, fastmath=True)
def _cell_segment_d2(qrx, qry, ecopy, start, end, buf):
    """Squared distances (float32, vectorised) from the query (relative to the cell centre) to the segments
    listed in entries ``start:end``, into ``buf``."""
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for e in range(start, end):
        rx = qrx - ecopy[0, e]
        ry = qry - ecopy[1, e]
        ddx = ecopy[2, e]
        ddy = ecopy[3, e]
        t = min(max((rx * ddx + ry * ddy) * ecopy[4, e], zero), one)
        ex = rx - t * ddx
        ey = ry - t * ddy
        buf[e - start] = ex * ex + ey * ey


@nb.njit(cache=True, error_model="numpy", inline="always")
def _segment_d2(qx, qy, seg, i):
    """Squared distance from (qx, qy) to segment ``i`` of ``seg`` and the clamped parameter t of its
    closest point (eqs. 13-14)."""
    rx = qx - seg[i, 0]
    ry = qy - seg[i, 1]
    t = min(max((rx * seg[i, 2] + ry * seg[i, 3]) * seg[i, 4], 0.0), 1.0)
    ex = rx - t * seg[i, 2]
    ey = ry - t * seg[i, 3]
    return ex * ex + ey * ey, t


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def knn_segments(qx, qy, segments, k, best_d2, best_id, best_t, warm, n_warm, buf, cand):
    """The k segments of ``segments`` (a :class:`SegmentSet`) nearest (qx, qy): squared distances, ids and
    the clamped parameter t in [0, 1] of the closest point ``s + t d`` (eqs. 13-14); returns how many were
    found. A cell is first screened by a vectorised float32 pass over its entries (into ``buf``,
    ``segments.index.most`` long) and only candidates within the current k-th distance plus 0.1 mm are
    evaluated exactly, in float64 (listed in ``cand``, (3, ``segments.index.most``) float64 scratch, see
    ``_offer_screened``): the result is exact. A segment listed in several cells is counted once.
    ``warm[:n_warm]``: distinct candidates tried first (as in :func:`knn_points`)."""
    count = 0
    if k == 0 or segments.index.items.shape[0] == 0:
        return 0
    seg = segments.seg
    entries = segments.entries
    cell_start = segments.index.cell_start
    items = segments.index.items
    grid = segments.index.grid
    cell = grid.cell
    nx = grid.nx
    ny = grid.ny
    gx = (qx - grid.x0) / cell
    gy = (qy - grid.y0) / cell
    qcx = math.floor(gx)
    qcy = math.floor(gy)
    inside = 0 <= qcx < nx and 0 <= qcy < ny
    qc = qcx * ny + qcy
    square = False
    if n_warm == k and inside and cell_start[qc + 1] - cell_start[qc] > 4 * k:
        # warm start in a dense cell: the cell's counting bound (as _segment_cell finds it after the warm
        # candidates) decides which warm candidates can matter; only those are inserted, in their order.
        kth = 0.0
        for w in range(n_warm):
            d2, t = _segment_d2(qx, qy, seg, warm[w])
            best_d2[w] = d2
            best_t[w] = t
            kth = max(kth, d2)
        start = cell_start[qc]
        end = cell_start[qc + 1]
        n = end - start
        ccx = grid.x0 + (qcx + 0.5) * cell
        ccy = grid.y0 + (qcy + 0.5) * cell
        _cell_segment_d2(np.float32(qx - ccx), np.float32(qy - ccy), entries, start, end, buf)
        lim = math.sqrt(kth) + 1e-4
        lim2 = lim * lim
        cell_lim2 = _dense_cell_limit(buf, n, lim2, k)
        for w in range(n_warm):
            d2 = best_d2[w]
            if d2 < cell_lim2:
                best_d2[count] = d2
                best_t[count] = best_t[w]
                best_id[count] = warm[w]
                count += 1
        _rank_sort(best_d2, best_id, best_t, count)
        lim2 = min(_screen_limit(best_d2, count, k), cell_lim2)
        count = _offer_screened(
            qx, qy, seg, items, start, end, k, best_d2, best_id, best_t, buf, cand, count, True, lim2,
            cell_lim2,
        )  # fmt: skip
        # k found by now (the k segments that met the counting bound are listed, or better ones are); were
        # they not, the ring search below would finish the search
        square = count == k
    else:
        for w in range(n_warm):
            i = warm[w]
            d2, t = _segment_d2(qx, qy, seg, i)
            if n_warm <= k:
                best_d2[w] = d2
                best_t[w] = t
                best_id[w] = i
                count += 1
            else:
                count = _insert(best_d2, best_id, best_t, count, k, d2, i, t)
        if n_warm <= k:
            _rank_sort(best_d2, best_id, best_t, count)
        if count == k:  # warm start: the own cell, then the square of cells within the k-th distance
            # the query's own cell first: in dense areas it holds the nearest beams and tightens the bound
            if inside:
                count = _segment_cell(
                    qx, qy, seg, entries, cell_start, items, grid, k, best_d2, best_id, best_t, buf, cand,
                    qcx, qcy, count, True,
                )  # fmt: skip
            square = True
    if square:  # the other cells of the square within the current k-th distance
        lo_x, hi_x, lo_y, hi_y = _square(gx, gy, math.sqrt(best_d2[k - 1]) / cell, nx, ny)
        for ix in range(lo_x, hi_x + 1):
            for iy in range(lo_y, hi_y + 1):
                if inside and ix == qcx and iy == qcy:
                    continue
                c = ix * ny + iy
                # test the cell's list before calling: most cells of a wide square are empty
                near = _cell_d2(gx, gy, ix, iy) * cell * cell < best_d2[k - 1]
                if cell_start[c] < cell_start[c + 1] and near:
                    count = _segment_cell(
                        qx, qy, seg, entries, cell_start, items, grid, k, best_d2, best_id, best_t, buf,
                        cand, ix, iy, count, True,
                    )  # fmt: skip
        return count
    rings = rings_start(grid, gx, gy)
    while not rings.done:
        ix = rings.ix
        iy = rings.iy
        c = ix * ny + iy
        if cell_start[c] < cell_start[c + 1] and (
            count < k or _cell_d2(gx, gy, ix, iy) * cell * cell < best_d2[k - 1]
        ):
            count = _segment_cell(
                qx,
                qy,
                seg,
                entries,
                cell_start,
                items,
                grid,
                k,
                best_d2,
                best_id,
                best_t,
                buf,
                cand,
                ix,
                iy,
                count,
                rings.r > 0 or n_warm > 0,
            )
        rings = rings_next(grid, rings, count == k, best_d2[k - 1])
    return count
