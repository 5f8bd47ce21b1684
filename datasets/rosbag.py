"""ROS1 / ROS2 bags: the registry's entry points and the writers (implementation in :mod:`datasets.ros`).

- ``read_ros1(path, cfg)`` / ``read_ros2(path, cfg)`` -> :class:`~datasets.types.Recording`
  (:mod:`datasets.ros.reader`);
- ``write_recording(recording, path, progress=None)``: a recording to ``.bag`` / ``.mcap`` / a ROS2 folder;
- ``open_bag_writer(path)`` / ``write_messages(path, messages)``: arbitrary messages into a new bag
  (:mod:`datasets.ros.writer`);
- ``standard_typestore(kind)``: the ROS1 / ROS2 type stores with ``grid_map_msgs`` registered.
"""

from datasets.ros.reader import read_bag, read_ros1, read_ros2
from datasets.ros.typestores import standard_typestore
from datasets.ros.writer import (
    BagWriter,
    angle_parameters,
    bag_kind_of_path,
    check_output_path,
    open_bag_writer,
    write_messages,
    write_recording,
)

__all__ = [
    "BagWriter",
    "angle_parameters",
    "bag_kind_of_path",
    "check_output_path",
    "open_bag_writer",
    "read_bag",
    "read_ros1",
    "read_ros2",
    "standard_typestore",
    "write_messages",
    "write_recording",
]
