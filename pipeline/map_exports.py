"""Everything a run writes about its maps (SPEC section 4, ``DIR/maps``), from rendered layers.

Every export carries one classification (:class:`mapping.exports.Classification`, thresholds from
``mapping`` and ``export.unknown_variance_fraction``): the map_server PGM and the bag's OccupancyGrid hold
the same int8 values, computed once here.
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from datasets.ros.maps import Raster, write_map_bag
from datasets.types import Trajectory
from mapping.config import MappingConfig
from mapping.exports import (
    Classification,
    MapExportError,
    MapLayers,
    finite_range,
    write_layers_npz,
    write_map_server,
)
from mapping.figures import (
    collecting_new_objects_only,
    plot_before_after_maps,
    plot_classified,
    plot_difference,
    plot_layer,
    png_encoding_in,
)
from mapping.frontier import ExplorationSettings, plan_exploration
from mapping.train import GPParams
from pipeline.config import ExportConfig

#: The trajectory the maps bag's ``/tf`` (``map -> base_link``) follows, when the run has it.
TF_TRAJECTORY = "after"


def classify_layers(
    layers: MapLayers, params: GPParams, cfg: MappingConfig, export: ExportConfig
) -> MapLayers:
    """``layers`` with the run's :class:`~mapping.exports.Classification` attached."""
    prior = np.full(layers.shape, params.prior_variance, dtype=np.float32)
    rule = Classification(prior, export.unknown_variance_fraction, cfg.occupied_threshold, cfg.free_threshold)
    return dataclasses.replace(layers, classification=rule)


def map_metadata(layers: MapLayers) -> dict[str, Any]:
    """The scales and thresholds behind a classified map's grids: the extra keys of its map_server YAML and
    the JSON of its ``/NAME/metadata`` message. ``variance_full_scale`` is the variance that the bag's
    ``/NAME/variance`` grid shows as 100 (the prior)."""
    if layers.classification is None:
        raise MapExportError("map_metadata: the map has no classification")
    keys = layers.classification.yaml_keys()
    prior_range = finite_range(layers.classification.prior_variance)
    keys["variance_full_scale"] = prior_range[1] if prior_range is not None else float("nan")
    return keys


def write_map_data(folder: Path, layers: MapLayers) -> list[Path]:
    """``occupancy.pgm`` + ``occupancy.yaml`` and ``layers.npz`` of one classified map; returns the files."""
    folder.mkdir(parents=True, exist_ok=True)
    files = list(
        write_map_server(
            folder / "occupancy",
            layers.occupancy_values(),
            layers.resolution_m,
            layers.origin_xy_m,
            map_metadata(layers),
        )
    )
    files.append(write_layers_npz(folder / "layers.npz", layers))
    return files


def write_map_figures(
    folder: Path,
    layers: MapLayers,
    cfg: MappingConfig,
    title: str,
    path_xy_m: NDArray,
    ate_m: float | None = None,
) -> list[Path]:
    """The PNGs of one classified map (p(occupied), variance, classification); returns the files."""
    folder.mkdir(parents=True, exist_ok=True)
    unknown = layers.unknown
    prior = layers.classification.prior_variance if layers.classification is not None else None
    return [
        plot_layer(
            layers,
            "probability",
            folder / "occupancy.png",
            f"{title}: p(occupied)",
            path_xy_m,
            unknown=unknown,
            ate_m=ate_m,
        ),
        plot_layer(
            layers,
            "variance",
            folder / "variance.png",
            f"{title}: GP variance",
            path_xy_m,
            prior_variance=prior,
        ),
        plot_classified(
            layers,
            folder / "classified.png",
            cfg.occupied_threshold,
            cfg.free_threshold,
            f"{title}: the planners' classification",
            unknown=unknown,
            ate_m=ate_m,
        ),
    ]


def write_maps(
    maps_dir: Path,
    maps: dict[str, MapLayers],
    trajectories: dict[str, Trajectory],
    closures_xy_m: NDArray | None,
    cfg: MappingConfig,
    export: ExportConfig,
    stamp_ns: int,
    params: GPParams,
    ate_m: dict[str, float | None] | None = None,
) -> list[Path]:
    """Write ``maps/{name}/...`` for each map, ``maps/before_after.png``, ``maps/difference.png`` and the
    maps bag.

    ``trajectories`` holds each map's base poses (``frame_id`` "map", one per scan); the bag gets them as
    ``/{name}/path``, the ``after`` one (else the only one) as ``/tf``, and ``closures_xy_m`` (C, 2, 2)
    as ``/loop_closures`` unless it is None. With ``export.next_best_views`` > 0 each map's exploration
    plan (:func:`mapping.frontier.plan_exploration`) adds the ``frontier`` and ``information`` layers to
    its GridMap and its views as ``/{name}/next_best_views``. ``ate_m`` (by map name, when known) goes into
    the figures' titles.
    """
    ate_m = ate_m or {}
    maps = {name: classify_layers(layers, params, cfg, export) for name, layers in maps.items()}
    settings = None
    if export.next_best_views > 0:
        settings = ExplorationSettings.from_config(
            cfg, export.unknown_variance_fraction, n_views=export.next_best_views
        )
    for m in maps.values():
        _ = m.unknown  # computed once, before the threads below read it
    bag = maps_dir / ("maps.mcap" if export.bag_format == "mcap" else "maps.bag")
    # The exploration plans and the bag, the data files and the figures' PNG encoding run in worker
    # threads, the figures are drawn in this one (matplotlib is not thread-safe): most of the writers' time
    # is compression and copying, which release the GIL. Only the plans run parallel compiled loops, so no
    # two threads launch them at once (numba's workqueue threading layer, its fallback without OpenMP, does
    # not allow that).
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="export") as pool:
        bag_written = pool.submit(
            _write_bag, bag, maps, params, settings, trajectories, closures_xy_m, stamp_ns
        )
        data = {name: pool.submit(write_map_data, maps_dir / name, m) for name, m in maps.items()}
        figures = []
        if export.png:
            # encoded by whichever worker is free, while the next is drawn; the run's objects left out of
            # the collections that free each figure
            with png_encoding_in(pool), collecting_new_objects_only():
                figures = _write_figures(maps_dir, maps, trajectories, closures_xy_m, cfg, ate_m)
        return [f for name in maps for f in data[name].result()] + figures + [bag_written.result()]


def _write_figures(
    maps_dir: Path,
    maps: dict[str, MapLayers],
    trajectories: dict[str, Trajectory],
    closures_xy_m: NDArray | None,
    cfg: MappingConfig,
    ate_m: dict[str, float | None],
) -> list[Path]:
    """Each map's PNGs, then the before / after comparison and difference figures when there are both."""
    out: list[Path] = []
    for name, layers in maps.items():
        title = f"{name} loop closure" if name in ("before", "after") else name
        path_xy_m = trajectories[name].poses_xytheta[:, :2]
        out += write_map_figures(maps_dir / name, layers, cfg, title, path_xy_m, ate_m.get(name))
    if {"before", "after"} <= set(maps):
        out += [
            plot_before_after_maps(
                maps["before"],
                maps["after"],
                maps_dir / "before_after.png",
                trajectories["before"].poses_xytheta[:, :2],
                trajectories["after"].poses_xytheta[:, :2],
                closures_xy_m,
                ate_m=ate_m,
            ),
            plot_difference(
                maps["before"],
                maps["after"],
                maps_dir / "difference.png",
                path_after_xy_m=trajectories["after"].poses_xytheta[:, :2],
                closures_xy_m=closures_xy_m,
                ate_m=ate_m,
            ),
        ]
    return out


def _write_bag(
    bag: Path,
    maps: dict[str, MapLayers],
    params: GPParams,
    settings: ExplorationSettings | None,
    trajectories: dict[str, Trajectory],
    closures_xy_m: NDArray | None,
    stamp_ns: int,
) -> Path:
    """The maps bag (:func:`datasets.ros.maps.write_map_bag`) of the classified ``maps``, with each map's
    exploration plan when ``settings`` is given; returns its path."""
    # each plan's layers and views only: its masks and clusters are dropped before the next map's plan
    plan_layers: dict[str, dict[str, NDArray[np.float32]]] = {}
    views: dict[str, NDArray] = {}
    if settings is not None:
        for name, layers in maps.items():
            plan = plan_exploration(layers, params, settings)
            plan_layers[name], views[name] = plan.layers(), plan.views_xytheta
            del plan
    rasters = {
        name: Raster(
            {
                "probability": m.probability,
                "mean": m.mean,
                "variance": m.variance,
                "unknown": np.asarray(m.unknown, dtype=np.float32),
                **({} if m.placement_sigma_m is None else {"placement_sigma": m.placement_sigma_m}),
                **plan_layers.pop(name, {}),
            },
            m.resolution_m,
            m.origin_xy_m,
            m.frame_id,
        )
        for name, m in maps.items()
    }
    metadata = {name: map_metadata(m) for name, m in maps.items()}
    tf_name = TF_TRAJECTORY if TF_TRAJECTORY in trajectories else next(iter(trajectories), None)
    write_map_bag(
        bag,
        rasters,
        stamp_ns,
        variance_full_scale={name: meta["variance_full_scale"] for name, meta in metadata.items()},
        occupancy={name: m.occupancy_values() for name, m in maps.items()},
        metadata=metadata,
        paths=trajectories,
        loop_closures_xy_m=closures_xy_m,
        tf_trajectory=None if tf_name is None else trajectories[tf_name],
        views_xytheta=views,
    )
    return bag
