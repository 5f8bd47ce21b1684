"""Raster maps as ROS messages: ``nav_msgs/OccupancyGrid`` and ``grid_map_msgs/GridMap``, written and read.

Input rasters follow the project convention: (H, W) arrays, row 0 at the lowest y, column 0 at the lowest
x, ``origin_xy_m`` the lower-left corner of cell (0, 0).

- ``OccupancyGrid`` stores row-major from its origin cell, which is the same layout; values are int8
  0..100, -1 unknown (NaN in the raster).
- ``GridMap`` (ANYbotics grid_map) indexes cell (i, j) with i growing towards -x and j towards -y from the
  (max x, max y) corner, stores each layer as a column-major ``Float32MultiArray`` (dim 0 "column_index",
  dim 1 "row_index") and places the map by the pose of its centre. So the raster is flipped on both axes:
  ``M(i, j) = raster[H-1-j, W-1-i]``, column-major -> ``raster[::-1, ::-1].ravel()``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from datasets.errors import DatasetError
from datasets.ros.bag import open_bag
from datasets.ros.typestores import header_msg, pose_msg, time_msg, yaw_of_quaternion
from datasets.ros.writer import BagWriter, bag_kind_of_path, open_bag_writer

OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
GRID_MAP = "grid_map_msgs/msg/GridMap"


@dataclass(frozen=True)
class Raster:
    """One or more float layers of a map on a common grid (project raster convention)."""

    layers: Mapping[str, NDArray[np.float32]]
    resolution_m: float
    origin_xy_m: tuple[float, float]
    frame_id: str = "map"

    @property
    def shape(self) -> tuple[int, int]:
        return next(iter(self.layers.values())).shape  # type: ignore[return-value]


def percent_int8(values: NDArray, full_scale: float) -> NDArray[np.int8]:
    """``round(100 * values / full_scale)`` clipped to 0..100 as int8; NaN becomes -1 (unknown)."""
    v = np.asarray(values, dtype=np.float64)
    out = np.full(v.shape, -1, dtype=np.int8)
    ok = np.isfinite(v)
    scale = 100.0 / full_scale if full_scale > 0 else 0.0
    out[ok] = np.clip(np.round(v[ok] * scale), 0, 100).astype(np.int8)
    return out


def occupancy_grid_msg(w: BagWriter, values_0_100: NDArray[np.int8], raster: Raster, stamp_ns: int) -> object:
    """An OccupancyGrid of int8 ``values_0_100`` (H, W) placed like ``raster``."""
    t = w.types
    height, width = values_0_100.shape
    info = t["nav_msgs/msg/MapMetaData"](
        map_load_time=time_msg(w.typestore, stamp_ns),
        resolution=float(raster.resolution_m),
        width=int(width),
        height=int(height),
        origin=pose_msg(w.typestore, raster.origin_xy_m[0], raster.origin_xy_m[1], 0.0),
    )
    return t[OCCUPANCY_GRID](
        header=w.header(stamp_ns, raster.frame_id),
        info=info,
        data=np.ascontiguousarray(values_0_100, dtype=np.int8).reshape(-1),
    )


def grid_map_msg(w: BagWriter, raster: Raster, stamp_ns: int) -> object:
    """A GridMap with every layer of ``raster`` as float32."""
    t = w.types
    height, width = raster.shape
    res = float(raster.resolution_m)
    centre_x = raster.origin_xy_m[0] + 0.5 * width * res
    centre_y = raster.origin_xy_m[1] + 0.5 * height * res
    dims = [
        t["std_msgs/msg/MultiArrayDimension"](label="column_index", size=height, stride=height * width),
        t["std_msgs/msg/MultiArrayDimension"](label="row_index", size=width, stride=width),
    ]
    layout = t["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0)
    arrays = [
        t["std_msgs/msg/Float32MultiArray"](
            layout=layout, data=np.ascontiguousarray(np.asarray(a, np.float32)[::-1, ::-1]).reshape(-1)
        )
        for a in raster.layers.values()
    ]
    info = dict(
        resolution=res,
        length_x=width * res,
        length_y=height * res,
        pose=pose_msg(w.typestore, centre_x, centre_y, 0.0),
    )
    header = header_msg(w.typestore, w.kind, stamp_ns, raster.frame_id)
    common = dict(
        layers=list(raster.layers), basic_layers=[], data=arrays, outer_start_index=0, inner_start_index=0
    )
    if w.kind == "ros1":
        return t[GRID_MAP](info=t["grid_map_msgs/msg/GridMapInfo"](header=header, **info), **common)
    return t[GRID_MAP](header=header, info=t["grid_map_msgs/msg/GridMapInfo"](**info), **common)


def write_map_bag(
    path: Path,
    maps: Mapping[str, Raster],
    stamp_ns: int,
    variance_full_scale: Mapping[str, float] | None = None,
) -> dict[str, int]:
    """Write each named map of ``maps`` (e.g. ``{"before": ..., "after": ...}``) into a new bag.

    A map needs the layers ``probability``, ``mean`` and ``variance``. Per map ``NAME``:
    ``/NAME/occupancy`` (OccupancyGrid, 100 * p), ``/NAME/variance`` (OccupancyGrid, variance scaled so that
    ``variance_full_scale[NAME]`` -- default the layer's maximum -- is 100) and ``/NAME/grid_map`` (GridMap
    with every float layer). All latched. ROS1 ``.bag`` or ROS2 ``.mcap`` / folder by the path.
    Returns messages per topic.
    """
    variance_full_scale = dict(variance_full_scale or {})
    with open_bag_writer(path) as w:
        for name, raster in maps.items():
            missing = {"probability", "mean", "variance"} - set(raster.layers)
            if missing:
                raise DatasetError(f"{path}: map '{name}' lacks layer(s) {', '.join(sorted(missing))}")
            variance = np.asarray(raster.layers["variance"], np.float64)
            finite = variance[np.isfinite(variance)]
            full = variance_full_scale.get(name, float(finite.max()) if finite.size else 1.0)
            occ = occupancy_grid_msg(w, percent_int8(raster.layers["probability"], 1.0), raster, stamp_ns)
            var = occupancy_grid_msg(w, percent_int8(variance, full), raster, stamp_ns)
            w.write(f"/{name}/occupancy", OCCUPANCY_GRID, stamp_ns, occ, latching=True)
            w.write(f"/{name}/variance", OCCUPANCY_GRID, stamp_ns, var, latching=True)
            w.write(f"/{name}/grid_map", GRID_MAP, stamp_ns, grid_map_msg(w, raster, stamp_ns), latching=True)
        return dict(w.counts)


def read_map_bag(path: Path) -> dict[str, Raster]:
    """Read every OccupancyGrid and GridMap of a bag back into rasters (project convention), by topic.

    OccupancyGrid topics give one layer ``"value"`` (int8 as float32, -1 unknown); GridMap topics give
    their float layers.
    """
    kind, _ = bag_kind_of_path(Path(path))
    out: dict[str, Raster] = {}
    with open_bag(Path(path), kind) as bag:
        topics = [t.name for t in bag.topics.values() if t.msgtype in (OCCUPANCY_GRID, GRID_MAP)]
        for topic, _, msg in bag.messages(topics):
            if hasattr(msg.info, "width"):  # OccupancyGrid
                i = msg.info
                values = np.asarray(msg.data, np.int8).reshape(i.height, i.width).astype(np.float32)
                origin = (float(i.origin.position.x), float(i.origin.position.y))
                yaw = yaw_of_quaternion(
                    i.origin.orientation.x,
                    i.origin.orientation.y,
                    i.origin.orientation.z,
                    i.origin.orientation.w,
                )
                if abs(yaw) > 1e-9:
                    raise DatasetError(f"{path}: {topic}: rotated map origins are not supported")
                frame = msg.header.frame_id
                out[topic] = Raster({"value": values}, float(i.resolution), origin, frame)
                continue
            info = msg.info
            res = float(info.resolution)
            width = round(info.length_x / res)
            height = round(info.length_y / res)
            cx, cy = float(info.pose.position.x), float(info.pose.position.y)
            layers = {}
            for name, arr in zip(msg.layers, msg.data, strict=True):
                labels = [d.label for d in arr.layout.dim]
                data = np.asarray(arr.data, np.float32)
                if labels and labels[0] == "column_index":
                    layers[name] = data.reshape(height, width)[::-1, ::-1].copy()
                else:  # row-major storage: M(i, j) at i * cols + j
                    layers[name] = data.reshape(width, height).T[::-1, ::-1].copy()
            frame = msg.info.header.frame_id if kind == "ros1" else msg.header.frame_id
            origin = (cx - 0.5 * width * res, cy - 0.5 * height * res)
            out[topic] = Raster(layers, res, origin, frame)
    return out
