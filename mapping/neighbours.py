"""Beams made searchable: the occupied-endpoint and free-segment indexes, as the named tuples the compiled
core reads (:class:`mapping.index.PointSet`, :class:`mapping.index.SegmentSet`), plus the local training
problems (``k_occ + k_free`` neighbours of a query) used by training."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from mapping.beams import Beams
from mapping.core import gather_batch
from mapping.index import (
    GridIndex,
    PointSet,
    SegmentSet,
    build_point_index,
    build_segment_index,
    segment_entry_copies,
)
from mapping.unscented import BeamMoments, unpack_cov

FloatArray = NDArray[np.float64]


def auto_cell_m(beams: Beams, items_per_cell: float = 16.0, lo: float = 0.1, hi: float = 10.0) -> float:
    """A cell size for the neighbour grids: about ``items_per_cell`` endpoints per cell if they were spread
    evenly over their bounding box (decimetres indoors, metres for a few scans of a street), so that a
    sparse map is not searched through millions of empty cells; clamped to [lo, hi]."""
    pts = beams.hit_xy_m if beams.is_hit.any() else beams.ends_xy_m
    if pts.shape[0] == 0:
        return hi
    span = np.maximum(pts.max(axis=0) - pts.min(axis=0), lo)
    return float(np.clip(np.sqrt(items_per_cell * span[0] * span[1] / pts.shape[0]), lo, hi))


@dataclass(frozen=True)
class BeamIndex:
    """Searchable training data.

    - ``hit_xy`` (H, 2): occupied endpoints sorted by cell of ``point_index`` (its ``items`` are then
      ``0..H-1``); ``hit_beam`` (H,) maps them back to beams;
    - ``seg`` (M, 5): one row per beam, (start x, start y, d x, d y, 1/|d|^2) with d = free end - start
      (1/|d|^2 = 0 for a degenerate segment); ``segment_index`` lists the beams crossing each cell and
      ``seg_entries`` (5, E) float32 copies them per entry (see :func:`mapping.index.knn_segments`).
    """

    beams: Beams
    hit_xy: FloatArray
    hit_beam: NDArray[np.int64]
    seg: FloatArray
    point_index: GridIndex
    segment_index: GridIndex
    seg_entries: NDArray[np.float32]

    @classmethod
    def build(
        cls, beams: Beams, point_cell_m: float | None = None, segment_cell_m: float | None = None
    ) -> BeamIndex:
        """Index ``beams``; cell sizes default to :func:`auto_cell_m`."""
        auto = auto_cell_m(beams)
        point_cell_m = point_cell_m or auto
        segment_cell_m = segment_cell_m or auto
        hit_beam = np.flatnonzero(beams.is_hit)
        hits = beams.ends_xy_m[hit_beam]
        point_index = build_point_index(hits, point_cell_m)
        order = point_index.items.astype(np.int64)
        point_index = GridIndex(
            point_index.origin_xy_m,
            point_index.cell_m,
            point_index.shape,
            point_index.cell_start,
            np.arange(order.size, dtype=np.int32),
        )
        d = beams.free_ends_xy_m - beams.origins_xy_m
        l2 = np.einsum("ij,ij->i", d, d)
        inv = np.zeros_like(l2)
        np.divide(1.0, l2, out=inv, where=l2 > 0)
        seg = np.ascontiguousarray(np.column_stack([beams.origins_xy_m, d, inv]))
        segment_index = build_segment_index(beams.origins_xy_m, beams.free_ends_xy_m, segment_cell_m)
        return cls(
            beams=beams,
            hit_xy=np.ascontiguousarray(hits[order]),
            hit_beam=hit_beam[order],
            seg=seg,
            point_index=point_index,
            segment_index=segment_index,
            seg_entries=segment_entry_copies(segment_index, seg),
        )

    @property
    def hit_x(self) -> FloatArray:
        return self.hit_xy[:, 0]

    @property
    def hit_y(self) -> FloatArray:
        return self.hit_xy[:, 1]

    @property
    def seg_x(self) -> FloatArray:
        return self.seg[:, 0]

    @property
    def seg_y(self) -> FloatArray:
        return self.seg[:, 1]

    @property
    def seg_dx(self) -> FloatArray:
        return self.seg[:, 2]

    @property
    def seg_dy(self) -> FloatArray:
        return self.seg[:, 3]

    @cached_property
    def points(self) -> PointSet:
        """The occupied endpoints for the compiled core (:func:`mapping.index.knn_points`)."""
        return PointSet(self.hit_xy, self.point_index.packed)

    @cached_property
    def segments(self) -> SegmentSet:
        """The free segments for the compiled core (:func:`mapping.index.knn_segments`)."""
        return SegmentSet(self.seg, self.seg_entries, self.segment_index.packed)

    def gather(
        self, queries_xy_m: FloatArray, k_occ: int, k_free: int
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], FloatArray]:
        """Neighbours of (Q, 2) queries: endpoint ids (Q, k_occ), segment ids (Q, k_free) and the position
        t in [0, 1] of each free point along its segment (Q, k_free); -1 pads missing neighbours."""
        q = np.ascontiguousarray(queries_xy_m, dtype=np.float64).reshape(-1, 2)
        occ = np.empty((q.shape[0], k_occ), np.int64)
        free = np.empty((q.shape[0], k_free), np.int64)
        t = np.empty((q.shape[0], k_free))
        gather_batch(q, self.points, self.segments, k_occ, k_free, occ, free, t)
        return occ, free, t

    def local_problems(
        self, queries_xy_m: FloatArray, k_occ: int, k_free: int
    ) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        """Local GP training sets of (Q, 2) queries, centred on each query: X (Q', k_occ + k_free, 2) and
        labels y (Q', n) (+1 occupied, -1 free), for the Q' queries with a full neighbourhood (mask (Q,))."""
        q = np.asarray(queries_xy_m, dtype=np.float64).reshape(-1, 2)
        occ, free, t = self.gather(q, k_occ, k_free)
        full = (occ >= 0).all(axis=1) & (free >= 0).all(axis=1)
        occ, free, t, q = occ[full], free[full], t[full], q[full]
        xo = np.stack([self.hit_x[occ], self.hit_y[occ]], axis=-1)
        xf = np.stack(
            [self.seg_x[free] + t * self.seg_dx[free], self.seg_y[free] + t * self.seg_dy[free]], axis=-1
        )
        X = np.concatenate([xo, xf], axis=1) - q[:, None, :]
        y = np.concatenate([np.ones((q.shape[0], k_occ)), -np.ones((q.shape[0], k_free))], axis=1)
        return X, y, full

    def local_gaussians(
        self,
        queries_xy_m: FloatArray,
        k_occ: int,
        k_free: int,
        moments: BeamMoments,
        free_moments: BeamMoments | None = None,
    ) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
        """GPPOL local training sets of (Q, 2) queries: input means X (Q', n, 2) centred on each query, their
        covariances (Q', n, 2, 2) from the per-beam UT ``moments`` (endpoints at d = range, free points at
        d = t |free part|; ``free_moments`` for the free points if given), labels y (Q', n), for the Q'
        queries
        with a full neighbourhood (mask (Q,))."""
        X, cov, y, full, _, _ = self._local(queries_xy_m, k_occ, k_free, moments, free_moments)
        return X, cov, y, full

    def local_gaussians_by_scan(
        self,
        queries_xy_m: FloatArray,
        k_occ: int,
        k_free: int,
        moments: BeamMoments,
        free_moments: BeamMoments | None,
        local_moments: BeamMoments,
        local_free_moments: BeamMoments,
    ) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.int64], FloatArray, NDArray[np.bool_]]:
        """:meth:`local_gaussians` plus, per training input, the covariance of the laser noise alone (from
        ``local_moments`` / ``local_free_moments``, (Q', n, 2, 2)) and its scan index (Q', n): returns
        ``X, cov, local_cov, scans, y, full``."""
        X, cov, y, full, hb, free = self._local(queries_xy_m, k_occ, k_free, moments, free_moments)
        _, local_cov, _, _, _, _ = self._local(queries_xy_m, k_occ, k_free, local_moments, local_free_moments)
        scan = self.beams.scan_index
        return X, cov, local_cov, np.concatenate([scan[hb], scan[free]], axis=1), y, full

    def _local(self, queries_xy_m, k_occ, k_free, moments, free_moments):
        q = np.asarray(queries_xy_m, dtype=np.float64).reshape(-1, 2)
        occ, free, t = self.gather(q, k_occ, k_free)
        full = (occ >= 0).all(axis=1) & (free >= 0).all(axis=1)
        occ, free, t, q = occ[full], free[full], t[full], q[full]
        hb = self.hit_beam[occ]
        d_occ = self.beams.ranges_m[hb]
        free_len = np.sqrt(np.einsum("ij,ij->i", self.seg[:, 2:4], self.seg[:, 2:4]))
        d_free = t * free_len[free]
        fm = moments if free_moments is None else free_moments
        X = np.concatenate([moments.mean_at(d_occ, hb), fm.mean_at(d_free, free)], axis=1) - q[:, None, :]
        cov = unpack_cov(
            np.concatenate([moments.packed_cov_at(d_occ, hb), fm.packed_cov_at(d_free, free)], 1)
        )
        y = np.concatenate([np.ones((q.shape[0], k_occ)), -np.ones((q.shape[0], k_free))], axis=1)
        return X, cov, y, full, hb, free
