"""Tiled and incremental GP occupancy maps (paper sections 3.7 and 5.1).

The map is cut into tiles (:mod:`~mapping.tiling.grid`), each rendered independently from only the beams that
can influence it (:mod:`~mapping.tiling.support`: an exact support, so a tiled map equals the untiled one), by
any engine (:mod:`~mapping.tiling.render`; in-process here, Dask in :mod:`pipeline.scale`), into memory or a
folder on disk read back lazily (:mod:`~mapping.tiling.store`). :mod:`~mapping.tiling.incremental` re-renders
only the tiles that new scans or moved poses reach.
"""

from mapping.tiling.grid import TileGrid
from mapping.tiling.incremental import IncrementalMap, UpdateReport, default_index_cell_m
from mapping.tiling.render import (
    MapFactory,
    RenderJob,
    TileRenderer,
    TileResult,
    render_batched,
    render_per_tile,
    render_serial,
    render_tile,
)
from mapping.tiling.store import ArraySink, TileStore
from mapping.tiling.support import SupportIndex, beam_displacement_m, concat_beams, merge_beams

__all__ = [
    "ArraySink",
    "IncrementalMap",
    "MapFactory",
    "RenderJob",
    "SupportIndex",
    "TileGrid",
    "TileRenderer",
    "TileResult",
    "TileStore",
    "UpdateReport",
    "beam_displacement_m",
    "concat_beams",
    "default_index_cell_m",
    "merge_beams",
    "render_batched",
    "render_per_tile",
    "render_serial",
    "render_tile",
]
