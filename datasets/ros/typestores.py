"""Type stores for reading and writing bags, with ``grid_map_msgs`` registered, and message helpers.

ROS1 bags use the ROS1 Noetic definitions, ROS2 bags the Humble ones (the LTS distribution; the message
types we write have the same RIHS01 hashes in later distributions). ``grid_map_msgs`` is not a standard
package, so its messages are registered here from their definitions (ROS1 and ROS2 forms differ: the
ROS2 ``GridMap`` carries the header, the ROS1 ``GridMapInfo`` does).
"""

from __future__ import annotations

from functools import cache
from typing import Literal

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

BagKind = Literal["ros1", "ros2"]

# grid_map_msgs (ANYbotics/grid_map), ROS1 (noetic) definitions.
GRID_MAP_INFO_ROS1 = """\
std_msgs/Header header
float64 resolution
float64 length_x
float64 length_y
geometry_msgs/Pose pose
"""
GRID_MAP_ROS1 = """\
grid_map_msgs/GridMapInfo info
string[] layers
string[] basic_layers
std_msgs/Float32MultiArray[] data
uint16 outer_start_index
uint16 inner_start_index
"""
# grid_map_msgs, ROS2 (humble and later) definitions.
GRID_MAP_INFO_ROS2 = """\
float64 resolution
float64 length_x
float64 length_y
geometry_msgs/Pose pose
"""
GRID_MAP_ROS2 = """\
std_msgs/Header header
grid_map_msgs/GridMapInfo info
string[] layers
string[] basic_layers
std_msgs/Float32MultiArray[] data
uint16 outer_start_index
uint16 inner_start_index
"""
# std_msgs multi-arrays (present in the standard stores; registered only if missing).
MULTI_ARRAY_DIMENSION = "string label\nuint32 size\nuint32 stride\n"
MULTI_ARRAY_LAYOUT = "std_msgs/MultiArrayDimension[] dim\nuint32 data_offset\n"
FLOAT32_MULTI_ARRAY = "std_msgs/MultiArrayLayout layout\nfloat32[] data\n"
# tf2_msgs (not in rosbags' ROS1 Noetic store).
TF_MESSAGE = "geometry_msgs/TransformStamped[] transforms\n"

EXTRA_DEFINITIONS: dict[BagKind, dict[str, str]] = {
    "ros1": {
        "tf2_msgs/msg/TFMessage": TF_MESSAGE,
        "std_msgs/msg/MultiArrayDimension": MULTI_ARRAY_DIMENSION,
        "std_msgs/msg/MultiArrayLayout": MULTI_ARRAY_LAYOUT,
        "std_msgs/msg/Float32MultiArray": FLOAT32_MULTI_ARRAY,
        "grid_map_msgs/msg/GridMapInfo": GRID_MAP_INFO_ROS1,
        "grid_map_msgs/msg/GridMap": GRID_MAP_ROS1,
    },
    "ros2": {
        "tf2_msgs/msg/TFMessage": TF_MESSAGE,
        "std_msgs/msg/MultiArrayDimension": MULTI_ARRAY_DIMENSION,
        "std_msgs/msg/MultiArrayLayout": MULTI_ARRAY_LAYOUT,
        "std_msgs/msg/Float32MultiArray": FLOAT32_MULTI_ARRAY,
        "grid_map_msgs/msg/GridMapInfo": GRID_MAP_INFO_ROS2,
        "grid_map_msgs/msg/GridMap": GRID_MAP_ROS2,
    },
}


@cache
def standard_typestore(kind: BagKind) -> Typestore:
    """The standard store of ``kind`` (ROS1 Noetic / ROS2 Humble) plus ``grid_map_msgs`` and ``tf2_msgs``.

    Cached and shared: do not register more types in it.
    """
    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    for name, text in EXTRA_DEFINITIONS[kind].items():
        if name not in store.fielddefs:
            store.register(get_types_from_msg(text, name))
    return store


def time_msg(store: Typestore, stamp_ns: int) -> object:
    """A ``builtin_interfaces/msg/Time`` for integer nanoseconds."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def stamp_ns_of(stamp: object) -> int:
    """Integer nanoseconds of a ``Time`` message."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)  # type: ignore[attr-defined]


def header_msg(store: Typestore, kind: BagKind, stamp_ns: int, frame_id: str, seq: int = 0) -> object:
    """A ``std_msgs/msg/Header`` (with ``seq`` in ROS1)."""
    header = store.types["std_msgs/msg/Header"]
    if kind == "ros1":
        return header(seq=seq, stamp=time_msg(store, stamp_ns), frame_id=frame_id)
    return header(stamp=time_msg(store, stamp_ns), frame_id=frame_id)


def yaw_quaternion_msg(store: Typestore, yaw_rad: float) -> object:
    """A ``geometry_msgs/msg/Quaternion`` rotating by ``yaw_rad`` about z."""
    half = 0.5 * float(yaw_rad)
    return store.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(half), w=np.cos(half))


def pose_msg(store: Typestore, x_m: float, y_m: float, yaw_rad: float) -> object:
    """A planar ``geometry_msgs/msg/Pose`` (z = 0)."""
    point = store.types["geometry_msgs/msg/Point"](x=float(x_m), y=float(y_m), z=0.0)
    return store.types["geometry_msgs/msg/Pose"](
        position=point, orientation=yaw_quaternion_msg(store, yaw_rad)
    )


def yaw_of_quaternion(qx: float, qy: float, qz: float, qw: float) -> float:
    """Yaw (rotation about z, rad) of a unit quaternion (ZYX convention)."""
    return float(np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz)))
