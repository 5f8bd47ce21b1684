"""Uniform grids of square cells as compiled code sees them, and the walk over the cells a segment crosses.

:class:`GridGeometry` names a grid's lower-left corner, cell side and size in cells. It is a named tuple of
scalars, so compiled functions take it as an argument (numba passes it by value and reads its fields as
locals) and cache it like any other argument type. The neighbour indexes (:mod:`mapping.index`), the tile
support index (:mod:`mapping.tiling.support`) and the occupancy-grid baseline (:mod:`mapping.grid`) all
describe their grids with it; they store cells differently (the indexes by id ``ix * ny + iy``, the baseline
as a raster ``L[iy, ix]``).

The cell walk (Amanatides & Woo, "A fast voxel traversal algorithm for ray tracing", 1987) visits, in
order, the cells a segment crosses, one cell boundary at a time: :func:`segment_walk` starts it and
:func:`walk_next` steps it. The callers own the loop, as they stop, clip and act on cells differently: the
segment index lists the cells of a beam (start and end clamped into the grid, stopping where the walk
leaves it), the baseline updates the cells of a ray (anywhere, out-of-grid cells skipped).
:func:`segment_cells` lists the in-grid cells of a segment for callers that only act on each of them (the
placement layer, the evaluation's pass masks). The walk is
exact up to round-off: a segment through a cell corner steps in x or in y, not diagonally.

The distance transform of a raster mask (:func:`squared_distances_cells`, :func:`within_distance`) gives
every cell its Euclidean distance to the nearest marked cell, exactly, as scipy's
``distance_transform_edt`` does, compiled and parallel: the reach raster (:mod:`mapping.reach`) and the
views' clearance (:mod:`mapping.frontier`) use it on rasters of millions of cells.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import NDArray


class GridGeometry(NamedTuple):
    """A uniform grid of ``nx`` by ``ny`` square cells of side ``cell`` whose lower-left corner is
    (``x0``, ``y0``): cell (ix, iy) covers ``[x0 + ix cell, x0 + (ix + 1) cell)`` in x, likewise in y."""

    x0: float
    y0: float
    cell: float
    nx: int
    ny: int

    @classmethod
    def of(cls, x0: float, y0: float, cell: float, nx: int, ny: int) -> GridGeometry:
        """The geometry with Python float / int fields, so that every grid has the same compiled type."""
        return cls(float(x0), float(y0), float(cell), int(nx), int(ny))


@nb.njit(cache=True, error_model="numpy", inline="always")
def in_grid(grid, ix, iy):
    """Whether cell (ix, iy) lies in the grid."""
    return 0 <= ix < grid.nx and 0 <= iy < grid.ny


class CellWalk(NamedTuple):
    """State of a walk along a segment: the current cell (ix, iy), the step (+1 or -1) in x and y, the
    segment parameters ``tmx``, ``tmy`` at which the walk next crosses a cell boundary in x and in y (the
    segment runs from 0 to 1), and the parameter spans ``tdx``, ``tdy`` of one cell in x and y."""

    ix: int
    iy: int
    sx: int
    sy: int
    tmx: float
    tmy: float
    tdx: float
    tdy: float


@nb.njit(cache=True, error_model="numpy", inline="always")
def segment_walk(grid, x0, y0, x1, y1, clamp):
    """The walk from (x0, y0) to (x1, y1) over the cells of ``grid``: (walk at the start cell, end cell
    ex, ey, number of steps ``|ex - ix| + |ey - iy|`` from start to end cell). With ``clamp`` the start and
    end cells are clamped into the grid (the walk then starts from the clamped cell)."""
    gx0 = (x0 - grid.x0) / grid.cell
    gy0 = (y0 - grid.y0) / grid.cell
    gx1 = (x1 - grid.x0) / grid.cell
    gy1 = (y1 - grid.y0) / grid.cell
    ix = math.floor(gx0)
    iy = math.floor(gy0)
    ex = math.floor(gx1)
    ey = math.floor(gy1)
    if clamp:
        ix = min(max(ix, 0), grid.nx - 1)
        iy = min(max(iy, 0), grid.ny - 1)
        ex = min(max(ex, 0), grid.nx - 1)
        ey = min(max(ey, 0), grid.ny - 1)
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
    steps = abs(ex - ix) + abs(ey - iy)
    return CellWalk(ix, iy, sx, sy, tmx, tmy, tdx, tdy), ex, ey, steps


@nb.njit(cache=True, error_model="numpy", inline="always")
def walk_next(w):
    """The walk one cell further: across the nearer of the next x and y cell boundaries (y on a tie)."""
    if w.tmx < w.tmy:
        return CellWalk(w.ix + w.sx, w.iy, w.sx, w.sy, w.tmx + w.tdx, w.tmy, w.tdx, w.tdy)
    return CellWalk(w.ix, w.iy + w.sy, w.sx, w.sy, w.tmx, w.tmy + w.tdy, w.tdx, w.tdy)


@nb.njit(cache=True, error_model="numpy", inline="always")
def point_cell(grid, x, y):
    """The cell (ix, iy) holding (x, y), which may lie outside the grid (:func:`in_grid` tells)."""
    return math.floor((x - grid.x0) / grid.cell), math.floor((y - grid.y0) / grid.cell)


@nb.njit(cache=True, error_model="numpy")
def segment_cells(grid, x0, y0, x1, y1, out):
    """The cells of ``grid`` the segment (x0, y0)-(x1, y1) crosses, in walking order, those outside the
    grid left out: rows (ix, iy) of ``out`` (int64, at least ``nx + ny`` rows: the walk is monotone in x and
    y, so it crosses at most ``nx + ny - 1`` cells of the grid); returns how many."""
    w, ex, ey, steps = segment_walk(grid, x0, y0, x1, y1, False)
    n = 0
    k = 0
    while True:
        if in_grid(grid, w.ix, w.iy):
            out[k, 0] = w.ix
            out[k, 1] = w.iy
            k += 1
        n += 1
        if (w.ix == ex and w.iy == ey) or n > steps:
            return k
        w = walk_next(w)


def squared_distances_cells(marked: NDArray[np.bool_]) -> NDArray[np.float64]:
    """(H, W) squared Euclidean distances, in cell widths, from each cell's centre to the centre of the
    nearest ``marked`` cell (integers as float64; ``H^2 + W^2 + 1`` everywhere when none is marked): the
    square of ``scipy.ndimage.distance_transform_edt(~marked)``, by the separable transform of Felzenszwalb
    and Huttenlocher (2012), in parallel over columns, then rows."""
    m = np.ascontiguousarray(marked, dtype=np.bool_)
    if m.ndim != 2:
        raise ValueError(f"a distance transform needs a 2-D mask, not {m.shape}")
    return _squared_distances(m)


def within_distance(marked: NDArray[np.bool_], radius_cells: float) -> NDArray[np.bool_]:
    """(H, W) bool: the cells whose centre lies within ``radius_cells`` cell widths of the centre of a
    ``marked`` cell (``distance_transform_edt(~marked) <= radius_cells``; nothing when none is marked)."""
    m = np.ascontiguousarray(marked, dtype=np.bool_)
    if not (m.any() and radius_cells >= 0):  # nothing marked, or a negative or NaN radius
        return np.zeros(m.shape, dtype=bool)
    if not np.isfinite(radius_cells):
        return np.ones(m.shape, dtype=bool)
    return squared_distances_cells(m) <= float(radius_cells) ** 2


@nb.njit(cache=True, error_model="numpy", parallel=True)
def _squared_distances(marked):
    h, w = marked.shape
    big = float(h * h + w * w + 1)  # beyond every distance on the raster
    col = np.empty((h, w))  # squared distance to the nearest marked cell of the same column
    for j in nb.prange(w):
        last = -1
        for i in range(h):
            if marked[i, j]:
                last = i
            col[i, j] = big if last < 0 else float((i - last) * (i - last))
        last = -1
        for i in range(h - 1, -1, -1):
            if marked[i, j]:
                last = i
            if last >= 0:
                col[i, j] = min(col[i, j], float((last - i) * (last - i)))
    out = np.empty((h, w))
    for i in nb.prange(h):
        # lower envelope of the parabolas (x - q)^2 + col[i, q] along the row
        v = np.empty(w, np.int64)
        z = np.empty(w + 1)
        f = col[i]
        k = 0
        v[0] = 0
        z[0] = -np.inf
        z[1] = np.inf
        for q in range(1, w):
            while True:
                p = v[k]
                s = ((f[q] + q * q) - (f[p] + p * p)) / (2.0 * (q - p))
                if s <= z[k] and k > 0:
                    k -= 1
                    continue
                if s <= z[k]:  # k == 0: q replaces the first parabola
                    v[0] = q
                    z[1] = np.inf
                    break
                k += 1
                v[k] = q
                z[k] = s
                z[k + 1] = np.inf
                break
        k = 0
        for x in range(w):
            while z[k + 1] < x:
                k += 1
            p = v[k]
            out[i, x] = min((x - p) * (x - p) + f[p], big)
    return out
