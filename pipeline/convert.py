"""``convert``: any readable recording (typically a CARMEN log) to a ROS bag.

The output name chooses the kind: a ROS1 ``.bag``, a ROS2 ``.mcap`` / ``.db3`` file or a ROS2 bag folder
(see :mod:`datasets.ros.writer` for the topics written).
"""

from __future__ import annotations

from pathlib import Path

from datasets import guess_format, open_dataset
from pipeline.progress import Progress


def convert_recording(
    input_path: Path,
    output_path: Path,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    progress: Progress | None = None,
) -> dict:
    """Read ``input_path`` and write its scans, odometry, scan poses and reference poses to ``output_path``.

    The input and the output name are checked before anything is read (a missing input, an unknown format,
    an existing output: one-line :class:`~datasets.errors.DatasetError`). The bag is written under a
    temporary name and renamed, so a failed conversion leaves nothing behind. Returns counts of what was
    written (``topics``: messages per topic).
    """
    from datasets.rosbag import check_output_path, write_recording

    input_path, output_path = Path(input_path), Path(output_path)
    guess_format(input_path)
    check_output_path(output_path)
    recording = open_dataset(input_path, scan_topic=scan_topic, odom_topic=odom_topic)
    counts = write_recording(recording, output_path, progress=progress)
    return {
        "output": str(output_path),
        "scans": len(recording.scans) if recording.scans is not None else 0,
        "odometry": len(recording.odometry) if recording.odometry is not None else 0,
        "poses": len(recording.reference) if recording.reference is not None else 0,
        "topics": counts,
    }
