"""An incrementally updated GP occupancy map (paper section 5.1: "only the query points influenced by the new
observations would need to be updated").

:class:`IncrementalMap` keeps a rendered raster (in memory or in a :class:`~mapping.tiling.store.TileStore`),
the beams it shows and, per tile, the radii of its support (:mod:`mapping.tiling.support`). Two updates:

- :meth:`IncrementalMap.add_scans`: new beams; a tile is re-rendered iff a new endpoint lies within its
  ``rho_occ`` or a new free segment within its ``rho_free`` (radii from the data before, conservative since
  new data only shrink the k-th neighbour distances);
- :meth:`IncrementalMap.update_poses`: the same beams at other poses (a loop closure, ``remap``) and, for
  GPPOL, other pose covariances; a tile is re-rendered iff a beam that changed lay (before) or lies (after)
  within its radii. A beam changed if its origin, end or free end moved by more than ``tolerance_m``, or (when
  the map has covariances) its scan's covariance changed by more than ``cov_tolerance`` in any entry.

In both cases the raster afterwards equals, bit for bit, a full rendering of :attr:`IncrementalMap.beams` (the
tiles that were not re-rendered would have got the same support, hence the same numbers). With tolerances of
0 (the default) those beams are the new ones; with a tolerance, a beam that moved less than it keeps its old
position in :attr:`beams`, so the map stays an exact rendering of beams each within the tolerance of the new
ones.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mapping.beams import Beams
from mapping.exports import MapLayers
from mapping.tiling.grid import TileGrid
from mapping.tiling.render import MapFactory, RenderJob, TileRenderer, TileResult, render_serial
from mapping.tiling.store import ArraySink
from mapping.tiling.support import SupportIndex, beam_displacement_m, concat_beams, merge_beams

FloatArray = NDArray[np.float64]
OnTile = Callable[[TileResult], None] | None


def default_index_cell_m(grid: TileGrid) -> float:
    """Cell of the coarse support index: half a tile, within [0.5, 50] m."""
    return float(np.clip(0.5 * grid.tile_cells * grid.resolution_m, 0.5, 50.0))


@dataclass(frozen=True)
class UpdateReport:
    """What an update did: tiles re-rendered out of the total, beams that changed, wall seconds."""

    tiles_total: int
    tiles_recomputed: int
    changed_beams: int
    seconds: float

    @property
    def fraction_recomputed(self) -> float:
        return self.tiles_recomputed / self.tiles_total if self.tiles_total else 0.0

    def to_dict(self) -> dict:
        return {
            "tiles_total": self.tiles_total,
            "tiles_recomputed": self.tiles_recomputed,
            "fraction_recomputed": self.fraction_recomputed,
            "changed_beams": self.changed_beams,
            "seconds": self.seconds,
        }


class IncrementalMap:
    """A tiled GP map of ``beams`` over ``grid``, updated incrementally (see the module docstring).

    ``factory(beams, cov_xytheta)`` builds the map object of a tile's support (GPFOL or GPPOL, anything with
    ``query``); ``k_occ`` / ``k_free`` must be its neighbour counts. ``cov_xytheta`` (N, 3, 3): per-scan pose
    covariances indexed by ``beams.scan_index`` (None: the mapper does not use them). ``sink``: where tiles go
    (default an in-memory :class:`ArraySink`); ``renderer``: the engine (default in-process, one tile after
    another; :mod:`pipeline.scale` has a Dask one). Nothing is rendered until :meth:`render_all` (or
    :meth:`adopt_rendered` for a raster rendered earlier from the same beams).
    """

    def __init__(
        self,
        beams: Beams,
        grid: TileGrid,
        factory: MapFactory,
        k_occ: int,
        k_free: int,
        cov_xytheta: FloatArray | None = None,
        sink=None,
        renderer: TileRenderer = render_serial,
        index_cell_m: float | None = None,
    ) -> None:
        self.grid = grid
        self.factory = factory
        self.k_occ = int(k_occ)
        self.k_free = int(k_free)
        self.sink = sink if sink is not None else ArraySink(grid)
        self.renderer = renderer
        self.index_cell_m = float(index_cell_m or default_index_cell_m(grid))
        self.rects = grid.rects()
        self.rho_occ = np.full(len(grid), np.nan)
        self.rho_free = np.full(len(grid), np.nan)
        self.support_beams = np.zeros(len(grid), np.int64)
        self.tile_seconds = np.zeros(len(grid))
        self.rendered = np.zeros(len(grid), dtype=bool)  # the sink holds the tile
        self.adopted = False  # the sink holds a rendering made elsewhere (adopt_rendered)
        self.cov_xytheta = None if cov_xytheta is None else np.asarray(cov_xytheta, dtype=np.float64)
        self._set_beams(beams)

    def _set_beams(self, beams: Beams) -> None:
        self.beams = beams
        self.index = SupportIndex.build(beams, self.index_cell_m)

    # -- full rendering -----------------------------------------------------------------------------------
    def render_all(self, on_tile: OnTile = None) -> UpdateReport:
        """Render every tile (``on_tile`` is called with each result, e.g. to report progress)."""
        t0 = time.perf_counter()
        n = self._render(np.arange(len(self.grid)), on_tile)
        return UpdateReport(len(self.grid), n, len(self.beams), time.perf_counter() - t0)

    def adopt_rendered(self) -> None:
        """Declare that the sink already holds a full rendering of :attr:`beams` (same grid, mapper and
        parameters, e.g. a run's map read back). The tiles' radii, which updates need, are computed on the
        first update (a map that is only written out never pays for them)."""
        self.adopted = True
        self.rendered[:] = True

    def ensure_radii(self) -> None:
        """Compute the support radii of the tiles rendered without them (adopted by :meth:`adopt_rendered`,
        or rendered through one map of all beams, :func:`mapping.tiling.render.render_batched`); done by the
        first update."""
        s = self.index.scratch()
        for t in np.flatnonzero(np.isnan(self.rho_occ) & self.rendered):
            radii = self.index.tile_radii(self.rects[t], self.k_occ, self.k_free, s)
            self.rho_occ[t], self.rho_free[t] = radii

    def _render(self, tiles: NDArray[np.int64], on_tile: OnTile = None) -> int:
        job = RenderJob(self.index, self.grid, self.factory, self.cov_xytheta, self.k_occ, self.k_free)
        n = 0
        for r in self.renderer(job, [int(t) for t in tiles]):
            self.sink.write(r)
            self.rho_occ[r.tile] = r.r_occ_m
            self.rho_free[r.tile] = r.r_free_m
            self.support_beams[r.tile] = r.support_beams
            self.tile_seconds[r.tile] = r.seconds
            self.rendered[r.tile] = True
            n += 1
            if on_tile is not None:
                on_tile(r)
        if n != len(tiles):
            raise RuntimeError(f"the renderer returned {n} of {len(tiles)} tiles")
        return n

    def _check_rendered(self) -> None:
        self.ensure_radii()
        if np.isnan(self.rho_occ).any():
            raise RuntimeError("render_all (or adopt_rendered) must come before an incremental update")

    def affected_tiles(self, changed: Beams) -> NDArray[np.int64]:
        """Tiles whose support radii reach any of the ``changed`` beams (their endpoints or free segments)."""
        if len(changed) == 0:
            return np.zeros(0, np.int64)
        idx = SupportIndex.build(changed, self.index_cell_m)
        return np.flatnonzero(idx.any_within(self.rects, self.rho_occ, self.rho_free))

    # -- updates ------------------------------------------------------------------------------------------
    def add_scans(
        self, new_beams: Beams, cov_xytheta: FloatArray | None = None, on_tile: OnTile = None
    ) -> UpdateReport:
        """Add the beams of new scans (appended after the current ones) and re-render the tiles they reach.
        ``cov_xytheta``: the per-scan covariances covering the new scans too (required when the map has
        covariances)."""
        self._check_rendered()
        t0 = time.perf_counter()
        if self.cov_xytheta is not None:
            if cov_xytheta is None:
                raise ValueError("this map uses pose covariances: give them for the new scans too")
            self.cov_xytheta = np.asarray(cov_xytheta, dtype=np.float64)
        tiles = self.affected_tiles(new_beams)
        self._set_beams(concat_beams(self.beams, new_beams))
        self._render(tiles, on_tile)
        return UpdateReport(len(self.grid), len(tiles), len(new_beams), time.perf_counter() - t0)

    def update_poses(
        self,
        beams: Beams,
        cov_xytheta: FloatArray | None = None,
        tolerance_m: float = 0.0,
        cov_tolerance: float = 0.0,
        on_tile: OnTile = None,
    ) -> UpdateReport:
        """The same beams at other poses (and other per-scan covariances): re-render the tiles that a changed
        beam reaches, before or after the change (see the module docstring for the tolerances)."""
        self._check_rendered()
        t0 = time.perf_counter()
        changed = beam_displacement_m(self.beams, beams) > tolerance_m
        new_cov = self.cov_xytheta
        if self.cov_xytheta is not None and cov_xytheta is not None:
            cov = np.asarray(cov_xytheta, dtype=np.float64)
            if cov.shape != self.cov_xytheta.shape:
                raise ValueError(f"covariances of shape {cov.shape}, expected {self.cov_xytheta.shape}")
            scan_changed = np.abs(cov - self.cov_xytheta).reshape(len(cov), -1).max(axis=1) > cov_tolerance
            changed |= scan_changed[beams.scan_index]
            new_cov = np.where(scan_changed[:, None, None], cov, self.cov_xytheta)
        old_changed = self.beams.subset(changed)
        new_changed = beams.subset(changed)
        tiles = self.affected_tiles(concat_beams(old_changed, new_changed))
        self.cov_xytheta = new_cov
        self._set_beams(merge_beams(self.beams, beams, changed))
        self._render(tiles, on_tile)
        return UpdateReport(len(self.grid), len(tiles), int(changed.sum()), time.perf_counter() - t0)

    def layers(self) -> MapLayers:
        """The current map (in-memory sink only)."""
        if not isinstance(self.sink, ArraySink):
            raise TypeError("layers() needs an in-memory sink; read a TileStore with TileStore.open")
        return self.sink.layers()
