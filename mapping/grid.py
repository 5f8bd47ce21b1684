"""The baseline: a log-odds occupancy grid with the inverse sensor model of Thrun et al. (2005, ch. 9).

Every beam is ray-traced through the grid (Amanatides & Woo, compiled): the cells it crosses before its
endpoint get ``logit(p_free)``, the endpoint's cell gets ``logit(p_occ)``; a no-return beam only frees cells
along its configured free length. Log-odds are clamped to ``[-l_max, l_max]``; the prior is 0.5. The grid
answers the same questions as the GP map: p(occ) at arbitrary points (cell lookup) and as a raster.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mapping.beams import Beams

FloatArray = NDArray[np.float64]


def logit(p: float) -> float:
    return math.log(p / (1.0 - p))


@nb.njit(cache=True)
def _trace(ox, oy, ex, ey, hit, x0, y0, res, nx, ny, l_free, l_occ, l_max, L):
    """Update log-odds L (ny, nx) along the ray from (ox, oy) to (ex, ey); returns the cells updated."""
    gx0 = (ox - x0) / res
    gy0 = (oy - y0) / res
    gx1 = (ex - x0) / res
    gy1 = (ey - y0) / res
    ix = math.floor(gx0)
    iy = math.floor(gy0)
    jx = math.floor(gx1)
    jy = math.floor(gy1)
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
    updated = 0
    steps = abs(jx - ix) + abs(jy - iy)
    for _ in range(steps):
        if 0 <= ix < nx and 0 <= iy < ny:
            v = L[iy, ix] + l_free
            L[iy, ix] = max(v, -l_max)
            updated += 1
        if tmx < tmy:
            tmx += tdx
            ix += sx
        else:
            tmy += tdy
            iy += sy
    if 0 <= jx < nx and 0 <= jy < ny:
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
    total = 0
    for i in range(origins.shape[0]):
        total += _trace(
            origins[i, 0], origins[i, 1], ends[i, 0], ends[i, 1], is_hit[i],
            x0, y0, res, nx, ny, l_free, l_occ, l_max, L,
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
    ) -> OccupancyGrid:
        """Integrate every beam (in order) into a grid over ``bounds_xy_m`` (default: the beams' bounds)."""
        x0, y0, x1, y1 = bounds_xy_m or beams.bounds_xy_m(margin_m=resolution_m)
        nx = max(1, math.ceil((x1 - x0) / resolution_m))
        ny = max(1, math.ceil((y1 - y0) / resolution_m))
        L = np.zeros((ny, nx), np.float64)
        t0 = time.perf_counter()
        updates = _integrate(
            np.ascontiguousarray(beams.origins_xy_m),
            np.ascontiguousarray(beams.ends_xy_m),
            np.ascontiguousarray(beams.is_hit),
            float(x0),
            float(y0),
            float(resolution_m),
            nx,
            ny,
            logit(p_free),
            logit(p_occ),
            logit(p_clamp),
            L,
        )
        seconds = time.perf_counter() - t0
        return cls(
            L.astype(np.float32), np.array([x0, y0], float), float(resolution_m), int(updates), seconds
        )

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
