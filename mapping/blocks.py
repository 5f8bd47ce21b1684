"""Neighbour search shared by a block of nearby queries: one range search per block, not one k-NN per query.

A map's queries come in compact groups (the cells of a tile). For a block of queries within ``h`` of a
centre ``c`` whose k-th nearest item lies at ``d_c``, every query ``q`` has its k-th nearest within
``B_q <= d_c + |q - c|`` (the centre's k nearest are that close to it), so each of its k nearest lies within
``R = d_c + 2 h`` of the centre (triangle inequality; a point-to-segment distance obeys it too). The block
lists the items within ``R`` once (a segment crossing several index cells once); each query measures them
all and offers those within ``B_q``, measured on the centre's k nearest, to its top k. The result is exact:
the k nearest the per-query search of :mod:`mapping.index` finds, nearest first; where several items lie at
exactly the same distance (the beams of one fan at their common start) the two may keep different ones.

Far from the data (the k-th neighbour metres away) a per-query search scans every index cell within its
k-th distance, for every query; here that scan is done once per block, and a query measures the k nearest
plus the shell between ``d_c`` and ``R``. Where the data are dense and the index cells small, that shell
holds far more items than a query's own k, and the per-query search, bounded within dense cells, is
cheaper: blocks whose range search would screen more than :data:`MAX_ENTRY_RATIO` times the index entries
of one query's search, blocks smaller than :data:`MIN_BLOCK` queries and blocks whose range search would
list more than :data:`MAX_CANDIDATES` items use the per-query search.

:func:`chunk_neighbours` is the driver (it allocates); the per-block and per-query steps allocate nothing
and are compiled without reference counting (see :mod:`mapping.core`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np
from numpy.typing import NDArray

from mapping.index import (
    _cell_d2,
    _cell_segment_d2,
    _insert,
    _segment_d2,
    _square,
    knn_points,
    knn_segments,
)

#: Side of a block (m): queries of a chunk are grouped by the square of this side they fall in, counted
#: from the chunk's lower-left query. At a 0.1 m map resolution a block holds 6 x 6 cells.
BLOCK_M = 0.6
#: Fewer queries than this in a block: each is searched alone (warm-started from the previous one).
MIN_BLOCK = 4
#: A block whose range search lists more items than this (queries far from all data) searches per query.
MAX_CANDIDATES = 65536
#: A block is searched as one only where its range search screens at most this many times the index entries
#: one query's search screens: index cells much larger than the block (a big building's sparse beams), or
#: the k-th nearest far compared with the block. Where the data are dense and the index cells small, the
#: shell between d_c and R lists far more items than a query's own k, and each query's search is cheaper.
MAX_ENTRY_RATIO = 4.0


# ---------------------------------------------------------------------------------------------------------
# Range searches around a block's centre: every item within r, with its exact squared distance.


@nb.njit(cache=True, error_model="numpy", inline="always")
def _keep(raw_d2, raw_id, n, d2, i, r2):
    """Count item i at squared distance d2 if within r2, listing it while ``raw_d2`` has room; the count."""
    if d2 <= r2:
        if n < raw_d2.shape[0]:
            raw_d2[n] = d2
            raw_id[n] = i
        n += 1
    return n


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def _points_within(cx, cy, r, points, raw_d2, raw_id):
    """The points of ``points`` (a :class:`mapping.index.PointSet`) within ``r`` of (cx, cy) into
    ``raw_d2`` / ``raw_id``; returns their number (only the first ``raw_d2.size`` are written)."""
    pts = points.xy
    cell_start = points.index.cell_start
    grid = points.index.grid
    cell = grid.cell
    gx = (cx - grid.x0) / cell
    gy = (cy - grid.y0) / cell
    r2 = r * r
    n = 0
    lo_x, hi_x, lo_y, hi_y = _square(gx, gy, r / cell, grid.nx, grid.ny)
    for ix in range(lo_x, hi_x + 1):
        for iy in range(lo_y, hi_y + 1):
            if _cell_d2(gx, gy, ix, iy) * cell * cell > r2:
                continue
            c = ix * grid.ny + iy
            for i in range(cell_start[c], cell_start[c + 1]):
                dx = pts[i, 0] - cx
                dy = pts[i, 1] - cy
                n = _keep(raw_d2, raw_id, n, dx * dx + dy * dy, i, r2)
    return n


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def _segments_within(cx, cy, r, segments, buf, raw_d2, raw_id):
    """The segments of ``segments`` (a :class:`mapping.index.SegmentSet`) within ``r`` of (cx, cy) into
    ``raw_d2`` / ``raw_id``, once per index cell that lists them (so possibly repeated); returns their
    number (only the first ``raw_d2.size`` are written). Each cell is screened in float32 with a 0.1 mm
    margin (as :func:`mapping.index.knn_segments` does), the survivors measured exactly."""
    seg = segments.seg
    entries = segments.entries
    cell_start = segments.index.cell_start
    items = segments.index.items
    grid = segments.index.grid
    cell = grid.cell
    gx = (cx - grid.x0) / cell
    gy = (cy - grid.y0) / cell
    r2 = r * r
    lim = r + 1e-4
    lim2 = np.float32(lim * lim)
    n = 0
    lo_x, hi_x, lo_y, hi_y = _square(gx, gy, r / cell, grid.nx, grid.ny)
    for ix in range(lo_x, hi_x + 1):
        for iy in range(lo_y, hi_y + 1):
            c = ix * grid.ny + iy
            start = cell_start[c]
            end = cell_start[c + 1]
            if start == end or _cell_d2(gx, gy, ix, iy) * cell * cell > r2:
                continue
            ccx = grid.x0 + (ix + 0.5) * cell
            ccy = grid.y0 + (iy + 0.5) * cell
            _cell_segment_d2(np.float32(cx - ccx), np.float32(cy - ccy), entries, start, end, buf)
            for e in range(start, end):
                if buf[e - start] > lim2:
                    continue
                i = items[e]
                d2, _ = _segment_d2(cx, cy, seg, i)
                n = _keep(raw_d2, raw_id, n, d2, i, r2)
    return n


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def _unique(raw_id, n, table_id, table_gen, gen, out_id):
    """The first n ids of ``raw_id`` with repeats dropped (first copy kept) into ``out_id``; returns their
    number. ``table_id`` / ``table_gen``
    (a power of two, at least 2 n long): an open-addressing set whose slots count as empty unless their
    generation is ``gen`` (a new one per call), so that it is never cleared."""
    mask = table_id.shape[0] - 1
    m = 0
    for j in range(n):
        i = raw_id[j]
        h = (i * 2654435761) & mask
        while table_gen[h] == gen and table_id[h] != i:
            h = (h + 1) & mask
        if table_gen[h] == gen:
            continue
        table_gen[h] = gen
        table_id[h] = i
        out_id[m] = i
        m += 1
    return m


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def _entries_within(index, cx, cy, r):
    """How many entries the index cells of the square of half-side ``r`` around (cx, cy) list: what a
    search out to ``r`` screens (one sum per column of cells)."""
    grid = index.grid
    gx = (cx - grid.x0) / grid.cell
    gy = (cy - grid.y0) / grid.cell
    lo_x, hi_x, lo_y, hi_y = _square(gx, gy, r / grid.cell, grid.nx, grid.ny)
    total = 0
    if lo_y > hi_y:
        return total
    for ix in range(lo_x, hi_x + 1):
        total += index.cell_start[ix * grid.ny + hi_y + 1] - index.cell_start[ix * grid.ny + lo_y]
    return total


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def _worth_a_block(index, cx, cy, d_c, h, entry_ratio):
    """Whether a block (centre (cx, cy), radius h, the centre's k-th nearest at d_c) is searched as one:
    when its range search screens at most ``entry_ratio`` times the entries one query's search does."""
    return _entries_within(index, cx, cy, d_c + 2.0 * h) <= entry_ratio * _entries_within(index, cx, cy, d_c)


# ---------------------------------------------------------------------------------------------------------
# One query of a block, against the block's candidates.


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def _query_points(qx, qy, pts, k, cen_id, cand, cand_id, m, qd2, best_d2, best_id, best_t):
    """The k points nearest (qx, qy) among a block's ``m`` candidates (``cand`` (2, m): x, y; ids
    ``cand_id``), nearest first; returns the count (k). Only candidates within the bound of the block
    centre's k nearest ``cen_id`` are offered. ``qd2``: scratch."""
    bound = 0.0
    for j in range(k):
        i = cen_id[j]
        dx = pts[i, 0] - qx
        dy = pts[i, 1] - qy
        bound = max(bound, dx * dx + dy * dy)
    for c in range(m):
        dx = cand[0, c] - qx
        dy = cand[1, c] - qy
        qd2[c] = dx * dx + dy * dy
    count = 0
    for c in range(m):
        d2 = qd2[c]
        if d2 <= bound:
            count = _insert(best_d2, best_id, best_t, count, k, d2, cand_id[c], 0.0)
    return count


@nb.njit(cache=True, error_model="numpy", _nrt=False)
def _query_segments(qx, qy, seg, k, cen_id, cand, cand_id, m, qd2, qt, best_d2, best_id, best_t):
    """The k segments nearest (qx, qy) among a block's ``m`` candidates (``cand`` (5, m): their rows of
    ``seg`` transposed; ids ``cand_id``), nearest first, with the clamped parameter t of each closest
    point (eqs. 13-14); returns the count (k). Only candidates within the bound of the block centre's k
    nearest ``cen_id`` are offered. ``qd2``, ``qt``: scratch."""
    bound = 0.0
    for j in range(k):
        d2, _ = _segment_d2(qx, qy, seg, cen_id[j])
        bound = max(bound, d2)
    for c in range(m):  # _segment_d2's arithmetic on the transposed rows (vectorised)
        rx = qx - cand[0, c]
        ry = qy - cand[1, c]
        t = min(max((rx * cand[2, c] + ry * cand[3, c]) * cand[4, c], 0.0), 1.0)
        ex = rx - t * cand[2, c]
        ey = ry - t * cand[3, c]
        qd2[c] = ex * ex + ey * ey
        qt[c] = t
    count = 0
    for c in range(m):
        d2 = qd2[c]
        if d2 <= bound:
            count = _insert(best_d2, best_id, best_t, count, k, d2, cand_id[c], qt[c])
    return count


# ---------------------------------------------------------------------------------------------------------
# One block: the centre's k nearest, the items within R listed once, then each query.


class _Scratch(NamedTuple):
    """A block's candidates: the range search's raw (squared distance, id) pairs, the unique ids ``ids``,
    their coordinates ``cand`` (5, n) (a point's x, y; a segment's
    row of ``seg``), a query's distances ``qd2`` and parameters ``qt``, and the set of ids seen
    (:func:`_unique`)."""

    raw_d2: NDArray[np.float64]
    raw_id: NDArray[np.int64]
    ids: NDArray[np.int64]
    cand: NDArray[np.float64]
    qd2: NDArray[np.float64]
    qt: NDArray[np.float64]
    table_id: NDArray[np.int64]
    table_gen: NDArray[np.int64]


@nb.njit(cache=True, error_model="numpy")
def _scratch(n):
    """Block scratch for n candidates."""
    size = 1
    while size < 2 * n:
        size *= 2
    return _Scratch(
        np.empty(n), np.empty(n, np.int64), np.empty(n, np.int64), np.empty((5, n)),
        np.empty(n), np.empty(n), np.empty(size, np.int64), np.zeros(size, np.int64),
    )  # fmt: skip


@nb.njit(cache=True, error_model="numpy")
def _fit(sc, n):
    """``sc`` if it holds n candidates, else larger scratch."""
    if sc.raw_d2.shape[0] >= n:
        return sc
    return _scratch(max(n, 2 * sc.raw_d2.shape[0]))


@nb.njit(cache=True, error_model="numpy")
def _block_points(queries, lo, members, cx, cy, h, points, k, cen, sc, max_candidates, ido, no, d2, ids, tt):
    """The k nearest endpoints of the block's queries ``lo + members`` (centre (cx, cy), radius h) from
    the points within ``R`` of the centre, the centre's k nearest ``cen`` at squared distances ``d2``
    (module docstring); returns whether it did (not when more than ``max_candidates`` points lie within
    R) and the scratch, grown if it had to."""
    pts = points.xy
    r = math.sqrt(d2[k - 1]) + 2.0 * h + 1e-9
    m = _points_within(cx, cy, r, points, sc.raw_d2, sc.raw_id)
    if m > max_candidates:
        return False, sc
    if m > sc.raw_d2.shape[0]:
        sc = _fit(sc, m)
        m = _points_within(cx, cy, r, points, sc.raw_d2, sc.raw_id)
    for c in range(m):  # a point is listed in one cell: no repeats
        sc.cand[0, c] = pts[sc.raw_id[c], 0]
        sc.cand[1, c] = pts[sc.raw_id[c], 1]
    for j in members:
        qx = queries[lo + j, 0]
        qy = queries[lo + j, 1]
        no[j] = _query_points(qx, qy, pts, k, cen, sc.cand, sc.raw_id, m, sc.qd2, d2, ids, tt)
        ido[j, : no[j]] = ids[: no[j]]
    return True, sc


@nb.njit(cache=True, error_model="numpy")
def _block_segments(
    queries, lo, members, cx, cy, h, segments, k, cen, sc, gen, max_candidates, sbuf, idf, tf, nf, d2, ids, tt
):  # fmt: skip
    """:func:`_block_points` for the free segments, each listed once (``gen``: a new generation of the
    scratch's id set); returns whether it did and the scratch."""
    seg = segments.seg
    r = math.sqrt(d2[k - 1]) + 2.0 * h + 1e-9
    nraw = _segments_within(cx, cy, r, segments, sbuf, sc.raw_d2, sc.raw_id)
    if nraw > max_candidates:
        return False, sc
    if nraw > sc.raw_d2.shape[0]:
        sc = _fit(sc, nraw)
        nraw = _segments_within(cx, cy, r, segments, sbuf, sc.raw_d2, sc.raw_id)
    m = _unique(sc.raw_id, nraw, sc.table_id, sc.table_gen, gen, sc.ids)
    for c in range(m):
        for col in range(5):
            sc.cand[col, c] = seg[sc.ids[c], col]
    for j in members:
        qx = queries[lo + j, 0]
        qy = queries[lo + j, 1]
        nf[j] = _query_segments(qx, qy, seg, k, cen, sc.cand, sc.ids, m, sc.qd2, sc.qt, d2, ids, tt)
        idf[j, : nf[j]] = ids[: nf[j]]
        tf[j, : nf[j]] = tt[: nf[j]]
    return True, sc


# ---------------------------------------------------------------------------------------------------------
# The driver.


@nb.njit(cache=True, error_model="numpy")
def _block_keys(queries, lo, hi, block_m):
    """The block of each of ``queries[lo:hi]``: squares of ``block_m`` counted from the lower-left query."""
    n = hi - lo
    x0 = np.inf
    y0 = np.inf
    for j in range(n):
        x0 = min(x0, queries[lo + j, 0])
        y0 = min(y0, queries[lo + j, 1])
    bx = np.empty(n, np.int64)
    by = np.empty(n, np.int64)
    span_y = 1
    for j in range(n):
        bx[j] = math.floor((queries[lo + j, 0] - x0) / block_m)
        by[j] = math.floor((queries[lo + j, 1] - y0) / block_m)
        span_y = max(span_y, by[j] + 1)
    return bx * span_y + by


@nb.njit(cache=True, error_model="numpy")
def _centre(queries, lo, members):
    """Centre of the bounding box of the queries ``lo + members`` and their largest distance from it."""
    xmin = np.inf
    xmax = -np.inf
    ymin = np.inf
    ymax = -np.inf
    for j in members:
        xmin = min(xmin, queries[lo + j, 0])
        xmax = max(xmax, queries[lo + j, 0])
        ymin = min(ymin, queries[lo + j, 1])
        ymax = max(ymax, queries[lo + j, 1])
    cx = 0.5 * (xmin + xmax)
    cy = 0.5 * (ymin + ymax)
    h = 0.0
    for j in members:
        hx = queries[lo + j, 0] - cx
        hy = queries[lo + j, 1] - cy
        h = max(h, math.sqrt(hx * hx + hy * hy))
    return cx, cy, h


@nb.njit(cache=True, error_model="numpy")
def chunk_neighbours(
    queries, lo, hi, points, segments, k_occ, k_free, ido, no, idf, tf, nf, block_m=BLOCK_M,
    max_candidates=MAX_CANDIDATES, entry_ratio=MAX_ENTRY_RATIO,
):  # fmt: skip
    """The ``k_occ`` nearest endpoints and ``k_free`` nearest free segments of each of ``queries[lo:hi]``
    (exact, as :func:`mapping.index.knn_points` / :func:`mapping.index.knn_segments` find them): query
    ``lo + j`` gets ``no[j]`` endpoint ids in ``ido[j]`` and ``nf[j]`` segment ids in ``idf[j]`` with the
    parameters of their closest points in ``tf[j]``, nearest first. Queries are searched in blocks of
    ``block_m`` (module docstring), a block of fewer than :data:`MIN_BLOCK` queries or whose range search
    lists more than ``max_candidates`` items or would screen more than ``entry_ratio`` times the index
    entries of one query's search query by query."""
    n = hi - lo
    if n == 0:
        return
    kmax = max(k_occ, k_free, 1)
    d2 = np.empty(kmax)
    ids = np.empty(kmax, np.int64)
    tt = np.empty(kmax)
    warm_o = np.empty(max(k_occ, 1), np.int64)  # warm starts of the per-query searches
    warm_f = np.empty(max(k_free, 1), np.int64)
    cen_o = np.empty(max(k_occ, 1), np.int64)  # the last block centre's neighbours
    cen_f = np.empty(max(k_free, 1), np.int64)
    pbuf = np.empty(max(points.index.most, 1))
    sbuf = np.empty(max(segments.index.most, 1), np.float32)
    scand = np.empty((3, max(segments.index.most, 1)))
    sc = _scratch(1024)
    keys = _block_keys(queries, lo, hi, block_m)
    order = np.argsort(keys, kind="mergesort")
    nwo = 0
    nwf = 0
    nco = 0
    ncf = 0
    gen = 0
    s = 0
    while s < n:
        e = s + 1
        while e < n and keys[order[e]] == keys[order[s]]:
            e += 1
        members = order[s:e]
        done_o = False
        done_f = False
        if e - s >= MIN_BLOCK:
            cx, cy, h = _centre(queries, lo, members)
            if k_occ > 0:
                nco = knn_points(cx, cy, points, k_occ, d2, ids, tt, cen_o, nco, pbuf)
                cen_o[:nco] = ids[:nco]
                if nco == k_occ and _worth_a_block(
                    points.index, cx, cy, math.sqrt(d2[k_occ - 1]), h, entry_ratio
                ):
                    done_o, sc = _block_points(
                        queries, lo, members, cx, cy, h, points, k_occ, cen_o, sc, max_candidates, ido, no,
                        d2, ids, tt,
                    )  # fmt: skip
            if k_free > 0:
                ncf = knn_segments(cx, cy, segments, k_free, d2, ids, tt, cen_f, ncf, sbuf, scand)
                cen_f[:ncf] = ids[:ncf]
                if ncf == k_free and _worth_a_block(
                    segments.index, cx, cy, math.sqrt(d2[k_free - 1]), h, entry_ratio
                ):
                    gen += 1
                    done_f, sc = _block_segments(
                        queries, lo, members, cx, cy, h, segments, k_free, cen_f, sc, gen, max_candidates,
                        sbuf, idf, tf, nf, d2, ids, tt,
                    )  # fmt: skip
        for j in members:
            qx = queries[lo + j, 0]
            qy = queries[lo + j, 1]
            if not done_o:
                no[j] = knn_points(qx, qy, points, k_occ, d2, ids, tt, warm_o, nwo, pbuf)
                ido[j, : no[j]] = ids[: no[j]]
            if not done_f:
                nf[j] = knn_segments(qx, qy, segments, k_free, d2, ids, tt, warm_f, nwf, sbuf, scand)
                idf[j, : nf[j]] = ids[: nf[j]]
                tf[j, : nf[j]] = tt[: nf[j]]
            nwo = no[j]
            warm_o[:nwo] = ido[j, :nwo]
            nwf = nf[j]
            warm_f[:nwf] = idf[j, :nwf]
        s = e
