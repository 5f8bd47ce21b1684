"""Rendering one tile from its exact support (paper section 5.1: query evaluation is embarrassingly parallel).

A :class:`RenderJob` holds everything a tile needs and nothing per tile, so that an engine ships it to its
workers once (:mod:`pipeline.scale`); :func:`render_tile` selects the tile's support
(:meth:`mapping.tiling.support.SupportIndex.support`), builds a map object of only those beams with the
job's ``factory`` and queries the tile's cell centres. Memory per tile is bounded by the data near the tile,
not by the map.

The factory is any callable ``(beams, cov_xytheta) -> map`` whose map has ``query(points, sort=False)``
returning mean, variance and probability (:class:`mapping.gpmap.GPOccupancyMap` and the GPPOL map alike;
``cov_xytheta`` (N, 3, 3) are the per-scan pose covariances indexed by ``beams.scan_index``, None for GPFOL).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from mapping.beams import Beams
from mapping.tiling.grid import TileGrid
from mapping.tiling.support import Scratch, SupportIndex

FloatArray = NDArray[np.float64]
MapFactory = Callable[[Beams, FloatArray | None], Any]
LAYERS = ("probability", "mean", "variance")


@dataclass(frozen=True)
class RenderJob:
    """What every tile of one rendering shares: the indexed beams, the grid, the map factory, the per-scan
    pose covariances (or None) and the neighbour counts of the mapper."""

    index: SupportIndex
    grid: TileGrid
    factory: MapFactory
    cov_xytheta: FloatArray | None
    k_occ: int
    k_free: int


@dataclass(frozen=True)
class TileResult:
    """One rendered tile: float32 (h, w) layers, the support radii ``r_occ_m`` / ``r_free_m`` of the tile
    (see :mod:`mapping.tiling.support`), the number of beams in its support and the seconds it took."""

    tile: int
    probability: NDArray[np.float32]
    mean: NDArray[np.float32]
    variance: NDArray[np.float32]
    r_occ_m: float
    r_free_m: float
    support_beams: int
    seconds: float


def render_tile(job: RenderJob, tile: int, scratch: Scratch | None = None) -> TileResult:
    """Render ``tile`` of ``job.grid`` from its exact support."""
    t0 = time.perf_counter()
    scratch = scratch or job.index.scratch()
    rect = job.grid.rects([tile])[0]
    r_occ, r_free = job.index.tile_radii(rect, job.k_occ, job.k_free, scratch)
    ids = job.index.support(rect, r_occ, r_free, scratch)
    gp = job.factory(job.index.beams.subset(ids), job.cov_xytheta)
    pred = gp.query(job.grid.cell_centres(tile), sort=False)
    shape = job.grid.tile_shape(tile)
    return TileResult(
        tile=int(tile),
        probability=pred.probability.reshape(shape).astype(np.float32),
        mean=pred.mean.reshape(shape).astype(np.float32),
        variance=pred.variance.reshape(shape).astype(np.float32),
        r_occ_m=r_occ,
        r_free_m=r_free,
        support_beams=int(ids.size),
        seconds=time.perf_counter() - t0,
    )


class TileRenderer(Protocol):
    """An engine: renders ``tiles`` of ``job`` and yields their results in any order."""

    def __call__(self, job: RenderJob, tiles: Iterable[int]) -> Iterator[TileResult]: ...


#: The in-process engine renders tiles one at a time up to this share of the grid's tiles, and beyond it
#: through one map of all beams (:func:`render_batched`): each tile's own map rebuilds its support's neighbour
#: index and input Gaussians, which on a building-sized map re-render costs several times the whole map's
#: single rendering, while a few tiles (an incremental update) cost less than building the whole map.
BATCH_SHARE = 0.05
#: Cells queried at once by :func:`render_batched` (bounds its memory on a map of any size).
BATCH_CELLS = 4_000_000


def render_per_tile(job: RenderJob, tiles: Iterable[int]) -> Iterator[TileResult]:
    """One tile after another, each from its own support (each tile's queries run on numba's threads)."""
    scratch = job.index.scratch()
    for t in tiles:
        yield render_tile(job, int(t), scratch)


def render_batched(job: RenderJob, tiles: Iterable[int]) -> Iterator[TileResult]:
    """The tiles' cells queried on one map of all of ``job``'s beams, :data:`BATCH_CELLS` cells at a time.
    A tile's support holds every beam its cells' neighbour searches can find, so this is the map that
    :func:`render_per_tile` gives, except that a cell beyond the reach of every input of a tile's support
    reads the prior there and may be solved here (unknown either way, :mod:`mapping.reach`).
    No tile has a support of its own here: the results carry NaN radii and 0 support beams, and
    :class:`mapping.tiling.IncrementalMap` computes the radii when an update first needs them (a map that
    is only written out never pays for them)."""
    tiles = [int(t) for t in tiles]
    if not tiles:
        return
    t0 = time.perf_counter()
    gp = job.factory(job.index.beams, job.cov_xytheta)
    build_s = time.perf_counter() - t0
    start = 0
    while start < len(tiles):
        group = [tiles[start]]
        cells = int(np.prod(job.grid.tile_shape(tiles[start])))
        while start + len(group) < len(tiles):
            more = int(np.prod(job.grid.tile_shape(tiles[start + len(group)])))
            if cells + more > BATCH_CELLS:
                break
            group.append(tiles[start + len(group)])
            cells += more
        start += len(group)
        t1 = time.perf_counter()
        centres = [job.grid.cell_centres(t) for t in group]
        pred = gp.query(np.concatenate(centres), sort=False)
        share_s = (time.perf_counter() - t1 + build_s * cells / max(1, job.grid.cells)) / len(group)
        lo = 0
        for t, c in zip(group, centres, strict=True):
            hi = lo + c.shape[0]
            shape = job.grid.tile_shape(t)
            yield TileResult(
                tile=t,
                probability=pred.probability[lo:hi].reshape(shape).astype(np.float32),
                mean=pred.mean[lo:hi].reshape(shape).astype(np.float32),
                variance=pred.variance[lo:hi].reshape(shape).astype(np.float32),
                r_occ_m=float("nan"),
                r_free_m=float("nan"),
                support_beams=0,
                seconds=share_s,
            )
            lo = hi


def render_serial(job: RenderJob, tiles: Iterable[int]) -> Iterator[TileResult]:
    """The in-process engine: :func:`render_per_tile` for a few tiles, :func:`render_batched` beyond
    :data:`BATCH_SHARE` of the grid."""
    tiles = [int(t) for t in tiles]
    if len(tiles) > 1 and len(tiles) > BATCH_SHARE * len(job.grid):
        yield from render_batched(job, tiles)
    else:
        yield from render_per_tile(job, tiles)
