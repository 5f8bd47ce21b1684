"""Which beams can influence a tile: the exact training support of a tile, and the change tests of incremental
updates.

The local GP of a query ``q`` (paper section 3.7) uses its ``k_occ`` nearest occupied endpoints and its
``k_free`` nearest free segments. The k-th nearest distance ``r_k(q)`` is 1-Lipschitz in ``q`` (for points
and for point-to-segment distances alike). For a tile whose cell centres fill the rectangle ``B``, sample
``r_k`` at the corners of an ``s x s`` subdivision of ``B``: every query of the tile lies within ``m`` (half
a sub-cell diagonal) of a sample, so ``r_k(q) <= rho = max_samples r_k + m``, and every neighbour any query
of the tile can use lies within ``rho`` of ``B``. The beams whose endpoint lies within ``rho_occ`` (from
``k_occ``) or whose free segment passes within ``rho_free`` (from ``k_free``) of ``B`` are therefore
sufficient: a map built from them gives every query of the tile the same neighbours as the map of all beams.
They are kept in their original order. (Bounding ``r_k`` by its value at the centre ``c`` plus the
half-diagonal ``h`` and taking the disc of radius ``r_k(c) + 2h`` is exact too, but with ``r_k << h`` that
disc, of radius about the tile's diagonal, covers about 2 pi tiles, where this support covers the tile grown
by a margin of ``r_k``.)

Incremental updates use the same radii. New data can only shrink ``r_k``: if no new endpoint lies within
``rho_occ`` and no new segment within ``rho_free`` of ``B``, no new item is nearer any query of the tile than
its old k-th neighbour, the samples' ``r_k`` do not change, and the tile's support (hence its rendering) is
the same bit for bit. Likewise for beams that moved: if none lay (before) or lies (after) within the radii,
nothing the tile sees changed. :class:`SupportIndex` answers these questions through a coarse uniform grid
(:mod:`mapping.index`); distances are exact in float64 and radii carry a small slack, so a selection can only
be larger than needed, never smaller.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mapping.beams import Beams
from mapping.index import GridIndex, build_point_index, build_segment_index

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# added to every radius: float64 round-off in these distances is ~1e-14 m, so this only ever grows a selection
RADIUS_SLACK_M = 1e-6
# spacing of the r_k samples over a tile (at most MAX_SUBDIVISIONS per side)
SAMPLE_SPACING_M = 1.0
MAX_SUBDIVISIONS = 32
MAX_K = 1000


@nb.njit(cache=True, error_model="numpy", inline="always")
def _cells_around(xa, ya, xb, yb, rho, grid):
    """Cell ranges (inclusive, clipped) of the rectangle grown by ``rho`` and one cell of ``grid`` (a
    :class:`~mapping.raster.GridGeometry`), and whether the unclipped range covers the whole grid."""
    ox, oy, cell, nx, ny = grid.x0, grid.y0, grid.cell, grid.nx, grid.ny
    if not math.isfinite(rho):
        return 0, nx - 1, 0, ny - 1, True
    ix0 = math.floor((xa - rho - ox) / cell) - 1
    ix1 = math.floor((xb + rho - ox) / cell) + 1
    iy0 = math.floor((ya - rho - oy) / cell) - 1
    iy1 = math.floor((yb + rho - oy) / cell) + 1
    whole = ix0 <= 0 and iy0 <= 0 and ix1 >= nx - 1 and iy1 >= ny - 1
    return max(ix0, 0), min(ix1, nx - 1), max(iy0, 0), min(iy1, ny - 1), whole


@nb.njit(cache=True, error_model="numpy", inline="always")
def _point_rect(x, y, xa, ya, xb, yb):
    """Distance from (x, y) to the rectangle [xa, xb] x [ya, yb] (0 inside)."""
    dx = max(max(xa - x, x - xb), 0.0)
    dy = max(max(ya - y, y - yb), 0.0)
    return math.sqrt(dx * dx + dy * dy)


@nb.njit(cache=True, error_model="numpy", inline="always")
def _point_segment(px, py, sx, sy, dx, dy):
    """Distance from (px, py) to the segment from (sx, sy) along (dx, dy) (closest point, eqs. 13-14)."""
    rx = px - sx
    ry = py - sy
    l2 = dx * dx + dy * dy
    t = 0.0
    if l2 > 0.0:
        t = min(max((rx * dx + ry * dy) / l2, 0.0), 1.0)
    ex = rx - t * dx
    ey = ry - t * dy
    return math.sqrt(ex * ex + ey * ey)


@nb.njit(cache=True, error_model="numpy")
def _segment_rect(seg, i, xa, ya, xb, yb):
    """Distance from segment ``i`` of ``seg`` (M, 4: start x, y, end x, y) to the rectangle (0 if they
    meet)."""
    sx = seg[i, 0]
    sy = seg[i, 1]
    dx = seg[i, 2] - sx
    dy = seg[i, 3] - sy
    # Liang-Barsky: does the segment meet the rectangle?
    t0 = 0.0
    t1 = 1.0
    meets = True
    for side in range(4):
        if side == 0:
            p, q = -dx, sx - xa
        elif side == 1:
            p, q = dx, xb - sx
        elif side == 2:
            p, q = -dy, sy - ya
        else:
            p, q = dy, yb - sy
        if p == 0.0:
            if q < 0.0:
                meets = False
                break
        else:
            r = q / p
            if p < 0.0:
                t0 = max(t0, r)
            else:
                t1 = min(t1, r)
            if t0 > t1:
                meets = False
                break
    if meets:
        return 0.0
    # disjoint convex sets: the distance is reached at a vertex of one of them
    d = min(_point_rect(sx, sy, xa, ya, xb, yb), _point_rect(sx + dx, sy + dy, xa, ya, xb, yb))
    d = min(d, _point_segment(xa, ya, sx, sy, dx, dy))
    d = min(d, _point_segment(xb, ya, sx, sy, dx, dy))
    d = min(d, _point_segment(xa, yb, sx, sy, dx, dy))
    return min(d, _point_segment(xb, yb, sx, sy, dx, dy))


@nb.njit(cache=True, error_model="numpy", inline="always")
def _item_rect(xy, is_seg, i, xa, ya, xb, yb):
    if is_seg:
        return _segment_rect(xy, i, xa, ya, xb, yb)
    return _point_rect(xy[i, 0], xy[i, 1], xa, ya, xb, yb)


@nb.njit(cache=True, error_model="numpy")
def _collect(xa, ya, xb, yb, rho, index, xy, is_seg, mark, stamp, out_id, out_d):
    """Items in the cells around the rectangle grown by ``rho`` (deduplicated with ``mark[i] == stamp``) and
    their distances to it; returns (count, whether every cell of the grid was visited)."""
    ny = index.grid.ny
    cell_start = index.cell_start
    items = index.items
    ix0, ix1, iy0, iy1, whole = _cells_around(xa, ya, xb, yb, rho, index.grid)
    n = 0
    for ix in range(ix0, ix1 + 1):
        for iy in range(iy0, iy1 + 1):
            c = ix * ny + iy
            for e in range(cell_start[c], cell_start[c + 1]):
                i = items[e]
                if mark[i] == stamp:
                    continue
                mark[i] = stamp
                out_id[n] = i
                out_d[n] = _item_rect(xy, is_seg, i, xa, ya, xb, yb)
                n += 1
    return n, whole


@nb.njit(cache=True, error_model="numpy")
def _kth_distance(px, py, k, index, xy, is_seg, mark, stamp, out_id, out_d):
    """Exact distance from (px, py) to its k-th nearest item (inf if there are fewer than k), searching
    squares of doubling size; returns (distance, next free stamp)."""
    radius = index.grid.cell
    while True:
        n, whole = _collect(px, py, px, py, radius, index, xy, is_seg, mark, stamp, out_id, out_d)
        stamp += 1
        inside = 0
        for j in range(n):
            if out_d[j] <= radius:
                inside += 1
        if inside >= k:
            # every item within ``radius`` was collected, so the k-th smallest of them is the k-th overall
            m = 0
            for j in range(n):
                if out_d[j] <= radius:
                    out_d[m] = out_d[j]
                    m += 1
            return np.partition(out_d[:m], k - 1)[k - 1], stamp
        if whole:  # every item was collected
            if n >= k:
                return np.partition(out_d[:n], k - 1)[k - 1], stamp
            return np.inf, stamp
        radius *= 2.0


@nb.njit(cache=True, error_model="numpy")
def _tile_radius(
    xa, ya, xb, yb, subdiv, k, reach, index, xy, is_seg, mark, stamp, out_id, out_d, best
):  # fmt: skip
    """rho = max of r_k over the (subdiv + 1)^2 corners of a subdivision of the rectangle, plus half a
    sub-cell diagonal: an upper bound of r_k over the rectangle, r_k being 1-Lipschitz. Returns
    (rho, the reach that sufficed, next free stamp).

    The samples share one candidate set: every item within ``reach`` of the rectangle, sorted by that
    distance, which is a lower bound of its distance to any sample (samples lie in the rectangle). A sample's
    search stops at the first candidate whose lower bound reaches its current k-th distance (its r_k is then
    exact when within ``reach``), or as soon as k candidates lie within the maximum so far (its r_k cannot
    raise it). Otherwise ``reach`` doubles (starting from the given one)."""
    sx = (xb - xa) / subdiv
    sy = (yb - ya) / subdiv
    reach = max(reach, 1e-3)
    while True:
        n, whole = _collect(xa, ya, xb, yb, reach, index, xy, is_seg, mark, stamp, out_id, out_d)
        stamp += 1
        if not whole:  # keep the candidates within reach
            m = 0
            for j in range(n):
                if out_d[j] <= reach:
                    out_id[m] = out_id[j]
                    out_d[m] = out_d[j]
                    m += 1
            n = m
        order = np.argsort(out_d[:n])
        worst = 0.0
        complete = True
        for i in range(subdiv + 1):
            px = xb if i == subdiv else xa + i * sx
            for j in range(subdiv + 1):
                py = yb if j == subdiv else ya + j * sy
                count = 0
                for c in range(n):
                    o = order[c]
                    if count == k and (out_d[o] >= best[k - 1] or best[k - 1] <= worst):
                        break  # r_k here is known, or cannot raise the maximum
                    e = out_id[o]
                    if is_seg:
                        d = _point_segment(
                            px, py, xy[e, 0], xy[e, 1], xy[e, 2] - xy[e, 0], xy[e, 3] - xy[e, 1]
                        )
                    else:
                        ddx = xy[e, 0] - px
                        ddy = xy[e, 1] - py
                        d = math.sqrt(ddx * ddx + ddy * ddy)
                    if count < k or d < best[k - 1]:  # insert into the sorted top k
                        p = count if count < k else k - 1
                        if count < k:
                            count += 1
                        while p > 0 and best[p - 1] > d:
                            best[p] = best[p - 1]
                            p -= 1
                        best[p] = d
                if count == k and (whole or best[k - 1] <= reach):
                    worst = max(worst, best[k - 1])
                elif whole:
                    worst = np.inf  # fewer than k items in all
                else:
                    complete = False
                    break
            if not complete:
                break
        if complete:
            return worst + 0.5 * math.sqrt(sx * sx + sy * sy), reach, stamp
        reach *= 2.0


@nb.njit(cache=True, error_model="numpy")
def _within(xa, ya, xb, yb, rho, index, xy, is_seg, mark, stamp, out_id, out_d):
    """Ids (unsorted) of the items within ``rho`` of the rectangle."""
    n, _ = _collect(xa, ya, xb, yb, rho, index, xy, is_seg, mark, stamp, out_id, out_d)
    m = 0
    for j in range(n):
        if out_d[j] <= rho:
            out_id[m] = out_id[j]
            m += 1
    return out_id[:m].copy()


@nb.njit(cache=True, error_model="numpy")
def _any_within(rects, rhos, index, xy, is_seg):
    """(T,) whether any item lies within ``rhos[t]`` of rectangle ``rects[t]``."""
    ny = index.grid.ny
    cell_start = index.cell_start
    items = index.items
    out = np.zeros(rects.shape[0], np.bool_)
    for t in range(rects.shape[0]):
        xa, ya, xb, yb = rects[t, 0], rects[t, 1], rects[t, 2], rects[t, 3]
        ix0, ix1, iy0, iy1, _ = _cells_around(xa, ya, xb, yb, rhos[t], index.grid)
        found = False
        for ix in range(ix0, ix1 + 1):
            for iy in range(iy0, iy1 + 1):
                c = ix * ny + iy
                for e in range(cell_start[c], cell_start[c + 1]):
                    if _item_rect(xy, is_seg, items[e], xa, ya, xb, yb) <= rhos[t]:
                        found = True
                        break
                if found:
                    break
            if found:
                break
        out[t] = found
    return out


class Scratch:
    """Work buffers of the support queries: ``mark`` (n,) deduplicates segments listed in several cells
    (an item is seen when ``mark[i] == stamp``; each query takes fresh stamps, so nothing is reset)."""

    def __init__(self, n: int) -> None:
        self.mark = np.zeros(n, np.int64)
        self.ids = np.empty(n, np.int64)
        self.d = np.empty(n)
        self.best = np.empty(MAX_K)
        self.stamp = 1
        self.reach_m = 0.0  # the reach that sufficed for the last tile: where the next one starts


def subdivisions(rect: FloatArray, spacing_m: float = SAMPLE_SPACING_M) -> int:
    """Sub-cells per side of the r_k samples of a tile rectangle (xa, ya, xb, yb)."""
    extent = max(float(rect[2] - rect[0]), float(rect[3] - rect[1]))
    return int(min(max(math.ceil(extent / spacing_m - 1e-9), 1), MAX_SUBDIVISIONS))


@dataclass(frozen=True)
class SupportIndex:
    """Beams binned in a coarse uniform grid (cells of ``cell_m``) for support and change queries.

    ``hit_xy`` (H, 2) occupied endpoints and ``hit_beam`` (H,) their beams; ``seg_xy`` (M, 4) free segments
    (laser origin, end of the free part), one per beam, as the mapper's neighbour search sees them."""

    beams: Beams
    cell_m: float
    hit_xy: FloatArray
    hit_beam: IntArray
    seg_xy: FloatArray
    point_index: GridIndex
    segment_index: GridIndex

    @classmethod
    def build(cls, beams: Beams, cell_m: float) -> SupportIndex:
        if not cell_m > 0:
            raise ValueError(f"support index cell must be positive, got {cell_m}")
        hit_beam = np.flatnonzero(beams.is_hit).astype(np.int64)
        hit_xy = np.ascontiguousarray(beams.ends_xy_m[hit_beam])
        seg_xy = np.ascontiguousarray(np.column_stack([beams.origins_xy_m, beams.free_ends_xy_m]))
        return cls(
            beams=beams,
            cell_m=float(cell_m),
            hit_xy=hit_xy,
            hit_beam=hit_beam,
            seg_xy=seg_xy,
            point_index=build_point_index(hit_xy, cell_m),
            segment_index=build_segment_index(seg_xy[:, :2], seg_xy[:, 2:], cell_m),
        )

    def __len__(self) -> int:
        return len(self.beams)

    def _args(self, kind: str) -> tuple:
        """(index for compiled code, item coordinates, whether the items are segments) of ``kind``."""
        if kind == "occ":
            return self.point_index.packed, self.hit_xy, False
        return self.segment_index.packed, self.seg_xy, True

    def scratch(self) -> Scratch:
        """Work buffers for the queries below (as long as the index has items), reusable across calls."""
        return Scratch(max(self.hit_xy.shape[0], self.seg_xy.shape[0], 1))

    def kth_distance(
        self, point_xy_m: FloatArray, k: int, kind: str, scratch: Scratch | None = None
    ) -> float:
        """Exact distance from a point to its ``k``-th nearest endpoint (``kind="occ"``) or free segment
        (``"free"``); inf when there are fewer than ``k``."""
        s = scratch or self.scratch()
        d, s.stamp = _kth_distance(
            float(point_xy_m[0]), float(point_xy_m[1]), int(k), *self._args(kind), s.mark, s.stamp, s.ids, s.d
        )
        return float(d)

    def tile_radii(
        self, rect: FloatArray, k_occ: int, k_free: int, scratch: Scratch | None = None
    ) -> tuple[float, float]:
        """``(rho_occ, rho_free)`` of a tile whose cell centres fill ``rect`` (xa, ya, xb, yb): upper bounds
        of the k-th neighbour distance of any of its queries, slack included (inf with fewer than k items)."""
        s = scratch or self.scratch()
        xa, ya, xb, yb = (float(v) for v in rect)
        n = subdivisions(rect)
        out = []
        for k, kind in ((k_occ, "occ"), (k_free, "free")):
            if not 1 <= k <= MAX_K:
                raise ValueError(f"neighbour count {k} outside 1..{MAX_K}")
            start = 0.5 * s.reach_m if s.reach_m > 0 else 0.25 * self.cell_m
            rho, s.reach_m, s.stamp = _tile_radius(
                xa, ya, xb, yb, n, int(k), start, *self._args(kind), s.mark, s.stamp, s.ids, s.d, s.best
            )
            out.append(float(rho) + RADIUS_SLACK_M)
        return out[0], out[1]

    def support(
        self, rect: FloatArray, rho_occ: float, rho_free: float, scratch: Scratch | None = None
    ) -> IntArray:
        """Beam ids, sorted (i.e. in their original order), whose endpoint lies within ``rho_occ`` or whose
        free segment lies within ``rho_free`` of ``rect`` (xa, ya, xb, yb)."""
        s = scratch or self.scratch()
        xa, ya, xb, yb = (float(v) for v in rect)
        hits = _within(xa, ya, xb, yb, float(rho_occ), *self._args("occ"), s.mark, s.stamp, s.ids, s.d)
        segs = _within(xa, ya, xb, yb, float(rho_free), *self._args("free"), s.mark, s.stamp + 1, s.ids, s.d)
        s.stamp += 2
        return np.union1d(self.hit_beam[hits], segs)

    def any_within(self, rects: FloatArray, rho_occ: FloatArray, rho_free: FloatArray) -> NDArray[np.bool_]:
        """(T,) whether any endpoint lies within ``rho_occ[t]`` or any free segment within ``rho_free[t]`` of
        rectangle ``rects[t]`` ((T, 4) xa, ya, xb, yb)."""
        r = np.ascontiguousarray(rects, dtype=np.float64).reshape(-1, 4)
        if len(self.beams) == 0:
            return np.zeros(r.shape[0], bool)
        occ = _any_within(r, np.ascontiguousarray(rho_occ, np.float64), *self._args("occ"))
        free = _any_within(r, np.ascontiguousarray(rho_free, np.float64), *self._args("free"))
        return occ | free


# ---------------------------------------------------------------------------------------------------------
# Beams as a whole: concatenation (added scans), displacement and merging (moved scans). Written against the
# dataclass's fields so that fields added to :class:`Beams` (e.g. by GPPOL) follow.


def _per_beam_fields(beams: Beams) -> tuple[list[str], list[str]]:
    """Names of the per-beam array fields of ``beams`` and of the shared ones (e.g. a mounting)."""
    empty = beams.subset(np.zeros(0, np.int64))
    per, shared = [], []
    for f in fields(beams):
        v = getattr(empty, f.name)
        full = getattr(beams, f.name)
        if isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == 0 and full.shape[0] == len(beams):
            per.append(f.name)
        else:
            shared.append(f.name)
    return per, shared


def concat_beams(a: Beams, b: Beams) -> Beams:
    """The beams of ``a`` followed by those of ``b`` (shared fields must agree)."""
    per, shared = _per_beam_fields(a)
    for name in shared:
        va, vb = getattr(a, name), getattr(b, name)
        same = np.array_equal(va, vb) if isinstance(va, np.ndarray) else va == vb
        if not same:
            raise ValueError(f"cannot join beams with different {name}: {va!r} and {vb!r}")
    kw = {name: np.concatenate([getattr(a, name), getattr(b, name)]) for name in per}
    kw.update({name: getattr(a, name) for name in shared})
    return type(a)(**kw)


def check_same_beams(old: Beams, new: Beams) -> None:
    """``new`` must be ``old``'s beams (same scans, beams and order), possibly at other poses."""
    if len(old) != len(new) or not (
        np.array_equal(old.scan_index, new.scan_index) and np.array_equal(old.beam_index, new.beam_index)
    ):
        raise ValueError(
            f"the new beams ({len(new)}) are not the old beams ({len(old)}) at other poses: scans or beams "
            "differ (use add_scans for new scans)"
        )


def beam_displacement_m(old: Beams, new: Beams) -> FloatArray:
    """(M,) largest move of a beam's origin, end or free end between ``old`` and ``new`` (same beams)."""
    check_same_beams(old, new)
    d = np.zeros(len(old))
    for name in ("origins_xy_m", "ends_xy_m", "free_ends_xy_m"):
        a, b = getattr(old, name), getattr(new, name)
        d = np.maximum(d, np.hypot(a[:, 0] - b[:, 0], a[:, 1] - b[:, 1]))
    return d


def merge_beams(old: Beams, new: Beams, take_new: NDArray[np.bool_]) -> Beams:
    """Per beam, ``new`` where ``take_new`` else ``old`` (same beams)."""
    check_same_beams(old, new)
    per, shared = _per_beam_fields(old)
    m = np.asarray(take_new, bool)
    kw = {}
    for name in per:
        a, b = getattr(old, name), getattr(new, name)
        kw[name] = np.where(m.reshape((-1,) + (1,) * (a.ndim - 1)), b, a)
    kw.update({name: getattr(new, name) for name in shared})
    return type(old)(**kw)
