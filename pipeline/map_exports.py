"""Everything a run writes about its maps (SPEC section 4, ``DIR/maps``), from rendered layers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datasets.ros.maps import Raster, write_map_bag
from mapping.config import MappingConfig
from mapping.exports import MapLayers, write_layers_npz, write_map_server
from mapping.figures import plot_before_after_maps, plot_classified, plot_layer
from pipeline.config import ExportConfig


def write_map_folder(
    folder: Path, layers: MapLayers, cfg: MappingConfig, export: ExportConfig, title: str, path_xy_m: NDArray
) -> list[Path]:
    """``occupancy.pgm`` + ``occupancy.yaml``, ``layers.npz`` and the PNGs of one map; returns the files."""
    folder.mkdir(parents=True, exist_ok=True)
    files = list(
        write_map_server(
            folder / "occupancy",
            layers.probability,
            layers.resolution_m,
            layers.origin_xy_m,
            cfg.occupied_threshold,
            cfg.free_threshold,
        )
    )
    files.append(write_layers_npz(folder / "layers.npz", layers))
    if export.png:
        files.append(
            plot_layer(layers, "probability", folder / "occupancy.png", f"{title}: p(occupied)", path_xy_m)
        )
        files.append(
            plot_layer(layers, "variance", folder / "variance.png", f"{title}: GP variance", path_xy_m)
        )
        files.append(
            plot_classified(
                layers,
                folder / "classified.png",
                cfg.occupied_threshold,
                cfg.free_threshold,
                f"{title}: occupied (black) / free (white) / unsure (grey)",
            )
        )
    return files


def write_maps(
    maps_dir: Path,
    maps: dict[str, MapLayers],
    paths_xy_m: dict[str, NDArray],
    closures_xy_m: NDArray,
    cfg: MappingConfig,
    export: ExportConfig,
    stamp_ns: int,
    variance_full_scale: float,
) -> list[Path]:
    """Write ``maps/{name}/...`` for each map, ``maps/before_after.png`` and the maps bag."""
    files: list[Path] = []
    for name, layers in maps.items():
        title = f"{name} loop closure" if name in ("before", "after") else name
        files += write_map_folder(maps_dir / name, layers, cfg, export, title, paths_xy_m[name])
    if export.png and {"before", "after"} <= set(maps):
        files.append(
            plot_before_after_maps(
                maps["before"],
                maps["after"],
                maps_dir / "before_after.png",
                paths_xy_m["before"],
                paths_xy_m["after"],
                closures_xy_m,
            )
        )
    bag = maps_dir / ("maps.mcap" if export.bag_format == "mcap" else "maps.bag")
    rasters = {
        name: Raster(
            {"probability": m.probability, "mean": m.mean, "variance": m.variance},
            m.resolution_m,
            m.origin_xy_m,
            m.frame_id,
        )
        for name, m in maps.items()
    }
    write_map_bag(bag, rasters, stamp_ns, dict.fromkeys(maps, variance_full_scale))
    files.append(bag)
    return files


def max_variance(maps: dict[str, MapLayers]) -> float:
    """The largest finite variance of all maps (a common full scale for the variance grids)."""
    values = [float(np.nanmax(m.variance)) for m in maps.values() if np.isfinite(m.variance).any()]
    return max(values) if values else 1.0
