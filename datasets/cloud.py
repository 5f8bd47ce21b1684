"""3D point clouds to planar scans: the points of a height band, binned by bearing, nearest per bin."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from datasets.types import beam_angles_rad


def cloud_to_scan(
    points_xyz_m: NDArray,
    height_band_m: tuple[float, float],
    num_beams: int,
    range_max_m: float,
    range_min_m: float = 0.0,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Turn a cloud (P, 3) in the sensor frame into a 360-degree scan of ``num_beams`` beams.

    Points with ``height_band_m[0] <= z <= height_band_m[1]`` and planar range in
    ``[range_min_m, range_max_m)`` are binned by bearing; each beam keeps the nearest point. Beams without a
    point get ``inf`` (no return). Returns ``(ranges_m, angles_rad)``, both (num_beams,) float32, with
    angles from -pi in steps of 2 pi / num_beams (beam i covers [angle_i - step/2, angle_i + step/2)).
    """
    pts = np.asarray(points_xyz_m, dtype=np.float64)
    lo, hi = height_band_m
    z = pts[:, 2]
    band = (z >= lo) & (z <= hi)
    xy = pts[band, :2]
    r = np.hypot(xy[:, 0], xy[:, 1])
    keep = (r >= range_min_m) & (r < range_max_m) & (r > 0)
    xy, r = xy[keep], r[keep]
    step = 2.0 * np.pi / num_beams
    angles = beam_angles_rad(-np.pi, step, num_beams)
    bearing = np.arctan2(xy[:, 1], xy[:, 0])
    idx = np.floor((bearing + np.pi + 0.5 * step) / step).astype(np.int64) % num_beams
    ranges = np.full(num_beams, np.inf)
    np.minimum.at(ranges, idx, r)
    return ranges.astype(np.float32), angles
