"""Guess a recording's format from its path and dispatch to the reader of that format.

One reader per format, imported lazily (so reading a CARMEN log never imports the bag libraries):

========  =====================================================  ===============================
format    paths                                                  reader
========  =====================================================  ===============================
ros1      ``*.bag``                                              ``datasets.rosbag.read_ros1``
ros2      a folder with ``metadata.yaml``, ``*.mcap``, ``*.db3``  ``datasets.rosbag.read_ros2``
carmen    ``*.clf``, ``*.log``, either ``.gz`` / ``.bz2``         ``datasets.carmen.read_carmen``
kitti     ``*.bin`` or a folder of them                          ``datasets.kitti.read_kitti``
========  =====================================================  ===============================
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from datasets.config import InputConfig
from datasets.errors import DatasetError, UnknownFormatError
from datasets.types import Recording
from datasets.validate import validate_recording

READERS: dict[str, str] = {
    "ros1": "datasets.rosbag:read_ros1",
    "ros2": "datasets.rosbag:read_ros2",
    "carmen": "datasets.carmen:read_carmen",
    "kitti": "datasets.kitti:read_kitti",
}

CARMEN_SUFFIXES = (".clf", ".log")
COMPRESSION_SUFFIXES = (".gz", ".bz2")


def guess_format(path: str | Path) -> str:
    """The format name of ``path`` (a key of :data:`READERS`); UnknownFormatError if none fits.

    Raises DatasetError when the path does not exist.
    """
    p = Path(path)
    if not p.exists():
        raise DatasetError(f"{p}: no such file or directory")
    if p.is_dir():
        if (p / "metadata.yaml").is_file():
            return "ros2"
        if any(p.glob("*.bin")):
            return "kitti"
        raise UnknownFormatError(
            f"{p}: a folder that is neither a ROS 2 bag (no metadata.yaml) nor KITTI frames (no *.bin)"
        )
    if not p.is_file():  # a FIFO (reading it would wait for a writer forever), a socket, a device
        raise DatasetError(f"{p}: not a regular file (a pipe, socket or device): give a recording's file")
    suffixes = [s.lower() for s in p.suffixes]
    last = suffixes[-1] if suffixes else ""
    if last == ".bag":
        return "ros1"
    if last in (".mcap", ".db3"):
        return "ros2"
    if last == ".bin":
        return "kitti"
    if last in CARMEN_SUFFIXES or (
        last in COMPRESSION_SUFFIXES and len(suffixes) >= 2 and suffixes[-2] in CARMEN_SUFFIXES
    ):
        return "carmen"
    raise UnknownFormatError(
        f"{p}: unknown format (expected a ROS1 .bag, a ROS2 bag folder / .mcap / .db3, "
        "a CARMEN .clf / .log (optionally .gz / .bz2), or KITTI .bin frames)"
    )


def open_dataset(path: str | Path, config: InputConfig | None = None, **overrides: Any) -> Recording:
    """Read the recording at ``path``, guessing its format from the path.

    ``config`` selects topics and options; keyword ``overrides`` replace single fields of it
    (e.g. ``open_dataset(p, scan_topic="/scan")``). Raises a :class:`~datasets.errors.DatasetError`
    subclass on any bad input, with the file named in the message; what it returns passed
    :func:`~datasets.validate.validate_recording` (finite angles, limits, poses; stamps in time order).
    """
    cfg = config or InputConfig()
    if overrides:
        cfg = cfg.model_copy(update=overrides)
        cfg = InputConfig.model_validate(cfg.model_dump())
    fmt = guess_format(path)
    module_name, func_name = READERS[fmt].split(":")
    reader = getattr(importlib.import_module(module_name), func_name)
    return validate_recording(reader(Path(path), cfg))
