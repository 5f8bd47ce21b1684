"""``convert``: any readable recording (typically a CARMEN log) to a ROS1 or ROS2 bag."""

from __future__ import annotations

from pathlib import Path

from datasets import open_dataset
from pipeline.progress import Progress


def convert_recording(
    input_path: Path,
    output_path: Path,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    progress: Progress | None = None,
) -> dict:
    """Read ``input_path`` and write its scans, odometry and reference poses to the bag ``output_path``.

    Returns counts of what was written. The bag is written under a temporary name and renamed, so a failed
    conversion leaves nothing behind.
    """
    recording = open_dataset(input_path, scan_topic=scan_topic, odom_topic=odom_topic)
    from datasets.rosbag import write_recording

    write_recording(recording, output_path, progress=progress)
    return {
        "output": str(output_path),
        "scans": len(recording.scans) if recording.scans is not None else 0,
        "odometry": len(recording.odometry) if recording.odometry is not None else 0,
        "poses": len(recording.reference) if recording.reference is not None else 0,
    }
