"""Raster maps as ROS messages: ``nav_msgs/OccupancyGrid`` and ``grid_map_msgs/GridMap``, written and read,
and the run's trajectories, loop closures and TF beside them in the maps bag.

Input rasters follow the project convention: (H, W) arrays, row 0 at the lowest y, column 0 at the lowest
x, ``origin_xy_m`` the lower-left corner of cell (0, 0).

- ``OccupancyGrid`` stores row-major from its origin cell, which is the same layout. A map's occupancy grid
  is *trinary*, the classification a planner acts on (:func:`trinary_occupancy`): 100 occupied, 0 free,
  -1 unknown -- the values nav2's ``map_server`` gives the map's ``trinary`` PGM, so that a planner reading
  the bag and one reading the PGM see the same cells. The continuous p(occ) is a GridMap layer.
- ``GridMap`` (ANYbotics grid_map) indexes cell (i, j) with i growing towards -x and j towards -y from the
  (max x, max y) corner, stores each layer as a column-major ``Float32MultiArray`` (dim 0 "column_index",
  dim 1 "row_index") and places the map by the pose of its centre. So the raster is flipped on both axes:
  ``M(i, j) = raster[H-1-j, W-1-i]``, column-major -> ``raster[::-1, ::-1].ravel()``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numba as nb
import numpy as np
from numpy.typing import NDArray

from datasets.errors import DatasetError, shown_name
from datasets.ros.bag import open_bag
from datasets.ros.typestores import header_msg, pose_msg, time_msg, yaw_of_quaternion
from datasets.ros.writer import (
    BagWriter,
    StreamedArray,
    _transform_stamped,
    bag_kind_of_path,
    open_bag_writer,
)
from datasets.types import Trajectory

OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
GRID_MAP = "grid_map_msgs/msg/GridMap"
PATH = "nav_msgs/msg/Path"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
#: nav_msgs/OccupancyGrid values (nav2_util/occ_grid_values.hpp: OCC_GRID_OCCUPIED, _FREE, _UNKNOWN).
OCCUPIED_VALUE, FREE_VALUE, UNKNOWN_VALUE = 100, 0, -1
LINE_LIST = 5  # visualization_msgs/Marker type
MARKER_ADD = 0  # visualization_msgs/Marker action
LOOP_CLOSURE_LINE_WIDTH_M = 0.1
GRID_MAP_BAND_ROWS = 256  # rows of a layer flipped and written at a time (a 15 M-cell layer: ~22 bands)


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
    """``round(100 * values / full_scale)`` (half to even) clipped to 0..100 as int8; NaN and infinities
    become -1 (unknown)."""
    v = np.asarray(values)
    if v.dtype.kind != "f":
        v = v.astype(np.float64)
    scale = 100.0 / full_scale if full_scale > 0 else 0.0
    return _percent_int8(np.ascontiguousarray(v), scale)


@nb.njit(cache=True)
def _percent_int8(values: NDArray, scale: float) -> NDArray[np.int8]:
    """:func:`percent_int8` of a C-contiguous float array in one pass (float64 arithmetic)."""
    out = np.empty(values.shape, dtype=np.int8)
    v, o = values.ravel(), out.ravel()
    for i in range(v.size):
        x = np.float64(v[i])
        if not np.isfinite(x):
            o[i] = -1
        else:
            o[i] = np.int8(min(max(np.rint(x * scale), 0.0), 100.0))
    return out


def trinary_occupancy(
    probability: NDArray,
    unknown: NDArray | None = None,
    occupied_threshold: float = 0.65,
    free_threshold: float = 0.35,
) -> NDArray[np.int8]:
    """(H, W) int8 OccupancyGrid values of a p(occ) raster: 100 where ``p >= occupied_threshold``, 0 where
    ``p <= free_threshold``, -1 (unknown) in between, where p is NaN and wherever the (H, W) bool mask
    ``unknown`` is set (space no data constrained: it is never free nor occupied)."""
    if not 0.0 < free_threshold < occupied_threshold < 1.0:
        raise DatasetError(f"need 0 < free ({free_threshold}) < occupied ({occupied_threshold}) < 1")
    p = np.asarray(probability)
    if p.dtype.kind != "f":
        p = p.astype(np.float64)
    if unknown is None:
        mask = np.zeros(0, dtype=np.bool_)
    else:
        mask = np.asarray(unknown)
        if mask.shape != p.shape:
            raise DatasetError(f"unknown mask of shape {mask.shape} for a map of shape {p.shape}")
        mask = np.ascontiguousarray(mask.astype(np.bool_, copy=False))
    return _trinary(np.ascontiguousarray(p), mask, float(occupied_threshold), float(free_threshold))


@nb.njit(cache=True)
def _trinary(
    probability: NDArray, unknown: NDArray[np.bool_], occupied_threshold: float, free_threshold: float
) -> NDArray[np.int8]:
    """:func:`trinary_occupancy` of a C-contiguous float array in one pass (float64 comparisons);
    ``unknown`` is a mask of the same shape, or empty for none."""
    out = np.empty(probability.shape, dtype=np.int8)
    p, o = probability.ravel(), out.ravel()
    u = unknown.ravel()
    masked = u.size > 0
    for i in range(p.size):
        x = np.float64(p[i])
        if masked and u[i]:
            o[i] = UNKNOWN_VALUE
        elif x <= free_threshold:
            o[i] = FREE_VALUE
        elif x >= occupied_threshold:
            o[i] = OCCUPIED_VALUE
        else:
            o[i] = UNKNOWN_VALUE
    return out


def occupancy_grid_msg(
    w: BagWriter, values_0_100: NDArray[np.int8], raster: Raster, stamp_ns: int, data: NDArray | None = None
) -> object:
    """An OccupancyGrid of int8 ``values_0_100`` (H, W) placed like ``raster``; ``data`` replaces the values
    (flattened) when given."""
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
        data=np.ascontiguousarray(values_0_100, dtype=np.int8).reshape(-1) if data is None else data,
    )


def grid_map_msg(
    w: BagWriter, raster: Raster, stamp_ns: int, data: Sequence[NDArray] | None = None
) -> object:
    """A GridMap with every layer of ``raster`` as float32; ``data`` (one 1-D float32 array per layer, in
    GridMap order: :func:`grid_map_layer_data`) replaces the layers' values when given."""
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
    if data is None:
        data = [layer.whole() for layer in grid_map_layer_data(raster)]
    arrays = [t["std_msgs/msg/Float32MultiArray"](layout=layout, data=d) for d in data]
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


def grid_map_layer_data(raster: Raster, band_rows: int = GRID_MAP_BAND_ROWS) -> list[StreamedArray]:
    """Each layer of ``raster`` as a GridMap stores it (float32, both axes reversed: grid_map's first cell is
    the map's top-right corner), produced ``band_rows`` rows at a time."""
    height, width = raster.shape

    def bands(layer: NDArray) -> Iterator[NDArray[np.float32]]:
        for top in range(height, 0, -band_rows):
            band = np.asarray(layer[max(top - band_rows, 0) : top], dtype=np.float32)
            yield np.ascontiguousarray(band[::-1, ::-1]).reshape(-1)

    return [
        StreamedArray(np.dtype(np.float32), height * width, lambda layer=layer: bands(layer))
        for layer in raster.layers.values()
    ]


def path_msg(w: BagWriter, trajectory: Trajectory, stamp_ns: int) -> object:
    """A ``nav_msgs/Path`` of every pose of ``trajectory`` (each stamped with its own time), in its frame."""
    t = w.types
    poses = [
        t["geometry_msgs/msg/PoseStamped"](
            header=w.header(int(s), trajectory.frame_id, i), pose=pose_msg(w.typestore, *xyt)
        )
        for i, (s, xyt) in enumerate(zip(trajectory.stamps_ns, trajectory.poses_xytheta, strict=True))
    ]
    return t[PATH](header=w.header(stamp_ns, trajectory.frame_id), poses=poses)


def pose_array_msg(w: BagWriter, poses_xytheta: NDArray, stamp_ns: int, frame_id: str = "map") -> object:
    """A ``geometry_msgs/PoseArray`` of the (K, 3) planar poses (x, y in m, yaw in rad) in ``frame_id``."""
    poses = [pose_msg(w.typestore, *map(float, xyt)) for xyt in np.asarray(poses_xytheta, np.float64)]
    return w.types[POSE_ARRAY](header=w.header(stamp_ns, frame_id), poses=poses)


def line_list_msg(
    w: BagWriter, segments_xy_m: NDArray, stamp_ns: int, frame_id: str = "map", ns: str = "loop_closures"
) -> object:
    """A ``visualization_msgs/MarkerArray`` of one LINE_LIST marker: a line per (2, 2) segment of the
    (C, 2, 2) ``segments_xy_m`` (m, in ``frame_id``); with no segment the marker has no points."""
    t = w.types
    segs = np.asarray(segments_xy_m, dtype=np.float64).reshape(-1, 2, 2)
    points = [t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0) for x, y in segs.reshape(-1, 2)]
    fields: dict[str, Any] = dict(
        header=w.header(stamp_ns, frame_id),
        ns=ns,
        id=0,
        type=LINE_LIST,
        action=MARKER_ADD,
        pose=pose_msg(w.typestore, 0.0, 0.0, 0.0),
        scale=t["geometry_msgs/msg/Vector3"](x=LOOP_CLOSURE_LINE_WIDTH_M, y=0.0, z=0.0),
        color=t["std_msgs/msg/ColorRGBA"](r=0.9, g=0.1, b=0.1, a=1.0),
        lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
        frame_locked=False,
        points=points,
        colors=[],
        text="",
        mesh_resource="",
        mesh_use_embedded_materials=False,
    )
    if w.kind == "ros2":  # Humble's Marker adds a texture and an embedded mesh
        empty = np.zeros(0, dtype=np.uint8)
        fields.update(
            texture_resource="",
            texture=t["sensor_msgs/msg/CompressedImage"](header=w.header(0, ""), format="", data=empty),
            uv_coordinates=[],
            mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=empty),
        )
    return t[MARKER_ARRAY](markers=[t["visualization_msgs/msg/Marker"](**fields)])


def write_map_bag(
    path: Path,
    maps: Mapping[str, Raster],
    stamp_ns: int,
    variance_full_scale: Mapping[str, float] | None = None,
    occupancy: Mapping[str, NDArray[np.int8]] | None = None,
    metadata: Mapping[str, Mapping[str, Any]] | None = None,
    paths: Mapping[str, Trajectory] | None = None,
    loop_closures_xy_m: NDArray | None = None,
    tf_trajectory: Trajectory | None = None,
    tf_child_frame: str = "base_link",
    views_xytheta: Mapping[str, NDArray] | None = None,
) -> dict[str, int]:
    """Write each named map of ``maps`` (e.g. ``{"before": ..., "after": ...}``) into a new bag.

    A map needs the layers ``probability``, ``mean`` and ``variance``. Per map ``NAME``, latched:

    - ``/NAME/occupancy``: OccupancyGrid, ``occupancy[NAME]`` (int8 100 / 0 / -1) or by default
      :func:`trinary_occupancy` of the probability with its default thresholds and the raster's ``unknown``
      layer (non-zero: unknown) if it has one;
    - ``/NAME/variance``: OccupancyGrid, ``round(100 variance / variance_full_scale[NAME])`` (default full
      scale: the layer's maximum) -- a picture; the exact variance is the GridMap's float layer;
    - ``/NAME/grid_map``: GridMap with every float layer of the raster;
    - ``/NAME/metadata``: ``std_msgs/String``, ``metadata[NAME]`` as JSON (the scales and thresholds behind
      the grids), when given;
    - ``/NAME/next_best_views``: ``geometry_msgs/PoseArray`` of the (K, 3) poses ``views_xytheta[NAME]``
      (:mod:`mapping.frontier`), when given.

    Then, when given: ``/NAME/path`` (``nav_msgs/Path``, latched) per trajectory of ``paths``;
    ``/loop_closures`` (``visualization_msgs/MarkerArray``, latched: one LINE_LIST, a line per (2, 2)
    segment of the (C, 2, 2) ``loop_closures_xy_m``, in the frame of the first map); ``/tf``
    (``tf2_msgs/TFMessage``): one transform ``tf_trajectory.frame_id -> tf_child_frame`` per pose, at the
    pose's stamp. ROS1 ``.bag`` or ROS2 ``.mcap`` / folder by the path, its chunks compressed (float layers
    of a big building: a few hundred megabytes otherwise; see :func:`open_bag_writer`). Returns messages
    per topic.
    """
    variance_full_scale = dict(variance_full_scale or {})
    occupancy = dict(occupancy or {})
    metadata = dict(metadata or {})
    with open_bag_writer(path, compress=True) as w:
        if tf_trajectory is not None:
            for s, xyt in zip(tf_trajectory.stamps_ns, tf_trajectory.poses_xytheta, strict=True):
                tf = _transform_stamped(w, int(s), tf_trajectory.frame_id, tf_child_frame, xyt)
                w.write("/tf", TF_MESSAGE, int(s), w.types[TF_MESSAGE](transforms=[tf]))
        for name, raster in maps.items():
            missing = {"probability", "mean", "variance"} - set(raster.layers)
            if missing:
                raise DatasetError(f"{path}: map '{name}' lacks layer(s) {', '.join(sorted(missing))}")
            variance = raster.layers["variance"]
            full = variance_full_scale.get(name)
            if full is None:
                finite = np.asarray(variance, np.float64)
                finite = finite[np.isfinite(finite)]
                full = float(finite.max()) if finite.size else 1.0
            values = occupancy.get(name)
            if values is None:
                values = trinary_occupancy(raster.layers["probability"], raster.layers.get("unknown"))
            elif np.shape(values) != raster.shape:
                raise DatasetError(f"{path}: map '{name}': occupancy of shape {np.shape(values)}")
            for topic, grid in (
                (f"/{name}/occupancy", np.asarray(values, np.int8)),
                (f"/{name}/variance", percent_int8(variance, full)),
            ):
                w.write_arrays_streamed(
                    topic,
                    OCCUPANCY_GRID,
                    stamp_ns,
                    lambda data, g=grid, r=raster: occupancy_grid_msg(w, g, r, stamp_ns, data[0]),
                    [StreamedArray.of(grid)],
                    latching=True,
                )
            w.write_arrays_streamed(
                f"/{name}/grid_map",
                GRID_MAP,
                stamp_ns,
                lambda data, r=raster: grid_map_msg(w, r, stamp_ns, data),
                grid_map_layer_data(raster),
                latching=True,
            )
            if name in metadata:
                text = json.dumps(dict(metadata[name]), sort_keys=True)
                w.write(f"/{name}/metadata", STRING, stamp_ns, w.types[STRING](data=text), latching=True)
            if views_xytheta is not None and name in views_xytheta:
                views = pose_array_msg(w, views_xytheta[name], stamp_ns, raster.frame_id)
                w.write(f"/{name}/next_best_views", POSE_ARRAY, stamp_ns, views, latching=True)
        for name, trajectory in (paths or {}).items():
            w.write(f"/{name}/path", PATH, stamp_ns, path_msg(w, trajectory, stamp_ns), latching=True)
        if loop_closures_xy_m is not None:
            frame = next(iter(maps.values())).frame_id if maps else "map"
            markers = line_list_msg(w, loop_closures_xy_m, stamp_ns, frame)
            w.write("/loop_closures", MARKER_ARRAY, stamp_ns, markers, latching=True)
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
                    raise DatasetError(f"{path}: {shown_name(topic)}: rotated map origins are not supported")
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
