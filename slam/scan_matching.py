"""2D scan matching against a point map on a grid: correlative search and point-to-line Gauss-Newton.

A :class:`PointGrid` stores, for every cell of a regular grid, the index of the nearest map point within a
radius (so a nearest-neighbour query is one array lookup) and a smooth score ``exp(-d^2 / 2 sigma^2)`` of the
distance ``d`` from the cell centre to that point. On it:

- :func:`correlative_search` (Olson, "Real-time correlative scan matching", ICRA 2009): the exhaustive
  search of a window of poses maximising the summed score of the transformed scan points; coarse-to-fine
  for large windows (a max-pooled score grid bounds the fine score, then the best coarse cells are refined).
- :func:`refine_point_to_line`: robust (Cauchy) Gauss-Newton on point-to-line residuals ``n_j . (R p_i + t -
  m_j)`` with an optional Gaussian prior on the pose (the wheel odometry), returning the Hessian that is
  the information of the alignment.

All hot loops are numba; points are (P, 2) float64 arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import maximum_filter

from slam import geometry as se2

FloatArray = NDArray[np.float64]


# ---------------------------------------------------------------------------------------------------------
# Point normals


@nb.njit(cache=True)
def _scan_normals(
    points: FloatArray,
    radius_m: float,
    max_half_window: int,
    max_flatness: float,
    min_points: int,
    viewpoint: FloatArray,
    radius_per_m: float,
) -> FloatArray:
    p = points.shape[0]
    normals = np.full((p, 2), np.nan)
    for i in range(p):
        rng = math.hypot(points[i, 0] - viewpoint[0], points[i, 1] - viewpoint[1])
        rad = max(radius_m, radius_per_m * rng)
        r2 = rad * rad
        # neighbours within the radius, walking the scan order both ways from i; a walk stops after 3
        # consecutive points beyond the radius (a depth edge) or max_half_window steps
        sx = 0.0
        sy = 0.0
        sxx = 0.0
        sxy = 0.0
        syy = 0.0
        cnt = 1
        for d in (-1, 1):
            j = i + d
            misses = 0
            steps = 0
            while 0 <= j < p and steps < max_half_window:
                dx = points[j, 0] - points[i, 0]
                dy = points[j, 1] - points[i, 1]
                if dx * dx + dy * dy <= r2:
                    sx += dx
                    sy += dy
                    sxx += dx * dx
                    sxy += dx * dy
                    syy += dy * dy
                    cnt += 1
                    misses = 0
                else:
                    misses += 1
                    if misses >= 3:
                        break
                j += d
                steps += 1
        if cnt < min_points:
            continue
        mx = sx / cnt
        my = sy / cnt
        cxx = sxx / cnt - mx * mx
        cxy = sxy / cnt - mx * my
        cyy = syy / cnt - my * my
        # eigen-decomposition of [[cxx, cxy], [cxy, cyy]]
        tr = cxx + cyy
        det = cxx * cyy - cxy * cxy
        disc = math.sqrt(max(tr * tr / 4.0 - det, 0.0))
        lmax = tr / 2.0 + disc
        lmin = tr / 2.0 - disc
        if lmax <= 0.0 or lmin > max_flatness * lmax:
            continue
        # eigenvector of lmin
        if abs(cxy) > 1e-12:
            nx = lmin - cyy
            ny = cxy
        elif cxx <= cyy:
            nx = 1.0
            ny = 0.0
        else:
            nx = 0.0
            ny = 1.0
        norm = math.sqrt(nx * nx + ny * ny)
        if nx * (viewpoint[0] - points[i, 0]) + ny * (viewpoint[1] - points[i, 1]) < 0.0:
            norm = -norm  # facing the sensor
        normals[i, 0] = nx / norm
        normals[i, 1] = ny / norm
    return normals


def scan_normals(
    points_xy: FloatArray,
    radius_m: float = 0.3,
    max_half_window: int = 40,
    max_flatness: float = 0.2,
    min_points: int = 3,
    viewpoint_xy: FloatArray | None = None,
    radius_per_m: float = 0.0,
) -> FloatArray:
    """(P, 2) unit normals of ordered scan points (NaN where the neighbourhood is not line-like).

    The neighbourhood of point ``i`` is every point within ``radius_m`` of it reached by walking the scan
    order both ways (at most ``max_half_window`` steps each way; a walk ends after 3 consecutive points
    beyond the radius). The normal is its direction of least spread; at least ``min_points`` points
    (``i`` included) and ``lambda_min <= max_flatness * lambda_max`` are required. A metric radius
    averages the range noise over many beams of a dense scanner (0.25 deg beams at 1 m are 4 mm apart)
    and stays local on a sparse one; ``radius_per_m`` widens it in proportion to the point's distance from
    the viewpoint, so that far points of a sparse scanner (1 deg beams are 35 cm apart at 20 m) still find
    their neighbours. Normals face ``viewpoint_xy`` (default: the origin of the points' frame;
    odometry and loop closure pass base-frame points, so they face the base, which sees the same side of a
    surface as the laser mounted on it), so that the normals of one surface seen in several scans agree in
    sign. The
    pipeline passes ``max_half_window = SlamConfig.odometry.normal_max_neighbours`` (2 by default); 40 is the
    default of this function for dense scanners.
    """
    pts = np.ascontiguousarray(points_xy, dtype=np.float64)
    vp = np.zeros(2) if viewpoint_xy is None else np.asarray(viewpoint_xy, dtype=np.float64)
    return _scan_normals(
        pts,
        float(radius_m),
        int(max_half_window),
        float(max_flatness),
        int(min_points),
        vp,
        float(radius_per_m),
    )


@nb.njit(cache=True)
def _first_of_each(keys: NDArray[np.int64]) -> NDArray[np.int64]:
    """Indices (in increasing order) of the first occurrence of each distinct value of ``keys`` (n,):
    one pass with an open-addressing hash table (Fibonacci hashing, linear probing), no sort."""
    n = keys.shape[0]
    bits = 4
    while (1 << bits) < 2 * n:
        bits += 1
    mask = (1 << bits) - 1
    slots = np.full(1 << bits, -1, dtype=np.int64)  # the index of the first key that took the slot
    out = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        k = keys[i]
        slot = np.int64((np.uint64(k) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(64 - bits))
        while True:
            j = slots[slot]
            if j < 0:
                slots[slot] = i
                out[m] = i
                m += 1
                break
            if keys[j] == k:
                break
            slot = (slot + 1) & mask
    return out[:m]


def voxel_thin(points_xy: FloatArray, voxel_m: float) -> NDArray[np.int64]:
    """Indices, in input order, of the first point (P, 2) in each occupied ``voxel_m`` square."""
    if points_xy.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(points_xy / voxel_m).astype(np.int64)
    cells -= cells.min(axis=0)
    return _first_of_each(cells[:, 0] * (int(cells[:, 1].max()) + 1) + cells[:, 1])


# ---------------------------------------------------------------------------------------------------------
# The grid


@nb.njit(cache=True, inline="always")
def _footprint(px, py, x0, y0, res, radius, h, w):
    """The cells ``[r0, r1) x [c0, c1)`` of an (h, w) grid within ``ceil(radius / res)`` cells of the cell
    holding (px, py): those a point inserted there may write (empty when it lies that far off the grid)."""
    rc = math.ceil(radius / res)
    ix = math.floor((px - x0) / res)
    iy = math.floor((py - y0) / res)
    return max(0, iy - rc), min(h, iy + rc + 1), max(0, ix - rc), min(w, ix + rc + 1)


@nb.njit(cache=True)
def _insert_points(
    nearest: NDArray[np.int32],
    d2: NDArray[np.float32],
    score: NDArray[np.float32],
    points: FloatArray,
    first_index: int,
    x0: float,
    y0: float,
    res: float,
    radius: float,
    sigma: float,
    touched: NDArray[np.int64],
) -> None:
    h, w = nearest.shape
    r2 = radius * radius
    inv2s2 = 1.0 / (2.0 * sigma * sigma)
    cx2 = np.empty(2 * math.ceil(radius / res) + 1)  # squared x offsets of a footprint's columns
    for k in range(points.shape[0]):
        px = points[k, 0]
        py = points[k, 1]
        r0, r1, c0, c1 = _footprint(px, py, x0, y0, res, radius, h, w)
        if r1 <= r0 or c1 <= c0:
            continue
        touched[0] = min(touched[0], r0)
        touched[1] = max(touched[1], r1)
        touched[2] = min(touched[2], c0)
        touched[3] = max(touched[3], c1)
        n = c1 - c0
        for j in range(n):
            cx = x0 + (c0 + j + 0.5) * res - px
            cx2[j] = cx * cx
        for jy in range(r0, r1):
            cy = y0 + (jy + 0.5) * res - py
            cy2 = cy * cy
            row = d2[jy]
            # most rows of a wall seen again are already nearer another point: a branch-free pass (vector
            # code) finds the rows this point improves, and only those are written
            better = False
            for j in range(n):
                dd = cx2[j] + cy2
                better |= (dd <= r2) & (dd < row[c0 + j])
            if not better:
                continue
            for j in range(n):
                dd = cx2[j] + cy2
                if dd <= r2 and dd < row[c0 + j]:
                    row[c0 + j] = dd
                    nearest[jy, c0 + j] = first_index + k
                    score[jy, c0 + j] = math.exp(-dd * inv2s2)


@nb.njit(cache=True)
def _clear_around(
    nearest: NDArray[np.int32],
    d2: NDArray[np.float32],
    score: NDArray[np.float32],
    points: FloatArray,
    count: int,
    x0: float,
    y0: float,
    res: float,
    radius: float,
) -> None:
    """Undo :func:`_insert_points` of the first ``count`` ``points`` (same origin, resolution and radius):
    every cell of their footprints (:func:`_footprint`) is emptied again."""
    h, w = nearest.shape
    for k in range(count):
        r0, r1, c0, c1 = _footprint(points[k, 0], points[k, 1], x0, y0, res, radius, h, w)
        for jy in range(r0, r1):
            for jx in range(c0, c1):
                if d2[jy, jx] != np.inf:  # neighbouring points share most of their cells
                    nearest[jy, jx] = -1
                    d2[jy, jx] = np.inf
                    score[jy, jx] = 0.0


class PointGrid:
    """Map points on a fixed grid: nearest-point index and correlative score per cell; points can be added.

    ``origin_xy_m`` is the lower-left corner of cell (0, 0); row index = y. ``nearest`` (H, W) int32 is -1
    where no map point lies within ``radius_m`` of the cell centre; ``score`` (H, W) float32 is
    ``exp(-d^2 / (2 sigma^2))`` of the distance ``d`` from the cell centre to the nearest point (0 beyond
    the radius). Inserting points updates only the cells near them. Points outside the grid are kept in
    ``points_xy`` but influence no cell.
    """

    def __init__(
        self,
        origin_xy_m: FloatArray,
        shape: tuple[int, int],
        resolution_m: float = 0.05,
        radius_m: float = 0.3,
        sigma_m: float = 0.05,
    ) -> None:
        self.origin_xy_m = np.asarray(origin_xy_m, dtype=np.float64)
        self.resolution_m = float(resolution_m)
        self.radius_m = float(radius_m)
        self.sigma_m = float(sigma_m)
        self.nearest = np.full(shape, -1, dtype=np.int32)
        self._d2 = np.full(shape, np.inf, dtype=np.float32)
        self.score = np.zeros(shape, dtype=np.float32)
        self._points = np.empty((1024, 2))
        self._normals = np.empty((1024, 2))
        self._count = 0
        self._coarse: dict[int, NDArray[np.float32]] = {}
        self.free: NDArray[np.bool_] | None = None  # cells seen free by the map's beams (optional)
        # row/column bounds [r0, r1) x [c0, c1) of the cells ever written, so a reset touches only those and
        # a pyramid reads only those (every cell with a score above 0 is inside: insert writes all scores)
        self._touched = np.array([shape[0], 0, shape[1], 0], dtype=np.int64)
        # memory of the pyramids branch_and_bound_search builds of this grid, reused from one to the next
        self._pyramid_buffer = np.empty(0, dtype=np.float32)

    def reset(self, origin_xy_m: FloatArray) -> None:
        """Empty the grid and move it to a new origin, reusing its memory (cheaper than a new grid)."""
        r0, r1, c0, c1 = (int(v) for v in self._touched)
        rc = math.ceil(self.radius_m / self.resolution_m)
        if self._count * (2 * rc + 1) ** 2 < (r1 - r0) * (c1 - c0):
            # fewer cells around the points than in their bounding box (long-range scans spread a few
            # thousand points over most of the grid): empty only the cells the points could write
            _clear_around(
                self.nearest,
                self._d2,
                self.score,
                self._points,
                self._count,
                float(self.origin_xy_m[0]),
                float(self.origin_xy_m[1]),
                self.resolution_m,
                self.radius_m,
            )
        elif r1 > r0 and c1 > c0:
            self.nearest[r0:r1, c0:c1] = -1
            self._d2[r0:r1, c0:c1] = np.inf
            self.score[r0:r1, c0:c1] = 0.0
        self._touched[:] = (self.shape[0], 0, self.shape[1], 0)
        self.origin_xy_m = np.asarray(origin_xy_m, dtype=np.float64).copy()
        self._count = 0
        self._coarse.clear()
        self.free = None

    @classmethod
    def around(
        cls,
        center_xy_m: FloatArray,
        half_size_m: float,
        resolution_m: float = 0.05,
        radius_m: float = 0.3,
        sigma_m: float = 0.05,
    ) -> PointGrid:
        """A square grid of side ``2 * half_size_m`` centred on ``center_xy_m``."""
        n = math.ceil(2.0 * half_size_m / resolution_m)
        origin = np.asarray(center_xy_m, dtype=np.float64)[:2] - 0.5 * n * resolution_m
        return cls(origin, (n, n), resolution_m, radius_m, sigma_m)

    @classmethod
    def from_points(
        cls,
        points_xy: FloatArray,
        normals_xy: FloatArray,
        resolution_m: float = 0.05,
        radius_m: float = 0.3,
        sigma_m: float = 0.05,
        margin_m: float = 1.0,
    ) -> PointGrid:
        """A grid over the points' bounding box plus ``margin_m``, holding the points."""
        pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        lo = pts.min(axis=0) if pts.shape[0] else np.zeros(2)
        hi = pts.max(axis=0) if pts.shape[0] else np.zeros(2)
        w = math.ceil((hi[0] - lo[0] + 2 * margin_m) / resolution_m) + 1
        h = math.ceil((hi[1] - lo[1] + 2 * margin_m) / resolution_m) + 1
        grid = cls(lo - margin_m, (h, w), resolution_m, radius_m, sigma_m)
        grid.insert(pts, normals_xy)
        return grid

    @property
    def shape(self) -> tuple[int, int]:
        return self.nearest.shape  # type: ignore[return-value]

    @property
    def points_xy(self) -> FloatArray:
        """(M, 2) the map points (a view)."""
        return self._points[: self._count]

    @property
    def normals_xy(self) -> FloatArray:
        """(M, 2) their unit normals, NaN where unknown (a view)."""
        return self._normals[: self._count]

    def __len__(self) -> int:
        return self._count

    def insert(self, points_xy: FloatArray, normals_xy: FloatArray) -> None:
        """Add (P, 2) world points with their (P, 2) normals."""
        pts = np.ascontiguousarray(points_xy, dtype=np.float64).reshape(-1, 2)
        nrm = np.ascontiguousarray(normals_xy, dtype=np.float64).reshape(-1, 2)
        need = self._count + pts.shape[0]
        if need > self._points.shape[0]:
            cap = max(need, 2 * self._points.shape[0])
            for name in ("_points", "_normals"):
                old = getattr(self, name)
                new = np.empty((cap, 2))
                new[: self._count] = old[: self._count]
                setattr(self, name, new)
        self._points[self._count : need] = pts
        self._normals[self._count : need] = nrm
        _insert_points(
            self.nearest,
            self._d2,
            self.score,
            pts,
            self._count,
            float(self.origin_xy_m[0]),
            float(self.origin_xy_m[1]),
            self.resolution_m,
            self.radius_m,
            self.sigma_m,
            self._touched,
        )
        self._count = need
        self._coarse.clear()

    def coarse_score(self, factor: int) -> NDArray[np.float32]:
        """The score max-pooled over ``factor + 1`` cells (cached until the next insertion)."""
        out = self._coarse.get(factor)
        if out is None:
            out = maximum_filter(self.score, size=factor + 1, mode="constant", cval=0.0)
            self._coarse[factor] = out
        return out


# ---------------------------------------------------------------------------------------------------------
# Correlative search


@nb.njit(cache=True)
def _csm(
    score: NDArray[np.float32],
    x0: float,
    y0: float,
    res: float,
    points: FloatArray,
    cx: float,
    cy: float,
    ctheta: float,
    n_lin: int,
    lin_step_cells: int,
    n_ang: int,
    ang_step: float,
    top_k: int,
):
    """Exhaustive search; returns the ``top_k`` best (score, x, y, theta) rows, best first."""
    h, w = score.shape
    p = points.shape[0]
    best = np.full((top_k, 4), -1.0)
    ixs = np.empty(p, dtype=np.int64)
    iys = np.empty(p, dtype=np.int64)
    flat = score.ravel()
    reach = n_lin * lin_step_cells
    for a in range(-n_ang, n_ang + 1):
        th = ctheta + a * ang_step
        c = math.cos(th)
        s = math.sin(th)
        lo_x, hi_x, lo_y, hi_y = w, -1, h, -1
        for k in range(p):
            qx = c * points[k, 0] - s * points[k, 1] + cx
            qy = s * points[k, 0] + c * points[k, 1] + cy
            ixs[k] = math.floor((qx - x0) / res)
            iys[k] = math.floor((qy - y0) / res)
            lo_x = min(lo_x, ixs[k])
            hi_x = max(hi_x, ixs[k])
            lo_y = min(lo_y, iys[k])
            hi_y = max(hi_y, iys[k])
        # every shifted point inside the grid (the usual case: submaps reach past the laser's range): no
        # bounds test per point, and one flat index per point (the same sums, in the same order)
        inside = lo_x - reach >= 0 and hi_x + reach < w and lo_y - reach >= 0 and hi_y + reach < h
        if inside:
            for k in range(p):
                ixs[k] = iys[k] * w + ixs[k]
        for dyi in range(-n_lin, n_lin + 1):
            dy = dyi * lin_step_cells
            for dxi in range(-n_lin, n_lin + 1):
                dx = dxi * lin_step_cells
                tot = 0.0
                if inside:
                    shift = dy * w + dx
                    for k in range(p):
                        tot += flat[ixs[k] + shift]
                else:
                    for k in range(p):
                        jx = ixs[k] + dx
                        jy = iys[k] + dy
                        if 0 <= jx < w and 0 <= jy < h:
                            tot += score[jy, jx]
                if tot > best[top_k - 1, 0]:
                    # insert sorted
                    pos = top_k - 1
                    while pos > 0 and best[pos - 1, 0] < tot:
                        best[pos, :] = best[pos - 1, :]
                        pos -= 1
                    best[pos, 0] = tot
                    best[pos, 1] = cx + dx * res
                    best[pos, 2] = cy + dy * res
                    best[pos, 3] = th
    return best


@dataclass(frozen=True)
class SearchResult:
    """Best pose of a correlative search and its mean per-point score in [0, 1]."""

    pose_xytheta: FloatArray
    score: float


def correlative_search(
    grid: PointGrid,
    points_xy: FloatArray,
    center_xytheta: FloatArray,
    window_xy_m: float,
    window_theta_rad: float,
    theta_step_rad: float | None = None,
    coarse_factor: int = 4,
    coarse_theta_step_rad: float | None = None,
    coarse_candidates: int = 8,
) -> SearchResult:
    """The pose within ``center +- window`` that maximises the mean score of the transformed points.

    Translations are searched on the grid's cells and rotations at ``theta_step_rad`` (default: the step
    that moves the farthest point by about one cell). Windows wider than ``coarse_factor`` cells are
    searched coarse-to-fine: a max-pooled grid (an upper bound of the fine score for translations within
    half a coarse step) scores translations ``coarse_factor`` cells and rotations ``coarse_theta_step_rad``
    apart, and the ``coarse_candidates`` best are searched at full resolution around them.
    """
    pts = np.ascontiguousarray(points_xy, dtype=np.float64)
    n = max(pts.shape[0], 1)
    res = grid.resolution_m
    if theta_step_rad is None:
        r_max = float(np.max(np.hypot(pts[:, 0], pts[:, 1]))) if pts.shape[0] else 1.0
        theta_step_rad = float(np.clip(res / max(r_max, 1e-3), math.radians(0.05), math.radians(1.0)))
    n_lin = math.ceil(window_xy_m / res)
    n_ang = math.ceil(window_theta_rad / theta_step_rad)
    c = np.asarray(center_xytheta, dtype=np.float64)
    ox, oy = float(grid.origin_xy_m[0]), float(grid.origin_xy_m[1])
    f = int(coarse_factor)
    if f <= 1 or n_lin <= f:
        best = _csm(grid.score, ox, oy, res, pts, c[0], c[1], c[2], n_lin, 1, n_ang, theta_step_rad, 1)
        return SearchResult(best[0, 1:].copy(), float(best[0, 0]) / n)
    coarse = grid.coarse_score(f)
    n_lin_c = math.ceil(n_lin / f)
    ang_c = (
        theta_step_rad * f if coarse_theta_step_rad is None else max(coarse_theta_step_rad, theta_step_rad)
    )
    n_ang_c = math.ceil(window_theta_rad / ang_c)
    cand = _csm(coarse, ox, oy, res, pts, c[0], c[1], c[2], n_lin_c, f, n_ang_c, ang_c, coarse_candidates)
    best_pose = c.copy()
    best_score = -1.0
    half = math.ceil(f / 2)
    n_ang_f = math.ceil(0.5 * ang_c / theta_step_rad)
    for row in cand:
        if row[0] < 0 or row[0] <= best_score:
            continue
        fine = _csm(grid.score, ox, oy, res, pts, row[1], row[2], row[3], half, 1, n_ang_f, theta_step_rad, 1)
        if fine[0, 0] > best_score:
            best_score = float(fine[0, 0])
            best_pose = fine[0, 1:].copy()
    return SearchResult(best_pose, best_score / n)


# ---------------------------------------------------------------------------------------------------------
# Branch-and-bound correlative search


@nb.njit(cache=True)
def _max_pool(score: NDArray[np.float32], r0: int, c0: int, pool: int, h: int, w: int) -> NDArray[np.float32]:
    """(h, w) maxima of the ``pool`` x ``pool`` blocks of ``score`` from cell ``(r0, c0)`` on: ``out[y, x]``
    is the largest of the cells ``[r0 + y pool, r0 + (y + 1) pool) x [c0 + x pool, ...)``, 0 counting for
    cells outside the grid (scores are >= 0)."""
    gh, gw = score.shape
    out = np.zeros((h, w), dtype=np.float32)
    for y in range(h):
        for i in range(pool):
            gy = r0 + y * pool + i
            if gy < 0 or gy >= gh:
                continue
            for x in range(w):
                m = out[y, x]
                for j in range(pool):
                    gx = c0 + x * pool + j
                    if 0 <= gx < gw and score[gy, gx] > m:
                        m = score[gy, gx]
                out[y, x] = m
    return out


# The pyramid's kernels only copy and take maxima of finite scores >= 0 (no -0.0): fastmath lets them
# vectorise without changing a value.
@nb.njit(cache=True, fastmath=True, inline="always")
def _max4_rows(
    a0: NDArray[np.float32],
    a1: NDArray[np.float32],
    b0: NDArray[np.float32],
    b1: NDArray[np.float32],
    out: NDArray[np.float32],
) -> None:
    """``out[x] = max(a0[x], a1[x], b0[x], b1[x])`` over ``out``'s length (rows of equal length)."""
    for x in range(out.shape[0]):
        out[x] = max(max(a0[x], a1[x]), max(b0[x], b1[x]))


@nb.njit(cache=True, fastmath=True, inline="always")
def _max2_rows(a0: NDArray[np.float32], a1: NDArray[np.float32], out: NDArray[np.float32]) -> None:
    """``out[x] = max(a0[x], a1[x])`` over ``out``'s length."""
    for x in range(out.shape[0]):
        out[x] = max(a0[x], a1[x])


@nb.njit(cache=True)
def _column_spans(
    tiles: NDArray[np.bool_],
    lo: int,
    hi: int,
    tile: int,
    ext: int,
    w: int,
    span_s: NDArray[np.int64],
    span_e: NDArray[np.int64],
) -> int:
    """The column spans of the runs of tile columns marked in any of the tile rows ``lo..hi`` of
    ``tiles``, each extended by ``ext`` columns and clipped to ``w``: written to ``span_s`` / ``span_e``
    (starts, ends); returns how many."""
    n = 0
    tx = 0
    n_tx = tiles.shape[1]
    while tx < n_tx:
        if not tiles[lo : hi + 1, tx].any():
            tx += 1
            continue
        first = tx
        while tx < n_tx and tiles[lo : hi + 1, tx].any():
            tx += 1
        span_s[n] = first * tile
        span_e[n] = min(tx * tile + ext, w)
        n += 1
    return n


@nb.njit(cache=True, fastmath=True)
def _score_pyramid(
    score: NDArray[np.float32],
    r0: int,
    c0: int,
    h: int,
    w: int,
    depth: int,
    nz_r0: int,
    nz_r1: int,
    nz_c0: int,
    nz_c1: int,
    buffer: NDArray[np.float32],
    tiles: NDArray[np.bool_],
    tile: int,
):
    """(depth + 1, h, w) max-pooled scores of the window ``score[r0:r0+h, c0:c0+w]``, reading only the cells
    ``[nz_r0, nz_r1) x [nz_c0, nz_c1)`` of ``score`` (the rest of it, and cells outside the grid, count as
    0): level ``d`` holds at ``(y, x)`` the largest score of the cells ``[y, y + 2^d) x [x, x + 2^d)``.
    Scores are >= 0, so a pool reaching past the window takes the max of the cells inside it.

    Only the cells of the ``tile`` x ``tile`` tiles marked in ``tiles`` (ceil(h / tile), ceil(w / tile))
    are computed on every level; the others are left as they were (a single search reads no other cell,
    :func:`_reached_tiles`). A level-``d`` cell needs level ``d - 1`` up to ``2^(d-1)`` rows and columns
    beyond it, so level ``d`` is computed ``2^depth - 2^d`` rows and columns beyond the marked tiles (towards
    higher indices). The result is a view of the flat ``buffer`` when it is large enough, else a new
    array."""
    gh, gw = score.shape
    size = (depth + 1) * h * w
    if buffer.shape[0] >= size:
        out = buffer[:size].reshape((depth + 1, h, w))
    else:
        out = np.empty((depth + 1, h, w), dtype=np.float32)
    ya = max(nz_r0, 0)
    yb = min(nz_r1, gh)
    xa = max(max(nz_c0, 0) - c0, 0)
    xb = min(min(nz_c1, gw) - c0, w)
    n_ty, n_tx = tiles.shape
    # per level, the column spans [s, e) of the current band of tile rows (they change only where a row
    # enters or leaves a tile row's extent, so they are found again only there)
    span_s = np.empty((depth + 1, n_tx), dtype=np.int64)
    span_e = np.empty((depth + 1, n_tx), dtype=np.int64)
    n_spans = np.zeros(depth + 1, dtype=np.int64)
    band = np.full((depth + 1, 2), -1, dtype=np.int64)
    # one pass from the top row down, every level of a row at once: level d of row y needs level d - 1 of
    # rows y and y + 2^(d-1), both done, and still in cache
    for y in range(h - 1, -1, -1):
        gy = r0 + y
        for d in range(depth + 1):
            # level d of row y: the tile rows it lies in or extends (by ext rows and columns)
            ext = (1 << depth) - (1 << d)
            lo, hi = max((y - ext) // tile, 0), min(y // tile, n_ty - 1)
            if band[d, 0] != lo or band[d, 1] != hi:
                band[d, 0], band[d, 1] = lo, hi
                n_spans[d] = _column_spans(tiles, lo, hi, tile, ext, w, span_s[d], span_e[d])
            half = (1 << (d - 1)) if d > 0 else 0
            for k in range(n_spans[d]):
                s = span_s[d, k]
                e = span_e[d, k]
                row = out[d, y]
                if d == 0:
                    if gy < ya or gy >= yb or xa >= xb:
                        row[s:e] = 0.0
                    else:
                        a = min(max(xa, s), e)
                        b = max(min(xb, e), a)
                        row[s:a] = 0.0
                        row[a:b] = score[gy, c0 + a : c0 + b]
                        row[b:e] = 0.0
                    continue
                p0 = out[d - 1, y]
                m = min(max(w - half, s), e)  # x + half inside the window below m
                if y + half < h:
                    p1 = out[d - 1, y + half]
                    _max4_rows(p0[s:m], p0[s + half : m + half], p1[s:m], p1[s + half : m + half], row[s:m])
                    _max2_rows(p0[m:e], p1[m:e], row[m:e])
                else:
                    _max2_rows(p0[s:m], p0[s + half : m + half], row[s:m])
                    row[m:e] = p0[m:e]
    return out


#: Side in cells of the tiles in which a single search builds its pyramid (:func:`_reached_tiles`).
PYRAMID_TILE_CELLS = 32

#: Searches over a wider heading window build their whole pyramid: each point's arc then crosses most of
#: the tiles (a sparse log without wheels, searched over every heading), so marking them would cost more
#: than it saves.
LAZY_MAX_WINDOW_RAD = 1.0


@nb.njit(cache=True)
def _rotated_cells(
    points: FloatArray,
    cx: float,
    cy: float,
    ctheta: float,
    n_ang: int,
    ang_step: float,
    x0: float,
    y0: float,
    res: float,
    row0: int,
    col0: int,
):
    """``(ixs, iys)`` (2 n_ang + 1, P) int64: the cell of each point at zero translation offset, rotated by
    ``ctheta + a * ang_step`` for ``a = -n_ang .. n_ang``, in the pyramid part stored from cell ``(row0,
    col0)`` of the window whose lower-left cell is at ``(x0, y0)``."""
    n_rot = 2 * n_ang + 1
    p = points.shape[0]
    ixs = np.empty((n_rot, p), dtype=np.int64)
    iys = np.empty((n_rot, p), dtype=np.int64)
    for a in range(n_rot):
        th = ctheta + (a - n_ang) * ang_step
        c = math.cos(th)
        s = math.sin(th)
        for k in range(p):
            qx = c * points[k, 0] - s * points[k, 1] + cx
            qy = s * points[k, 0] + c * points[k, 1] + cy
            # the cell in the window (the arithmetic of a whole-window pyramid, so the same cell), then its
            # index in the stored part; a point outside that part scores 0, so skipping it changes no sum
            ixs[a, k] = math.floor((qx - x0) / res) - col0
            iys[a, k] = math.floor((qy - y0) / res) - row0
    return ixs, iys


@nb.njit(cache=True)
def _reached_tiles(
    ixs: NDArray[np.int64], iys: NDArray[np.int64], n_lin: int, h: int, w: int, tile: int
) -> NDArray[np.bool_]:
    """(ceil(h / tile), ceil(w / tile)) the ``tile`` x ``tile`` tiles of an (h, w) pyramid part that
    :func:`_bnb` reads on some level: those within ``+-n_lin`` cells of a rotated point's cell
    (:func:`_rotated_cells`), every node's offsets lying in that window."""
    n_ty = (h + tile - 1) // tile
    n_tx = (w + tile - 1) // tile
    out = np.zeros((max(n_ty, 1), max(n_tx, 1)), dtype=np.bool_)
    for a in range(ixs.shape[0]):
        for k in range(ixs.shape[1]):
            ya = max(iys[a, k] - n_lin, 0)
            yb = min(iys[a, k] + n_lin, h - 1)
            xa = max(ixs[a, k] - n_lin, 0)
            xb = min(ixs[a, k] + n_lin, w - 1)
            if ya > yb or xa > xb:
                continue
            for ty in range(ya // tile, yb // tile + 1):
                for tx in range(xa // tile, xb // tile + 1):
                    out[ty, tx] = True
    return out


@nb.njit(cache=True)
def _bnb(
    pyramid: NDArray[np.float32],
    ixs: NDArray[np.int64],
    iys: NDArray[np.int64],
    res: float,
    cx: float,
    cy: float,
    ctheta: float,
    n_lin: int,
    n_ang: int,
    ang_step: float,
    min_total: float,
    cost_lin: float,
    cost_ang: float,
):
    """Exact maximum of the summed score minus the motion cost ``cost_lin * (dx^2 + dy^2) + cost_ang *
    dtheta^2`` (offsets in cells and rad) over the translations ``+-n_lin`` cells and rotations
    ``ctheta + a * ang_step``, ``|a| <= n_ang``, by branch and bound (Hess et al., ICRA 2016, section V.C; a
    node's bound subtracts the least cost over its offsets). ``pyramid`` is :func:`_score_pyramid` of a
    part of the window, ``ixs``, ``iys`` the points' cells in that part at each rotation
    (:func:`_rotated_cells` about the centre ``(cx, cy, ctheta)``; the window's cells outside the part score
    0). Returns ``(found, objective, x, y, theta, nodes, score)``; ``found`` is False when no objective
    exceeds ``min_total``."""
    depth = pyramid.shape[0] - 1
    h = pyramid.shape[1]
    w = pyramid.shape[2]
    p = ixs.shape[1]
    n_rot = 2 * n_ang + 1
    # roots: every rotation x the top-level translation cells covering the window
    step = 1 << depth
    n_top = (2 * n_lin + 1 + step - 1) // step
    roots = n_rot * n_top * n_top
    r_a = np.empty(roots, dtype=np.int64)
    r_x = np.empty(roots, dtype=np.int64)
    r_y = np.empty(roots, dtype=np.int64)
    r_s = np.empty(roots, dtype=np.float64)
    i = 0
    for a in range(n_rot):
        for ty in range(n_top):
            for tx in range(n_top):
                dx = -n_lin + tx * step
                dy = -n_lin + ty * step
                # the least motion cost over the node's offsets (0 where its box holds the centre)
                mx = 0 if dx <= 0 < dx + step else min(abs(dx), abs(dx + step - 1))
                my = 0 if dy <= 0 < dy + step else min(abs(dy), abs(dy + step - 1))
                tot = -cost_lin * (mx * mx + my * my) - cost_ang * ((a - n_ang) * ang_step) ** 2
                for k in range(p):
                    jx = ixs[a, k] + dx
                    jy = iys[a, k] + dy
                    if 0 <= jx < w and 0 <= jy < h:
                        tot += pyramid[depth, jy, jx]
                r_a[i] = a
                r_x[i] = dx
                r_y[i] = dy
                r_s[i] = tot
                i += 1
    # depth-first stack of nodes (rotation, dx, dy, level) covering the offsets [dx, dx + 2^level) x
    # [dy, dy + 2^level); each expansion adds at most 3 entries, so roots + 3 * depth + 1 suffice
    cap = roots + 4 * (depth + 1)
    stack_a = np.empty(cap, dtype=np.int64)
    stack_x = np.empty(cap, dtype=np.int64)
    stack_y = np.empty(cap, dtype=np.int64)
    stack_l = np.empty(cap, dtype=np.int64)
    stack_s = np.empty(cap, dtype=np.float64)
    top = 0
    order = np.argsort(r_s)
    for j in range(roots):  # ascending, so that the best root is popped first
        o = order[j]
        stack_a[top] = r_a[o]
        stack_x[top] = r_x[o]
        stack_y[top] = r_y[o]
        stack_l[top] = depth
        stack_s[top] = r_s[o]
        top += 1
    best = min_total
    best_a = -1
    best_x = 0
    best_y = 0
    nodes = roots
    cs = np.empty(4)
    cx_ = np.empty(4, dtype=np.int64)
    cy_ = np.empty(4, dtype=np.int64)
    while top > 0:
        top -= 1
        s = stack_s[top]
        if s <= best:
            continue
        a = stack_a[top]
        lvl = stack_l[top]
        dx = stack_x[top]
        dy = stack_y[top]
        if lvl == 0:
            best = s
            best_a = a
            best_x = dx
            best_y = dy
            continue
        half = 1 << (lvl - 1)
        nc = 0
        for q in range(4):
            ndx = dx + (q % 2) * half
            ndy = dy + (q // 2) * half
            if ndx > n_lin or ndy > n_lin:
                continue
            mx = 0 if ndx <= 0 < ndx + half else min(abs(ndx), abs(ndx + half - 1))
            my = 0 if ndy <= 0 < ndy + half else min(abs(ndy), abs(ndy + half - 1))
            tot = -cost_lin * (mx * mx + my * my) - cost_ang * ((a - n_ang) * ang_step) ** 2
            for k in range(p):
                jx = ixs[a, k] + ndx
                jy = iys[a, k] + ndy
                if 0 <= jx < w and 0 <= jy < h:
                    tot += pyramid[lvl - 1, jy, jx]
            nodes += 1
            if tot <= best:
                continue
            cs[nc] = tot
            cx_[nc] = ndx
            cy_[nc] = ndy
            nc += 1
        # push the children worst first, so that the best is explored next
        for _ in range(nc):
            m = 0
            for q in range(1, nc):
                if cs[q] < cs[m]:
                    m = q
            stack_a[top] = a
            stack_x[top] = cx_[m]
            stack_y[top] = cy_[m]
            stack_l[top] = lvl - 1
            stack_s[top] = cs[m]
            top += 1
            cs[m] = np.inf
    if best_a < 0:
        return False, 0.0, cx, cy, ctheta, nodes, 0.0
    dth = (best_a - n_ang) * ang_step
    score = best + cost_lin * (best_x * best_x + best_y * best_y) + cost_ang * dth * dth
    return True, best, cx + best_x * res, cy + best_y * res, ctheta + dth, nodes, score


@dataclass(frozen=True)
class ScorePyramid:
    """Max-pooled copies of a score grid for :func:`branch_and_bound_search`: level ``d`` holds at cell
    ``(y, x)`` of a window the largest score of the cells ``[y, y + 2^d) x [x, x + 2^d)``. ``origin_xy_m`` is
    the lower-left corner of the window's cell (0, 0); the window starts ``2^D`` cells before the part it
    was built for, since a node's pool reaches that far below the cells its leaves use. ``levels``
    (D + 1, h, w) float32 stores only the window's cells from ``offset_rc`` (row, column) on that can score
    above 0 (those near a map point); every other cell of the window scores 0."""

    levels: NDArray[np.float32]
    origin_xy_m: FloatArray
    resolution_m: float
    offset_rc: tuple[int, int] = (0, 0)

    @property
    def depth(self) -> int:
        return self.levels.shape[0] - 1

    @classmethod
    def of_grid(
        cls,
        grid: PointGrid,
        depth: int,
        pool: int = 1,
        bounds_xy_m: FloatArray | None = None,
        buffer: NDArray[np.float32] | None = None,
    ) -> ScorePyramid:
        """The pyramid of ``grid.score`` (max-pooled by ``pool`` cells first: a coarser, cheaper search
        whose optimum the refinement then sharpens), over the grid or the box ``bounds_xy_m``
        ``(xmin, ymin, xmax, ymax)``; cells outside the grid score 0. ``buffer`` (flat float32): memory to
        build the levels in when large enough (a pyramid used once, then discarded: no fresh pages to
        fault in); the pyramid is then valid until the buffer's next use."""
        return _PyramidLayout.of_grid(grid, depth, pool, bounds_xy_m).build(buffer)


@dataclass(frozen=True)
class _PyramidLayout:
    """Where a :class:`ScorePyramid` of a grid lies before it is built: the score array ``src`` it reads
    (the grid's, or its max-pooled copy), the stored part's first cell ``(r0, c0)`` and size ``(h, w)`` in
    ``src``'s cells, the part of ``src`` that can score above 0 ``nz = (r0, r1, c0, c1)``, and the
    pyramid's ``depth``, ``origin_xy_m``, ``resolution_m`` and ``offset_rc``."""

    src: NDArray[np.float32]
    r0: int
    c0: int
    h: int
    w: int
    nz: tuple[int, int, int, int]
    depth: int
    origin_xy_m: FloatArray
    resolution_m: float
    offset_rc: tuple[int, int]

    @classmethod
    def of_grid(
        cls, grid: PointGrid, depth: int, pool: int = 1, bounds_xy_m: FloatArray | None = None
    ) -> _PyramidLayout:
        """The layout of :meth:`ScorePyramid.of_grid` (same arguments)."""
        res = grid.resolution_m
        ox, oy = float(grid.origin_xy_m[0]), float(grid.origin_xy_m[1])
        gh, gw = grid.shape
        if bounds_xy_m is None:
            r0, c0, h, w = 0, 0, gh, gw
        else:
            c0 = math.floor((bounds_xy_m[0] - ox) / res)
            r0 = math.floor((bounds_xy_m[1] - oy) / res)
            w = math.ceil((bounds_xy_m[2] - ox) / res) + 1 - c0
            h = math.ceil((bounds_xy_m[3] - oy) / res) + 1 - r0
        h, w = -(-h // pool) * pool, -(-w // pool) * pool
        pad = 1 << depth
        # only the cells the grid ever wrote can score above 0: those within the box, in pooled cells
        tr0, tr1, tc0, tc1 = (int(v) for v in grid._touched)
        pr0, pr1 = max((tr0 - r0) // pool, 0), min(-(-(tr1 - r0) // pool), h // pool)
        pc0, pc1 = max((tc0 - c0) // pool, 0), min(-(-(tc1 - c0) // pool), w // pool)
        if pool == 1:
            # read the grid in place: window cell (y, x) is grid cell (r0 - pad + y, c0 - pad + x)
            src = grid.score
            wr0, wc0 = r0 - pad, c0 - pad
            nz = (r0 + pr0, r0 + pr1, c0 + pc0, c0 + pc1)
        else:
            # the pooled cells [pr0, pr1) x [pc0, pc1) of the box (zero outside the grid)
            hs, ws = max(pr1 - pr0, 0), max(pc1 - pc0, 0)
            src = _max_pool(grid.score, r0 + pr0 * pool, c0 + pc0 * pool, pool, hs, ws)
            wr0, wc0 = -pad - pr0, -pad - pc0
            nz = (0, hs, 0, ws)
        # the window's part whose pools reach a readable cell: from 2^D - 1 cells before them
        big_h, big_w = h // pool + pad, w // pool + pad
        sr0, sr1 = max(nz[0] - wr0 - (pad - 1), 0), min(nz[1] - wr0, big_h)
        sc0, sc1 = max(nz[2] - wc0 - (pad - 1), 0), min(nz[3] - wc0, big_w)
        if sr1 <= sr0 or sc1 <= sc0:
            sr0 = sr1 = sc0 = sc1 = 0
        cres = res * pool
        origin = np.array([ox + c0 * res - pad * cres, oy + r0 * res - pad * cres])
        return cls(src, wr0 + sr0, wc0 + sc0, sr1 - sr0, sc1 - sc0, nz, depth, origin, cres, (sr0, sc0))

    def build(
        self,
        buffer: NDArray[np.float32] | None = None,
        tiles: NDArray[np.bool_] | None = None,
        tile: int = PYRAMID_TILE_CELLS,
    ) -> ScorePyramid:
        """The pyramid, whole, or only on the ``tile`` x ``tile`` tiles of its stored part marked in
        ``tiles`` (:func:`_reached_tiles`: a pyramid for one search; its other cells hold garbage)."""
        buf = np.empty(0, dtype=np.float32) if buffer is None else buffer
        if tiles is None:
            tiles, tile = np.ones((1, 1), dtype=np.bool_), max(self.h, self.w, 1)
        levels = _score_pyramid(
            self.src, self.r0, self.c0, self.h, self.w, self.depth, *self.nz, buf, tiles, tile
        )
        return ScorePyramid(levels, self.origin_xy_m, self.resolution_m, self.offset_rc)


def bnb_depth(window_xy_m: float, resolution_m: float) -> int:
    """Levels of a pyramid whose top cell covers the translational window (at most 7)."""
    n_lin = max(math.ceil(window_xy_m / resolution_m), 0)
    return max(0, min(7, math.ceil(math.log2(2 * n_lin + 1)) - 1))


def branch_and_bound_search(
    grid: PointGrid | ScorePyramid,
    points_xy: FloatArray,
    center_xytheta: FloatArray,
    window_xy_m: float,
    window_theta_rad: float,
    theta_step_rad: float | None = None,
    min_score: float = 0.0,
    prior_sigma_xy_m: float | None = None,
    prior_sigma_theta_rad: float | None = None,
    prior_weight: float = 0.0,
    pool: int = 1,
) -> SearchResult:
    """The pose within ``center +- window`` maximising the mean score of the transformed points, found
    exactly by branch and bound over max-pooled score grids (Hess et al., "Real-time loop closure in 2D
    LIDAR SLAM", ICRA 2016): the same optimum as :func:`correlative_search` without coarse-to-fine
    shortcuts, at a cost that grows little with the window. ``grid``: a :class:`PointGrid` (its pyramid is
    built for the part the search can reach) or a prebuilt :class:`ScorePyramid` covering that part (a map
    searched many times); translations are searched on its cells. ``min_score`` (mean per point) prunes:
    below it the result's score is 0 and its pose the centre. ``theta_step_rad`` as in
    :func:`correlative_search`. ``pool`` > 1 searches a :class:`PointGrid` at that many times its cells.

    With ``prior_weight > 0`` the objective is the mean score minus ``prior_weight / 2`` times the squared
    Mahalanobis distance of the pose from the centre (sigmas ``prior_sigma_xy_m``,
    ``prior_sigma_theta_rad``): a motion prior, as in Olson's correlative matcher, so that in a wide window
    a far pose wins only when it matches clearly better. The returned score is the mean score alone.
    """
    pts = np.ascontiguousarray(points_xy, dtype=np.float64)
    c = np.asarray(center_xytheta, dtype=np.float64)
    n = pts.shape[0]
    if n == 0:
        return SearchResult(c.copy(), 0.0)
    pool = 1 if isinstance(grid, ScorePyramid) else max(int(pool), 1)
    res = grid.resolution_m * pool
    r_max = float(np.max(np.hypot(pts[:, 0], pts[:, 1])))
    if theta_step_rad is None:
        theta_step_rad = float(np.clip(res / max(r_max, 1e-3), math.radians(0.05), math.radians(1.0)))
    n_lin = max(math.ceil(window_xy_m / res), 0)
    n_ang = max(math.ceil(window_theta_rad / theta_step_rad), 0)
    layout = None
    if isinstance(grid, ScorePyramid):
        pyramid = grid
    else:
        # the part of the grid any transformed point can reach: within r_max of the centre, and within
        # the box of the points at the centre's heading grown by the farthest one's arc over the headings
        # searched (a point at range r moves at most r |dtheta|) and the translation window
        reach = r_max + window_xy_m + 2 * res
        box = np.array([c[0] - reach, c[1] - reach, c[0] + reach, c[1] + reach])
        at_centre = se2.transform_points(c, pts)
        grow = r_max * n_ang * theta_step_rad + window_xy_m + 2 * res
        box[:2] = np.maximum(box[:2], at_centre.min(axis=0) - grow)
        box[2:] = np.minimum(box[2:], at_centre.max(axis=0) + grow)
        # placed here, built below once the points are placed in it
        layout = _PyramidLayout.of_grid(grid, bnb_depth(window_xy_m, res), pool, box)
    cost_lin = cost_ang = 0.0
    if prior_weight > 0 and prior_sigma_xy_m and prior_sigma_theta_rad:
        cost_lin = 0.5 * prior_weight * n * (res / prior_sigma_xy_m) ** 2
        cost_ang = 0.5 * prior_weight * n / prior_sigma_theta_rad**2
    place = pyramid if layout is None else layout  # the pyramid's origin and stored part
    (x0, y0), (row0, col0) = place.origin_xy_m, place.offset_rc
    ixs, iys = _rotated_cells(pts, c[0], c[1], c[2], n_ang, theta_step_rad, x0, y0, res, row0, col0)
    if layout is not None:
        buf = grid._pyramid_buffer
        # marking the reached tiles costs about as much per transformed point as the pyramid per cell: it
        # pays where the points are few against the cells (not so a wide heading search of a dense scan),
        # and where their arcs over the headings leave most tiles out (not so beyond LAZY_MAX_WINDOW_RAD)
        few = ixs.size * 4 < (layout.depth + 1) * layout.h * layout.w
        if few and window_theta_rad < LAZY_MAX_WINDOW_RAD:
            tile = max(PYRAMID_TILE_CELLS, 1 << layout.depth)
            tiles = _reached_tiles(ixs, iys, n_lin, layout.h, layout.w, tile)
            pyramid = layout.build(buf, tiles, tile)
        else:
            pyramid = layout.build(buf)
        if pyramid.levels.size > buf.size:  # built in new memory: the next search reuses it
            grid._pyramid_buffer = pyramid.levels.reshape(-1)
    found, _, x, y, th, _, score = _bnb(
        pyramid.levels,
        ixs,
        iys,
        res,
        c[0],
        c[1],
        c[2],
        n_lin,
        n_ang,
        theta_step_rad,
        min_score * n - 1e-9 if min_score > 0 else -np.inf,
        cost_lin,
        cost_ang,
    )
    if not found:
        return SearchResult(c.copy(), 0.0)
    return SearchResult(np.array([x, y, th]), float(score) / n)


# ---------------------------------------------------------------------------------------------------------
# Point-to-line Gauss-Newton


@nb.njit(cache=True)
def _accumulate(
    nearest: NDArray[np.int32],
    x0: float,
    y0: float,
    res: float,
    map_pts: FloatArray,
    map_nrm: FloatArray,
    points: FloatArray,
    point_nrm: FloatArray,
    pose: FloatArray,
    max_dist: float,
    kernel: float,
):
    h, w = nearest.shape
    use_nrm = point_nrm.shape[0] == points.shape[0]
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    hess = np.zeros((3, 3))
    grad = np.zeros(3)
    n_in = 0
    sum_r2 = 0.0
    sum_w = 0.0
    cost = 0.0
    md2 = max_dist * max_dist
    for k in range(points.shape[0]):
        rx = c * points[k, 0] - s * points[k, 1]
        ry = s * points[k, 0] + c * points[k, 1]
        qx = rx + pose[0]
        qy = ry + pose[1]
        jx = math.floor((qx - x0) / res)
        jy = math.floor((qy - y0) / res)
        if jx < 0 or jy < 0 or jx >= w or jy >= h:
            continue
        m = nearest[jy, jx]
        if m < 0:
            continue
        nx = map_nrm[m, 0]
        ny = map_nrm[m, 1]
        if nx != nx:  # NaN normal
            continue
        if use_nrm:
            # the two faces of a thin wall: the point's normal (facing its sensor) points away from the
            # map normal (facing the sensors that saw the other face)
            px = point_nrm[k, 0]
            py = point_nrm[k, 1]
            if (c * px - s * py) * nx + (s * px + c * py) * ny < 0.0:
                continue
        ex = qx - map_pts[m, 0]
        ey = qy - map_pts[m, 1]
        if ex * ex + ey * ey > md2:
            continue
        r = nx * ex + ny * ey
        # Cauchy weight
        u = r / kernel
        wt = 1.0 / (1.0 + u * u)
        j0 = nx
        j1 = ny
        j2 = nx * (-ry) + ny * rx
        hess[0, 0] += wt * j0 * j0
        hess[0, 1] += wt * j0 * j1
        hess[0, 2] += wt * j0 * j2
        hess[1, 1] += wt * j1 * j1
        hess[1, 2] += wt * j1 * j2
        hess[2, 2] += wt * j2 * j2
        grad[0] += wt * j0 * r
        grad[1] += wt * j1 * r
        grad[2] += wt * j2 * r
        n_in += 1
        sum_r2 += wt * r * r
        sum_w += wt
        cost += 0.5 * kernel * kernel * math.log1p(u * u)
    hess[1, 0] = hess[0, 1]
    hess[2, 0] = hess[0, 2]
    hess[2, 1] = hess[1, 2]
    return hess, grad, n_in, sum_r2, sum_w, cost


@dataclass(frozen=True)
class Alignment:
    """Result of :func:`refine_point_to_line`.

    ``hessian`` (3, 3) is ``sum_i w_i J_i^T J_i`` of the point-to-line residuals at the solution (world
    frame, order x, y, theta; units 1, m, m^2), without the prior; divide by the point noise variance to get
    the information of the scan alone. ``inliers`` counts points with a correspondence, ``rms_m`` is the
    weighted residual RMS.
    """

    pose_xytheta: FloatArray
    hessian: FloatArray
    inliers: int
    rms_m: float
    iterations: int


@nb.njit(cache=True)
def _gauss_newton(
    nearest: NDArray[np.int32],
    x0: float,
    y0: float,
    res: float,
    map_pts: FloatArray,
    map_nrm: FloatArray,
    points: FloatArray,
    point_nrm: FloatArray,
    pose0: FloatArray,
    max_dist: float,
    kernel: float,
    inv_s2: float,
    prior: FloatArray,
    prior_info: FloatArray,
    max_iterations: int,
    tolerance: float,
):
    x = pose0.copy()
    iterations = 0
    for _ in range(max_iterations):
        iterations += 1
        hess, grad, n_in, _, _, _ = _accumulate(
            nearest, x0, y0, res, map_pts, map_nrm, points, point_nrm, x, max_dist, kernel
        )
        a = hess * inv_s2 + prior_info
        e0 = x[0] - prior[0]
        e1 = x[1] - prior[1]
        e2 = x[2] - prior[2]
        e2 = (e2 + np.pi) % (2.0 * np.pi) - np.pi
        b = grad * inv_s2
        for r in range(3):
            b[r] += prior_info[r, 0] * e0 + prior_info[r, 1] * e1 + prior_info[r, 2] * e2
        for r in range(3):
            a[r, r] += 1e-9
        if n_in < 3 and prior_info[0, 0] == 0.0:
            break
        step = -np.linalg.solve(a, b)
        if not (np.isfinite(step[0]) and np.isfinite(step[1]) and np.isfinite(step[2])):
            break
        x += step
        x[2] = (x[2] + np.pi) % (2.0 * np.pi) - np.pi
        if abs(step[0]) + abs(step[1]) < tolerance and abs(step[2]) < tolerance:
            break
    hess, _, n_in, sum_r2, sum_w, _ = _accumulate(
        nearest, x0, y0, res, map_pts, map_nrm, points, point_nrm, x, max_dist, kernel
    )
    rms = math.sqrt(sum_r2 / sum_w) if sum_w > 0 else np.inf
    return x, hess, n_in, rms, iterations


def refine_point_to_line(
    grid: PointGrid,
    points_xy: FloatArray,
    initial_xytheta: FloatArray,
    max_dist_m: float = 0.3,
    kernel_m: float = 0.05,
    point_sigma_m: float = 0.05,
    prior_xytheta: FloatArray | None = None,
    prior_information: FloatArray | None = None,
    max_iterations: int = 30,
    tolerance: float = 1e-6,
    normals_xy: FloatArray | None = None,
) -> Alignment:
    """Robust Gauss-Newton on point-to-line residuals, from ``initial_xytheta``.

    Minimises ``sum_i rho(n_j . (R p_i + t - m_j)) / sigma^2 + (x - x_prior)^T Lambda (x - x_prior)`` with a
    Cauchy ``rho`` of scale ``kernel_m``; ``m_j`` is the map point nearest to the transformed point (within
    ``max_dist_m``) and ``n_j`` its normal. The prior (e.g. the wheel-odometry prediction, ``Lambda`` its
    (3, 3) world-frame information) keeps directions the scan does not constrain (a corridor's axis) where
    the wheels put them. ``normals_xy`` (P, 2), the points' normals facing their sensor (NaN: unknown), makes
    a point skip a map point whose normal faces the other way: the far face of a thin wall seen from the
    other side (a nearest-neighbour match to it drags the scan by the wall's thickness).
    """
    pts = np.ascontiguousarray(points_xy, dtype=np.float64)
    nrm = (
        np.zeros((0, 2))
        if normals_xy is None
        else np.ascontiguousarray(normals_xy, dtype=np.float64).reshape(pts.shape[0], 2)
    )
    x0 = np.asarray(initial_xytheta, dtype=np.float64)
    if prior_xytheta is None or prior_information is None:
        prior = np.zeros(3)
        info = np.zeros((3, 3))
    else:
        prior = np.asarray(prior_xytheta, dtype=np.float64)
        info = np.ascontiguousarray(prior_information, dtype=np.float64)
    x, hess, n_in, rms, it = _gauss_newton(
        grid.nearest,
        float(grid.origin_xy_m[0]),
        float(grid.origin_xy_m[1]),
        grid.resolution_m,
        grid.points_xy,
        grid.normals_xy,
        pts,
        nrm,
        x0,
        float(max_dist_m),
        float(kernel_m),
        1.0 / (point_sigma_m * point_sigma_m),
        prior,
        info,
        int(max_iterations),
        float(tolerance),
    )
    return Alignment(x, hess, int(n_in), float(rms), int(it))


@nb.njit(cache=True)
def _raycast_free(
    free: NDArray[np.bool_],
    x0: float,
    y0: float,
    res: float,
    origins: FloatArray,
    ends: FloatArray,
    stop_short_m: float,
) -> None:
    """Mark the cells crossed by each beam ``origins[i] -> ends[i]`` as free, up to ``stop_short_m`` before
    the end point (sampled every half cell)."""
    h, w = free.shape
    step = 0.5 * res
    for i in range(origins.shape[0]):
        ox = origins[i, 0]
        oy = origins[i, 1]
        dx = ends[i, 0] - ox
        dy = ends[i, 1] - oy
        length = math.sqrt(dx * dx + dy * dy) - stop_short_m
        if length <= 0.0:
            continue
        norm = math.sqrt(dx * dx + dy * dy)
        ux = dx / norm
        uy = dy / norm
        n = int(length / step)
        for k in range(n + 1):
            t = k * step
            jx = math.floor((ox + t * ux - x0) / res)
            jy = math.floor((oy + t * uy - y0) / res)
            if 0 <= jx < w and 0 <= jy < h:
                free[jy, jx] = True


@nb.njit(cache=True)
def _overlap(score, free, x0, y0, res, points, pose, thr):
    """``(hits, conflicts)``: points at ``pose`` on a map point (score >= thr), and, when ``free`` has the
    grid's shape, points elsewhere in cells the map's beams saw free."""
    h, w = score.shape
    check_free = free.shape[0] == h and free.shape[1] == w
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    hits = 0
    conflicts = 0
    for k in range(points.shape[0]):
        qx = c * points[k, 0] - s * points[k, 1] + pose[0]
        qy = s * points[k, 0] + c * points[k, 1] + pose[1]
        jx = math.floor((qx - x0) / res)
        jy = math.floor((qy - y0) / res)
        if 0 <= jx < w and 0 <= jy < h:
            if score[jy, jx] >= thr:
                hits += 1
            elif check_free and free[jy, jx]:
                conflicts += 1
    return hits, conflicts


def mark_free_space(
    grid: PointGrid, origins_xy: FloatArray, ends_xy: FloatArray, stop_short_m: float
) -> None:
    """Record the free space seen by beams ``origins -> ends`` (P, 2) in ``grid.free`` (created if absent)."""
    if grid.free is None:
        grid.free = np.zeros(grid.shape, dtype=np.bool_)
    _raycast_free(
        grid.free,
        float(grid.origin_xy_m[0]),
        float(grid.origin_xy_m[1]),
        grid.resolution_m,
        np.ascontiguousarray(origins_xy, dtype=np.float64),
        np.ascontiguousarray(ends_xy, dtype=np.float64),
        float(stop_short_m),
    )


def overlap(
    grid: PointGrid, points_xy: FloatArray, pose_xytheta: FloatArray, inlier_m: float = 0.1
) -> tuple[int, int]:
    """``(hits, conflicts)`` of points at a pose: near a map point (within ``inlier_m``), or in space the
    map's beams saw free (requires :func:`mark_free_space`). Points elsewhere are unknown to the map."""
    if grid.free is None:
        raise ValueError("overlap() needs the grid's free space (mark_free_space)")
    pts = np.ascontiguousarray(points_xy, dtype=np.float64)
    thr = math.exp(-(inlier_m**2) / (2.0 * grid.sigma_m**2))
    hits, conflicts = _overlap(
        grid.score,
        grid.free,
        float(grid.origin_xy_m[0]),
        float(grid.origin_xy_m[1]),
        grid.resolution_m,
        pts,
        np.asarray(pose_xytheta, dtype=np.float64),
        thr,
    )
    return int(hits), int(conflicts)


def fitness(grid: PointGrid, points_xy: FloatArray, pose_xytheta: FloatArray, inlier_m: float = 0.1) -> float:
    """Fraction of points whose nearest map point is within ``inlier_m`` (cell-centre distance)."""
    pts = np.ascontiguousarray(points_xy, dtype=np.float64)
    if pts.shape[0] == 0:
        return 0.0
    thr = math.exp(-(inlier_m**2) / (2.0 * grid.sigma_m**2))
    n_ok, _ = _overlap(
        grid.score,
        np.zeros((0, 0), dtype=np.bool_),
        float(grid.origin_xy_m[0]),
        float(grid.origin_xy_m[1]),
        grid.resolution_m,
        pts,
        np.asarray(pose_xytheta, dtype=np.float64),
        thr,
    )
    return n_ok / pts.shape[0]
