"""The GP occupancy map: GPFOL (paper section 3.5, Algorithm 1) or, given Gaussian inputs, GPPOL (section
3.6.3, Algorithm 3). Query anywhere, render any grid.

Rendered maps are :class:`mapping.exports.MapLayers` (raster convention of that module: row 0 at the lowest
y, ``origin_xy_m`` the lower-left corner of cell (0, 0)).

The map holds the beams (indexed) and the learnt :class:`~mapping.train.GPParams`; nothing is fitted per
rendering, so a coarse map and a fine map of any bounds come from the same object ("anytime": coarse first,
then fine, see :meth:`GPOccupancyMap.render_anytime`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mapping.beams import Beams
from mapping.core import INPUTS_GIRARD, InputGaussians, LocalGP, predict_batch
from mapping.exports import MapLayers
from mapping.gppol import GaussianInputs
from mapping.neighbours import BeamIndex
from mapping.reach import (
    REACH_MIN_PEAK,
    ReachMask,
    kernel_reach_m,
    largest_eigenvalue,
    quadratic_range,
    reach_mask,
    reach_tolerance,
    se_girard_peak,
    se_girard_reach_m,
    segment_pieces,
    spread_factor,
)
from mapping.train import GPParams

FloatArray = NDArray[np.float64]

OCCUPIED = 1
FREE = 0
UNSURE = -1


@dataclass(frozen=True)
class Prediction:
    """Per query point (Q,): GP mean (eq. 2), latent variance (eq. 3) and p(occ) (PLS link)."""

    mean: FloatArray
    variance: FloatArray
    probability: FloatArray


def classify(probability: NDArray, occupied_threshold: float = 0.65, free_threshold: float = 0.35) -> NDArray:
    """Occupied (1) where p >= ``occupied_threshold``, free (0) where p <= ``free_threshold``, unsure (-1)
    between (paper Fig. 6: 0.65 / 0.35)."""
    if not 0 < free_threshold < occupied_threshold < 1:
        raise ValueError(f"need 0 < free ({free_threshold}) < occupied ({occupied_threshold}) < 1")
    p = np.asarray(probability)
    out = np.full(p.shape, UNSURE, dtype=np.int8)
    out[p >= occupied_threshold] = OCCUPIED
    out[p <= free_threshold] = FREE
    return out


def grid_axes(
    bounds_xy_m: tuple[float, float, float, float], resolution_m: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The cell centres of a grid covering ``(xmin, ymin, xmax, ymax)`` by axis: (W,) x and (H,) y
    coordinates (a cell's centre is ``(xs[col], ys[row])``), the origin (lower-left corner) and the shape
    (H, W) as an int array."""
    x0, y0, x1, y1 = bounds_xy_m
    if not (x1 > x0 and y1 > y0 and resolution_m > 0):
        raise ValueError(f"bad map bounds {bounds_xy_m} or resolution {resolution_m}")
    w = max(1, math.ceil((x1 - x0) / resolution_m - 1e-9))
    h = max(1, math.ceil((y1 - y0) / resolution_m - 1e-9))
    xs = x0 + (np.arange(w) + 0.5) * resolution_m
    ys = y0 + (np.arange(h) + 0.5) * resolution_m
    return xs, ys, np.array([x0, y0]), np.array([h, w])


def grid_centres(
    bounds_xy_m: tuple[float, float, float, float], resolution_m: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Cell centres of a grid covering ``(xmin, ymin, xmax, ymax)``: (H*W, 2) row-major points, the origin
    (lower-left corner) and the shape (H, W) as an int array (:func:`grid_axes`)."""
    xs, ys, origin, shape = grid_axes(bounds_xy_m, resolution_m)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
    return pts, origin, shape


def tile_order(h: int, w: int, tile: int = 16) -> NDArray[np.int64]:
    """Indices of the cells of an (h, w) row-major grid, tile by tile (``tile`` x ``tile`` cells, tiles in
    row-major order), each tile's rows in turn, alternately left to right and right to left.

    Rendering in this order keeps consecutive queries adjacent (each search is warm-started from the previous
    query's neighbours) and a parallel chunk of ``tile**2`` queries compact, so that the index cells it reads
    stay in cache; raster rows, 30 m long, sweep more cells than the cache holds before the next row reuses
    them. The results do not depend on the order (exact k-NN, independent local GPs)."""
    th, tw = -(-h // tile), -(-w // tile)
    cells = np.full((th * tile, tw * tile), -1, np.int64)
    cells[:h, :w] = np.arange(h * w, dtype=np.int64).reshape(h, w)
    blocks = cells.reshape(th, tile, tw, tile)
    blocks[:, 1::2] = blocks[:, 1::2, :, ::-1]  # odd rows of each tile right to left
    blocks = blocks.transpose(0, 2, 1, 3).ravel()
    return blocks[blocks >= 0]


@nb.njit(cache=True)
def tile_order_where(selected: NDArray[np.bool_], tile: int = 16) -> NDArray[np.int64]:
    """The row-major indices of the ``selected`` cells of an (h, w) grid in :func:`tile_order`'s order
    (``tile_order(h, w, tile)`` filtered by ``selected``), without the (h * w,) order of every cell: a big
    building's map selects a part of its bounding box."""
    h, w = selected.shape
    out = np.empty(np.count_nonzero(selected), np.int64)
    n = 0
    for ti in range(0, h, tile):
        for tj in range(0, w, tile):
            for r in range(tile):
                i = ti + r
                if i >= h:
                    break
                for c in range(tile):
                    j = tj + (c if r % 2 == 0 else tile - 1 - c)
                    if j < w and selected[i, j]:
                        out[n] = i * w + j
                        n += 1
    return out


@nb.njit(cache=True)
def cell_centres(cells: NDArray[np.int64], xs_m: FloatArray, ys_m: FloatArray) -> FloatArray:
    """(C, 2) centres ``(xs_m[col], ys_m[row])`` of the row-major ``cells`` (C,) of a grid with the (W,) x and
    (H,) y coordinates of :func:`grid_axes`."""
    w = xs_m.size
    out = np.empty((cells.size, 2))
    for k in range(cells.size):
        out[k, 0] = xs_m[cells[k] % w]
        out[k, 1] = ys_m[cells[k] // w]
    return out


@nb.njit(cache=True, parallel=True)
def _fill_layers(cells, prob_solved, mean_solved, var_solved, prior, probability, mean, variance):
    """The float32 layers (h * w,) of a render: the prior (``prior``: probability, mean, variance) and the
    solved values at ``cells``, in parallel (a big building's three layers of 15 M cells)."""
    for i in nb.prange(probability.size):
        probability[i] = prior[0]
        mean[i] = prior[1]
        variance[i] = prior[2]
    for k in nb.prange(cells.size):
        c = cells[k]
        probability[c] = prob_solved[k]
        mean[c] = mean_solved[k]
        variance[c] = var_solved[k]


class GPOccupancyMap:
    """GP map over ``beams`` with learnt ``params``; ``k_occ`` + ``k_free`` neighbours per query.

    ``inputs`` (:class:`mapping.gppol.GaussianInputs`, the beams' input Gaussians) makes it GPPOL; without
    it the training inputs are points (GPFOL). ``unknown_variance_fraction`` (the classification's, see
    :mod:`mapping.exports`) lets places whose variance provably stays above that fraction of the prior, which
    are unknown anyway, read the prior unsolved (:func:`mapping.reach.reach_tolerance`); None solves every
    place where the solve would not give the prior to float32."""

    def __init__(
        self,
        beams: Beams,
        params: GPParams,
        k_occ: int = 15,
        k_free: int = 15,
        jitter: float = 1e-8,
        index_cell_m: float | None = None,
        chunk: int = 256,
        inputs: GaussianInputs | None = None,
        unknown_variance_fraction: float | None = None,
    ) -> None:
        self.beams = beams
        self.unknown_variance_fraction = unknown_variance_fraction
        self.params = params
        self.k_occ = int(k_occ)
        self.k_free = int(k_free)
        self.jitter = float(jitter)
        self.chunk = int(chunk)
        t0 = time.perf_counter()
        self.index = BeamIndex.build(beams, index_cell_m, index_cell_m)
        self.inputs = inputs
        if inputs is None:
            self._inputs = InputGaussians.points()
        else:
            if len(inputs.moments) != len(beams):
                raise ValueError(f"{len(inputs.moments)} input moments for {len(beams)} beams")
            self._inputs = InputGaussians(
                inputs.core_mode(params.kernel),
                *inputs.core_arrays(beams, self.index.hit_beam),
                *inputs.rule(),
            )
        self.index_seconds = time.perf_counter() - t0
        self.last_render_seconds = 0.0
        self._reach: ReachMask | None = None
        self._reach_done = False
        self.last_query_stats: dict[str, float] = {}

    @property
    def mapper(self) -> str:
        """``"gppol"`` (Gaussian training inputs) or ``"gpfol"``."""
        return "gpfol" if self.inputs is None else "gppol"

    def bounds_xy_m(self, margin_m: float = 1.0) -> tuple[float, float, float, float]:
        """Bounds of the occupied endpoints and laser origins, grown by ``margin_m``."""
        b = self.beams
        pts = np.concatenate([b.origins_xy_m, b.hit_xy_m])
        lo = pts.min(axis=0) - margin_m
        hi = pts.max(axis=0) + margin_m
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def reach(self) -> ReachMask | None:
        """Where a training input can inform a prediction (:mod:`mapping.reach`), computed on first use;
        None for a kernel that does not decay (the neural-network kernel), whose every query is solved."""
        if not self._reach_done:
            self._reach = self._reach_mask()
            self._reach_done = True
        return self._reach

    def _reach_mask(self) -> ReachMask | None:
        p = self.params
        tol = reach_tolerance(
            p.noise_var, p.prior_variance, self.k_occ + self.k_free, self.unknown_variance_fraction
        )
        r0 = kernel_reach_m(p.kernel, tol)
        if r0 is None or len(self.beams) == 0:
            return None
        idx = self.index
        if self.inputs is None:  # exact inputs: the endpoints and the free segments as indexed
            starts = np.concatenate([idx.hit_xy, idx.seg[:, :2]])
            ends = np.concatenate([idx.hit_xy, idx.seg[:, :2] + idx.seg[:, 2:4]])
            reach = np.full(starts.shape[0], r0)
        else:  # Gaussian inputs at their UT means, each reaching further by its spread
            occ, seg = self._inputs.occ_moments, self._inputs.seg_moments
            # a free segment's input covariance Sigma(d) = C0 + d C1 + d^2 C2 (d along the beam), bounded
            # piece by piece: its largest eigenvalue lies between half its trace and its trace, both
            # quadratics in d (extremes at a piece's ends or the vertex)
            which, d0, d1 = segment_pieces(seg[:, 13])
            t0, t1, t2 = (seg[which, k] + seg[which, k + 2] for k in (4, 7, 10))
            tr_lo, tr_hi = quadratic_range(t0, t1, t2, d0, d1)
            direction = seg[which, 2:4]
            starts = np.concatenate([occ[:, :2], seg[which, :2] + d0[:, None] * direction])
            ends = np.concatenate([occ[:, :2], seg[which, :2] + d1[:, None] * direction])
            occ_lam = largest_eigenvalue(occ[:, 2:5])
            lam = np.concatenate([occ_lam, np.maximum(tr_hi, 0.0)])
            if self._inputs.mode == INPUTS_GIRARD:
                ell = self.params.kernel.as_dict()["length_scale"]
                # a piece's largest eigenvalue lies between half its least trace and its largest trace
                reach = se_girard_reach_m(ell, lam, tol, np.concatenate([occ_lam, 0.5 * tr_lo]))
                # inputs too spread to inform a place on their own (REACH_MIN_PEAK) reach nowhere
                peak = se_girard_peak(ell, np.concatenate([occ_lam, 0.5 * tr_lo]))
                reach[peak < REACH_MIN_PEAK] = 0.0
            else:
                c = spread_factor(float(np.max(np.linalg.norm(self._inputs.nodes, axis=1))))
                reach = r0 + c * np.sqrt(lam)
        return reach_mask(starts, ends, reach)

    def query(self, points_xy_m: FloatArray, sort: bool = True) -> Prediction:
        """Mean, variance and p(occ) at (Q, 2) points. ``sort`` processes them in index-cell order (faster
        for scattered points; results come back in the input order). Points beyond every training input's
        reach (:meth:`reach`) get the prior (mean 0, the prior variance, the unseen probability) unsolved."""
        pts = np.ascontiguousarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
        t0 = time.perf_counter()
        mask = self.reach()
        return self._query(pts, sort, mask.contains(pts) if mask is not None else None, t0)

    def _query(self, pts: FloatArray, sort: bool, near: NDArray[np.bool_] | None, t0: float) -> Prediction:
        """:meth:`query` of the (Q, 2) points given which of them lie within reach (``near``, None: all)."""
        if near is None or near.all():
            t1 = time.perf_counter()
            out = self._solve(pts, sort)
            self._note_query(pts.shape[0], t1 - t0, pts.shape[0], time.perf_counter() - t1)
            return out
        p = self.params
        mean = np.zeros(pts.shape[0])
        var = np.full(pts.shape[0], p.prior_variance)
        prob = np.full(pts.shape[0], p.unseen_probability)
        t1 = time.perf_counter()
        n_near = int(near.sum())
        if n_near:
            solved = self._solve(np.ascontiguousarray(pts[near]), sort)
            mean[near], var[near], prob[near] = solved.mean, solved.variance, solved.probability
        self._note_query(pts.shape[0], t1 - t0, n_near, time.perf_counter() - t1)
        return Prediction(mean, var, prob)

    def _note_query(self, n: int, prior_s: float, n_solved: int, solved_s: float) -> None:
        """``last_query_stats``: the points of the last query, those solved and the seconds each part took
        (``prior_s``: the reach test and the prior's fill, which includes building the reach raster on the
        first query; for :meth:`render`, filling the layers with the prior and the solved values)."""
        self.last_query_stats = {
            "points": n,
            "solved": n_solved,
            "prior": n - n_solved,
            "solved_s": solved_s,
            "prior_s": prior_s,
        }

    def _solve(self, pts: FloatArray, sort: bool) -> Prediction:
        """The local GPs at (Q, 2) contiguous points (:meth:`query` without the reach test)."""
        order = None
        if sort and pts.shape[0] > 1:
            idx = self.index.segment_index
            cell = np.floor((pts - idx.origin_xy_m) / idx.cell_m).astype(np.int64)
            order = np.lexsort((cell[:, 1], cell[:, 0]))
            pts = np.ascontiguousarray(pts[order])
        n = pts.shape[0]
        mean, var, prob = np.empty(n), np.empty(n), np.empty(n)
        kid, kp = self.params.kernel.packed()
        p = self.params
        gp = LocalGP.of(
            self.k_occ, self.k_free, kid, kp, p.noise_var, self.jitter, p.alpha, p.beta, self.chunk,
            mean_cap=p.mean_cap,
        )  # fmt: skip
        predict_batch(pts, self.index.points, self.index.segments, gp, self._inputs, mean, var, prob)
        if order is not None:
            inv = np.empty_like(order)
            inv[order] = np.arange(n)
            mean, var, prob = mean[inv], var[inv], prob[inv]
        return Prediction(mean, var, prob)

    def render(
        self, bounds_xy_m: tuple[float, float, float, float] | None = None, resolution_m: float = 0.1
    ) -> MapLayers:
        """Probability, mean and variance on a grid of ``resolution_m`` over ``bounds_xy_m`` (default: the
        data bounds); any resolution and bounds, no retraining."""
        bounds = bounds_xy_m or self.bounds_xy_m()
        xs, ys, origin, shape = grid_axes(bounds, resolution_m)
        h, w = int(shape[0]), int(shape[1])
        t0 = time.perf_counter()
        mask = self.reach()
        # Only the cells within reach are made into query points (tile by tile, see tile_order); the rest
        # keep the prior the layers start from.
        near = np.ones((h, w), dtype=bool) if mask is None else mask.contains_grid(xs, ys)
        cells = tile_order_where(near)
        pts = cell_centres(cells, xs, ys)
        p = self.params
        t1 = time.perf_counter()
        solved = self._solve(pts, False) if cells.size else Prediction(np.zeros(0), np.zeros(0), np.zeros(0))
        t2 = time.perf_counter()
        probability, mean, variance = (np.empty(h * w, dtype=np.float32) for _ in range(3))
        prior = np.array([p.unseen_probability, 0.0, p.prior_variance], dtype=np.float32)
        _fill_layers(
            cells, solved.probability, solved.mean, solved.variance, prior, probability, mean, variance
        )
        self._note_query(h * w, t1 - t0 + time.perf_counter() - t2, int(cells.size), t2 - t1)
        self.last_render_seconds = time.perf_counter() - t0
        return MapLayers(
            probability=probability.reshape(h, w),
            mean=mean.reshape(h, w),
            variance=variance.reshape(h, w),
            resolution_m=float(resolution_m),
            origin_xy_m=(float(origin[0]), float(origin[1])),
        )

    def render_anytime(
        self,
        bounds_xy_m: tuple[float, float, float, float] | None = None,
        resolutions_m: Sequence[float] = (1.0, 0.5, 0.2, 0.1),
    ) -> Iterator[MapLayers]:
        """Maps from coarse to fine: a caller may stop after any of them."""
        for res in sorted(resolutions_m, reverse=True):
            yield self.render(bounds_xy_m, res)
