"""The tile layout of a rendered map: a raster (SPEC raster convention, :mod:`mapping.exports`) cut into
square tiles of ``tile_cells`` x ``tile_cells`` cells (the last row and column of tiles may be smaller).

Tile ``t`` is at tile row ``t // n_cols`` and tile column ``t % n_cols``. Cell centres are computed exactly as
:func:`mapping.gpmap.grid_centres` computes them for the whole raster (``x0 + (c + 0.5) * resolution``), so a
tile's query points are bit for bit the points of the same cells in an untiled rendering.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
Bounds = tuple[float, float, float, float]


@dataclass(frozen=True)
class TileGrid:
    """A raster of ``shape_hw`` = (H, W) cells of ``resolution_m``, lower-left corner ``origin_xy_m``, cut
    into tiles of ``tile_cells`` cells a side."""

    origin_xy_m: tuple[float, float]
    resolution_m: float
    shape_hw: tuple[int, int]
    tile_cells: int

    def __post_init__(self) -> None:
        if self.tile_cells < 1 or self.resolution_m <= 0 or min(self.shape_hw) < 1:
            raise ValueError(
                f"bad tile grid: tile_cells {self.tile_cells}, resolution {self.resolution_m}, "
                f"shape {self.shape_hw}"
            )

    @classmethod
    def from_bounds(cls, bounds_xy_m: Bounds, resolution_m: float, tile_cells: int) -> TileGrid:
        """The raster :func:`mapping.gpmap.grid_centres` makes of ``bounds_xy_m`` (same origin and shape)."""
        x0, y0, x1, y1 = bounds_xy_m
        if not (x1 > x0 and y1 > y0 and resolution_m > 0):
            raise ValueError(f"bad map bounds {bounds_xy_m} or resolution {resolution_m}")
        w = max(1, math.ceil((x1 - x0) / resolution_m - 1e-9))
        h = max(1, math.ceil((y1 - y0) / resolution_m - 1e-9))
        return cls((float(x0), float(y0)), float(resolution_m), (int(h), int(w)), int(tile_cells))

    @property
    def n_rows(self) -> int:
        """Tile rows."""
        return -(-self.shape_hw[0] // self.tile_cells)

    @property
    def n_cols(self) -> int:
        """Tile columns."""
        return -(-self.shape_hw[1] // self.tile_cells)

    def __len__(self) -> int:
        return self.n_rows * self.n_cols

    def tiles(self) -> range:
        """Every tile id."""
        return range(len(self))

    @property
    def cells(self) -> int:
        return self.shape_hw[0] * self.shape_hw[1]

    def slices(self, tile: int) -> tuple[int, int, int, int]:
        """Raster rows ``r0:r1`` and columns ``c0:c1`` of ``tile``."""
        if not 0 <= tile < len(self):
            raise IndexError(f"tile {tile} outside 0..{len(self) - 1}")
        i, j = divmod(int(tile), self.n_cols)
        t = self.tile_cells
        return i * t, min((i + 1) * t, self.shape_hw[0]), j * t, min((j + 1) * t, self.shape_hw[1])

    def tile_shape(self, tile: int) -> tuple[int, int]:
        r0, r1, c0, c1 = self.slices(tile)
        return r1 - r0, c1 - c0

    def cell_centres(self, tile: int) -> FloatArray:
        """(h*w, 2) cell centres of ``tile``, row-major (row 0 at the lowest y)."""
        r0, r1, c0, c1 = self.slices(tile)
        x0, y0 = self.origin_xy_m
        xs = x0 + (np.arange(c0, c1) + 0.5) * self.resolution_m
        ys = y0 + (np.arange(r0, r1) + 0.5) * self.resolution_m
        gx, gy = np.meshgrid(xs, ys)
        return np.stack([gx.ravel(), gy.ravel()], axis=1)

    def rects(self, tiles: NDArray | None = None) -> FloatArray:
        """(T, 4) ``xmin, ymin, xmax, ymax`` of the cell centres of each tile (default: every tile)."""
        t = np.arange(len(self)) if tiles is None else np.asarray(tiles, dtype=np.int64).reshape(-1)
        i, j = np.divmod(t, self.n_cols)
        ts = self.tile_cells
        res = self.resolution_m
        x0, y0 = self.origin_xy_m
        return np.stack(
            [
                x0 + (j * ts + 0.5) * res,
                y0 + (i * ts + 0.5) * res,
                x0 + (np.minimum((j + 1) * ts, self.shape_hw[1]) - 0.5) * res,
                y0 + (np.minimum((i + 1) * ts, self.shape_hw[0]) - 0.5) * res,
            ],
            axis=1,
        )

    def to_dict(self) -> dict:
        return {
            "origin_xy_m": list(self.origin_xy_m),
            "resolution_m": self.resolution_m,
            "shape_hw": list(self.shape_hw),
            "tile_cells": self.tile_cells,
        }

    @classmethod
    def from_dict(cls, d: dict) -> TileGrid:
        return cls(
            (float(d["origin_xy_m"][0]), float(d["origin_xy_m"][1])),
            float(d["resolution_m"]),
            (int(d["shape_hw"][0]), int(d["shape_hw"][1])),
            int(d["tile_cells"]),
        )
