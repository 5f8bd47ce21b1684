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
leaves it), the baseline updates the cells of a ray (anywhere, out-of-grid cells skipped). The walk is
exact up to round-off: a segment through a cell corner steps in x or in y, not diagonally.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb


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
