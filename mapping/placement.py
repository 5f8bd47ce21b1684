"""Placement uncertainty: how far from where a map draws it each observed place may lie in the world frame.

GPPOL blurs a scan by its pose uncertainty relative to the other passes over the places it sees
(:mod:`slam.consistency`), because that is what makes a map inconsistent. The world-frame marginals say
something else: how uncertain the map's placement is relative to the graph's anchor (the first pose), which
grows with the distance travelled from it even where every scan agrees with its neighbours. Blurring the
map with them erases consistent corridors; a planner that takes goals or constraints in world coordinates
from elsewhere (a floor plan, GNSS waypoints, another robot's map) still needs to know it. So it is a layer
of its own: per cell, the standard deviation (m) along the most uncertain direction of the world position
of the cell's content, as placed by the best-placed scan that observed the cell.

Each beam's points are propagated through its scan's world covariance by the same exact unscented transform
as GPPOL's inputs (:func:`mapping.gppol.input_moments`, pose only: the laser noise is part of the map's
local variance, not of its placement), ``Sigma(d) = C0 + d C1 + d^2 C2`` at distance ``d`` along the beam;
a cell takes the smallest largest-eigenvalue over the beams whose free part crosses it or whose return lies
in it, and NaN where no beam touched it.
"""

from __future__ import annotations

import dataclasses
import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mapping.beams import Beams
from mapping.exports import MapLayers
from mapping.gppol import SensorNoise, input_moments
from mapping.raster import GridGeometry, in_grid, point_cell, segment_cells

FloatArray = NDArray[np.float64]


@nb.njit(cache=True, error_model="numpy", inline="always")
def _largest_variance(c0, c1, c2, i, d):
    """Largest eigenvalue of ``C0 + d C1 + d^2 C2`` of beam i (packed (xx, xy, yy) rows)."""
    a = c0[i, 0] + d * (c1[i, 0] + d * c2[i, 0])
    b = c0[i, 1] + d * (c1[i, 1] + d * c2[i, 1])
    c = c0[i, 2] + d * (c1[i, 2] + d * c2[i, 2])
    half = 0.5 * (a - c)
    return max(0.5 * (a + c) + math.sqrt(half * half + b * b), 0.0)


@nb.njit(cache=True, error_model="numpy", inline="always")
def _keep_smaller(out, ix, iy, v):
    if v < out[iy, ix]:
        out[iy, ix] = v


@nb.njit(cache=True, error_model="numpy", nogil=True)
def _smallest_variances(origins, free_ends, ends, is_hit, ranges, c0, c1, c2, grid, out):
    """``out`` (ny, nx) <- per cell the smallest largest-eigenvalue over the beams touching it (cells no
    beam touches keep their value). Releases the GIL: a run's maps get theirs in parallel threads."""
    cells = np.empty((grid.nx + grid.ny, 2), np.int64)
    for i in range(origins.shape[0]):
        ox = origins[i, 0]
        oy = origins[i, 1]
        length = math.hypot(free_ends[i, 0] - ox, free_ends[i, 1] - oy)
        if length > 0.0:
            ux = (free_ends[i, 0] - ox) / length
            uy = (free_ends[i, 1] - oy) / length
            for k in range(segment_cells(grid, ox, oy, free_ends[i, 0], free_ends[i, 1], cells)):
                ix, iy = cells[k, 0], cells[k, 1]
                # the distance along the beam of the cell centre's foot on it
                cx = grid.x0 + (ix + 0.5) * grid.cell - ox
                cy = grid.y0 + (iy + 0.5) * grid.cell - oy
                d = min(max(cx * ux + cy * uy, 0.0), length)
                _keep_smaller(out, ix, iy, _largest_variance(c0, c1, c2, i, d))
        if is_hit[i]:
            ix, iy = point_cell(grid, ends[i, 0], ends[i, 1])
            if in_grid(grid, ix, iy):
                _keep_smaller(out, ix, iy, _largest_variance(c0, c1, c2, i, ranges[i]))


def placement_sigma_m(
    beams: Beams,
    pose_cov_world_xytheta: FloatArray,
    origin_xy_m: tuple[float, float] | FloatArray,
    resolution_m: float,
    shape: tuple[int, int],
) -> NDArray[np.float32]:
    """(H, W) float32 placement uncertainty (m) of a map grid (lower-left corner ``origin_xy_m``, cells of
    ``resolution_m``, ``shape`` (H, W), row 0 at the lowest y): per cell the square root of the largest
    eigenvalue of the world-frame covariance of the cell's point on the best-placed beam touching it; NaN
    where no beam touches it. ``pose_cov_world_xytheta`` (N, 3, 3): each scan's world-frame base-pose
    covariance (the SLAM marginals), indexed by ``beams.scan_index``."""
    h, w = (int(v) for v in shape)
    out = np.full((h, w), np.inf)
    if len(beams) and h and w:
        moments = input_moments(beams, pose_cov_world_xytheta, [SensorNoise()] * len(beams.source_names))
        grid = GridGeometry.of(origin_xy_m[0], origin_xy_m[1], resolution_m, w, h)
        _smallest_variances(
            np.ascontiguousarray(beams.origins_xy_m, dtype=np.float64),
            np.ascontiguousarray(beams.free_ends_xy_m, dtype=np.float64),
            np.ascontiguousarray(beams.ends_xy_m, dtype=np.float64),
            np.ascontiguousarray(beams.is_hit),
            np.ascontiguousarray(beams.ranges_m, dtype=np.float64),
            np.ascontiguousarray(moments.c0),
            np.ascontiguousarray(moments.c1),
            np.ascontiguousarray(moments.c2),
            grid,
            out,
        )
    sigma = np.empty((h, w), np.float32)
    _sigma_of(out, sigma)
    return sigma


@nb.njit(cache=True, nogil=True)
def _sigma_of(variance, sigma):
    """``sigma`` <- float32 square roots of ``variance`` (same shape), NaN where it is not finite (no beam):
    one pass, without the temporaries of the numpy expression (a big building's layer is 15 M cells)."""
    v = variance.reshape(-1)
    s = sigma.reshape(-1)
    for i in range(v.size):
        s[i] = math.sqrt(v[i]) if math.isfinite(v[i]) else np.nan


def with_placement(layers: MapLayers, beams: Beams, pose_cov_world_xytheta: FloatArray | None) -> MapLayers:
    """``layers`` with its :func:`placement_sigma_m` layer from the ``beams`` it was rendered from and their
    scans' world-frame covariances (N, 3, 3); unchanged when there are none."""
    if pose_cov_world_xytheta is None:
        return layers
    sigma = placement_sigma_m(
        beams, pose_cov_world_xytheta, layers.origin_xy_m, layers.resolution_m, layers.shape
    )
    return dataclasses.replace(layers, placement_sigma_m=sigma)
