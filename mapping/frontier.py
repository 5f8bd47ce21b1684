"""Frontiers and the expected information of a scan: where a robot should look next on a GP occupancy map.

Every cell of a rendered map (:class:`mapping.exports.MapLayers`, raster convention of that module) is

- *unknown* when its latent GP variance (eq. 3) exceeds ``unknown_variance_fraction`` of the prior variance
  ``k(x*, x*)`` -- what the map answers where no data reach (NaN variances count as unknown too). The map
  solves every query in query-centred coordinates (:mod:`mapping.core`), so the prior is ``kernel.diag`` at
  the origin for every cell, also for the non-stationary NN kernel (eq. 7);
- *free* when it is known and ``p(occ) <= free_threshold``; *occupied* when ``p(occ) >= occupied_threshold``
  (occupied cells stop the rays of a simulated scan whatever their variance: the map predicts a surface).

A *frontier* cell is a free cell with an unknown 4- or 8-neighbour; cells beyond the raster count as unknown
(``outside_unknown``), since the rendered map says nothing there. Frontier cells are grouped into connected
clusters (``scipy.ndimage.label``, 8-connected), and long clusters are cut into blocks of
``anchor_spacing_m`` so that a 100 m frontier offers more than one place to stand.

Expected information of a scan (:func:`expected_variance_reduction`). A laser at pose (x, y, theta) casts
``n_beams`` rays over its field of view up to ``range_max_m`` through the classified map (the cell walk of
:mod:`mapping.raster`); a ray sees every cell it enters and stops in the first occupied one (unknown cells
are assumed see-through: optimistic exploration). Seeing a cell is modelled as one new training point at the
cell's centre with the map's noise variance ``sigma_n^2``. Eqs. (2)-(3) with one training point at the
query, applied to the current posterior (variance ``v`` there), give the posterior variance

    v' = v - v^2 / (v + sigma_n^2) = v sigma_n^2 / (v + sigma_n^2),

so the cell's variance falls by ``v^2 / (v + sigma_n^2)``: nearly all of it in unknown cells
(``v >> sigma_n^2``), almost nothing in cells already mapped (``v << sigma_n^2``). The scan's expected
variance reduction is the sum over the cells it sees, each counted once. The update is exact for one cell
seen alone; the sum ignores the correlation between neighbouring cells (one cell's observation also lowers
its neighbours' variance, and several cells share information, which the sum counts twice) and a beam's
several free points in one cell. It needs no neighbour search and no matrix solve, only the rendered layers.

Next-best views (:func:`plan_exploration`). Each anchor (the frontier cell nearest a cluster block's
centroid) is pushed ``step_m`` back into free space, away from the centroid of the unknown cells around it,
keeping ``clearance_m`` from occupied cells (a shorter step when the full one fails). Each such position is
scored at ``n_headings`` headings, the first facing the unknown. The K views are chosen greedily: the best
candidate, then the map's variance is updated as if its scan had been taken (v -> v' on the cells it sees),
the candidates are scored again, and so on, so that the second view is not the first one again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from mapping.exports import UNKNOWN_VARIANCE_FRACTION, Classification, MapLayers
from mapping.raster import GridGeometry, in_grid, segment_walk, squared_distances_cells, walk_next
from mapping.train import GPParams

if TYPE_CHECKING:
    from mapping.config import MappingConfig

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class LaserModel:
    """The scanner of a candidate view: ``n_beams`` rays evenly over ``fov_rad`` centred on the heading
    (a full circle when ``fov_rad >= 2 pi``), each up to ``range_max_m``."""

    range_max_m: float = 10.0
    fov_rad: float = math.pi
    n_beams: int = 181

    def __post_init__(self) -> None:
        if not (self.range_max_m > 0 and self.fov_rad > 0 and self.n_beams >= 1):
            raise ValueError(f"bad laser model {self}")

    def beam_offsets_rad(self) -> FloatArray:
        """(n_beams,) beam directions relative to the heading, rad."""
        if self.fov_rad >= 2.0 * math.pi - 1e-9:
            return -math.pi + 2.0 * math.pi * np.arange(self.n_beams) / self.n_beams
        if self.n_beams == 1:
            return np.zeros(1)
        return np.linspace(-0.5 * self.fov_rad, 0.5 * self.fov_rad, self.n_beams)


@dataclass(frozen=True)
class ExplorationSettings:
    """Thresholds and planner knobs (module docstring). ``free_threshold`` / ``occupied_threshold`` are the
    mapping configuration's; ``unknown_variance_fraction`` is the export configuration's."""

    free_threshold: float = 0.35
    occupied_threshold: float = 0.65
    unknown_variance_fraction: float = UNKNOWN_VARIANCE_FRACTION
    connectivity: int = 8
    outside_unknown: bool = True
    min_cluster_cells: int = 3
    anchor_spacing_m: float = 5.0
    step_m: float = 1.0
    clearance_m: float = 0.3
    n_headings: int = 8
    n_views: int = 5
    laser: LaserModel = field(default_factory=LaserModel)

    def __post_init__(self) -> None:
        if not 0 < self.free_threshold < self.occupied_threshold < 1:
            raise ValueError(
                f"need 0 < free ({self.free_threshold}) < occupied ({self.occupied_threshold}) < 1"
            )
        if not 0 < self.unknown_variance_fraction <= 1:
            raise ValueError(
                f"unknown_variance_fraction must be in (0, 1], got {self.unknown_variance_fraction}"
            )
        if self.connectivity not in (4, 8):
            raise ValueError(f"connectivity must be 4 or 8, got {self.connectivity}")
        if self.n_headings < 1 or self.n_views < 0 or self.step_m < 0 or self.clearance_m < 0:
            raise ValueError(f"bad exploration settings {self}")

    @classmethod
    def from_config(
        cls,
        mapping: MappingConfig,
        unknown_variance_fraction: float = UNKNOWN_VARIANCE_FRACTION,
        **knobs: Any,
    ) -> ExplorationSettings:
        """The thresholds of a :class:`~mapping.config.MappingConfig`, the export configuration's
        ``unknown_variance_fraction`` and any other field by keyword."""
        return cls(
            free_threshold=mapping.free_threshold,
            occupied_threshold=mapping.occupied_threshold,
            unknown_variance_fraction=unknown_variance_fraction,
            **knobs,
        )


@dataclass(frozen=True)
class Knowledge:
    """(H, W) masks of a map: free, occupied and unknown cells (free and unknown are disjoint), and the
    prior variance ``k(x*, x*)`` they were judged against."""

    free: BoolArray
    occupied: BoolArray
    unknown: BoolArray
    prior_variance: float


@dataclass(frozen=True)
class FrontierClusters:
    """Connected frontier clusters: ``labels`` (H, W) int32 (0: not frontier, 1..C: cluster), per cluster
    ``sizes_cells`` (C,) and ``centroids_xy_m`` (C, 2) in the map frame."""

    labels: NDArray[np.int32]
    sizes_cells: NDArray[np.int64]
    centroids_xy_m: FloatArray

    def __len__(self) -> int:
        return int(self.sizes_cells.shape[0])


@dataclass(frozen=True)
class ExplorationPlan:
    """What :func:`plan_exploration` found on one map.

    - ``knowledge``, ``frontier`` (H, W) bool, ``clusters``;
    - ``candidates_xytheta`` (N, 3) map-frame poses (m, m, rad) and ``candidate_gains`` (N,) their expected
      variance reduction on the map as it is;
    - ``views_xytheta`` (K, 3) the next-best views in the order chosen, ``view_gains`` (K,) the reduction
      each adds after the views before it;
    - ``information`` (H, W) float32 the expected variance reduction per cell of the K scans together (sums
      to the total of ``view_gains``)."""

    knowledge: Knowledge
    frontier: BoolArray
    clusters: FrontierClusters
    candidates_xytheta: FloatArray
    candidate_gains: FloatArray
    views_xytheta: FloatArray
    view_gains: FloatArray
    information: NDArray[np.float32]

    def layers(self) -> dict[str, NDArray[np.float32]]:
        """GridMap layers: ``frontier`` (1.0 on frontier cells, else 0.0) and ``information``, float32."""
        return {
            "frontier": self.frontier.astype(np.float32),
            "information": np.asarray(self.information, dtype=np.float32),  # no copy: already float32
        }


def classify_knowledge(
    layers: MapLayers,
    params: GPParams,
    free_threshold: float = 0.35,
    occupied_threshold: float = 0.65,
    unknown_variance_fraction: float = UNKNOWN_VARIANCE_FRACTION,
) -> Knowledge:
    """Free / occupied / unknown (H, W) masks of ``layers`` (module docstring)."""
    prior = params.prior_variance
    rule = Classification(
        np.full(layers.shape, prior, np.float32),
        unknown_variance_fraction,
        occupied_threshold,
        free_threshold,
    )
    unknown = rule.unknown(layers.variance)  # as every export calls a cell unknown (NaN included)
    prob = np.asarray(layers.probability)
    # float64 thresholds: the comparison runs in float64 (cast chunk by chunk, no float64 copy of the map)
    with np.errstate(invalid="ignore"):
        free = np.less_equal(prob, np.float64(free_threshold)) & ~unknown
        occupied = np.greater_equal(prob, np.float64(occupied_threshold))
    return Knowledge(free, occupied, unknown, prior)


def frontier_mask(
    free: BoolArray, unknown: BoolArray, connectivity: int = 8, outside_unknown: bool = True
) -> BoolArray:
    """(H, W) free cells with an unknown neighbour (4- or 8-connected); beyond the raster is unknown when
    ``outside_unknown``."""
    structure = ndimage.generate_binary_structure(2, 1 if connectivity == 4 else 2)
    padded = np.pad(np.asarray(unknown, bool), 1, constant_values=outside_unknown)
    near_unknown = ndimage.binary_dilation(padded, structure=structure)[1:-1, 1:-1]
    return np.asarray(free, bool) & near_unknown


def cell_centres_xy_m(rows: NDArray, cols: NDArray, layers: MapLayers) -> FloatArray:
    """(N, 2) map-frame centres of cells (rows (N,), cols (N,))."""
    x0, y0 = layers.origin_xy_m
    r = layers.resolution_m
    return np.stack([x0 + (np.asarray(cols) + 0.5) * r, y0 + (np.asarray(rows) + 0.5) * r], axis=1)


def cluster_frontier(frontier: BoolArray, layers: MapLayers, min_cells: int = 1) -> FrontierClusters:
    """8-connected clusters of the (H, W) ``frontier`` with at least ``min_cells`` cells, numbered 1..C by
    decreasing size."""
    labels, n = ndimage.label(frontier, structure=np.ones((3, 3), bool))
    if n == 0:
        return FrontierClusters(np.zeros(frontier.shape, np.int32), np.zeros(0, np.int64), np.zeros((0, 2)))
    rows, cols = np.nonzero(labels)
    lab = labels[rows, cols]
    sizes = np.bincount(lab, minlength=n + 1)
    keep = np.nonzero(sizes >= min_cells)[0]
    keep = keep[keep > 0]
    keep = keep[np.argsort(-sizes[keep], kind="stable")]
    relabel = np.zeros(n + 1, np.int32)
    relabel[keep] = np.arange(1, keep.size + 1, dtype=np.int32)
    out = relabel[labels]
    xy = cell_centres_xy_m(rows, cols, layers)
    sx = np.bincount(lab, weights=xy[:, 0], minlength=n + 1)
    sy = np.bincount(lab, weights=xy[:, 1], minlength=n + 1)
    sz = sizes[keep].astype(np.float64)
    centroids = np.stack([sx[keep] / sz, sy[keep] / sz], axis=1)
    return FrontierClusters(out.astype(np.int32), sizes[keep].astype(np.int64), centroids.reshape(-1, 2))


def frontier_anchors(
    clusters: FrontierClusters, layers: MapLayers, spacing_m: float | None
) -> NDArray[np.int64]:
    """(A, 2) (row, col) frontier cells to plan from: per cluster, cut into square blocks of ``spacing_m``
    (None: whole clusters), the member cell nearest the block's centroid."""
    rows, cols = np.nonzero(clusters.labels)
    if rows.size == 0:
        return np.zeros((0, 2), np.int64)
    lab = clusters.labels[rows, cols].astype(np.int64)
    if spacing_m is None or spacing_m <= 0:
        block = np.zeros_like(lab)
    else:
        b = max(1, round(spacing_m / layers.resolution_m))
        block = (rows // b) * (cols.max() // b + 1) + cols // b
    _, group = np.unique(lab * (block.max() + 1) + block, return_inverse=True)
    count = np.bincount(group).astype(np.float64)
    mr = np.bincount(group, weights=rows) / count
    mc = np.bincount(group, weights=cols) / count
    d2 = (rows - mr[group]) ** 2 + (cols - mc[group]) ** 2
    order = np.lexsort((d2, group))
    first = order[np.r_[True, group[order][1:] != group[order][:-1]]]
    return np.stack([rows[first], cols[first]], axis=1).astype(np.int64)


def candidate_poses(
    anchors_rc: NDArray[np.int64], knowledge: Knowledge, layers: MapLayers, settings: ExplorationSettings
) -> FloatArray:
    """(N, 3) candidate views: each anchor cell pushed back into free space (module docstring), at
    ``settings.n_headings`` headings, the first facing the unknown (rad, map frame). Anchors with no free
    cell of enough clearance along the push are dropped."""
    res = layers.resolution_m
    h, w = knowledge.free.shape
    if knowledge.occupied.any():
        ok = knowledge.free & (
            squared_distances_cells(knowledge.occupied) >= _min_squared_cells(res, settings.clearance_m)
        )
    else:
        ok = knowledge.free
    r_cells = max(1, round(max(settings.step_m, 2 * res) / res))
    unknown = np.pad(knowledge.unknown, r_cells, constant_values=settings.outside_unknown)
    dr, dc = np.mgrid[-r_cells : r_cells + 1, -r_cells : r_cells + 1]
    disc = dr**2 + dc**2 <= r_cells**2
    heading_steps = 2.0 * math.pi * np.arange(settings.n_headings) / settings.n_headings
    fractions = (1.0, 0.75, 0.5, 0.25, 0.0)
    out = []
    for r, c in anchors_rc:
        win = unknown[r : r + 2 * r_cells + 1, c : c + 2 * r_cells + 1] & disc
        if win.any():
            away = -np.array([dc[win].mean(), dr[win].mean()])  # (x, y) from the unknown to the anchor
        else:
            away = np.zeros(2)
        norm = float(np.hypot(*away))
        away = away / norm if norm > 1e-9 else np.zeros(2)
        base = cell_centres_xy_m(np.array([r]), np.array([c]), layers)[0]
        for f in fractions:
            xy = base + f * settings.step_m * away
            cc = math.floor((xy[0] - layers.origin_xy_m[0]) / res)
            rr = math.floor((xy[1] - layers.origin_xy_m[1]) / res)
            if 0 <= rr < h and 0 <= cc < w and ok[rr, cc]:
                facing = math.atan2(-away[1], -away[0]) if norm > 1e-9 else 0.0
                for dh in heading_steps:
                    out.append((xy[0], xy[1], math.atan2(math.sin(facing + dh), math.cos(facing + dh))))
                break
    return np.asarray(out, dtype=np.float64).reshape(-1, 3)


def _min_squared_cells(resolution_m: float, clearance_m: float) -> int:
    """The least squared distance ``k`` in cell widths (an integer, as distance transforms give them) with
    ``sqrt(k) * resolution_m >= clearance_m``, in the float arithmetic of that expression."""
    k = max(0, math.floor((clearance_m / resolution_m) ** 2) - 2)
    while math.sqrt(k) * resolution_m < clearance_m:
        k += 1
    return k


@nb.njit(cache=True)
def _cell_gain(v, noise_var):
    """:func:`variance_reduction_per_cell` of one cell, in the same float64 operations."""
    return v * v / (v + noise_var)


@nb.njit(cache=True)
def _cast_scans(poses, offsets, range_max, grid, blocking, variance, noise_var, seen_by, first_tag):
    """Per pose (N, 3): the sum of :func:`variance_reduction_per_cell` of ``variance`` (ny, nx, float64)
    over the cells its rays see (each once), rays stopping in ``blocking`` cells or at the grid's edge.
    ``seen_by`` (ny, nx), int32 or int64, is scratch: pose ``i`` marks the cells it sees with ``first_tag + i
    + 1``, so one scratch serves many calls as long as their tags differ."""
    n = poses.shape[0]
    gains = np.zeros(n)
    for i in range(n):
        tag = first_tag + i + 1
        x = poses[i, 0]
        y = poses[i, 1]
        g = 0.0
        for b in range(offsets.shape[0]):
            a = poses[i, 2] + offsets[b]
            w, _ex, _ey, steps = segment_walk(
                grid, x, y, x + range_max * math.cos(a), y + range_max * math.sin(a), False
            )
            for s in range(steps + 1):
                if not in_grid(grid, w.ix, w.iy):
                    break
                if seen_by[w.iy, w.ix] != tag:
                    seen_by[w.iy, w.ix] = tag
                    g += _cell_gain(variance[w.iy, w.ix], noise_var)
                if blocking[w.iy, w.ix]:
                    break
                if s < steps:
                    w = walk_next(w)
        gains[i] = g
    return gains


@nb.njit(cache=True)
def _seen_cells(pose, offsets, range_max, grid, blocking, seen_by, tag):
    """The flat indices (row-major, ``iy * nx + ix``) of the cells one (3,) pose's rays see, each once, in
    the order they are first seen; ``seen_by`` scratch as in :func:`_cast_scans`, marked with ``tag``."""
    out = np.empty(1024, np.int64)
    count = 0
    for b in range(offsets.shape[0]):
        a = pose[2] + offsets[b]
        w, _ex, _ey, steps = segment_walk(
            grid,
            pose[0],
            pose[1],
            pose[0] + range_max * math.cos(a),
            pose[1] + range_max * math.sin(a),
            False,
        )
        for s in range(steps + 1):
            if not in_grid(grid, w.ix, w.iy):
                break
            if seen_by[w.iy, w.ix] != tag:
                seen_by[w.iy, w.ix] = tag
                if count == out.shape[0]:
                    grown = np.empty(2 * count, np.int64)
                    grown[:count] = out
                    out = grown
                out[count] = w.iy * grid.nx + w.ix
                count += 1
            if blocking[w.iy, w.ix]:
                break
            if s < steps:
                w = walk_next(w)
    return out[:count].copy()


@nb.njit(cache=True)
def _effective_variance_into(variance, prior, out):
    """``out`` (float64, the shape of ``variance``): the variance with NaN and infinities (no estimate)
    read as ``prior`` and negative rounding clipped to 0, in one pass."""
    v, o = variance.ravel(), out.ravel()
    for i in range(v.size):
        x = np.float64(v[i])
        o[i] = max(x, 0.0) if np.isfinite(x) else prior
    return out


def _grid_of(layers: MapLayers) -> GridGeometry:
    h, w = layers.shape
    return GridGeometry.of(layers.origin_xy_m[0], layers.origin_xy_m[1], layers.resolution_m, w, h)


def variance_reduction_per_cell(variance: FloatArray, noise_var: float) -> FloatArray:
    """(H, W) ``v - v' = v^2 / (v + sigma_n^2)``: what one observation at a cell removes from its variance
    ``v`` (eqs. 2-3 with one training point at the query)."""
    v = np.asarray(variance, dtype=np.float64)
    return v * v / (v + noise_var)


@nb.njit(cache=True, parallel=True)
def _cast_scans_parallel(poses, offsets, range_max, grid, blocking, variance, noise_var, seen_by, first_tag):
    """:func:`_cast_scans` of the (N, 3) poses in parallel runs, one per (ny, nx) scratch of ``seen_by``
    (C, ny, nx), pose ``i`` tagged ``first_tag + i + 1`` in any run."""
    n = poses.shape[0]
    chunks = seen_by.shape[0]
    gains = np.zeros(n)
    for c in nb.prange(chunks):
        lo = c * n // chunks
        hi = (c + 1) * n // chunks
        gains[lo:hi] = _cast_scans(
            poses[lo:hi], offsets, range_max, grid, blocking, variance, noise_var, seen_by[c], first_tag + lo
        )
    return gains


class _RayCaster:
    """Simulated scans through one map: the compiled walks' arguments and one scratch raster per thread,
    allocated once and reused by every call (their tags never repeat), so that a plan over a big building
    touches each scratch page once instead of once per round."""

    def __init__(self, layers: MapLayers, occupied: BoolArray, laser: LaserModel, threads: int) -> None:
        self.offsets = np.ascontiguousarray(laser.beam_offsets_rad())
        self.range_max = float(laser.range_max_m)
        self.grid = _grid_of(layers)
        self.blocking = np.ascontiguousarray(occupied, dtype=np.bool_)
        # numpy's zeros come from the OS as zero pages, touched only where rays pass (a compiled fill would
        # write every cell of a big building's map)
        self.seen_by = np.zeros((max(1, threads), *self.blocking.shape), np.int32)
        self.tags_used = 0

    def _tags(self, n: int) -> int:
        first = self.tags_used
        self.tags_used += n
        if self.tags_used >= np.iinfo(np.int32).max:
            raise OverflowError("too many simulated scans for one ray caster")
        return first

    def gains(self, poses_xytheta: FloatArray, variance: FloatArray, noise_var: float) -> FloatArray:
        """(N,) per (N, 3) pose: the summed ``v^2 / (v + noise_var)`` of the (H, W) float64 ``variance``
        over the cells its scan sees, the poses scanned in parallel."""
        poses = np.ascontiguousarray(np.asarray(poses_xytheta, dtype=np.float64).reshape(-1, 3))
        chunks = max(1, min(poses.shape[0], self.seen_by.shape[0]))
        return _cast_scans_parallel(
            poses,
            self.offsets,
            self.range_max,
            self.grid,
            self.blocking,
            np.ascontiguousarray(variance, dtype=np.float64),
            float(noise_var),
            self.seen_by[:chunks],
            self._tags(poses.shape[0]),
        )

    def seen(self, pose_xytheta: FloatArray) -> NDArray[np.int64]:
        """The flat (row-major) indices of the cells one (3,) pose's scan sees."""
        pose = np.ascontiguousarray(np.asarray(pose_xytheta, dtype=np.float64).reshape(3))
        return _seen_cells(
            pose, self.offsets, self.range_max, self.grid, self.blocking, self.seen_by[0], self._tags(1) + 1
        )


def _effective_variance(layers: MapLayers, prior: float) -> FloatArray:
    """(H, W) float64 variance with NaN and infinities (no estimate) read as the prior."""
    v = np.ascontiguousarray(layers.variance)
    return _effective_variance_into(v, float(prior), np.empty(v.shape, np.float64))


def expected_variance_reduction(
    poses_xytheta: FloatArray,
    layers: MapLayers,
    params: GPParams,
    occupied: BoolArray,
    laser: LaserModel | None = None,
) -> FloatArray:
    """(N,) expected reduction of the summed latent variance of the map by one scan from each of the (N, 3)
    map-frame poses (m, m, rad), rays stopped by the (H, W) ``occupied`` cells (module docstring)."""
    variance = _effective_variance(layers, params.prior_variance)
    caster = _RayCaster(layers, occupied, laser or LaserModel(), nb.get_num_threads())
    return caster.gains(poses_xytheta, variance, params.noise_var)


def visible_cells(
    pose_xytheta: FloatArray, layers: MapLayers, occupied: BoolArray, laser: LaserModel | None = None
) -> BoolArray:
    """(H, W) the cells one scan from the (3,) pose sees."""
    seen = np.zeros(occupied.shape, np.bool_)
    seen.reshape(-1)[_RayCaster(layers, occupied, laser or LaserModel(), 1).seen(pose_xytheta)] = True
    return seen


#: Candidates whose gain bounds are recomputed together in a round of the lazy greedy choice.
LAZY_BATCH = 16


def plan_exploration(
    layers: MapLayers, params: GPParams, settings: ExplorationSettings | None = None
) -> ExplorationPlan:
    """Frontiers, candidate views and the ``settings.n_views`` next-best views of one map (module
    docstring)."""
    s = settings or ExplorationSettings()
    knowledge = classify_knowledge(
        layers, params, s.free_threshold, s.occupied_threshold, s.unknown_variance_fraction
    )
    frontier = frontier_mask(knowledge.free, knowledge.unknown, s.connectivity, s.outside_unknown)
    clusters = cluster_frontier(frontier, layers, s.min_cluster_cells)
    anchors = frontier_anchors(clusters, layers, s.anchor_spacing_m)
    candidates = candidate_poses(anchors, knowledge, layers, s)
    current = _effective_variance(layers, knowledge.prior_variance)  # updated where views see
    noise = params.noise_var
    caster = _RayCaster(layers, knowledge.occupied, s.laser, nb.get_num_threads())
    first = np.zeros(candidates.shape[0])
    chosen: list[int] = []
    view_gains: list[float] = []
    seen_cells: list[NDArray[np.int64]] = []
    # Lazy greedy (Minoux): a view's gain only shrinks as earlier views lower the variance (v^2 / (v + s^2)
    # grows with v), so the gains of the last round bound this round's. Recomputing the best bounds until
    # the first of the maxima is fresh picks exactly what recomputing every candidate would, ties included.
    bound = np.zeros(candidates.shape[0])
    fresh = np.zeros(candidates.shape[0], dtype=bool)
    for k in range(min(s.n_views, candidates.shape[0])):
        if k == 0:
            first = caster.gains(candidates, current, noise)
            bound = first.copy()
            fresh[:] = True
        else:
            fresh[:] = False
            fresh[chosen] = True
            while True:
                best = int(np.argmax(bound))
                if fresh[best]:
                    break
                stale = np.flatnonzero(~fresh)
                batch = stale[np.argsort(-bound[stale], kind="stable")[:LAZY_BATCH]]
                bound[batch] = caster.gains(candidates[batch], current, noise)
                fresh[batch] = True
        best = int(np.argmax(bound))
        if not bound[best] > 0:
            break
        chosen.append(best)
        view_gains.append(float(bound[best]))
        bound[best] = -np.inf  # chosen: never again
        seen = caster.seen(candidates[best])
        seen_cells.append(seen)
        flat = current.reshape(-1)  # a view: current is contiguous
        flat[seen] = flat[seen] * noise / (flat[seen] + noise)
    # the views changed the variance only where they saw: the information is zero elsewhere
    information = np.zeros(layers.shape, np.float32)
    if seen_cells:
        seen = np.unique(np.concatenate(seen_cells))
        before = _effective_variance_into(
            np.ascontiguousarray(layers.variance).reshape(-1)[seen],
            float(knowledge.prior_variance),
            np.empty(seen.size, np.float64),
        )
        information.reshape(-1)[seen] = before - current.reshape(-1)[seen]
    return ExplorationPlan(
        knowledge=knowledge,
        frontier=frontier,
        clusters=clusters,
        candidates_xytheta=candidates,
        candidate_gains=first,
        views_xytheta=candidates[chosen].reshape(-1, 3),
        view_gains=np.asarray(view_gains, dtype=np.float64),
        information=information,
    )


def frontier_layers(
    layers: MapLayers, params: GPParams, settings: ExplorationSettings | None = None
) -> dict[str, NDArray[np.float32]]:
    """``{"frontier": (H, W), "information": (H, W)}`` float32 layers for a GridMap (:meth:`ExplorationPlan.
    layers`); call :func:`plan_exploration` once instead when the views are wanted too."""
    return plan_exploration(layers, params, settings).layers()


def next_best_views(
    layers: MapLayers, params: GPParams, settings: ExplorationSettings | None = None
) -> FloatArray:
    """(K, 3) next-best views (x m, y m, theta rad, map frame), best first; K <= ``settings.n_views``."""
    return plan_exploration(layers, params, settings).views_xytheta
