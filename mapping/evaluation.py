"""Evaluation protocols of SPEC section 6: the map hold-out protocol and the simulated-world protocol.

The hold-out protocol is the one of the Hilbert-maps reference code (Ramos & Ott, RSS 2015), written so that
any two implementations score the same test points: Python's ``random.Random``, ``randint`` and ``uniform``
in a fixed order. Do not vectorise it.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Sequence

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mapping.beams import Beams
from mapping.exports import MapLayers
from mapping.metrics import auc_shortfall_per_point, roc_auc
from mapping.raster import GridGeometry, in_grid, point_cell, segment_cells

FloatArray = NDArray[np.float64]

HOLDOUT_FRACTION = 0.1
HOLDOUT_BLOCK = 40
HOLDOUT_SHORT_BLOCK = 10  # recordings under 400 scans, where no 40-scan block fits (SPEC section 6)
HOLDOUT_MAX_RANGE_M = 40.0


def holdout_split(
    n_scans: int, seed: int, fraction: float = HOLDOUT_FRACTION, block: int = HOLDOUT_BLOCK
) -> list[int]:
    """Indices (ascending) of the held-out scans among ``n_scans`` in log order (SPEC section 6).

    ``rng = random.Random(seed)``; ``blocks = int(n * fraction / block)``; repeat ``start = rng.randint(0,
    n - block)``, draw again if ``start`` or ``start + block`` is already held out, else hold out
    ``range(start, start + block)``, until ``blocks`` blocks are held out."""
    rng = random.Random(seed)
    blocks = int(n_scans * fraction / block)
    held: set[int] = set()
    done = 0
    while done < blocks:
        start = rng.randint(0, n_scans - block)
        if start in held or start + block in held:
            continue
        held.update(range(start, start + block))
        done += 1
    return sorted(held)


def holdout_block_scans(n_scans: int, fraction: float = HOLDOUT_FRACTION) -> int | None:
    """The block size of the hold-out protocol for ``n_scans`` scans (SPEC section 6): 40, or 10 when no
    40-scan block fits (under 400 scans); None when not even a 10-scan block fits (under 100)."""
    for block in (HOLDOUT_BLOCK, HOLDOUT_SHORT_BLOCK):
        if int(n_scans * fraction / block) >= 1:
            return block
    return None


def holdout_test_points(
    ranges_m: Sequence[NDArray],
    angles_rad: Sequence[NDArray],
    laser_poses_xytheta: FloatArray,
    held_out: Sequence[int],
    seed: int,
    carmen_180: bool,
    max_range_m: float = HOLDOUT_MAX_RANGE_M,
    with_ranges: bool = False,
) -> tuple[FloatArray, NDArray[np.bool_]] | tuple[FloatArray, NDArray[np.bool_], FloatArray]:
    """Test points of the held-out scans (SPEC section 6): (T, 2) world points and (T,) labels (True =
    occupied); with ``with_ranges`` also (T,) each point's distance from its laser (m).

    ``rng = random.Random(seed + 1)``; for each held-out scan in order, for each beam ``i`` in order with
    range ``r <= max_range_m``, at angle ``a = theta - pi/2 + i pi / n_beams`` (``carmen_180``) or
    ``theta + angles_rad[i]``: the endpoint (occupied), then ``max(1, int(r / 2))`` points at distance
    ``rng.uniform(0, max(0, r - 0.1))`` along the beam (free)."""
    rng = random.Random(seed + 1)
    xs: list[float] = []
    ys: list[float] = []
    labels: list[bool] = []
    dists: list[float] = []
    for s in held_out:
        x, y, theta = (float(v) for v in laser_poses_xytheta[s])
        ranges = np.asarray(ranges_m[s], dtype=np.float64)
        angles = np.asarray(angles_rad[s], dtype=np.float64)
        n_beams = ranges.shape[0]
        for i in range(n_beams):
            r = float(ranges[i])
            if not r <= max_range_m:  # also drops NaN
                continue
            a = theta - math.pi / 2 + i * math.pi / n_beams if carmen_180 else theta + float(angles[i])
            c, sn = math.cos(a), math.sin(a)
            xs.append(x + r * c)
            ys.append(y + r * sn)
            labels.append(True)
            dists.append(r)
            for _ in range(max(1, int(r / 2))):
                d = rng.uniform(0, max(0.0, r - 0.1))
                xs.append(x + d * c)
                ys.append(y + d * sn)
                labels.append(False)
                dists.append(d)
    points = np.stack([np.asarray(xs), np.asarray(ys)], axis=1).reshape(-1, 2)
    if with_ranges:
        return points, np.asarray(labels, dtype=bool), np.asarray(dists, dtype=np.float64)
    return points, np.asarray(labels, dtype=bool)


#: Bins of :func:`auc_by_bins` used by ``evaluate map --breakdown``: a test point's distance from its laser
#: (m, up to the protocol's 40 m), and the training beams' endpoints within :data:`HIT_RADIUS_M` of it.
RANGE_EDGES_M = (0.0, 2.0, 5.0, 10.0, 20.0, HOLDOUT_MAX_RANGE_M)
HIT_COUNT_EDGES = (0.0, 1.0, 5.0, 20.0, 100.0, math.inf)
HIT_RADIUS_M = 1.0
#: ... and its distance from the nearest of the training beams' endpoints (m): a wall the map places a few
#: centimetres off leaves its occupied test points in the first bins beyond the map's returns.
NEAREST_HIT_EDGES_M = (0.0, 0.05, 0.1, 0.2, 0.5, 1.0, math.inf)


def hits_within(hits_xy_m: FloatArray, points_xy_m: FloatArray, radius_m: float = HIT_RADIUS_M) -> NDArray:
    """(T,) int64: how many of the (H, 2) ``hits_xy_m`` lie within ``radius_m`` of each (T, 2) point (the
    local density of returns a map can lean on there)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    hits = np.asarray(hits_xy_m, dtype=np.float64).reshape(-1, 2)
    if hits.shape[0] == 0:
        return np.zeros(points.shape[0], dtype=np.int64)
    counts = cKDTree(hits).query_ball_point(points, radius_m, return_length=True)
    return np.asarray(counts, dtype=np.int64).reshape(points.shape[0])


def nearest_hit_m(hits_xy_m: FloatArray, points_xy_m: FloatArray) -> FloatArray:
    """(T,) the distance (m) from each (T, 2) point to the nearest of the (H, 2) ``hits_xy_m`` (infinity
    without any)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    hits = np.asarray(hits_xy_m, dtype=np.float64).reshape(-1, 2)
    if hits.shape[0] == 0:
        return np.full(points.shape[0], math.inf)
    return np.asarray(cKDTree(hits).query(points)[0], dtype=np.float64).reshape(points.shape[0])


def auc_by_bins(
    probability: FloatArray,
    labels: NDArray[np.bool_],
    values: FloatArray,
    edges: Sequence[float],
    shortfall: FloatArray | None = None,
) -> list[dict]:
    """The test points split by ``values`` (T,) into the bins ``[edges[i], edges[i + 1])`` (the last one
    closed): per bin ``from``, ``to`` (None: no upper end), ``test_points``, ``occupied``, ``auc`` of
    ``probability`` (None unless both labels occur), the mean probability of its occupied and of its
    free points (``p_occupied``, ``p_free``; None without any), and how much of the AUC over all the test
    points falls short of 1 on its occupied and on its free points (``auc_lost_occupied``,
    ``auc_lost_free``: :func:`mapping.metrics.auc_shortfall_per_point` summed over the bin; over all bins
    each sums to ``1 - AUC``; None unless both labels occur among all the points). Where a map wins or
    loses: near or far from the sensor, where returns are dense or sparse; the bin's AUC compares its own
    points, its lost share ranks them against all the others. ``shortfall``: those per-point parts when the
    caller already has them (one ranking serves every split of the same scores)."""
    p = np.asarray(probability, dtype=np.float64)
    y = np.asarray(labels, dtype=bool)
    v = np.asarray(values, dtype=np.float64)
    lost = None
    if y.any() and not y.all():
        lost = auc_shortfall_per_point(p, y) if shortfall is None else np.asarray(shortfall, dtype=np.float64)
    out = []
    for i in range(len(edges) - 1):
        lo, hi = float(edges[i]), float(edges[i + 1])
        m = (v >= lo) & ((v <= hi) if i == len(edges) - 2 else (v < hi))
        yb, pb = y[m], p[m]
        both = bool(yb.any() and not yb.all())
        out.append(
            {
                "from": lo,
                "to": None if math.isinf(hi) else hi,  # open-ended (JSON has no infinity)
                "test_points": int(m.sum()),
                "occupied": int(yb.sum()),
                "auc": float(roc_auc(pb, yb)) if both else None,
                "p_occupied": float(pb[yb].mean()) if yb.any() else None,
                "p_free": float(pb[~yb].mean()) if (~yb).any() else None,
                "auc_lost_occupied": float(lost[m & y].sum()) if lost is not None else None,
                "auc_lost_free": float(lost[m & ~y].sum()) if lost is not None else None,
            }
        )
    return out


def is_carmen_180(angles_rad: NDArray, tol_rad: float = 1e-5) -> bool:
    """True when a scan's angles are the CARMEN 180-degree convention ``-pi/2 + i pi / n``."""
    a = np.asarray(angles_rad, dtype=np.float64)
    n = a.shape[0]
    return n > 0 and bool(np.allclose(a, -np.pi / 2 + np.arange(n) * np.pi / n, atol=tol_rad, rtol=0))


def raster_cell_centres(shape: tuple[int, int], origin_xy_m: FloatArray, resolution_m: float) -> FloatArray:
    """(H*W, 2) centres of the cells of an (H, W) raster (row i at y, column j at x), row-major."""
    h, w = shape
    xs = origin_xy_m[0] + (np.arange(w) + 0.5) * resolution_m
    ys = origin_xy_m[1] + (np.arange(h) + 0.5) * resolution_m
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def observed_cells(
    beams: Beams, bounds_xy_m: tuple[float, float, float, float], resolution_m: float
) -> NDArray:
    """(h, w) bool: the cells of the grid over ``bounds_xy_m`` at ``resolution_m`` (row 0 at the lowest y)
    that at least one of ``beams`` crosses or ends in -- the cells a sensor observed."""
    from mapping.grid import OccupancyGrid

    return np.asarray(OccupancyGrid.build(beams, resolution_m, bounds_xy_m).log_odds != 0)


def observed_points(
    beams: Beams,
    points_xy_m: FloatArray,
    resolution_m: float = 0.1,
    anchor_xy_m: tuple[float, float] | FloatArray | None = None,
) -> NDArray[np.bool_]:
    """(P,) bool: which of the (P, 2) ``points_xy_m`` lie in an *observed cell*, a cell of a regular grid of
    ``resolution_m`` that some beam touched: its free segment (origin to ``free_ends_xy_m``) crosses it or
    its occupied endpoint lies in it (a free part of length 0 crosses nothing).

    The cells are those of the occupancy-grid baseline (the same compiled ray walk, :mod:`mapping.grid`,
    with unit weights): a lattice with a corner at ``anchor_xy_m`` (default the baseline's, the beams'
    lower-left corner less one cell; a ground-truth raster's origin to use its cells), laid over the test
    points' bounding box only (a beam's cells outside it are never stored)."""
    from mapping.grid import _integrate

    pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    observed = np.zeros(pts.shape[0], dtype=bool)
    if pts.shape[0] == 0 or len(beams) == 0:
        return observed
    if not np.all(np.isfinite(pts)):
        raise ValueError("test points must be finite")
    res = float(resolution_m)
    if anchor_xy_m is None:
        anchor = np.asarray(beams.bounds_xy_m(margin_m=res)[:2], dtype=np.float64)
    else:
        anchor = np.asarray(anchor_xy_m, dtype=np.float64).reshape(2)
    first = np.floor((pts.min(axis=0) - anchor) / res)
    last = np.floor((pts.max(axis=0) - anchor) / res)
    origin = anchor + first * res
    nx, ny = (int(v) for v in last - first + 1)
    counts = np.zeros((ny, nx), dtype=np.float64)
    grid = (float(origin[0]), float(origin[1]), res, nx, ny)
    unit = (1.0, 1.0, math.inf)  # l_free, l_occ, l_max: every touch adds one, nothing is clamped
    free = np.any(beams.free_ends_xy_m != beams.origins_xy_m, axis=1)  # length 0: touches nothing
    origins = np.ascontiguousarray(beams.origins_xy_m[free], dtype=np.float64)
    free_ends = np.ascontiguousarray(beams.free_ends_xy_m[free], dtype=np.float64)
    _integrate(origins, free_ends, np.zeros(origins.shape[0], dtype=bool), *grid, *unit, counts)
    hits = np.ascontiguousarray(beams.ends_xy_m[beams.is_hit], dtype=np.float64)
    _integrate(hits, hits, np.ones(hits.shape[0], dtype=bool), *grid, *unit, counts)  # endpoint cells
    ij = np.floor((pts - origin) / res).astype(np.int64)
    ij[:, 0] = np.clip(ij[:, 0], 0, nx - 1)  # a rounding at a cell's edge never leaves the lattice
    ij[:, 1] = np.clip(ij[:, 1], 0, ny - 1)
    return counts[ij[:, 1], ij[:, 0]] > 0


def rendered_ground_truth_auc(
    rendered: MapLayers,
    occupancy: NDArray,
    origin_xy_m: NDArray,
    resolution_m: float,
    query: Callable[[FloatArray], FloatArray],
) -> float:
    """AUC of a map's p(occ) over every cell of a ground-truth raster (SPEC section 6, simulated worlds):
    ``occupancy`` (H, W) truthy where occupied, its lower-left corner at ``origin_xy_m``. The raster's cells
    that are cells of the map already ``rendered`` (same resolution and lattice, within its bounds) are
    scored on its float32 p(occ), the map as exported, and only the others on ``query`` ((P, 2) points ->
    (P,) p(occ) of the same map), which is not called when there are none."""
    origin = np.asarray(origin_xy_m, np.float64)
    centres = raster_cell_centres(occupancy.shape, origin, resolution_m)
    probability = np.empty(centres.shape[0])
    todo = np.ones(centres.shape[0], bool)
    rows_cols = _cells_in(rendered, occupancy.shape, origin, resolution_m)
    if rows_cols is not None:
        inside, rows, cols = rows_cols
        probability[inside] = rendered.probability[rows, cols]
        todo[inside] = False
    if todo.any():
        probability[todo] = query(centres[todo])
    return roc_auc(probability, np.asarray(occupancy).astype(bool).ravel())


def _cells_in(
    rendered: MapLayers, shape: tuple[int, int], origin_xy_m: FloatArray, resolution_m: float
) -> tuple[NDArray[np.bool_], NDArray[np.int64], NDArray[np.int64]] | None:
    """For the cells of a raster (``shape``, ``origin_xy_m``, ``resolution_m``), row-major: which are cells
    of ``rendered`` (mask (H*W,)) and their rows and columns there; None when the two grids do not share a
    lattice."""
    if not math.isclose(rendered.resolution_m, resolution_m, rel_tol=1e-9):
        return None
    offset = (origin_xy_m - np.asarray(rendered.origin_xy_m, np.float64)) / resolution_m
    whole = np.round(offset)
    if np.any(np.abs(offset - whole) > 1e-6):
        return None
    h, w = shape
    rows, cols = np.meshgrid(np.arange(h) + int(whole[1]), np.arange(w) + int(whole[0]), indexing="ij")
    rows, cols = rows.ravel(), cols.ravel()
    rh, rw = rendered.shape
    inside = (rows >= 0) & (rows < rh) & (cols >= 0) & (cols < rw)
    return inside, rows[inside], cols[inside]


@nb.njit(cache=True, error_model="numpy", inline="always")
def _visit(ix, iy, path_m, gap_m, last, revisited):
    """Cell (ix, iy) observed at ``path_m`` of travel: a new pass when the last observation lies more than
    ``gap_m`` of travel before."""
    prev = last[iy, ix]
    if path_m - prev > gap_m and math.isfinite(prev):
        revisited[iy, ix] = True
    last[iy, ix] = path_m


@nb.njit(cache=True, error_model="numpy")
def _passes(origins, free_ends, ends, is_hit, path_m, gap_m, grid, last, revisited):
    """Walk every beam (in the order of ``path_m`` (M,), non-decreasing) over the cells its free part
    crosses and the cell of its return, updating ``last`` / ``revisited`` (ny, nx) (:func:`_visit`)."""
    cells = np.empty((grid.nx + grid.ny, 2), np.int64)
    for i in range(origins.shape[0]):
        for k in range(
            segment_cells(grid, origins[i, 0], origins[i, 1], free_ends[i, 0], free_ends[i, 1], cells)
        ):
            _visit(cells[k, 0], cells[k, 1], path_m[i], gap_m, last, revisited)
        if is_hit[i]:
            ix, iy = point_cell(grid, ends[i, 0], ends[i, 1])
            if in_grid(grid, ix, iy):
                _visit(ix, iy, path_m[i], gap_m, last, revisited)


def pass_masks(
    beams: Beams,
    path_m: FloatArray,
    gap_m: float,
    shape: tuple[int, int],
    origin_xy_m: FloatArray,
    resolution_m: float,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """``(observed, revisited)`` (H, W) bool over a raster (``shape``, lower-left ``origin_xy_m``, cells of
    ``resolution_m``): the cells a beam's free part crosses or its return lies in, and those among them
    observed again after the robot travelled more than ``gap_m`` without observing them -- the places two
    passes see, where an inconsistent trajectory doubles walls (the visits of :mod:`slam.consistency`,
    per cell). ``path_m`` (N,): the distance travelled to each scan (``beams.scan_index`` indexes it)."""
    h, w = (int(v) for v in shape)
    last = np.full((h, w), -np.inf)
    revisited = np.zeros((h, w), dtype=bool)
    if len(beams):
        order = np.argsort(np.asarray(path_m, dtype=np.float64)[beams.scan_index], kind="stable")
        grid = GridGeometry.of(float(origin_xy_m[0]), float(origin_xy_m[1]), resolution_m, w, h)
        _passes(
            np.ascontiguousarray(beams.origins_xy_m[order], dtype=np.float64),
            np.ascontiguousarray(beams.free_ends_xy_m[order], dtype=np.float64),
            np.ascontiguousarray(beams.ends_xy_m[order], dtype=np.float64),
            np.ascontiguousarray(beams.is_hit[order]),
            np.ascontiguousarray(np.asarray(path_m, dtype=np.float64)[beams.scan_index[order]]),
            float(gap_m),
            grid,
            last,
            revisited,
        )
    return np.isfinite(last), revisited


def ground_truth_auc_over(
    rendered: MapLayers,
    occupancy: NDArray,
    origin_xy_m: FloatArray,
    resolution_m: float,
    cells: dict[str, NDArray[np.bool_]],
) -> dict[str, float | None]:
    """AUC of the ``rendered`` map's p(occ) against a ground-truth raster (as
    :func:`rendered_ground_truth_auc`) over each named subset ``cells`` ((H, W) bool on the raster) of its
    cells that lie in the map; None for a subset without both labels."""
    rows_cols = _cells_in(rendered, occupancy.shape, np.asarray(origin_xy_m, np.float64), resolution_m)
    out: dict[str, float | None] = {name: None for name in cells}
    if rows_cols is None:
        return out
    inside, rows, cols = rows_cols
    probability = np.full(inside.shape[0], np.nan)
    probability[inside] = rendered.probability[rows, cols]
    labels = np.asarray(occupancy).astype(bool).ravel()
    for name, mask in cells.items():
        keep = np.asarray(mask).ravel() & inside
        lab = labels[keep]
        if lab.any() and not lab.all():
            out[name] = roc_auc(probability[keep], lab)
    return out
