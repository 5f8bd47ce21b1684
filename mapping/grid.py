"""The baseline: a log-odds occupancy grid with the inverse sensor model of Thrun et al. (2005, ch. 9).

Narrow beams (``beam_width_deg = 0``, the default): every beam is ray-traced through the grid (the cell
walk of :mod:`mapping.raster`, compiled): the cells it crosses before its endpoint get ``logit(p_free)``,
the endpoint's cell gets ``logit(p_occ)``; a no-return beam only frees cells along its configured free
length.

Widened beams (``beam_width_deg > 0``): the paper's grid baseline on its sparse street data (section 4.1.1:
"add surplus noise to the sensor's bearing readings so as to artificially increase the width of the beam").
Each beam is a cone of that full angular width, updated once per cell with Thrun's
``inverse_range_sensor_model`` (Table 9.2): a cell whose centre lies in the cone (within half the width of
the beam's bearing, or within half a cell of its axis, so that the cone never gets thinner than a ray) at a
distance ``d`` from the laser gets ``logit(p_free)`` if ``d < z - alpha / 2`` and ``logit(p_occ)`` if the
beam has a return and ``|d - z| <= alpha / 2``, with ``z`` the range and ``alpha`` = one cell (the obstacle
thickness); the endpoint's own cell is always occupied. A cone is the bearing noise of the paper smeared
uniformly over the width, without sampling.

Log-odds are clamped to ``[-l_max, l_max]``; the prior is 0.5. The grid answers the same questions as the GP
map: p(occ) at arbitrary points (cell lookup) and as a raster.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mapping.beams import Beams
from mapping.config import GridBaselineConfig
from mapping.raster import GridGeometry, in_grid, segment_walk, walk_next

FloatArray = NDArray[np.float64]
Bounds = tuple[float, float, float, float]


def logit(p: float) -> float:
    return math.log(p / (1.0 - p))


@nb.njit(cache=True)
def _trace(ox, oy, ex, ey, hit, grid, l_free, l_occ, l_max, L):
    """Update log-odds L (ny, nx) of ``grid`` along the ray from (ox, oy) to (ex, ey): the cells it crosses
    before the endpoint's cell get ``l_free``, that cell ``l_occ`` if ``hit`` (else ``l_free``); cells
    outside the grid are skipped. Returns the cells updated."""
    w, jx, jy, steps = segment_walk(grid, ox, oy, ex, ey, False)
    updated = 0
    for _ in range(steps):
        if in_grid(grid, w.ix, w.iy):
            v = L[w.iy, w.ix] + l_free
            L[w.iy, w.ix] = max(v, -l_max)
            updated += 1
        w = walk_next(w)
    if in_grid(grid, jx, jy):
        if hit:
            v = L[jy, jx] + l_occ
            L[jy, jx] = min(v, l_max)
        else:
            v = L[jy, jx] + l_free
            L[jy, jx] = max(v, -l_max)
        updated += 1
    return updated


@nb.njit(cache=True)
def _integrate(origins, ends, is_hit, x0, y0, res, nx, ny, l_free, l_occ, l_max, L):
    """Trace every ray (in order) through the grid of ``nx`` x ``ny`` cells of ``res`` from (x0, y0)."""
    grid = GridGeometry(x0, y0, res, nx, ny)
    total = 0
    for i in range(origins.shape[0]):
        total += _trace(
            origins[i, 0], origins[i, 1], ends[i, 0], ends[i, 1], is_hit[i], grid, l_free, l_occ, l_max, L
        )
    return total


@nb.njit(cache=True)
def _cone(ox, oy, ex, ey, hit, half_width, grid, l_free, l_occ, l_max, L):
    """Update log-odds L (ny, nx) in the cone of full width ``2 half_width`` (rad) around the beam from
    (ox, oy) to (ex, ey) (Thrun et al. 2005, Table 9.2, obstacle thickness alpha = one cell); returns the
    number of cells updated. Each cell is updated at most once."""
    x0 = grid.x0
    y0 = grid.y0
    res = grid.cell
    nx = grid.nx
    ny = grid.ny
    z = math.hypot(ex - ox, ey - oy)
    if z <= 0.0:
        return 0
    ux = (ex - ox) / z
    uy = (ey - oy) / z
    half_alpha = 0.5 * res
    reach = z + half_alpha if hit else z
    cos_half = math.cos(half_width)
    # bounding box of the cone: the origin, the arc's ends and the axis extremes inside the cone, plus a cell
    bx0 = min(ox, ex) - res
    bx1 = max(ox, ex) + res
    by0 = min(oy, ey) - res
    by1 = max(oy, ey) + res
    th = math.atan2(uy, ux)
    for k in range(6):
        if k < 2:
            a = th + (half_width if k == 0 else -half_width)
        else:
            a = (k - 2) * 0.5 * math.pi
            if abs(math.atan2(math.sin(a - th), math.cos(a - th))) > half_width:
                continue
        px = ox + reach * math.cos(a)
        py = oy + reach * math.sin(a)
        bx0 = min(bx0, px - res)
        bx1 = max(bx1, px + res)
        by0 = min(by0, py - res)
        by1 = max(by1, py + res)
    i0 = max(0, math.floor((by0 - y0) / res))
    i1 = min(ny - 1, math.floor((by1 - y0) / res))
    j0 = max(0, math.floor((bx0 - x0) / res))
    j1 = min(nx - 1, math.floor((bx1 - x0) / res))
    jx = math.floor((ex - x0) / res)
    jy = math.floor((ey - y0) / res)
    updated = 0
    for i in range(i0, i1 + 1):
        cy = y0 + (i + 0.5) * res - oy
        for j in range(j0, j1 + 1):
            cx = x0 + (j + 0.5) * res - ox
            if hit and i == jy and j == jx:  # the endpoint's cell
                L[i, j] = min(L[i, j] + l_occ, l_max)
                updated += 1
                continue
            d = math.hypot(cx, cy)
            along = cx * ux + cy * uy
            if d > reach or along <= 0.0:
                continue
            if abs(cx * uy - cy * ux) > half_alpha and along < d * cos_half:
                continue  # outside the cone and more than half a cell from its axis
            if d < z - half_alpha:
                L[i, j] = max(L[i, j] + l_free, -l_max)
                updated += 1
            elif hit:
                L[i, j] = min(L[i, j] + l_occ, l_max)
                updated += 1
    return updated


@nb.njit(cache=True)
def _integrate_cones(origins, ends, is_hit, half_width, grid, l_free, l_occ, l_max, L):
    total = 0
    for i in range(origins.shape[0]):
        total += _cone(
            origins[i, 0], origins[i, 1], ends[i, 0], ends[i, 1], is_hit[i], half_width,
            grid, l_free, l_occ, l_max, L,
        )  # fmt: skip
    return total


@dataclass(frozen=True)
class OccupancyGrid:
    """Log-odds ``log_odds`` (H, W) float32 over cells of ``resolution_m`` from ``origin_xy_m`` (lower-left
    corner; row i is y, column j is x, as :class:`mapping.gpmap.MapLayers`)."""

    log_odds: NDArray[np.float32]
    origin_xy_m: FloatArray
    resolution_m: float
    cell_updates: int = 0
    seconds: float = 0.0

    @classmethod
    def build(
        cls,
        beams: Beams,
        resolution_m: float = 0.1,
        bounds_xy_m: tuple[float, float, float, float] | None = None,
        p_occ: float = 0.7,
        p_free: float = 0.4,
        p_clamp: float = 0.97,
        beam_width_deg: float = 0.0,
    ) -> OccupancyGrid:
        """Integrate every beam (in order) into a grid over ``bounds_xy_m`` (default: the beams' bounds);
        ``beam_width_deg > 0`` widens each beam into a cone of that full width (module docstring)."""
        if not 0.0 <= beam_width_deg < 180.0:
            raise ValueError(f"beam_width_deg must be in [0, 180), got {beam_width_deg}")
        x0, y0, x1, y1 = bounds_xy_m or beams.bounds_xy_m(margin_m=resolution_m)
        nx = max(1, math.ceil((x1 - x0) / resolution_m))
        ny = max(1, math.ceil((y1 - y0) / resolution_m))
        L = np.zeros((ny, nx), np.float64)
        rays = (
            np.ascontiguousarray(beams.origins_xy_m, dtype=np.float64),
            np.ascontiguousarray(beams.ends_xy_m, dtype=np.float64),
            np.ascontiguousarray(beams.is_hit),
        )
        grid = GridGeometry.of(x0, y0, resolution_m, nx, ny)
        model = (logit(p_free), logit(p_occ), logit(p_clamp))
        t0 = time.perf_counter()
        if beam_width_deg > 0.0:
            half_width = 0.5 * math.radians(beam_width_deg)
            updates = _integrate_cones(*rays, half_width, grid, *model, L)
        else:
            updates = _integrate(*rays, *grid, *model, L)
        seconds = time.perf_counter() - t0
        return cls(
            L.astype(np.float32), np.array([x0, y0], float), float(resolution_m), int(updates), seconds
        )

    @classmethod
    def from_config(
        cls, beams: Beams, config: GridBaselineConfig, bounds_xy_m: Bounds | None = None
    ) -> OccupancyGrid:
        """:meth:`build` with the settings of a :class:`~mapping.config.GridBaselineConfig`."""
        return cls.build(
            beams, config.resolution_m, bounds_xy_m, config.p_occupied, config.p_free, config.p_clamp,
            config.beam_width_deg,
        )  # fmt: skip

    @property
    def probability(self) -> NDArray[np.float32]:
        """(H, W) p(occ) = 1 - 1 / (1 + exp(l))."""
        return (1.0 / (1.0 + np.exp(-self.log_odds.astype(np.float64)))).astype(np.float32)

    def query(self, points_xy_m: FloatArray) -> FloatArray:
        """(Q,) p(occ) of the cells holding (Q, 2) points; 0.5 (the prior) outside the grid."""
        pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
        ij = np.floor((pts - self.origin_xy_m) / self.resolution_m).astype(np.int64)
        h, w = self.log_odds.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        out = np.full(pts.shape[0], 0.5)
        lo = self.log_odds[ij[inside, 1], ij[inside, 0]].astype(np.float64)
        out[inside] = 1.0 / (1.0 + np.exp(-lo))
        return out
