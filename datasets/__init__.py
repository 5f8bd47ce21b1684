"""Readers, writers and the data model of robot recordings (SPEC section 1: knows nothing of GPs or graphs).

Entry point: :func:`open_dataset` guesses the format from the path and returns a
:class:`~datasets.types.Recording`.
"""

from datasets.errors import DatasetError, GpomError, TopicError, UnknownFormatError
from datasets.registry import guess_format, open_dataset
from datasets.types import CloudSequence, LaserScan, PointCloud, Recording, ScanSequence, Trajectory

__all__ = [
    "CloudSequence",
    "DatasetError",
    "GpomError",
    "LaserScan",
    "PointCloud",
    "Recording",
    "ScanSequence",
    "TopicError",
    "Trajectory",
    "UnknownFormatError",
    "guess_format",
    "open_dataset",
]
