"""Where rendered tiles go: an in-memory raster (:class:`ArraySink`) or a folder on disk (:class:`TileStore`)
that a map larger than memory streams into, tile by tile, and that reads back lazily.

A tile store is a folder holding

- ``probability.npy``, ``mean.npy``, ``variance.npy``: standard NumPy ``.npy`` files, float32 (H, W), row 0 at
  the lowest y (the raster convention of :mod:`mapping.exports`). Tiles are written into them in place with
  ``os.pwrite`` (one write per tile row), never through a memory map, so the writer's memory holds one tile;
  ``numpy.load(path, mmap_mode="r")`` (or :meth:`TileStore.layer`) reads them lazily, any window at a time;
- ``tiles.bin``: one byte per tile, 1 once the tile's three layers are written (a reader can tell a finished
  map from an interrupted one, and the writer can resume);
- ``tiles.json``: the tile grid (:class:`mapping.tiling.grid.TileGrid`), the frame and the format name.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mapping.exports import MapExportError, MapLayers
from mapping.tiling.grid import TileGrid
from mapping.tiling.render import LAYERS, TileResult

STORE_FORMAT = "gpom-tile-store-1"
DONE_FILE = "tiles.bin"
INDEX_FILE = "tiles.json"


class ArraySink:
    """The three float32 (H, W) layers of a map in memory; :meth:`write` puts a tile in place."""

    def __init__(self, grid: TileGrid, layers: MapLayers | None = None, frame_id: str = "map") -> None:
        self.grid = grid
        self.frame_id = frame_id if layers is None else layers.frame_id
        if layers is None:
            self.arrays = {name: np.full(grid.shape_hw, np.nan, np.float32) for name in LAYERS}
        else:
            fits = (
                layers.shape == grid.shape_hw
                and layers.resolution_m == grid.resolution_m
                and tuple(layers.origin_xy_m) == tuple(grid.origin_xy_m)
            )
            if not fits:
                raise ValueError(
                    f"layers of shape {layers.shape} at {layers.resolution_m} m from {layers.origin_xy_m} do "
                    f"not fit the tile grid {grid.shape_hw} at {grid.resolution_m} m from {grid.origin_xy_m}"
                )
            self.arrays = {name: np.array(getattr(layers, name), dtype=np.float32) for name in LAYERS}

    def write(self, result: TileResult) -> None:
        r0, r1, c0, c1 = self.grid.slices(result.tile)
        for name in LAYERS:
            self.arrays[name][r0:r1, c0:c1] = getattr(result, name)

    def layers(self) -> MapLayers:
        """The map as :class:`MapLayers` (copies, so later writes do not change it)."""
        g = self.grid
        return MapLayers(
            probability=self.arrays["probability"].copy(),
            mean=self.arrays["mean"].copy(),
            variance=self.arrays["variance"].copy(),
            resolution_m=g.resolution_m,
            origin_xy_m=g.origin_xy_m,
            frame_id=self.frame_id,
        )


def _npy_header(shape_hw: tuple[int, int]) -> bytes:
    """The header of a C-order float32 ``.npy`` file of ``shape_hw`` (format 1.0 or 2.0)."""
    import io

    buf = io.BytesIO()
    header = {"descr": np.dtype(np.float32).str, "fortran_order": False, "shape": tuple(shape_hw)}
    try:
        np.lib.format.write_array_header_1_0(buf, header)
    except ValueError:  # header too long for format 1.0
        buf = io.BytesIO()
        np.lib.format.write_array_header_2_0(buf, header)
    return buf.getvalue()


class TileStore:
    """A map on disk, written tile by tile and read lazily (see the module docstring)."""

    def __init__(self, path: Path, grid: TileGrid, frame_id: str = "map") -> None:
        self.path = Path(path)
        self.grid = grid
        self.frame_id = frame_id
        self._offset = len(_npy_header(grid.shape_hw))
        self._fds: dict[str, int] = {}

    # -- writing ------------------------------------------------------------------------------------------
    @classmethod
    def create(cls, path: Path, grid: TileGrid, frame_id: str = "map") -> TileStore:
        """A new, empty store at ``path`` (a new folder; MapExportError if it exists)."""
        path = Path(path)
        try:
            path.mkdir(parents=True, exist_ok=False)
        except FileExistsError:
            raise MapExportError(f"{path}: already exists") from None
        except OSError as exc:
            raise MapExportError(f"{path}: cannot create the tile store ({exc.strerror})") from None
        store = cls(path, grid, frame_id)
        header = _npy_header(grid.shape_hw)
        size = len(header) + grid.cells * 4
        for name in LAYERS:
            with open(path / f"{name}.npy", "wb") as f:
                f.write(header)
                f.truncate(size)  # sparse: zeros until a tile is written
        (path / DONE_FILE).write_bytes(bytes(len(grid)))
        meta = {"format": STORE_FORMAT, "grid": grid.to_dict(), "frame_id": frame_id}
        (path / INDEX_FILE).write_text(json.dumps(meta, indent=2) + "\n")
        return store

    def _fd(self, name: str) -> int:
        if name not in self._fds:
            self._fds[name] = os.open(self.path / name, os.O_WRONLY)
        return self._fds[name]

    def write(self, result: TileResult) -> None:
        """Write one tile's layers in place, then mark it done."""
        r0, r1, c0, _ = self.grid.slices(result.tile)
        w = self.grid.shape_hw[1]
        for name in LAYERS:
            fd = self._fd(f"{name}.npy")
            block = np.ascontiguousarray(getattr(result, name), dtype="<f4")
            for i, r in enumerate(range(r0, r1)):
                os.pwrite(fd, block[i].tobytes(), self._offset + (r * w + c0) * 4)
        os.pwrite(self._fd(DONE_FILE), b"\x01", result.tile)

    def close(self) -> None:
        """Flush and close the files written to."""
        for fd in self._fds.values():
            os.fsync(fd)
            os.close(fd)
        self._fds.clear()

    def __enter__(self) -> TileStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- reading ------------------------------------------------------------------------------------------
    @classmethod
    def open(cls, path: Path) -> TileStore:
        """An existing store (MapExportError naming the folder if it is not one)."""
        path = Path(path)
        try:
            meta = json.loads((path / INDEX_FILE).read_text())
            if meta.get("format") != STORE_FORMAT:
                raise ValueError(f"format {meta.get('format')!r}, expected {STORE_FORMAT!r}")
            store = cls(path, TileGrid.from_dict(meta["grid"]), str(meta.get("frame_id", "map")))
            for name in LAYERS:
                if (path / f"{name}.npy").stat().st_size != store._offset + store.grid.cells * 4:
                    raise ValueError(f"{name}.npy has the wrong size")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise MapExportError(f"{path}: not a readable tile store ({exc})") from None
        return store

    def done(self) -> NDArray[np.bool_]:
        """(T,) whether each tile was written."""
        return np.frombuffer((self.path / DONE_FILE).read_bytes(), dtype=np.uint8).astype(bool)

    def layer(self, name: str) -> np.memmap:
        """A read-only memory map of one layer (float32 (H, W)): nothing is read until it is indexed."""
        if name not in LAYERS:
            raise KeyError(f"no layer {name!r} (layers: {', '.join(LAYERS)})")
        return np.load(self.path / f"{name}.npy", mmap_mode="r")

    def window(self, rows: slice, cols: slice) -> MapLayers:
        """The layers of a window of the raster, read from disk, as :class:`MapLayers`."""
        g = self.grid
        r0 = rows.start or 0
        c0 = cols.start or 0
        arrays = {name: np.array(self.layer(name)[rows, cols]) for name in LAYERS}
        return MapLayers(
            **arrays,
            resolution_m=g.resolution_m,
            origin_xy_m=(g.origin_xy_m[0] + c0 * g.resolution_m, g.origin_xy_m[1] + r0 * g.resolution_m),
            frame_id=self.frame_id,
        )

    def as_dask(self, name: str):
        """One layer as a lazy ``dask.array`` chunked by tile."""
        import dask.array as da

        t = self.grid.tile_cells
        return da.from_array(self.layer(name), chunks=(t, t))
