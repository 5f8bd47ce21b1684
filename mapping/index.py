"""Uniform-grid spatial indexes for occupied endpoints and free beam segments, with compiled k-NN search.

The paper stores training data in a kd-tree (section 3.7); a uniform grid does the same job faster for 2D
laser maps: each cell lists the items it holds (endpoints) or the segments crossing it (beams), in CSR form
(``cell_start`` (C+1,), ``items`` (E,)). A k-NN query walks square rings of cells around the query and
stops when the k-th best distance is below the distance to the next ring, so results are exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


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
    order = np.argsort(cell, kind="stable").astype(np.int32)
    counts = np.bincount(cell, minlength=nx * ny)
    start = np.zeros(nx * ny + 1, np.int64)
    np.cumsum(counts, out=start[1:])
    return GridIndex(origin, cell_m, (nx, ny), start, order)


@nb.njit(cache=True, error_model="numpy")
def _traverse_count(x0, y0, x1, y1, ox, oy, cell, nx, ny, out_cells, fill):
    """Cells crossed by segment (x0,y0)-(x1,y1) (Amanatides & Woo); writes them to out_cells when fill."""
    gx0 = (x0 - ox) / cell
    gy0 = (y0 - oy) / cell
    gx1 = (x1 - ox) / cell
    gy1 = (y1 - oy) / cell
    ix = min(max(math.floor(gx0), 0), nx - 1)
    iy = min(max(math.floor(gy0), 0), ny - 1)
    ex = min(max(math.floor(gx1), 0), nx - 1)
    ey = min(max(math.floor(gy1), 0), ny - 1)
    dx = gx1 - gx0
    dy = gy1 - gy0
    sx = 1 if dx > 0 else -1
    sy = 1 if dy > 0 else -1
    inf = 1e300
    tdx = abs(1.0 / dx) if dx != 0.0 else inf
    tdy = abs(1.0 / dy) if dy != 0.0 else inf
    if dx > 0:
        tmx = (ix + 1 - gx0) * tdx
    elif dx < 0:
        tmx = (gx0 - ix) * tdx
    else:
        tmx = inf
    if dy > 0:
        tmy = (iy + 1 - gy0) * tdy
    elif dy < 0:
        tmy = (gy0 - iy) * tdy
    else:
        tmy = inf
    n = 0
    limit = abs(ex - ix) + abs(ey - iy) + 1
    while True:
        if fill:
            out_cells[n] = ix * ny + iy
        n += 1
        if (ix == ex and iy == ey) or n >= limit:
            break
        if tmx < tmy:
            tmx += tdx
            ix += sx
        else:
            tmy += tdy
            iy += sy
        if ix < 0 or ix >= nx or iy < 0 or iy >= ny:
            break
    return n


@nb.njit(cache=True, error_model="numpy")
def _segment_cells(p0, p1, ox, oy, cell, nx, ny):
    m = p0.shape[0]
    counts = np.empty(m, np.int64)
    dummy = np.empty(1, np.int64)
    for i in range(m):
        counts[i] = _traverse_count(
            p0[i, 0], p0[i, 1], p1[i, 0], p1[i, 1], ox, oy, cell, nx, ny, dummy, False
        )
    offs = np.zeros(m + 1, np.int64)
    for i in range(m):
        offs[i + 1] = offs[i] + counts[i]
    cells = np.empty(offs[m], np.int64)
    for i in range(m):
        _traverse_count(
            p0[i, 0], p0[i, 1], p1[i, 0], p1[i, 1], ox, oy, cell, nx, ny, cells[offs[i] : offs[i + 1]], True
        )
    return counts, cells


def segment_entry_copies(index: GridIndex, seg: FloatArray) -> NDArray[np.float32]:
    """(5, E) float32 copies of the (M, 5) segments ``seg`` for every entry of a segment ``index``, in entry
    order, with the start relative to the centre of the entry's cell (for :func:`knn_segments`)."""
    nx, ny = index.shape
    counts = np.diff(index.cell_start)
    cell_of = np.repeat(np.arange(nx * ny), counts)
    centre_x = index.origin_xy_m[0] + (cell_of // ny + 0.5) * index.cell_m
    centre_y = index.origin_xy_m[1] + (cell_of % ny + 0.5) * index.cell_m
    rows = seg[index.items]
    out = np.empty((5, rows.shape[0]), np.float32)
    out[0] = rows[:, 0] - centre_x
    out[1] = rows[:, 1] - centre_y
    out[2:] = rows[:, 2:].T
    return out


def build_segment_index(starts_xy_m: FloatArray, ends_xy_m: FloatArray, cell_m: float) -> GridIndex:
    """Index of (M, 2)-(M, 2) segments: every cell lists the segments crossing it."""
    p0 = np.ascontiguousarray(starts_xy_m, dtype=np.float64).reshape(-1, 2)
    p1 = np.ascontiguousarray(ends_xy_m, dtype=np.float64).reshape(-1, 2)
    origin, (nx, ny) = _grid_geometry(np.concatenate([p0, p1]), cell_m)
    if p0.shape[0] == 0:
        return GridIndex(origin, cell_m, (nx, ny), np.zeros(nx * ny + 1, np.int64), np.zeros(0, np.int32))
    counts, cells = _segment_cells(p0, p1, float(origin[0]), float(origin[1]), float(cell_m), nx, ny)
    seg = np.repeat(np.arange(p0.shape[0], dtype=np.int32), counts)
    order = np.argsort(cells, kind="stable")
    per_cell = np.bincount(cells, minlength=nx * ny)
    start = np.zeros(nx * ny + 1, np.int64)
    np.cumsum(per_cell, out=start[1:])
    return GridIndex(origin, cell_m, (nx, ny), start, seg[order])


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


@nb.njit(cache=True, error_model="numpy")
def knn_points(qx, qy, pts, ox, oy, cell, nx, ny, cell_start, k, best_d2, best_id, best_t, warm, n_warm, buf):
    """The k points nearest (qx, qy) among (P, 2) ``pts`` stored in cell order (cell c holds
    ``pts[cell_start[c]:cell_start[c + 1]]``); writes sorted squared distances and indices into ``pts``;
    returns how many were found. ``warm[:n_warm]`` are distinct candidate indices tried first (e.g. the
    neighbours of the previous, nearby query): they only make the search faster, never change its result.
    ``buf`` (as long as the fullest cell) receives each cell's distances from a vectorised pass."""
    count = 0
    if k == 0 or pts.shape[0] == 0:
        return 0
    for w in range(n_warm):
        i = warm[w]
        dx = pts[i, 0] - qx
        dy = pts[i, 1] - qy
        count = _insert(best_d2, best_id, best_t, count, k, dx * dx + dy * dy, i, 0.0)
    gx = (qx - ox) / cell
    gy = (qy - oy) / cell
    if count == k:
        # warm start: every better point lies within the current k-th distance; scan that square of cells
        lo_x, hi_x, lo_y, hi_y = _square(gx, gy, math.sqrt(best_d2[k - 1]) / cell, nx, ny)
        for ix in range(lo_x, hi_x + 1):
            for iy in range(lo_y, hi_y + 1):
                if _cell_d2(gx, gy, ix, iy) * cell * cell < best_d2[k - 1]:
                    c = ix * ny + iy
                    start = cell_start[c]
                    end = cell_start[c + 1]
                    if end > start:
                        _cell_point_d2(qx, qy, pts, start, end, buf)
                        for i in range(start, end):
                            d2 = buf[i - start]
                            if d2 < best_d2[k - 1] and not _listed(best_id, count, i):
                                count = _insert(best_d2, best_id, best_t, count, k, d2, i, 0.0)
        return count
    cx = math.floor(gx)
    cy = math.floor(gy)
    # rings beyond this radius lie entirely outside the grid
    rmax = max(max(cx, nx - 1 - cx), max(cy, ny - 1 - cy))
    r = 0
    while True:
        x_lo = cx - r
        x_hi = cx + r
        y_lo = cy - r
        y_hi = cy + r
        for ix in range(max(x_lo, 0), min(x_hi, nx - 1) + 1):
            on_x_edge = ix == x_lo or ix == x_hi
            step = 1 if on_x_edge else y_hi - y_lo
            iy = y_lo
            while iy <= y_hi:
                if 0 <= iy < ny and (count < k or _cell_d2(gx, gy, ix, iy) * cell * cell < best_d2[k - 1]):
                    c = ix * ny + iy
                    start = cell_start[c]
                    end = cell_start[c + 1]
                    if end > start:
                        _cell_point_d2(qx, qy, pts, start, end, buf)
                        for i in range(start, end):
                            d2 = buf[i - start]
                            if count < k or d2 < best_d2[k - 1]:
                                if n_warm > 0 and _listed(best_id, count, i):
                                    continue
                                count = _insert(best_d2, best_id, best_t, count, k, d2, i, 0.0)
                if step == 0:
                    break
                iy += step
        if r >= rmax:
            break
        if count == k:
            # distance from the query to the outside of the (2r+1)^2 block of cells
            b = min(
                min(gx - (cx - r), (cx + r + 1) - gx),
                min(gy - (cy - r), (cy + r + 1) - gy),
            )
            b *= cell
            if b > 0 and b * b >= best_d2[k - 1]:
                break
        r += 1
    return count


@nb.njit(cache=True, error_model="numpy", fastmath=True)
def _cell_point_d2(qx, qy, pts, start, end, buf):
    """Squared distances from (qx, qy) to ``pts[start:end]`` into ``buf`` (vectorised)."""
    for i in range(start, end):
        dx = pts[i, 0] - qx
        dy = pts[i, 1] - qy
        buf[i - start] = dx * dx + dy * dy


@nb.njit(cache=True, error_model="numpy", inline="always")
def _square(gx, gy, radius, nx, ny):
    """Cell ranges (inclusive) of the square of half-side ``radius`` (cells) around (gx, gy), in the grid."""
    return (
        max(math.floor(gx - radius), 0),
        min(math.floor(gx + radius), nx - 1),
        max(math.floor(gy - radius), 0),
        min(math.floor(gy + radius), ny - 1),
    )


@nb.njit(cache=True, error_model="numpy", inline="always")
def _segment_cell(
    qx, qy, seg, ecopy, ox, oy, cell, ny, cell_start, items, k, best_d2, best_id, best_t, buf, ix, iy, count,
    check_dup,
):  # fmt: skip
    """Offer the segments of cell (ix, iy) to the top-k buffers (float32 screen, exact float64 check)."""
    c = ix * ny + iy
    start = cell_start[c]
    end = cell_start[c + 1]
    if start == end:
        return count
    ccx = ox + (ix + 0.5) * cell
    ccy = oy + (iy + 0.5) * cell
    _cell_segment_d2(np.float32(qx - ccx), np.float32(qy - ccy), ecopy, start, end, buf)
    lim2 = _screen_limit(best_d2, count, k)
    for e in range(start, end):
        if buf[e - start] > lim2:
            continue
        i = items[e]
        rx = qx - seg[i, 0]
        ry = qy - seg[i, 1]
        ddx = seg[i, 2]
        ddy = seg[i, 3]
        t = min(max((rx * ddx + ry * ddy) * seg[i, 4], 0.0), 1.0)
        ex = rx - t * ddx
        ey = ry - t * ddy
        d2 = ex * ex + ey * ey
        if count < k or d2 < best_d2[k - 1]:
            if check_dup and _listed(best_id, count, i):
                continue
            count = _insert(best_d2, best_id, best_t, count, k, d2, i, t)
            lim2 = _screen_limit(best_d2, count, k)
    return count


@nb.njit(cache=True, error_model="numpy", inline="always")
def _screen_limit(best_d2, count, k):
    """Float32 screening bound: (current k-th distance + 0.1 mm)^2, or infinity while fewer than k."""
    if count < k:
        return np.inf
    lim = math.sqrt(best_d2[k - 1]) + 1e-4
    return lim * lim


@nb.njit(cache=True, error_model="numpy", fastmath=True)
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


@nb.njit(cache=True, error_model="numpy")
def knn_segments(
    qx,
    qy,
    seg,
    ecopy,
    ox,
    oy,
    cell,
    nx,
    ny,
    cell_start,
    items,
    k,
    best_d2,
    best_id,
    best_t,
    warm,
    n_warm,
    buf,
):
    """The k segments nearest (qx, qy): squared distances, ids and the clamped parameter t in [0, 1] of the
    closest point ``s + t d`` (eqs. 13-14); returns how many were found. ``seg`` (M, 5) holds one segment
    per row, (start x, start y, d x, d y, 1 / |d|^2); ``ecopy`` (5, E) float32 repeats them per index entry
    (start relative to the entry's cell centre), so that a cell is first screened by a vectorised float32
    pass (into ``buf``, as long as the fullest cell) and only candidates within the current k-th distance
    plus 0.1 mm are evaluated exactly, in float64: the result is exact. A segment listed in several cells is
    counted once. ``warm[:n_warm]``: distinct candidates tried first (as in :func:`knn_points`)."""
    count = 0
    if k == 0 or items.shape[0] == 0:
        return 0
    for w in range(n_warm):
        i = warm[w]
        rx = qx - seg[i, 0]
        ry = qy - seg[i, 1]
        t = min(max((rx * seg[i, 2] + ry * seg[i, 3]) * seg[i, 4], 0.0), 1.0)
        ex = rx - t * seg[i, 2]
        ey = ry - t * seg[i, 3]
        count = _insert(best_d2, best_id, best_t, count, k, ex * ex + ey * ey, i, t)
    gx = (qx - ox) / cell
    gy = (qy - oy) / cell
    if count == k:  # warm start: scan the square of cells within the current k-th distance
        # the query's own cell first: in dense areas it holds the nearest beams and tightens the bound
        qcx = math.floor(gx)
        qcy = math.floor(gy)
        inside = 0 <= qcx < nx and 0 <= qcy < ny
        if inside:
            count = _segment_cell(
                qx, qy, seg, ecopy, ox, oy, cell, ny, cell_start, items, k, best_d2, best_id, best_t,
                buf, qcx, qcy, count, True,
            )  # fmt: skip
        lo_x, hi_x, lo_y, hi_y = _square(gx, gy, math.sqrt(best_d2[k - 1]) / cell, nx, ny)
        for ix in range(lo_x, hi_x + 1):
            for iy in range(lo_y, hi_y + 1):
                if inside and ix == qcx and iy == qcy:
                    continue
                if _cell_d2(gx, gy, ix, iy) * cell * cell < best_d2[k - 1]:
                    count = _segment_cell(
                        qx, qy, seg, ecopy, ox, oy, cell, ny, cell_start, items, k, best_d2, best_id, best_t,
                        buf, ix, iy, count, True,
                    )  # fmt: skip
        return count
    cx = math.floor(gx)
    cy = math.floor(gy)
    rmax = max(max(cx, nx - 1 - cx), max(cy, ny - 1 - cy))
    r = 0
    while True:
        x_lo = cx - r
        x_hi = cx + r
        y_lo = cy - r
        y_hi = cy + r
        for ix in range(max(x_lo, 0), min(x_hi, nx - 1) + 1):
            on_x_edge = ix == x_lo or ix == x_hi
            step = 1 if on_x_edge else y_hi - y_lo
            iy = y_lo
            while iy <= y_hi:
                if 0 <= iy < ny and (count < k or _cell_d2(gx, gy, ix, iy) * cell * cell < best_d2[k - 1]):
                    count = _segment_cell(
                        qx, qy, seg, ecopy, ox, oy, cell, ny, cell_start, items, k, best_d2, best_id, best_t,
                        buf, ix, iy, count, r > 0 or n_warm > 0,
                    )  # fmt: skip
                if step == 0:
                    break
                iy += step
        if r >= rmax:
            break
        if count == k:
            b = min(
                min(gx - (cx - r), (cx + r + 1) - gx),
                min(gy - (cy - r), (cy + r + 1) - gy),
            )
            b *= cell
            if b > 0 and b * b >= best_d2[k - 1]:
                break
        r += 1
    return count
