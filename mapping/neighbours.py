"""Beams made searchable: the occupied-endpoint and free-segment indexes, in the flat arrays the compiled core
reads, plus the local training problems (``k_occ + k_free`` neighbours of a query) used by training."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapping.beams import Beams
from mapping.core import gather_batch
from mapping.index import GridIndex, build_point_index, build_segment_index

FloatArray = NDArray[np.float64]


def _geom(index: GridIndex) -> FloatArray:
    return np.array(
        [index.origin_xy_m[0], index.origin_xy_m[1], index.cell_m, index.shape[0], index.shape[1]]
    )


@dataclass(frozen=True)
class BeamIndex:
    """Searchable training data: occupied endpoints ``hit_x/hit_y`` (H,) and free segments (M,) given by start
    ``seg_x/seg_y``, direction ``seg_dx/seg_dy`` (start to free end) and ``seg_inv_len2`` = 1/|d|^2 (0 for a
    degenerate segment); ``hit_beam`` (H,) maps endpoints back to beams."""

    beams: Beams
    hit_x: FloatArray
    hit_y: FloatArray
    hit_beam: NDArray[np.int64]
    seg_x: FloatArray
    seg_y: FloatArray
    seg_dx: FloatArray
    seg_dy: FloatArray
    seg_inv_len2: FloatArray
    point_index: GridIndex
    segment_index: GridIndex

    @classmethod
    def build(cls, beams: Beams, point_cell_m: float = 0.25, segment_cell_m: float = 0.25) -> BeamIndex:
        hit_beam = np.flatnonzero(beams.is_hit)
        hits = beams.ends_xy_m[hit_beam]
        d = beams.free_ends_xy_m - beams.origins_xy_m
        l2 = np.einsum("ij,ij->i", d, d)
        inv = np.zeros_like(l2)
        np.divide(1.0, l2, out=inv, where=l2 > 0)
        return cls(
            beams=beams,
            hit_x=np.ascontiguousarray(hits[:, 0]),
            hit_y=np.ascontiguousarray(hits[:, 1]),
            hit_beam=hit_beam,
            seg_x=np.ascontiguousarray(beams.origins_xy_m[:, 0]),
            seg_y=np.ascontiguousarray(beams.origins_xy_m[:, 1]),
            seg_dx=np.ascontiguousarray(d[:, 0]),
            seg_dy=np.ascontiguousarray(d[:, 1]),
            seg_inv_len2=inv,
            point_index=build_point_index(hits, point_cell_m),
            segment_index=build_segment_index(beams.origins_xy_m, beams.free_ends_xy_m, segment_cell_m),
        )

    def core_args(self) -> tuple:
        """The index arguments of :func:`mapping.core.predict_batch` / ``gather_batch``, in order."""
        p, s = self.point_index, self.segment_index
        return (
            self.hit_x,
            self.hit_y,
            _geom(p),
            p.cell_start,
            p.items,
            self.seg_x,
            self.seg_y,
            self.seg_dx,
            self.seg_dy,
            self.seg_inv_len2,
            _geom(s),
            s.cell_start,
            s.items,
        )

    def gather(
        self, queries_xy_m: FloatArray, k_occ: int, k_free: int
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], FloatArray]:
        """Neighbours of (Q, 2) queries: endpoint ids (Q, k_occ), segment ids (Q, k_free) and the position
        t in [0, 1] of each free point along its segment (Q, k_free); -1 pads missing neighbours."""
        q = np.ascontiguousarray(queries_xy_m, dtype=np.float64).reshape(-1, 2)
        occ = np.empty((q.shape[0], k_occ), np.int64)
        free = np.empty((q.shape[0], k_free), np.int64)
        t = np.empty((q.shape[0], k_free))
        gather_batch(q, *self.core_args(), k_occ, k_free, occ, free, t)
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
